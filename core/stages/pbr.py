"""The physically based inverse-rendering stage (paper Sec. 3.3, Eq. 6): lighting only.

Geometry and material are frozen (the volume stage's scene graph). The environment map ``E`` is a
log-radiance parameter (:class:`core.pbr.envmap.EnvironmentMap` with ``log_space=True``),
initialised from the lighting prior ``E_g``, and optimised so that the PBR pass (torch backend,
ray-traced Gaussian shadows) matches the training frames on random non-sky pixels:

    L = mean |C_ldr - C_gt|  +  lambda_E * mean_w |log E(w) - log E_g(w)|

with ``lambda_E`` decayed linearly from 1.0 to 0.1 over the stage (the supplement).

``E_g`` here is the physically fitted prior of :func:`core.lighting.prior.estimate_lighting`
(observed sky pixels placed by the poses, a parametric sky, the sun from saturated pixels and
shading), computed on the reconstruction's own G-buffers (depth, normals, albedo rasterized from
the scene graph), never on ground truth. The paper uses DiffusionLight for ``E_g``; this project's
learned lighting prior does not exist yet.

The sky the training frames saw is held fixed in ``E`` and ``E_g``
(:mod:`core.lighting.sky_evidence`: the reconstruction's sky dome where the frames' sky pixels
point, unclipped): the fit moves only what the frames did not see (not in the paper). Before the
fit, ``E_g``'s sun and unseen sky are rescaled by two gains fitted to the training frames
(:mod:`core.lighting.prior_gains`, ``prior_gains``: a global move the per-texel steps do not make;
not in the paper).

Outputs (``out_dir``): ``envmap.exr`` (the fitted ``E``, float32, 2:1 equirect in the project's
convention), ``envmap_prior.exr`` (``E_g``), ``preview.png`` (both tone-mapped), ``summary.json``
(losses, photometric PSNR on the sampled pixels before and after, the sky evidence's coverage),
``sky_evidence.npz`` (what is held, for the joint stage). The stage never reads the
bundle's ground truth; ``brdf evaluate`` (:mod:`core.synth.evaluate`) measures the sun direction error.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from core.camera import Camera
from core.conventions import envmap_directions
from core.errors import ConfigError, FormatError, NumericalError
from core.io.atomic import atomic_output
from core.io.envmap_file import write_envmap
from core.io.images import write_png
from core.lighting.prior import LightingSettings, estimate_lighting, numpy_visibility
from core.lighting.prior_gains import search_gains, split_map
from core.lighting.sky_evidence import SkyEvidence, observed_sky
from core.numerics import LOG_RADIANCE_FLOOR
from core.pbr.envmap import EnvironmentMap, resample
from core.pbr.render import render_pbr
from core.pbr.visibility import GaussianTracer
from core.raster import RasterSettings, rasterize_gaussians
from core.stages.early_stop import stalled
from core.stages.occluders import OccluderSettings, capture_views
from core.stages.pbr_settings import PBRStageConfig
from core.stages.wall_heights import OCCLUDERS_FILE, capture_frames, choose, hypothesis_occluders, save_occluders


@dataclass
class _FrameData:
    camera: object
    gbuf: dict
    target: torch.Tensor      # [H*W, 3] LDR in [0, 1]
    nonsky: torch.Tensor      # flat indices of non-sky pixels
    tracers: list
    sky: torch.Tensor | None = None  # [H*W] bool, the bundle's sky mask (None: the bundle has none)


def _frames(graph, bundle, cfg: PBRStageConfig) -> list[_FrameData]:
    frames = sorted(bundle.frames("train"), key=lambda f: (f.time_index, f.id))
    if not frames:
        raise ConfigError("bundle: no training frames for the PBR stage")
    pick = np.unique(np.linspace(0, len(frames) - 1, min(cfg.max_frames, len(frames))).round().astype(int))
    times = bundle.manifest.times
    rs = RasterSettings(threads=cfg.threads)
    static = graph._static_part().detach()
    shadow = graph.shadow_static()  # the static part plus the completed facades (core.stages.occluders)
    ts = cfg.trace_settings()
    static_tracer = GaussianTracer.from_gaussians(shadow, ts) if shadow.num else None
    out = []
    with torch.no_grad():
        for i in pick:
            fr = frames[int(i)]
            cam = Camera.from_bundle(bundle.camera(fr), fr)
            t = float(times[fr.time_index])
            g = graph.compose(t).detach()
            r = rasterize_gaussians(g, cam, settings=rs)
            gb = {k: v.detach() for k, v in r.as_dict().items()}
            tracers = [static_tracer] if static_tracer is not None else []
            if g.num > static.num:
                tracers.append(GaussianTracer.from_gaussians(g.index(slice(static.num, None)),
                                                             ts))
            target = torch.from_numpy(bundle.load_image(fr)).to(torch.float32).reshape(-1, 3)
            sky = bundle.load_sky_mask(fr)
            o = gb["opacity"].reshape(-1)
            ok = o >= 0.5
            sky_t = torch.from_numpy(np.asarray(sky, bool).reshape(-1)) if sky is not None else None
            if sky_t is not None:
                ok &= ~sky_t
            out.append(_FrameData(cam, gb, target, torch.nonzero(ok).reshape(-1), tracers, sky_t))
    return out, static_tracer


def sunless_capture(frames: list[_FrameData], bundle, cfg: PBRStageConfig) -> tuple[str | None, dict]:
    """Whether the training frames show an overcast or night sky (``("overcast" | "night" |
    None, statistics)``): overcast when at most ``cfg.overcast_max_clipped_sky`` of the sky
    pixels (the bundle's sky masks, else the render's uncovered pixels) are clipped, night when
    the median LDR value is at most ``cfg.night_max_median_ldr``."""
    clipped, sky_px, values = 0, 0, []
    for f in frames:
        h, w = f.camera.height, f.camera.width
        t = f.target.reshape(h * w, 3)
        values.append(t.reshape(-1))
        sky = f.sky if f.sky is not None else f.gbuf["opacity"].reshape(-1) < 0.5
        sky_px += int(sky.sum())
        clipped += int((t[sky] >= 0.98).any(-1).sum())
    frac = clipped / sky_px if sky_px else 0.0
    med = float(torch.cat(values).median()) if values else 0.0
    stats = {"clipped_sky_fraction": round(frac, 4), "sky_pixels": sky_px, "median_ldr": round(med, 4)}
    if med <= cfg.night_max_median_ldr:
        return "night", stats
    if sky_px and frac <= cfg.overcast_max_clipped_sky:
        return "overcast", stats
    return None, stats


def prior_inputs(frames: list[_FrameData], search_sun: bool = True) -> dict[str, np.ndarray]:
    """The lighting prior's inputs from the stage's frames: ``img`` [T, H, W, 3] LDR, ``sky``
    [T, H, W] bool (the render's uncovered pixels), ``depth`` [T, H, W] camera z-depth in metres
    (0 on sky, and everywhere when ``search_sun`` is False), ``normal`` [T, H, W, 3] unit world
    normals, ``albedo`` / ``roughness`` / ``metallic`` (coverage-normalised, in [0, 1];
    ``[T, H, W, 3]`` / ``[T, H, W]``)."""
    out: dict[str, list] = {k: [] for k in ("img", "sky", "depth", "normal", "albedo", "roughness", "metallic")}
    for f in frames:
        h, w = f.camera.height, f.camera.width
        o = f.gbuf["opacity"].reshape(h, w, 1).double()
        inv = torch.where(o > 1e-3, 1.0 / torch.where(o > 1e-3, o, torch.ones_like(o)), torch.zeros_like(o))
        out["img"].append(f.target.reshape(h, w, 3).numpy())
        sky = (o[..., 0] < 0.5).numpy()
        out["sky"].append(sky)
        out["depth"].append(np.where(sky | (not search_sun), 0.0, (f.gbuf["depth"].double() * inv)[..., 0].numpy()))
        n = f.gbuf["normal"].double()
        out["normal"].append((n / n.norm(dim=-1, keepdim=True).clamp_min(1e-9)).numpy().astype(np.float32))
        out["albedo"].append((f.gbuf["albedo"].double() * inv).clamp(0, 1).numpy())
        for k in ("roughness", "metallic"):
            out[k].append((f.gbuf[k].double() * inv).clamp(0, 1)[..., 0].numpy())
    return {k: np.stack(v) for k, v in out.items()}


def _prior(frames: list[_FrameData], bundle, height: int, tracer=None, search_sun: bool = True, *,
           points: int, basin_quantile: float, sun_model: str = "lambert"):
    """``E_g`` from the reconstruction's G-buffers (:func:`core.lighting.prior.estimate_lighting`),
    with cast shadows traced through ``tracer`` (the static Gaussians and completed facades; None =
    no shadows); ``points``, ``basin_quantile`` and ``sun_model`` (``"lambert"`` or
    ``"lambert+transport"``, :attr:`PBRStageConfig.prior_sun_model`) of the sun search. ``search_sun`` False: no
    surface sample is given (depth 0 everywhere), so the estimate runs no sun search and is the
    sky fit alone."""
    x = prior_inputs(frames, search_sun)
    m = bundle.manifest
    return estimate_lighting(x["img"], Camera.stack([f.camera for f in frames]), x["sky"], x["depth"], x["normal"],
                             albedo=x["albedo"], exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                             # not "transport" alone: with the reconstruction's shadows it put the
                             # default scene's sun 31.7 (later 80) deg off (benchmarks/bench_sun.py)
                             settings=LightingSettings(height=max(height, 8), sun_model=sun_model, max_points=points,
                                                       basin_quantile=basin_quantile),
                             visibility=numpy_visibility(tracer) if tracer is not None else None)


def wall_shadow_source(residuals: dict, chosen: str, cfg: "PBRStageConfig") -> tuple[str, float | None]:
    """Whose occluders cast the shadows after the wall hypotheses (:attr:`PBRStageConfig.wall_shadows`)
    and the chosen one's gain over the guess, ``residual_none / residual_chosen - 1`` (None when
    either residual is missing, not finite or not positive)."""
    r0, rc = residuals.get("none"), residuals.get(chosen)
    ok = all(r is not None and math.isfinite(r) and r > 0 for r in (r0, rc))
    gain = float(r0) / float(rc) - 1.0 if ok else None
    if cfg.wall_shadows == "chosen":
        return chosen, gain
    if cfg.wall_shadows == "guess" or chosen == "none":
        return "none", gain
    return (chosen if gain is not None and gain >= cfg.wall_shadows_min_gain else "none"), gain


def _choose_walls(graph, bundle, frames: list[_FrameData], static_tracer, occ: OccluderSettings,
                  cfg: PBRStageConfig, out: Path):
    """The prior under each wall-height hypothesis (:mod:`core.stages.wall_heights`): returns the
    chosen one's estimate and static shadow tracer (also put in each frame's tracers and in
    ``graph.occluders``) and the summary's ``wall_heights`` entry."""
    t0 = time.perf_counter()
    views = capture_views(graph, capture_frames(bundle), RasterSettings(threads=cfg.threads))
    occs = hypothesis_occluders(graph, views, occ)
    t_build = time.perf_counter() - t0
    ests, tracers = {}, {}
    own = graph.occluders
    try:  # each hypothesis's shadow casters: the graph's static part with its occluders
        for h, o in occs.items():
            graph.occluders = o
            shadow = graph.shadow_static()
            tracers[h] = (static_tracer if h == "none" else
                          GaussianTracer.from_gaussians(shadow, cfg.trace_settings()) if shadow.num else None)
            ests[h] = _prior(frames, bundle, 512, tracers[h], search_sun=True, points=cfg.prior_points,
                             basin_quantile=cfg.prior_basin_quantile)
    finally:
        graph.occluders = own  # a failed search leaves the graph as it came
    residuals = {h: e.diagnostics.get("shading_residual") for h, e in ests.items()}
    try:
        chosen = choose(residuals, cfg.wall_min_gain)
    except ConfigError:  # no search found a sun under any hypothesis: the graph's own occluders
        chosen = "none"
    if cfg.prior_sun_model != "lambert" and tracers.get(chosen) is not None:
        # the hypotheses are compared by the lambert search's residual; the chosen one's sun is
        # then placed by the stage's sun model (one more search, not eight)
        ests[chosen] = _prior(frames, bundle, 512, tracers[chosen], search_sun=True, points=cfg.prior_points,
                              basin_quantile=cfg.prior_basin_quantile, sun_model=cfg.prior_sun_model)
    render, gain = wall_shadow_source(residuals, chosen, cfg)  # whose shadows the stage renders
    graph.occluders = occs[render]
    tracer = tracers[render]
    if tracer is not static_tracer:
        for f in frames:
            if static_tracer is not None and f.tracers and f.tracers[0] is static_tracer:
                f.tracers.pop(0)
            if tracer is not None:
                f.tracers.insert(0, tracer)
    table = {h: {"residual": (None if r is None or not math.isfinite(r) else round(float(r), 5)),
                 "sun_dir": [round(float(x), 5) for x in ests[h].sun_dir], "occluders": int(occs[h].num)}
             for h, r in residuals.items()}
    walls = {"enabled": True, "chosen": chosen, "rendered_with": render, "wall_shadows": cfg.wall_shadows,
             "gain_over_guess": None if gain is None else round(gain, 5), "hypotheses": table,
             "build_seconds": round(t_build, 2), "seconds": round(time.perf_counter() - t0, 2)}
    if render != "none":
        save_occluders(out / OCCLUDERS_FILE, occs[render], {"hypothesis": render, "hypotheses": table})
    return ests[chosen], tracer, walls


