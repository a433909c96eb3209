"""Evaluation of a reconstruction against a bundle's ground truth (the paper's metrics).

``brdf evaluate RUN``. It lives in :mod:`core.synth`, the one package that reads ground truth (the
generator, and what measures or trains against its ground truth); the product path (the stages,
relight, night, the service) never imports it (an import-linter contract). Metrics, on the
bundle's **test** trajectory (novel views):

* intrinsics on non-sky pixels (ground-truth depth > 0): albedo si-PSNR (per-channel
  least-squares scale), roughness and metallic RMSE, normal mean angular error (degrees), from the
  reconstruction's rasterized G-buffers divided by the opacity;
* novel views: the volume pass with the reconstruction's sky (PSNR, SSIM, FLIP) against the
  test frames;
* re-render: the PBR pass under the recovered lighting against the test frames (PSNR, SSIM);
* relighting: the PBR pass under each held-back HDRI of the bundle against the Mitsuba relit
  frames, tone-mapped with the bundle's exposure and gamma (PSNR, SSIM, FLIP);
* sun direction error between the brightest direction of the recovered map and of the true map.

Rendered PBR frames go through the same denoiser a relight request uses by default.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from core.bundle import open_bundle
from core.camera import Camera
from core.errors import ConfigError
from core.io.envmap_file import read_envmap
from core.lighting.prior import brightest_direction, sun_direction_error_deg
from core.metrics import angular_error_deg, psnr, si_psnr, ssim
from core.numerics import OPACITY_EPS
from core.pbr.envmap import resample
from core.pbr.render import PRODUCT_DIFFUSE, PRODUCT_INDIRECT_SPECULAR_RAYS, PRODUCT_MASKING, PRODUCT_OPAQUE_ABOVE
from core.raster import RasterSettings, rasterize_gaussians
from core.render.scenario import Scenario, render_scenario, scene_corrector, views_from_frames
from core.stages.chain import RunDir
from core.tonemap import hdr_to_ldr


@dataclass(frozen=True)
class EvalSettings:
    """How the evaluation renders."""

    rays_per_pixel: int = 64
    """PBR rays per pixel of the re-render and relit frames."""
    denoiser: str = "oidn"
    """Denoiser of the PBR frames (``none``, ``oidn``, ``diffusion``), as a relight request."""
    max_frames: int = 0
    """Test frames evaluated (evenly spaced; 0 = all). Relighting uses the frames the bundle has
    relit ground truth for."""
    threads: int = 2
    """CPU threads."""
    flip: bool = True
    """Compute FLIP (flip-evaluator); off saves ~0.1 s per frame."""
    normal_offset_m: float = 0.1
    """Shadow-ray start offset along the normal, metres (:attr:`core.render.scenario.Scenario.normal_offset_m`)."""
    shadow_t_min_m: float = 0.5
    """Shadow rays ignore Gaussians this close, metres (:attr:`core.render.scenario.Scenario.shadow_t_min_m`)."""
    indirect_bounces: int = 2
    """Indirect light of the PBR renders: the approximate diffuse bounces
    (:attr:`core.pbr.render.PBRSettings.indirect_bounces`; 0 = direct light only, the paper)."""
    indirect_specular_rays: int = PRODUCT_INDIRECT_SPECULAR_RAYS
    """GGX shadow rays per pixel of the specular bounce
    (:attr:`core.render.scenario.Scenario.indirect_specular_rays`)."""
    diffuse: str = PRODUCT_DIFFUSE
    """The BRDF's diffuse lobe of the PBR renders (:attr:`core.render.scenario.Scenario.diffuse`)."""
    masking: str = PRODUCT_MASKING
    """The BRDF's masking term of the PBR renders (:attr:`core.render.scenario.Scenario.masking`)."""
    opaque_above: float = PRODUCT_OPAQUE_ABOVE
    """Surface pixels of the PBR renders (:attr:`core.render.scenario.Scenario.opaque_above`)."""
    object_solids: bool = True
    """Shadow rays meet the tracked objects' filled insides
    (:attr:`core.render.scenario.Scenario.object_solids`)."""
    corrector: bool = True
    """Apply the run's scene corrector (the ``corrector`` stage) where a relight request would: to
    the re-render under the recovered map (the light it was fitted under), not to the relit frames
    under held-back maps (:func:`core.render.scenario._corrector_gate`); False: the denoised PBR
    frames as they are."""
    object_shadow_t_min_m: float = 0.05
    """The same for objects an edit placed (:attr:`core.render.scenario.Scenario.object_shadow_t_min_m`;
    the evaluation renders no edits, so only a request that passes edits sees it)."""


def _flip(ref: np.ndarray, test: np.ndarray) -> float:
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(ref, np.float32),
                                         np.ascontiguousarray(test, np.float32), "LDR", applyMagma=False)
    return float(mean)


