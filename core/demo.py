"""The main job, end to end on one scene: reconstruct, relight under another sky, a night clip,
evaluate (when the bundle has ground truth), and a side-by-side sheet. ``brdf demo`` runs it; the
README's first command runs it on the bundled default scene.

Outputs (``out``):

* ``run/`` the reconstruction (:mod:`core.stages.chain`; a second call resumes it and keeps the
  stages that are done);
* ``relit/`` and ``night/``: EXR frames (HDR beauty + G-buffers), MP4, preview PNG;
* ``evaluation.json`` (:mod:`core.synth.evaluate`; only with ground truth, which the product path never
  reads: the evaluation and the sheet's reference panel alone do, through :mod:`core.synth`);
* ``sheet.png``: one test frame as input | novel view | albedo | normal | roughness | relit |
  Mitsuba ground truth of the relit frame (when the bundle has it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image, ImageDraw

from core.bundle import open_bundle
from core.camera import Camera
from core.errors import ConfigError
from core.io.hdri import load_hdri
from core.io.images import read_image, write_png
from core.numerics import OPACITY_EPS
from core.raster import RasterSettings, rasterize_gaussians
from core.render.scenario import Scenario, night_scenario, render_scenario, scene_corrector, views_from_frames
from core.stages.chain import RUN_FILE, RunDir, run_pipeline
from core.synth.evaluate import EvalSettings, evaluate_run, relit_reference_ldr


@dataclass(frozen=True)
class DemoSettings:
    """What the main job does besides the reconstruction."""

    profile: str = "quick"
    """Reconstruction profile (:data:`core.stages.chain.PROFILE_NAMES`)."""
    envmap: str | None = None
    """Relighting map: a bundled HDRI name or a file; None = the bundle's first held-back relit
    map (so the sheet can show its Mitsuba ground truth), else ``sunset``."""
    rays_per_pixel: int = 64
    """PBR rays per pixel of the relit and night frames."""
    denoiser: str = "oidn"
    """Denoiser of the relit and night frames."""
    evaluate: bool = True
    """Measure against the bundle's ground truth when it has some."""


def _relight_choice(bundle, name: str | None):
    """(map name or path, relit ground truth entry or None)."""
    gt = bundle.manifest.ground_truth
    relit = list(gt.relit) if gt is not None else []
    if name is None:
        return (relit[0].name, relit[0]) if relit else ("sunset", None)
    return name, next((r for r in relit if r.name == name), None)