def _sun_floor(hold: SkyEvidence | None, prior_full: np.ndarray, sun_dir, h: int, cfg: PBRStageConfig):
    """``hold`` (or an evidence that holds nothing) with the prior's sun as a floor
    (:attr:`PBRStageConfig.sun_floor`) on an ``h`` x 2 ``h`` map; returns it and its summary."""
    prior_h = resample(torch.from_numpy(np.asarray(prior_full, np.float64)), h, 2 * h)
    if hold is None:
        zero = torch.zeros(h, 2 * h, dtype=torch.float64)
        hold = SkyEvidence(torch.log(prior_h.clamp_min(LOG_RADIANCE_FLOOR)), zero,
                           torch.full_like(zero, math.log(LOG_RADIANCE_FLOOR)))
    dirs = torch.from_numpy(np.asarray(envmap_directions(h, 2 * h), np.float64))
    sun = torch.as_tensor(np.asarray(sun_dir, np.float64))
    disc = dirs @ (sun / sun.norm().clamp_min(1e-12)) >= math.cos(math.radians(cfg.sun_floor_deg))
    # the floor of a texel: the prior's radiance there (its dimmest channel) times sun_floor
    floor = torch.log((prior_h.min(dim=-1).values * cfg.sun_floor).clamp_min(LOG_RADIANCE_FLOOR))
    new_floor = torch.where(disc & (hold.weight < 1.0), torch.maximum(hold.log_floor, floor), hold.log_floor)
    held = SkyEvidence(hold.log_radiance, hold.weight, new_floor)
    return held, {"enabled": True, "texels": int(disc.sum()), "fraction": cfg.sun_floor,
                  "radius_deg": cfg.sun_floor_deg, "peak_floor": float(torch.exp(new_floor).max())}