def _img_metrics(pred: np.ndarray, ref: np.ndarray, with_flip: bool) -> dict:
    p, r = torch.from_numpy(np.clip(pred, 0, 1)).float(), torch.from_numpy(np.clip(ref, 0, 1)).float()
    out = {"psnr": float(psnr(p, r)), "ssim": float(ssim(p, r))}
    if with_flip:
        out["flip"] = _flip(ref, pred)
    return out


def _mean(rows: list[dict]) -> dict:
    keys = {k for r in rows for k in r}
    return {k: float(np.mean([r[k] for r in rows if k in r])) for k in sorted(keys)}


def relit_reference_ldr(bundle, relit_name: str, frame_id: str) -> np.ndarray:
    """The Mitsuba reference of frame ``frame_id`` under the held-back map ``relit_name``,
    tone-mapped with the bundle's exposure and gamma: [H, W, 3] in [0, 1]."""
    m = bundle.manifest
    return hdr_to_ldr(bundle.load_relit_frame(relit_name, frame_id), m.ldr_exposure, m.ldr_gamma)


def frame_intrinsics(r, gt_layers: dict, height: int, width: int) -> dict:
    """The intrinsics metrics of one rasterized frame ``r`` (:func:`core.raster.rasterize_gaussians`
    output, premultiplied layers divided by its opacity) against the bundle's ground-truth layers
    of the frame, on non-sky pixels (true depth > 0): albedo si-PSNR, normal MAE (degrees),
    roughness and metallic RMSE."""
    mask = torch.from_numpy(gt_layers["depth"].reshape(height, width) > 0)
    inv = 1.0 / r.opacity.clamp_min(OPACITY_EPS)
    row = {"albedo_si_psnr": float(si_psnr((r.albedo * inv).clamp(0, 1).float()[None],
                                           torch.from_numpy(gt_layers["albedo"])[None], mask[None])),
           "normal_mae_deg": float(angular_error_deg(r.normal.float()[None], torch.from_numpy(gt_layers["normal"])[None],
                                                     mask[None]))}
    for k in ("roughness", "metallic"):
        e = ((getattr(r, k) * inv).clamp(0, 1)[..., 0].float() - torch.from_numpy(gt_layers[k]).reshape(mask.shape))[mask]
        row[f"{k}_rmse"] = float(torch.sqrt((e ** 2).mean())) if e.numel() else float("nan")
    return row


def render_pbr_frames(graph, bundle, env_map: np.ndarray, frames, settings: EvalSettings,
                      views: dict | None = None, corrector=None) -> list[np.ndarray]:
    """LDR frames ``[H, W, 3]`` in [0, 1] of ``graph`` lit by ``env_map`` (``[H, 2H, 3]`` linear)
    at the views of the bundle's ``frames``, through the path of a relight request
    (:func:`core.render.scenario.render_scenario`, denoiser included) with ``settings``.
    ``views``: the bundle's views by frame id (default: made from the bundle); ``corrector``:
    the run's scene corrector (:func:`core.render.scenario.scene_corrector`) or None."""
    s = settings
    views = views if views is not None else {v.name: v for v in views_from_frames(bundle, "all")}
    m = bundle.manifest
    sc = Scenario(views=tuple(views[f.id] for f in frames), envmap=np.asarray(env_map, np.float32),
                  base_exposure=m.ldr_exposure, gamma=m.ldr_gamma, rays_per_pixel=s.rays_per_pixel,
                  denoiser=s.denoiser, denoiser_fallback=None, normal_offset_m=s.normal_offset_m,
                  shadow_t_min_m=s.shadow_t_min_m, object_shadow_t_min_m=s.object_shadow_t_min_m,
                  indirect_bounces=s.indirect_bounces, indirect_specular_rays=s.indirect_specular_rays,
                  diffuse=s.diffuse, masking=s.masking,
                  opaque_above=s.opaque_above, object_solids=s.object_solids,
                  outputs=("png",), corrector=corrector)
    with tempfile.TemporaryDirectory(prefix="brdf-eval-") as tmp:
        r = render_scenario(graph, sc, tmp)
    return list(r.result.frames)