def _colour(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[-1] == 1:
        x = np.repeat(x, 3, -1)
    return np.clip(x, 0.0, 1.0)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` with a caption strip above it (PIL's default bitmap font)."""
    h, w = img.shape[:2]
    strip = Image.new("RGB", (w, 14), (255, 255, 255))
    ImageDraw.Draw(strip).text((3, 1), text, fill=(0, 0, 0))
    return np.concatenate([np.asarray(strip, np.float32) / 255.0, img], 0)


def sheet(graph, sky, bundle, frame, relit_ldr: np.ndarray | None, gt_ldr: np.ndarray | None,
          threads: int = 2) -> np.ndarray:
    """[H', W', 3] in [0, 1]: the frame's input, novel view, albedo, normal, roughness, relit and
    ground truth side by side, each captioned."""
    c = bundle.camera(frame)
    t = float(bundle.manifest.times[frame.time_index])
    with torch.no_grad():
        g = graph.compose(t).detach()
        cam = Camera.from_bundle(c, frame)
        r = rasterize_gaussians(g, cam, settings=RasterSettings(threads=threads))
        dirs = torch.from_numpy(cam.ray_directions())
        nvs = (r.color + (1 - r.opacity) * sky(dirs.to(g.dtype)).to(r.color.dtype)).numpy()
        inv = (1.0 / r.opacity.clamp_min(OPACITY_EPS)).numpy()
        n = r.normal.numpy()
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    panels = [("input", bundle.load_image(frame)), ("novel view", nvs), ("albedo", r.albedo.numpy() * inv),
              ("normal", n * 0.5 + 0.5), ("roughness", r.roughness.numpy() * inv)]
    if relit_ldr is not None:
        panels.append(("relit", relit_ldr))
    if gt_ldr is not None:
        panels.append(("Mitsuba ground truth", gt_ldr))
    cols = [_label(_colour(x), name) for name, x in panels]
    sep = np.ones((cols[0].shape[0], 2, 3), np.float32)
    return np.concatenate([x for col in cols for x in (col, sep)][:-1], 1)


def run_demo(scene: str | Path, out: str | Path, settings: DemoSettings | None = None, *, progress: bool = True,
             say: Callable[[str], None] = print) -> dict:
    """Run the main job (module docstring) on the bundle at ``scene`` into ``out``. Returns
    ``{"seconds": {...}, "metrics": evaluation summary or None, "outputs": {...}}``."""
    s = settings or DemoSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    b = open_bundle(scene)
    secs: dict[str, float] = {}
    t0 = time.perf_counter()
    run_root = out / "run"
    resume = (run_root / RUN_FILE).is_file()

    def on_stage(name, what, summary):
        if what == "start":
            say(f"stage {name} ...")
        elif what == "skip":
            say(f"stage {name}: done already, kept")
        else:
            say(f"  {name}: {summary.get('seconds', 0):.0f} s")

    run_pipeline(b.root, run_root, s.profile, resume=resume, progress=progress, on_stage=on_stage)
    secs["reconstruct"] = round(time.perf_counter() - t0, 1)
    run = RunDir(run_root)
    graph, sky, _stage = run.load_scene()
    m = b.manifest
    name, relit_gt = _relight_choice(b, s.envmap)
    test = b.frames("test")
    if not test:
        test = b.frames("train")
    frames = [f for f in test if relit_gt is None or f.id in relit_gt.frames] or test
    views = views_from_frames(b, "all")
    views = [v for v in views if v.name in {f.id for f in frames}]
    if not views:
        raise ConfigError(f"scene {b.name!r}: no frames to render")
    common = dict(views=tuple(views), base_exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                  rays_per_pixel=s.rays_per_pixel, denoiser=s.denoiser)
    t1 = time.perf_counter()
    say(f"relight under {name!r} ({len(views)} frames) ...")
    relit = render_scenario(graph, Scenario(envmap=load_hdri(name), corrector=scene_corrector(run)[0], **common),
                            out / "relit")
    secs["relight"] = round(time.perf_counter() - t1, 1)
    t1 = time.perf_counter()
    say("night clip ...")
    night_sc, _note = night_scenario(run, **common)
    night = render_scenario(graph, night_sc, out / "night")
    secs["night"] = round(time.perf_counter() - t1, 1)
    metrics = None
    if s.evaluate and m.ground_truth is not None:
        t1 = time.perf_counter()
        say("evaluate against the bundle's ground truth ...")
        metrics = evaluate_run(run_root, b, EvalSettings(rays_per_pixel=s.rays_per_pixel, denoiser=s.denoiser),
                               out=out)["summary"]
        secs["evaluate"] = round(time.perf_counter() - t1, 1)
    # the sheet: the middle relit frame (the preview is the middle frame of the clip)
    mid = next(f for f in frames if f.id == views[len(views) // 2].name)
    relit_img = read_image(relit.result.preview).astype(np.float32) / 255.0 if relit.result.preview else None
    gt_img = None
    if relit_gt is not None and mid.id in relit_gt.frames:
        gt_img = relit_reference_ldr(b, relit_gt.name, mid.id)
    write_png(out / "sheet.png", sheet(graph, sky, b, mid, relit_img, gt_img))
    secs["total"] = round(time.perf_counter() - t0, 1)
    outputs = {"run": str(run_root), "relit": str(out / "relit"), "night": str(out / "night"),
               "sheet": str(out / "sheet.png")}
    if metrics is not None:
        outputs["evaluation"] = str(out / "evaluation.json")
    return {"seconds": secs, "metrics": metrics, "outputs": outputs, "relight_map": name,
            "night_frames": night.frames}


__all__ = ["DemoSettings", "run_demo", "sheet"]