def _prior_gains(frames: list[_FrameData], prior_full: np.ndarray, est, hold: SkyEvidence | None, bundle,
                 cfg: PBRStageConfig, search_sun: bool) -> tuple[np.ndarray, dict]:
    """The prior with its sun and unseen sky rescaled to the capture (:mod:`core.lighting.prior_gains`):
    the three parts rendered once each by the stage's PBR pass on ``prior_gains.pixels`` random
    non-sky pixels per frame, the two gains grid-searched. Returns the map and the summary entry."""
    gs = cfg.prior_gains
    if not gs.enabled:
        return prior_full, {"enabled": False, "why": "prior_gains.enabled is false"}
    if not search_sun or est.sun_source == "none":
        return prior_full, {"enabled": False, "why": "no sun in the prior"}
    t0 = time.perf_counter()
    h = prior_full.shape[0]
    w_held = hold.at(h).weight.double().numpy() if hold is not None else None
    parts = split_map(prior_full, est.sun_dir, w_held, gs.sun_cap_deg)
    m = bundle.manifest
    ps = cfg.pbr_settings(rays_per_pixel=cfg.rays_per_pixel, exposure=1.0, gamma=1.0, threads=cfg.threads,
                          seed=cfg.seed)
    envs = {k: EnvironmentMap(torch.from_numpy(np.maximum(v, LOG_RADIANCE_FLOOR))) for k, v in parts.items()}
    gen = torch.Generator().manual_seed(cfg.seed + 7)  # its own stream: the fit's stays as before
    renders: dict[str, list] = {k: [] for k in parts}
    targets = []
    with torch.no_grad():
        for f in frames:
            n = f.nonsky.numel()
            if not n:
                continue
            idx = f.nonsky[torch.randperm(n, generator=gen)[:min(gs.pixels, n)]]
            for k, e in envs.items():
                r = render_pbr(f.gbuf, f.camera, e, settings=ps, tracers=f.tracers, pixels=idx,
                               generator=torch.Generator().manual_seed(cfg.seed + 11))
                renders[k].append(r.hdr.detach().double().numpy().reshape(-1, 3))
            targets.append(f.target[idx].double().numpy())
    if not targets:
        return prior_full, {"enabled": False, "why": "no non-sky pixel"}
    res = search_gains({k: np.concatenate(v) for k, v in renders.items()}, np.concatenate(targets),
                       m.ldr_exposure, m.ldr_gamma, gs)
    out = (res["gain_sun"] * parts["sun"] + res["gain_sky"] * parts["sky"] + parts["held"]).astype(np.float32)
    return out, {"enabled": True, **{k: (round(v, 5) if isinstance(v, float) else v) for k, v in res.items()},
                 "seconds": round(time.perf_counter() - t0, 2)}


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def _render(f: _FrameData, env, settings, idx: torch.Tensor, gen: torch.Generator):
    return render_pbr(f.gbuf, f.camera, env, settings=settings, tracers=f.tracers, pixels=idx, generator=gen).ldr


