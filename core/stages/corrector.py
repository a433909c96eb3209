"""The corrector stage: fit the scene corrector (:mod:`core.gen.scene_corrector`) on the capture.

Not a stage of the paper (``docs/DESIGN.md``, departures). After the joint stage, the training
views are rendered through the path of a relight request (:func:`core.render.scenario.render_scenario`:
the PBR pass under the recovered map at the capture's exposure, the denoiser) and the corrector
is fitted to map each denoised frame and its G-buffers to the captured frame. A later render
applies it only under the light it was fitted at (the recovered map at the capture's exposure:
the evaluation's re-render, a new path or an edit under ``--envmap recovered``); a relight under
another map, a rotation, added lights, another exposure and the night clip render without it.
It is in the default chain (``DEFAULT_STAGES``) since it moves nothing but those renders.

It reads the capture's frames and the run's own scene graph and map; never ground truth.

Outputs (``<run>/corrector/``): ``corrector.pt``, ``summary.json``; the resume state (the
rendered features and the fit's checkpoint) in ``resume/``.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from core.errors import ConfigError, FormatError
from core.gen.scene_corrector import (CorrectorSettings, SceneCorrector, apply_corrector, fit_corrector,
                                      light_fingerprint, save_corrector)
from core.io.envmap_file import read_envmap
from core.metrics import psnr


@dataclass(frozen=True)
class CorrectorStageSettings:
    """Settings of the corrector stage."""

    fit: CorrectorSettings = field(default_factory=CorrectorSettings)
    """The network and its fit."""
    max_frames: int = 24
    """Training views rendered and fitted on (evenly spaced)."""
    holdout_every: int = 0
    """Every this many of those views is held out of the fit and scored (a held-out figure in the
    summary); 0: fit on every view, the summary's figure is in-sample."""
    rays_per_pixel: int = 64
    """PBR rays per pixel of the renders (the evaluation's and a relight request's)."""
    checkpoint_every: int = 100
    """Fit steps between checkpoints."""
    threads: int = 2
    """CPU threads of the renders and the fit."""

    def __post_init__(self) -> None:
        bad = [n for n, ok in (("fit", isinstance(self.fit, CorrectorSettings)), ("max_frames", self.max_frames >= 1),
                               ("holdout_every", self.holdout_every == 0 or self.holdout_every >= 2),
                               ("rays_per_pixel", 1 <= self.rays_per_pixel <= 4096),
                               ("checkpoint_every", self.checkpoint_every >= 1), ("threads", self.threads >= 1))
               if not ok]
        if bad:
            raise ConfigError(f"CorrectorStageSettings: out of range: {', '.join(bad)} ({self})")


def _render_features(graph, bundle, env: np.ndarray, views, cfg: CorrectorStageSettings) -> list[np.ndarray]:
    from core.render.scenario import Scenario, render_scenario

    m = bundle.manifest
    # cold: the features never depend on what else this process rendered before (a warm shared
    # visibility cache, Scenario.reuse_visibility_across_requests, moves shadowed pixels by up to
    # ~0.1 at shadow edges on the tiny street), so a resumed pipeline sees what a straight one does
    sc = Scenario(views=tuple(views), envmap=np.asarray(env, np.float32), base_exposure=m.ldr_exposure,
                  gamma=m.ldr_gamma, rays_per_pixel=cfg.rays_per_pixel, outputs=("png",),
                  reuse_visibility_across_requests=False)
    feats: list[np.ndarray] = []
    with tempfile.TemporaryDirectory(prefix="brdf-corrector-") as tmp:
        render_scenario(graph, sc, tmp, features_out=feats)
    return feats


def _score(net, feats, targets) -> dict:
    def mean_psnr(preds):
        return float(np.mean([float(psnr(torch.from_numpy(np.asarray(p, np.float32)), torch.from_numpy(t)))
                              for p, t in zip(preds, targets)]))

    before = mean_psnr([x[..., :3] for x in feats])
    after = mean_psnr([apply_corrector(net, x) for x in feats])
    return {"frames": len(feats), "psnr_before": round(before, 3), "psnr_after": round(after, 3),
            "gain_db": round(after - before, 3)}