def evaluate_run(run_dir: str | Path, bundle=None, settings: EvalSettings | None = None, *,
                 out: str | Path | None = None, on_step: Callable[[str], None] | None = None) -> dict:
    """Evaluate the reconstruction in ``run_dir`` (a :mod:`core.stages.chain` run) on ``bundle``
    (default: the run's own scene). Writes ``evaluation.json`` into ``out`` (default the run
    directory) and returns it. Raises ConfigError when the bundle has no ground truth or the run
    has no reconstructed scene graph."""
    s = settings or EvalSettings()
    run = RunDir(run_dir)
    b = bundle if bundle is not None else open_bundle(run.scene_path())
    gt = b.manifest.ground_truth
    if gt is None:
        raise ConfigError(f"bundle {b.name!r}: has no ground truth to evaluate against")
    graph, sky, graph_stage = run.load_scene()
    env_path, env_stage = run.latest_envmap()
    note = on_step or (lambda _m: None)
    test = sorted(b.frames("test"), key=lambda f: (f.time_index, f.id))
    if not test:
        raise ConfigError(f"bundle {b.name!r}: has no test frames")
    if s.max_frames and len(test) > s.max_frames:
        pick = np.unique(np.linspace(0, len(test) - 1, s.max_frames).round().astype(int))
        test = [test[i] for i in pick]
    times = b.manifest.times
    rs = RasterSettings(threads=s.threads)
    res: dict = {"scene": b.name, "run": str(run.root), "graph_stage": graph_stage, "envmap_stage": env_stage,
                 "frames": [f.id for f in test], "settings": s.__dict__}
    t0 = time.perf_counter()
    # -- intrinsics and novel views -----------------------------------------------------------
    intr, nvs = [], []
    with torch.no_grad():
        for f in test:
            c = b.camera(f)
            g = graph.compose(float(times[f.time_index])).detach()
            cam = Camera.from_bundle(c, f)
            r = rasterize_gaussians(g, cam, settings=rs)
            dirs = torch.from_numpy(cam.ray_directions()).to(g.dtype)
            rgb = r.color + (1 - r.opacity) * sky(dirs).to(g.dtype)
            img = b.load_image(f)
            nvs.append(_img_metrics(rgb.float().numpy(), img, s.flip))
            intr.append(frame_intrinsics(r, b.load_ground_truth(f), c.height, c.width))
    note("intrinsics and novel views")
    res["intrinsics"] = _mean(intr)
    res["nvs"] = _mean(nvs)

    # -- PBR renders: re-render under the recovered map, relight under held-back maps ----------
    # through the same path as a relight request (core.render.scenario), denoiser included

    all_views = {v.name: v for v in views_from_frames(b, "all")}
    corrector, res["corrector"] = (scene_corrector(run) if s.corrector
                                   else (None, "off (EvalSettings.corrector = False)"))

    def pbr_clip(env_map: np.ndarray, frames) -> list[np.ndarray]:
        return render_pbr_frames(graph, b, env_map, frames, s, views=all_views, corrector=corrector)

    if env_path is not None:
        env_rec = read_envmap(env_path)
        frames_rr = pbr_clip(env_rec, test)
        res["rerender"] = _mean([_img_metrics(p, b.load_image(f), False) for p, f in zip(frames_rr, test)])
        gt_env = b.load_envmap()
        gt_full = resample(torch.from_numpy(np.asarray(gt_env, np.float64)), 512, 1024).numpy()
        rec_full = resample(torch.from_numpy(np.asarray(env_rec, np.float64)), 512, 1024).numpy()
        res["sun_error_deg"] = float(sun_direction_error_deg(brightest_direction(rec_full), brightest_direction(gt_full)))
        note("re-render")
    relit = {}
    unrelit = []
    for rl in gt.relit:
        frames = [f for f in b.frames("test") if f.id in rl.frames]
        if not frames:
            continue
        preds = pbr_clip(b.load_envmap(rl.name), frames)
        rows = []
        for p, f in zip(preds, frames):
            ref = relit_reference_ldr(b, rl.name, f.id)
            rows.append(_img_metrics(p, ref, s.flip))
            unrelit.append(_img_metrics(b.load_image(f), ref, False)["ssim"])
        relit[rl.name] = _mean(rows)
        note(f"relight {rl.name}")
    if relit:
        res["relight"] = {"per_map": relit, **_mean(list(relit.values()))}
        res["relight_unrelit_input_ssim"] = float(np.mean(unrelit))
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["summary"] = summary_row(res)
    target = Path(out) if out is not None else run.root
    target.mkdir(parents=True, exist_ok=True)
    (target / "evaluation.json").write_text(json.dumps(res, indent=1))
    return res


def summary_row(res: dict) -> dict:
    """The flat keys of ``benchmarks/results/eval.json`` from one evaluation."""
    i, n = res.get("intrinsics", {}), res.get("nvs", {})
    rl = res.get("relight", {})
    row = {"albedo_si_psnr": i.get("albedo_si_psnr"), "roughness_rmse": i.get("roughness_rmse"),
           "metallic_rmse": i.get("metallic_rmse"), "normal_mae_deg": i.get("normal_mae_deg"),
           "nvs_psnr": n.get("psnr"), "nvs_ssim": n.get("ssim"), "nvs_flip": n.get("flip"),
           "rerender_psnr": res.get("rerender", {}).get("psnr"),
           "relight_psnr": rl.get("psnr"), "relight_ssim": rl.get("ssim"), "relight_flip": rl.get("flip"),
           "relight_unrelit_input_ssim": res.get("relight_unrelit_input_ssim"),
           "sun_error_deg": res.get("sun_error_deg")}
    return {k: (round(v, 4) if isinstance(v, float) and math.isfinite(v) else v) for k, v in row.items()}


__all__ = ["EvalSettings", "evaluate_run", "frame_intrinsics", "render_pbr_frames", "summary_row"]