def _ldr_map(rgb: np.ndarray) -> np.ndarray:
    x = rgb / (1.0 + rgb)
    return (np.clip(x, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def fit_lighting(graph, bundle, out_dir: str | Path, cfg: PBRStageConfig | None = None, *,
                 on_progress: Callable[[int, int, dict], None] | None = None,
                 resume_dir: str | Path | None = None, checkpoint_every: int = 0, sky=None,
                 occluder_settings: OccluderSettings | None = None) -> dict:
    """Run the stage on a reconstructed scene graph and its bundle; write the outputs (module
    docstring) to ``out_dir`` and return the summary.

    Args:
        graph: :class:`core.scene_graph.SceneGraph` from the volume stage (frozen).
        bundle: the :class:`core.bundle.SceneBundle` it was fitted to (training frames).
        out_dir: output directory (created).
        cfg: :class:`PBRStageConfig`.
        on_progress: ``(step, total, record)`` after each step (record has ``loss``, ``photo``,
            ``prior``, ``lambda_e``); may raise to stop the stage.
        resume_dir: where the optimisation state (map, Adam moments, random state, history) is
            saved every ``checkpoint_every`` steps; a run started with a state there continues
            from it (a killed stage resumes).
        sky: the reconstruction's :class:`core.train.sky.SkyDome`: the sky the frames saw is held
            fixed in the map (``cfg.sky_evidence``); None = fit the whole map.
        occluder_settings: the :class:`core.stages.occluders.OccluderSettings` the graph's
            occluders were built with; with ``cfg.wall_hypotheses`` the unseen walls' heights are
            chosen (:mod:`core.stages.wall_heights`), ``graph.occluders`` is replaced by the
            chosen ones and, when they are not the graph's own, written to ``occluders.pt``.
            None: the graph's occluders as they are.
    """
    cfg = cfg or PBRStageConfig()
    if not isinstance(cfg, PBRStageConfig):
        raise ConfigError(f"cfg: expected PBRStageConfig, got {type(cfg).__name__}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    frames, static_tracer = _frames(graph, bundle, cfg)
    t_frames = time.perf_counter() - t0
    fired: list[dict] = []
    sunless, sky_stats = sunless_capture(frames, bundle, cfg)
    search_sun = not (cfg.skip_sun_search and sunless)
    if not search_sun:
        fired.append({"skip": "skip_sun_search", "why": f"{sunless} capture: "
                      + (f"median LDR {sky_stats['median_ldr']:g} <= {cfg.night_max_median_ldr:g}" if sunless == "night"
                         else f"{sky_stats['clipped_sky_fraction']:.2%} of {sky_stats['sky_pixels']} sky pixels clipped "
                              f"(<= {cfg.overcast_max_clipped_sky:.2%}): no sun in view")
                      + "; no shading search for the sun, the lighting prior is the sky fit"})
    t_prior = time.perf_counter()
    walls: dict = {"enabled": False}
    (out / OCCLUDERS_FILE).unlink(missing_ok=True)  # a re-run chooses afresh
    if (cfg.wall_hypotheses and cfg.prior_shadows and search_sun and occluder_settings is not None
            and occluder_settings.enabled and graph.occluders is not None):
        est, static_tracer, walls = _choose_walls(graph, bundle, frames, static_tracer, occluder_settings, cfg, out)
    else:
        walls["why"] = ("wall_hypotheses is false" if not cfg.wall_hypotheses else
                        "no cast shadows in the prior" if not cfg.prior_shadows else
                        "no sun search" if not search_sun else
                        "the graph has no occluders, or their settings are unknown")
        est = _prior(frames, bundle, 512, static_tracer if cfg.prior_shadows else None, search_sun=search_sun,
                     points=cfg.prior_points, basin_quantile=cfg.prior_basin_quantile,
                     sun_model=cfg.prior_sun_model)
    t_prior = time.perf_counter() - t_prior
    prior_full = np.asarray(est.envmap, np.float32)
    h = cfg.env_height
    m = bundle.manifest
    hold = None
    if sky is None:
        sky_stats_obs = {"enabled": False, "why": "no sky dome"}
    elif not cfg.sky_evidence.enabled:
        sky_stats_obs = {"enabled": False, "why": "sky_evidence.enabled is false"}
    else:
        masks = [(f.sky if f.sky is not None else f.gbuf["opacity"].reshape(-1) < 0.5).reshape(
            f.camera.height, f.camera.width).numpy() for f in frames]
        rad_obs, w_obs, floor_obs, sky_stats_obs = observed_sky(sky, [f.camera for f in frames], masks, height=h,
                                                     exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                                                     settings=cfg.sky_evidence)
        ev = SkyEvidence.from_observed(rad_obs, w_obs, floor_obs)
        if not ev.empty:
            hold = ev
            ev.save(out / "sky_evidence.npz")
            # the prior E_g holds the observed sky too (what the joint stage's log prior pulls to)
            log_p = torch.log(resample(torch.from_numpy(prior_full).double(), h, 2 * h).clamp_min(LOG_RADIANCE_FLOOR))
            prior_full = resample(torch.exp(ev.hold(log_p)), 512, 1024).numpy().astype(np.float32)
    prior_full, gains = _prior_gains(frames, prior_full, est, hold, bundle, cfg, search_sun)
    sun_floor_stats = {"enabled": False}
    if cfg.sun_floor > 0 and est.sun_source != "none":
        hold, sun_floor_stats = _sun_floor(hold, prior_full, est.sun_dir, h, cfg)
        hold.save(out / "sky_evidence.npz")
    prior_t = resample(torch.from_numpy(prior_full).double(), h, 2 * h)
    env = EnvironmentMap(prior_t, log_space=True, requires_grad=True)
    log_prior = env.param.detach().clone()
    fine = env.param  # the per-texel log-radiance residual is the map's own leaf
    hc = cfg.coarse_height
    coarse = torch.zeros(hc, 2 * hc, 3, dtype=log_prior.dtype, requires_grad=True) if hc else None

    def compose() -> None:
        """Set the map's log radiance to ``fine + up(coarse)``, the observed sky held (a graph
        node when coarse or the sky evidence is on)."""
        if coarse is None and hold is None:
            return
        p = fine
        if coarse is not None:
            p = p + torch.nn.functional.interpolate(coarse.permute(2, 0, 1)[None], size=(h, 2 * h), mode="bilinear",
                                                    align_corners=False)[0].permute(1, 2, 0)
        env.param = hold.hold(p) if hold is not None else p
    ps = cfg.pbr_settings(rays_per_pixel=cfg.rays_per_pixel, exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                          threads=cfg.threads, seed=cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    eval_idx = []
    for f in frames:
        n = f.nonsky.numel()
        k = min(cfg.eval_pixels, n)
        eval_idx.append(f.nonsky[torch.randperm(n, generator=gen)[:k]] if n else f.nonsky)

    def evaluate(e) -> float:
        preds, tgts = [], []
        with torch.no_grad():
            for f, idx in zip(frames, eval_idx):
                if idx.numel():
                    preds.append(_render(f, e, ps, idx, torch.Generator().manual_seed(cfg.seed + 1)))
                    tgts.append(f.target[idx])
        if not preds:
            raise ConfigError("bundle: the reconstruction covers no non-sky pixel of the training frames")
        return _psnr(torch.cat(preds), torch.cat(tgts))

    psnr_before = evaluate(env)
    groups = [{"params": [fine], "lr": cfg.lr}] + ([{"params": [coarse], "lr": cfg.coarse_lr}] if hc else [])
    opt = torch.optim.Adam(groups)
    history = []
    stopped_at = None
    usable = [i for i, f in enumerate(frames) if f.nonsky.numel()]
    start = 0
    state_file = Path(resume_dir) / "state.pt" if resume_dir is not None else None
    if state_file is not None and state_file.is_file():
        try:
            st = torch.load(state_file, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - a corrupt state is reported, never silently reset
            raise FormatError(f"{state_file}: unreadable PBR-stage state ({exc})") from exc
        with torch.no_grad():
            fine.copy_(st["fine"] if "fine" in st else st["env"])
            if coarse is not None and "coarse" in st:
                coarse.copy_(st["coarse"])
        opt.load_state_dict(st["opt"])
        gen.set_state(st["gen"])
        history, start = st["history"], int(st["iteration"])
    for it in range(start, cfg.iterations):
        f = frames[usable[int(torch.randint(len(usable), (1,), generator=gen))]]
        n = f.nonsky.numel()
        idx = f.nonsky[torch.randperm(n, generator=gen)[:min(cfg.pixels, n)]]
        frac = it / max(cfg.iterations - 1, 1)
        lam = cfg.lambda_e_start + (cfg.lambda_e_end - cfg.lambda_e_start) * frac
        compose()
        env.rebuild_sampler()
        pred = _render(f, env, ps, idx, gen)
        photo = (pred - f.target[idx].to(pred.dtype)).abs().mean()
        prior = (env.param - log_prior).abs().mean()
        loss = photo + lam * prior
        if not torch.isfinite(loss):
            raise NumericalError(f"PBR stage: non-finite loss at step {it} (photometric {float(photo)}, "
                                 f"prior {float(prior)})")
        opt.zero_grad()
        loss.backward()
        opt.step()
        rec = {"step": it + 1, "loss": float(loss.detach()), "photo": float(photo.detach()),
               "prior": float(prior.detach()), "lambda_e": lam}
        history.append(rec)
        if state_file is not None and checkpoint_every and (it + 1) % checkpoint_every == 0:
            state_file.parent.mkdir(parents=True, exist_ok=True)

            with atomic_output(state_file) as tmp:
                torch.save({"iteration": it + 1, "env": env.param.detach().clone(), "fine": fine.detach().clone(),
                            **({"coarse": coarse.detach().clone()} if coarse is not None else {}),
                            "opt": opt.state_dict(), "gen": gen.get_state(), "history": history}, tmp)
        if on_progress is not None:
            on_progress(it + 1, cfg.iterations, rec)
        k = cfg.early_stop_every
        if k and (it + 1) % k == 0 and it + 1 < cfg.iterations:
            windows = [float(np.mean([h["photo"] for h in history[j:j + k]])) for j in range(0, it + 1 - k + 1, k)]
            if stalled(windows, cfg.early_stop_patience, cfg.early_stop_min_delta, higher_is_better=False,
                       relative=True):
                stopped_at = it + 1
                fired.append({"skip": "early_stop", "why": f"the photometric L1 of the last "
                              f"{cfg.early_stop_patience} windows of {k} steps did not improve by "
                              f"{cfg.early_stop_min_delta:.0%} on the best before them "
                              f"({', '.join(f'{w:.4f}' for w in windows[-cfg.early_stop_patience - 1:])}): "
                              f"stopped after {stopped_at} of {cfg.iterations} steps",
                              "stopped_at": stopped_at})
                break
    with torch.no_grad():
        compose()
        env.param = env.param.detach()
    env.rebuild_sampler()
    with torch.no_grad():
        fitted = env.radiance_map().detach()
    psnr_after = evaluate(env)
    fitted_full = resample(fitted.double(), 512, 1024).numpy().astype(np.float32)
    if not np.isfinite(fitted_full).all():
        raise NumericalError("PBR stage: the fitted environment map is not finite")
    write_envmap(out / "envmap.exr", fitted_full)
    write_envmap(out / "envmap_prior.exr", prior_full)
    rows = [_ldr_map(prior_full), _ldr_map(fitted_full)]
    summary = {"config": asdict(cfg), "frames": len(frames), "iterations": cfg.iterations,
               "iterations_run": len(history), "early_stopped_at": stopped_at, "sun_search": search_sun,
               "capture_sky": {"sunless": sunless, **sky_stats}, "skips_fired": fired,
               "photometric_psnr_prior": psnr_before, "photometric_psnr_fitted": psnr_after,
               "sun_source": est.sun_source, "sun_dir_prior": [float(x) for x in est.sun_dir],
               "sun_model": est.diagnostics.get("sun_model"),
               "transport_search": est.diagnostics.get("transport_search"),
               "sky_evidence": sky_stats_obs, "prior_gains": gains, "sun_floor": sun_floor_stats, "wall_heights": walls,
               "history": history, "resumed_from_iteration": start,
               "seconds": {"gbuffers": t_frames, "prior": t_prior, "total": time.perf_counter() - t0}}
    sep = np.full((4, 1024, 3), 255, np.uint8)
    strip = np.concatenate([x for r in rows for x in (r, sep)][:-1])
    write_png(out / "preview.png", strip[::2, ::2])
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def run_stage(ctx) -> dict:
    """The chain's entry point: the latest scene graph before this stage, frozen; the lighting
    fitted into ``<run>/pbr/``."""
    cfg: PBRStageConfig = ctx.settings
    graph, sky, graph_stage = ctx.run.load_scene(before=ctx.name)
    occ = (ctx.run.summary(graph_stage) or {}).get("settings", {}).get("occluders")
    try:
        occ_settings = OccluderSettings(**occ) if isinstance(occ, dict) else None
    except (TypeError, ConfigError):  # a summary of an older build: no hypotheses
        occ_settings = None
    total = cfg.iterations
    bar = None
    if ctx.progress:
        bar = tqdm(total=total, desc="pbr", unit="it")

    def report(it, n, rec):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{rec['loss']:.4f}")
        if ctx.on_progress is not None:
            ctx.on_progress(it, n, rec)

    try:
        summary = fit_lighting(graph, ctx.bundle, ctx.out_dir, cfg, on_progress=report, resume_dir=ctx.resume_dir,
                               checkpoint_every=max(1, total // 10), sky=sky, occluder_settings=occ_settings)
        shutil.rmtree(ctx.resume_dir, ignore_errors=True)  # done: the resume state is not needed
    finally:
        if bar is not None:
            bar.close()
    summary["graph_stage"] = graph_stage
    summary["timings"] = summary.pop("seconds")
    summary["seconds"] = round(summary["timings"]["total"], 2)
    return summary


__all__ = ["PBRStageConfig", "fit_lighting", "run_stage"]