def run_stage(ctx) -> dict:
    """Render the training views under the run's recovered map and fit the corrector (module
    docstring)."""
    from core.render.scenario import views_from_frames

    cfg: CorrectorStageSettings = ctx.settings
    b, run = ctx.bundle, ctx.run
    t0 = time.perf_counter()
    graph, _sky, graph_stage = run.load_scene(before=ctx.name)
    env_path, env_stage = run.latest_envmap(before=ctx.name)
    if env_path is None:
        raise ConfigError(f"stage 'corrector': needs a recovered environment map (the pbr stage) in {run.root}")
    env = read_envmap(env_path)
    views = sorted(views_from_frames(b, "train"), key=lambda v: (v.time_s, v.name))
    pick = np.unique(np.linspace(0, len(views) - 1, min(cfg.max_frames, len(views))).round().astype(int))
    views = [views[i] for i in pick]
    k = cfg.holdout_every
    held = [i for i in range(len(views)) if k and i % k == k - 1]
    fit_idx = [i for i in range(len(views)) if i not in held]
    ck = ctx.resume_dir
    ck.mkdir(parents=True, exist_ok=True)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        f_feats = ck / "features.npz"
        if f_feats.is_file():
            try:
                z = np.load(f_feats)
                feats = list(z["features"])
            except Exception as exc:  # noqa: BLE001 - a corrupt cache is reported, never silently reset
                raise FormatError(f"{f_feats}: unreadable corrector features ({exc}); delete it to re-render") from exc
        else:
            feats = _render_features(graph, b, env, views, cfg)
            tmp = f_feats.with_suffix(".tmp")  # renamed when whole: a kill mid-write leaves no bad cache
            with open(tmp, "wb") as fh:
                np.savez(fh, features=np.stack(feats))
            tmp.replace(f_feats)
        t_render = time.perf_counter() - t0
        frames = {f.id: f for f in b.frames("train")}
        targets = [np.ascontiguousarray(b.load_image(frames[v.name]), np.float32) for v in views]
        net = opt_state = None
        start = 0
        history: list[dict] = []
        f_state = ck / "fit.pt"
        if f_state.is_file():
            try:
                st = torch.load(f_state, map_location="cpu", weights_only=True)
            except Exception as exc:  # noqa: BLE001
                raise FormatError(f"{f_state}: unreadable corrector checkpoint ({exc})") from exc
            net = SceneCorrector(cfg.fit.width)
            net.load_state_dict(st["net"])
            opt_state, start, history = st["opt"], int(st["step"]), list(st["history"])
        if net is None:
            torch.manual_seed(cfg.fit.seed)
            net = SceneCorrector(cfg.fit.width)
        opt = torch.optim.Adam(net.parameters(), lr=cfg.fit.lr)
        if opt_state is not None:
            opt.load_state_dict(opt_state)
        bar = tqdm(total=cfg.fit.steps, initial=start, desc="corrector", unit="it", disable=not ctx.progress)

        def on_step(step: int, loss: float) -> None:
            bar.update(1)
            rec = {"it": step, "loss": round(loss, 6), "s": round(time.perf_counter() - t0, 2)}
            if step % 10 == 0 or step == cfg.fit.steps:
                history.append(rec)
                bar.set_postfix(loss=f"{loss:.4f}")
            if ctx.on_progress is not None:
                ctx.on_progress(step, cfg.fit.steps, rec)
            if step % cfg.checkpoint_every == 0 and step < cfg.fit.steps:
                tmp = f_state.with_suffix(".tmp")
                torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "step": step,
                            "history": history}, tmp)
                tmp.replace(f_state)

        net, opt = fit_corrector([feats[i] for i in fit_idx], [targets[i] for i in fit_idx], cfg.fit, net=net,
                                 optimizer=opt, start_step=start, on_step=on_step)
        bar.close()
        out_dir = ctx.out_dir
        save_corrector(out_dir / "corrector.pt", net, cfg.fit, {"graph_stage": graph_stage, "envmap_stage": env_stage,
                                                             "fitted_light": light_fingerprint(env)})
        summary = {"stage": ctx.name, "graph_stage": graph_stage, "envmap_stage": env_stage,
                   "views": [v.name for v in views], "held_out_views": [views[i].name for i in held],
                   "fit_steps": cfg.fit.steps, "render_seconds": round(t_render, 1),
                   "in_sample": _score(net, [feats[i] for i in fit_idx], [targets[i] for i in fit_idx]),
                   "held_out": (_score(net, [feats[i] for i in held], [targets[i] for i in held]) if held else None),
                   "resumed_from_iteration": start, "history": history, "seconds": round(time.perf_counter() - t0, 1), "skips_fired": []}
        shutil.rmtree(ck, ignore_errors=True)
        return summary
    finally:
        torch.set_num_threads(old_threads)
