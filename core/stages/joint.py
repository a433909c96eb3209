"""The joint refinement stage (paper Sec. 3.3 (d); supplement "Implementation Details").

Geometry, material and lighting move together under

    L_all = L_vol + lambda_pbr L_pbr,      lambda_pbr = 0.1

with ``L_vol`` the volume stage's Eq. 4 at the supplement's joint weights (``l_N = 0.3``,
``l_A = 0.4``, ``l_R = l_M = 0.1``) and ``L_pbr = |C_ldr - C_gt| + l_E sum |log E - log E_g|``
(Eq. 6) on a random subset of non-sky pixels per step: the PBR pass (torch backend, MIS) shades the
rasterized G-buffers of the frame, so its gradient reaches albedo, roughness, metallic and normals
of the Gaussians (through the rasterizer's backward) and the environment map. ``E_g`` is the PBR
stage's prior map; ``E`` starts from the PBR stage's fitted map.

Shadow rays are traced through the Gaussians of the start of the stage (the BVH is built once per
frame and not rebuilt while the Gaussians move a little: visibility has no gradient in this
project, as in the PBR stage).

Outputs (``<run>/joint/``): ``checkpoint/scene_graph.pt``, ``checkpoint/sky.pt``,
``envmap.exr``, ``summary.json``; the resume state in ``resume/``.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from core.errors import ConfigError, FormatError, NumericalError
from core.io.envmap_file import read_envmap, write_envmap
from core.lighting.sky_evidence import SkyEvidence
from core.metrics import ssim
from core.numerics import LOG_RADIANCE_FLOOR
from core.pbr.envmap import EnvironmentMap, resample
from core.pbr.render import render_pbr
from core.pbr.visibility import GaussianTracer
from core.raster import RasterSettings
from core.scene_graph import SceneGraph
from core.stages.early_stop import stalled
from core.stages.pbr_settings import StageShading
from core.stages.volume import (VolumeModel, _bce, _prior_tensors, _views, alignment_loss, attribute_prior_losses,
                                lidar_depth_loss, prior_losses)
from core.train.optim import GaussianAdam, GaussianLR


@dataclass(frozen=True)
class JointSettings(StageShading):
    """Settings of the joint refinement stage."""

    iterations: int = 300
    """Optimisation steps (one training frame each)."""
    pixels: int = 4096
    """Random non-sky pixels of the PBR term per step (the paper: 2048; see ``lambda_pbr``)."""
    rays_per_pixel: int = 32
    """Rays per pixel of the PBR pass during the stage (the paper: 512). 16 -> 32 with
    ``lambda_pbr`` 3.0 on 4096 pixels, development scenes at quick (joint re-run on the same pbr
    stage; ``benchmarks/results/joint_weight.json``): relit 21.43 -> 21.49 / 21.92 -> 21.97 /
    22.63 -> 22.66 dB (default, dev1, dev2), re-render 21.68 -> 21.88 / 20.48 -> 21.37 /
    23.66 -> 23.87 dB, relit FLIP within 0.002; the stage 49 -> 49-56 s."""
    lambda_pbr: float = 3.0
    """Weight of L_pbr against L_vol (supplement: 0.1, kept by the ``paper`` profile with its
    2048 pixels and 20k steps). At 0.1 with 1024 pixels a short stage barely moves the materials:
    the dense albedo prior outweighs the sparse photometric term, and the inverse model's albedo
    of a sunlit white wall (0.72) stays near 0.46, so relit bright walls came out 0.53-0.65 of
    Mitsuba's. Chosen on the development scenes at quick (the same pbr stage, joint re-run;
    ``benchmarks/results/joint_weight.json``): 0.1 / 1024 px -> 3.0 / 4096 px relit 20.97 ->
    21.43 dB (default scene), 21.92 -> 21.92 (dev1), 22.59 -> 22.63 (dev2), re-render
    19.96 -> 21.68, 19.21 -> 20.48, 21.88 -> 23.66 dB, NVS within 0.07 dB, relit FLIP
    0.008-0.023 worse; 10.0 gave the same relight with normals 0.4-0.6 deg worse."""
    lambda_e: float = 0.1
    """Weight of the log-space lighting prior inside L_pbr (the PBR stage's final value)."""
    lambda_ssim: float = 0.2
    """Weight of (1 - SSIM) against L1 in L_rgb."""
    lambda_opacity: float = 0.05
    """Weight of the opacity-vs-sky BCE (supplement: 0.05)."""
    lambda_depth: float = 0.01
    """Weight of the LiDAR depth term (supplement: 0.01)."""
    lambda_prior_depth: float = 0.01
    """Weight of the prior depth term, aligned per frame by a closed-form scale and shift
    (supplement: 0.01, as the LiDAR term; 0 with the other prior weights = no generative priors)."""
    lambda_normal: float = 0.3
    """Weight of the normal prior term (supplement, joint stage: 0.3)."""
    lambda_albedo: float = 0.4
    """Weight of the albedo prior term (supplement, joint stage: 0.4)."""
    lambda_roughness: float = 0.1
    """Weight of the roughness prior term (supplement, joint stage: 0.1)."""
    lambda_metallic: float = 0.1
    """Weight of the metallic prior term (supplement, joint stage: 0.1). 1.0 and 3.0 tried on
    the development scenes at quick (``benchmarks/results/joint_metallic.json``): metallic RMSE
    0.110 -> 0.107 / 0.106 on the default scene, 0.131 -> 0.133 / 0.133 on dev2, relight within
    0.04 dB: not kept."""
    lambda_align: float = 0.1
    """Weight of the disk-normal alignment (:func:`core.stages.volume.alignment_loss`)."""
    priors_move_geometry: bool = True
    """The normal and material prior terms move the geometry too (True, as the volume stages did
    before) or only the attributes they supervise (False: a second render with the geometry
    detached, :attr:`core.stages.volume.VolumeSettings.priors_move_geometry`). Kept True: measured
    at quick from the same pbr stage, False gave relit +0.05 dB on dev1 and +0.06 on the default
    scene (within run-to-run spread) with normals 0.2-0.3 deg worse on both."""
    lr_scale: float = 0.3
    """Learning rates of the Gaussians relative to the volume stage's (a refinement)."""
    env_lr: float = 0.01
    """Adam learning rate of the log-radiance map."""
    max_frames: int = 24
    """Training frames used (evenly spaced; their shadow BVHs are built once)."""
    threads: int = 2
    """CPU threads of the rasterizer and the shadow rays."""
    torch_threads: int = 1
    """Intra-op torch threads (see :class:`core.stages.volume.VolumeSettings`)."""
    seed: int = 0
    """Seed of the frame order, the pixel subsets and the ray samples."""
    early_stop_every: int = 0
    """Skip: stop once the loss stops improving: every this many steps the mean loss of those
    steps (fresh frames and pixels every step) is compared with the best window so far; after
    ``early_stop_patience`` windows without a relative gain of ``early_stop_min_delta`` the stage
    stops and its summary's ``skips_fired`` says so (:func:`core.stages.early_stop.stalled`).
    0 = off, the default: not within noise (``benchmarks/bench_skips.py``, 6 tiny streets, 100
    steps, a window of 5: fired on 5, 4.7 +- 0.4 s saved there, relight PSNR -0.07 +- 0.03 dB)."""
    early_stop_patience: int = 2
    """Windows without improvement before the stage stops."""
    early_stop_min_delta: float = 0.01
    """Relative gain of the window's mean loss that counts (0.01 = 1%)."""

    def __post_init__(self) -> None:
        bad = [n for n, ok in (("iterations", self.iterations >= 0), ("pixels", self.pixels >= 1),
                               ("early_stop_every", self.early_stop_every >= 0),
                               ("early_stop_patience", self.early_stop_patience >= 1),
                               ("early_stop_min_delta", 0 <= self.early_stop_min_delta < 1),
                               ("rays_per_pixel", self.rays_per_pixel >= 1), ("lambda_pbr", self.lambda_pbr >= 0),
                               ("lr_scale", self.lr_scale > 0), ("env_lr", self.env_lr > 0),
                               ("max_frames", self.max_frames >= 1), ("threads", self.threads >= 1)) if not ok]
        bad += self.shading_errors()
        if bad:
            raise ConfigError(f"JointSettings: out of range: {', '.join(bad)} ({self})")


def _scaled_lr(scale: float):
    base = GaussianLR()
    return GaussianLR(**{k: v * scale for k, v in asdict(base).items()})


def run_stage(ctx) -> dict:
    """Run the joint refinement on the latest scene graph, sky, environment map and priors of
    the run (see the module docstring)."""
    cfg: JointSettings = ctx.settings
    b = ctx.bundle
    run = ctx.run
    t0 = time.perf_counter()
    graph, sky, graph_stage = run.load_scene(before=ctx.name)
    env_path, env_stage = run.latest_envmap(before=ctx.name)
    if env_path is None:
        raise ConfigError(f"stage 'joint': needs the pbr stage's envmap.exr in {run.root}")
    prior_env = env_path.parent / "envmap_prior.exr"
    priors, prior_source = run.latest_priors(b, ctx.name, threads=cfg.threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    try:
        train = _views(b, "train", with_lidar=True)
        if not train:
            raise ConfigError("bundle: has no train frames")
        order = sorted(range(len(train)), key=lambda i: (train[i].time, train[i].frame_id))
        pick = np.unique(np.linspace(0, len(order) - 1, min(cfg.max_frames, len(order))).round().astype(int))
        train = [train[order[i]] for i in pick]
        pri = _prior_tensors(priors, train)
        for v in train:
            if v.nonsky is None and v.frame_id in pri:
                v.nonsky = pri[v.frame_id]["mask"].to(torch.float32)[..., None]
        ck = ctx.resume_dir
        state = None
        start_graph = graph  # the stage's input: its shadow rays, also after a resume
        if (ck / "state.pt").is_file():
            try:
                state = torch.load(ck / "state.pt", map_location="cpu", weights_only=True)
            except Exception as exc:  # noqa: BLE001 - a corrupt state is reported, never silently reset
                raise FormatError(f"{ck / 'state.pt'}: unreadable joint-stage state ({exc})") from exc

            graph = SceneGraph.load(ck / state["graph_file"])
            sky.load_state_dict(state["sky"])
        model = VolumeModel(graph, sky)
        # shadow BVHs of the start of the stage (its input, also when resumed, so a resumed run
        # traces what an uninterrupted one does): static once, moving nodes per frame
        static = start_graph._static_part().detach()
        ts = cfg.trace_settings()
        shadow = start_graph.shadow_static()  # the static part plus the completed facades (core.stages.occluders)
        static_tracer = GaussianTracer.from_gaussians(shadow, ts) if shadow.num else None
        tracers = {}
        for v in train:
            g = start_graph.compose(v.time).detach()
            tr = [static_tracer] if static_tracer is not None else []
            if g.num > static.num:
                tr.append(GaussianTracer.from_gaussians(g.index(slice(static.num, None)), ts))
            tracers[v.frame_id] = tr
        env_full = read_envmap(env_path)
        h = 128
        env_init = resample(torch.from_numpy(np.asarray(env_full, np.float64)), h, 2 * h)
        env = EnvironmentMap(env_init, log_space=True, requires_grad=True)
        if prior_env.is_file():
            prior_t = resample(torch.from_numpy(np.asarray(read_envmap(prior_env), np.float64)), h, 2 * h)
            log_prior = EnvironmentMap(prior_t, log_space=True).param.detach().clone()
        else:
            log_prior = env.param.detach().clone()
        if state is not None:
            with torch.no_grad():
                env.param.copy_(state["env"])
            env.rebuild_sampler()
        env_leaf = env.param  # the optimised log radiance; the observed sky is held over it
        ev_file = env_path.parent / "sky_evidence.npz"
        ev_full = SkyEvidence.load(ev_file) if ev_file.is_file() else None
        ev_low = ev_full.at(h) if ev_full is not None else None

        def compose_env() -> None:
            if ev_low is not None:
                env.param = ev_low.hold(env_leaf)
        m = b.manifest
        ps = cfg.pbr_settings(rays_per_pixel=cfg.rays_per_pixel, exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                              threads=cfg.threads, seed=cfg.seed)
        rs = RasterSettings(threads=cfg.threads)
        lr = _scaled_lr(cfg.lr_scale)
        opts = [GaussianAdam(g, lr) for g in model.containers()]
        sky_opt = torch.optim.Adam(model.sky.parameters(), lr=0.01)
        env_opt = torch.optim.Adam([env_leaf], lr=cfg.env_lr)
        history: list[dict] = []
        start = 1
        stopped_at, fired = None, []
        if state is not None:
            for o, st in zip(opts, state["opt"]):
                o.m, o.v, o.step_count = st["m"], st["v"], st["step"]
            sky_opt.load_state_dict(state["sky_opt"])
            env_opt.load_state_dict(state["env_opt"])
            rng.bit_generator.state = state["rng"]
            gen.set_state(state["gen"])
            history = state["history"]
            start = int(state["iteration"]) + 1
        weights = {"normal": cfg.lambda_normal, "albedo": cfg.lambda_albedo, "roughness": cfg.lambda_roughness,
                   "metallic": cfg.lambda_metallic, "depth": cfg.lambda_prior_depth}
        bar = tqdm(range(start, cfg.iterations + 1), desc="joint", unit="it", disable=not ctx.progress,
                   initial=start - 1, total=cfg.iterations)
        every = max(1, cfg.iterations // 10)
        for it in bar:
            v = train[int(rng.integers(len(train)))]
            for o in opts:
                o.zero_grad()
            sky_opt.zero_grad()
            env_opt.zero_grad()
            rgb, out, world, _spans = model.render(v, rs)
            l1 = (rgb - v.image).abs().mean()
            l_vol = (1 - cfg.lambda_ssim) * l1 + cfg.lambda_ssim * (1 - ssim(rgb, v.image))
            if v.nonsky is not None and cfg.lambda_opacity > 0:
                l_vol = l_vol + cfg.lambda_opacity * _bce(out.opacity, v.nonsky)
            if v.lidar_px is not None and cfg.lambda_depth > 0 and len(v.lidar_px):
                l_vol = l_vol + cfg.lambda_depth * lidar_depth_loss(out, v.lidar_px, v.lidar_z)
            terms = {}
            if cfg.lambda_align > 0:
                terms["align"] = alignment_loss(world)
                l_vol = l_vol + cfg.lambda_align * terms["align"]
            if v.frame_id in pri:
                terms.update(prior_losses(out, pri[v.frame_id], 0.5))
                if not cfg.priors_move_geometry:  # as in the volume stages (VolumeSettings)
                    terms.update(attribute_prior_losses(world, v.camera, rs, pri[v.frame_id], 0.5))
                for k, w in weights.items():
                    if w > 0:
                        l_vol = l_vol + w * terms[k]
            # PBR term on random non-sky pixels
            ok = out.opacity.detach().reshape(-1) >= 0.5
            if v.nonsky is not None:
                ok &= v.nonsky.reshape(-1) > 0.5
            cand = torch.nonzero(ok).reshape(-1)
            photo = prior = l_vol * 0
            if cand.numel():
                idx = cand[torch.randperm(cand.numel(), generator=gen)[:cfg.pixels]]
                compose_env()
                env.rebuild_sampler()
                res = render_pbr(out, v.camera, env, settings=ps, tracers=tracers[v.frame_id], pixels=idx, generator=gen)
                photo = (res.ldr.to(torch.float32) - v.image.reshape(-1, 3)[idx]).abs().mean()
                prior = (env.param - log_prior).abs().mean()
            l_pbr = photo + cfg.lambda_e * prior
            loss = l_vol + cfg.lambda_pbr * l_pbr
            if not torch.isfinite(loss):
                bad = [k for k, t in terms.items() if not torch.isfinite(t)]
                bad += [n for n, t in (("photometric", photo), ("lighting prior", prior)) if not torch.isfinite(t)]
                raise NumericalError(f"joint stage: non-finite loss at iteration {it} (term(s) {bad or ['rgb']}; "
                                     f"last good checkpoint kept in {ck})")
            loss.backward()
            for o in opts:
                o.step()
            sky_opt.step()
            env_opt.step()
            model.graph.invalidate()
            rec = {"it": it, "loss": float(loss.detach()), "l_vol": float(l_vol.detach()),
                   "l_pbr": float(l_pbr.detach()), "photo": float(photo.detach()),
                   "s": round(time.perf_counter() - t0, 2)}
            history.append(rec)
            bar.set_postfix(loss=f"{rec['loss']:.4f}", pbr=f"{rec['photo']:.4f}")
            if ctx.on_progress is not None:
                ctx.on_progress(it, cfg.iterations, rec)
            if it % every == 0 and it < cfg.iterations:
                _save_state(ck, it, model, opts, sky_opt, env_leaf, env_opt, rng, gen, history)
            k = cfg.early_stop_every
            if k and it % k == 0 and it < cfg.iterations:
                wins = [float(np.mean([h["loss"] for h in history[j:j + k]])) for j in range(0, len(history) - k + 1, k)]
                if stalled(wins, cfg.early_stop_patience, cfg.early_stop_min_delta, higher_is_better=False, relative=True):
                    stopped_at = it
                    fired.append({"skip": "early_stop", "stopped_at": it, "why": f"the mean loss of the last "
                                  f"{cfg.early_stop_patience} windows of {k} steps did not improve by "
                                  f"{cfg.early_stop_min_delta:.0%} on the best before them: stopped after {it} of "
                                  f"{cfg.iterations} steps"})
                    break
        bar.close()
        with torch.no_grad():
            compose_env()
            env.param = env.param.detach()
            fitted_t = resample(env.radiance_map().double(), 512, 1024)
            if ev_full is not None:  # the observed sky at its own resolution, not the stage's 128 rows
                fitted_t = torch.exp(ev_full.at(512).hold(torch.log(fitted_t.clamp_min(LOG_RADIANCE_FLOOR))))
            fitted = fitted_t.numpy().astype(np.float32)
        env.rebuild_sampler()
        if not np.isfinite(fitted).all():
            raise NumericalError("joint stage: the fitted environment map is not finite")
        out_dir = ctx.out_dir
        model.save(out_dir / "checkpoint", {"config": asdict(cfg)})
        write_envmap(out_dir / "envmap.exr", fitted)
        shutil.rmtree(ck, ignore_errors=True)
        n = sum(g.num for g in model.containers())
        return {"graph_stage": graph_stage, "envmap_stage": env_stage, "prior_source": prior_source,
                "iterations": cfg.iterations, "frames": len(train), "gaussians": n, "history": history,
                "resumed_from_iteration": start - 1, "seconds": round(time.perf_counter() - t0, 2),
                "iterations_run": stopped_at or cfg.iterations, "early_stopped_at": stopped_at, "skips_fired": fired}
    finally:
        torch.set_num_threads(old_threads)


def _save_state(ck: Path, it: int, model, opts, sky_opt, env_leaf, env_opt, rng, gen, history) -> None:
    """Scene graph of this iteration first, then the state file naming it (atomic), then older
    graphs removed: a crash at any point leaves a state that names a complete graph."""
    ck.mkdir(parents=True, exist_ok=True)
    gf = f"scene_graph.{it}.pt"
    model.graph.save(ck / gf)
    payload = {"iteration": it, "graph_file": gf, "sky": model.sky.state_dict(), "sky_opt": sky_opt.state_dict(),
               "env": env_leaf.detach().clone(), "env_opt": env_opt.state_dict(),
               "opt": [{"m": o.m, "v": o.v, "step": o.step_count} for o in opts],
               "rng": rng.bit_generator.state, "gen": gen.get_state(), "history": history}
    tmp = ck / "state.pt.tmp"
    torch.save(payload, tmp)
    tmp.replace(ck / "state.pt")
    for old in ck.glob("scene_graph.*.pt"):
        if old.name != gf:
            old.unlink(missing_ok=True)


__all__ = ["JointSettings", "run_stage"]
