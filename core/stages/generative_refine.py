"""The generative refinement stage (paper Sec. 3.3, "Generative Refinement Stage").

After the volume stage, each intrinsic map ``X`` in ``{N, D, A, R, M}`` is rendered from the
Gaussians for every training frame: these renders are multi-view consistent but blurrier than the
raw priors. They are the anchors of an SDEdit with the inverse model conditioned on the input
frames (the same operator as the forward pass, paper Eq. 5, applied to intrinsics):

    X'_g = SDEdit(X_render | D_inverse, frames, tau)

and the refined ``X'_g`` replace the priors of the next volume stage (:mod:`core.stages.volume2`).

Outputs (``<run>/generative_refine/``): ``priors.npz`` (:class:`core.stages.priors.GBufferPriors`),
``preview.png`` (one frame: rendered and refined albedo and normals), ``summary.json`` (seconds,
how far the refinement moved the anchors, and how far the refined priors are from the raw ones).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from core.camera import Camera
from core.errors import ConfigError
from core.gen.encoding import encode_gbuffer, world_to_camera_dirs
from core.io.images import write_png
from core.raster import RasterSettings, rasterize_gaussians
from core.stages.priors import run_inverse_model


@dataclass(frozen=True)
class RefineSettings:
    """Settings of the generative refinement."""

    sigma_tau: float = 20.0
    """SDEdit noise level (EDM sigma, G-buffer data space in [-1, 1]) added to the rendered
    intrinsics before the inverse model denoises them: small keeps the renders, large returns to
    the raw prior (at 80 the anchor is ignored). Chosen on the development scene (default, after
    the quick volume stage; refined priors of the training frames against their ground truth):
    sigma 0.3 / 1 / 2 / 5 / 20 / 80 gave albedo si-PSNR 18.3 / 18.7 / 19.4 / 20.0 / 20.1 / 20.2 dB
    and normals 17.4 / 16.0 / 12.5 / 9.8 / 8.7 / 8.7 deg; 4 Euler steps were worse at every sigma.
    The shipped model's one-step denoiser does not remove small noise, so refinement keeps close
    to the raw prior."""
    steps: int = 1
    """Denoising steps from ``sigma_tau`` down (Euler; 1 = the posterior mean in one step, the
    inverse model's own sampler)."""
    min_opacity: float = 0.5
    """Pixels the render covers less than this are sky in the anchors (no surface)."""
    threads: int = 2
    """CPU threads of the rasterizer and onnxruntime."""

    def __post_init__(self) -> None:
        if not (0 < self.sigma_tau <= 80):
            raise ConfigError(f"sigma_tau: must be in (0, 80], got {self.sigma_tau!r}")
        if not (isinstance(self.steps, int) and 1 <= self.steps <= 64):
            raise ConfigError(f"steps: must be an int in [1, 64], got {self.steps!r}")
        if not (0 < self.min_opacity < 1):
            raise ConfigError(f"min_opacity: must be in (0, 1), got {self.min_opacity!r}")
        if self.threads < 1:
            raise ConfigError(f"threads: must be >= 1, got {self.threads!r}")


def render_intrinsics(graph, bundle, frames, min_opacity: float = 0.5, threads: int = 2) -> dict[str, dict]:
    """``frame_id -> {albedo, roughness, metallic, normal (world), depth (metres, 0 = sky),
    opacity}`` rendered from the scene graph, channels-last float32 (expected values given a hit)."""
    rs = RasterSettings(threads=threads)
    times = bundle.manifest.times
    out = {}
    with torch.no_grad():
        for f in frames:
            g = graph.compose(float(times[f.time_index])).detach()
            r = rasterize_gaussians(g, Camera.from_bundle(bundle.camera(f), f), settings=rs)
            o = r.opacity.double()
            hit = o > min_opacity
            inv = torch.where(hit, 1.0 / o.clamp_min(min_opacity), torch.zeros_like(o))
            n = r.normal.double() * inv
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            out[f.id] = {"albedo": (r.albedo.double() * inv).clamp(0, 1).float().numpy(),
                         "roughness": (r.roughness.double() * inv).clamp(0, 1).float().numpy(),
                         "metallic": (r.metallic.double() * inv).clamp(0, 1).float().numpy(),
                         "normal": torch.where(hit, n, torch.zeros_like(n)).float().numpy(),
                         "depth": (r.depth.double() * inv).float().numpy(),
                         "opacity": o.float().numpy()}
    return out


def _anchor(layers: dict, cam_to_world) -> np.ndarray:
    return encode_gbuffer(layers["albedo"], layers["roughness"], layers["metallic"],
                          world_to_camera_dirs(layers["normal"], cam_to_world), layers["depth"])


def _preview(path, frame_img, rendered: dict, refined: dict) -> None:
    def n01(n):
        return np.clip(n * 0.5 + 0.5, 0, 1)

    row1 = np.concatenate([frame_img, np.clip(rendered["albedo"], 0, 1), n01(rendered["normal"])], 1)
    row2 = np.concatenate([frame_img, np.clip(refined["albedo"], 0, 1), n01(refined["normal"])], 1)
    write_png(path, np.concatenate([row1, row2], 0))


def run_stage(ctx) -> dict:
    """Render the intrinsics of the latest scene graph, refine them by SDEdit with the inverse
    model conditioned on the frames, write them as the next stage's priors."""
    cfg: RefineSettings = ctx.settings
    b = ctx.bundle
    t0 = time.perf_counter()
    graph, _sky, graph_stage = ctx.run.load_scene(before=ctx.name)
    raw, raw_source = ctx.run.latest_priors(b, ctx.name, threads=cfg.threads)
    frames = b.frames("train")
    rendered = render_intrinsics(graph, b, frames, cfg.min_opacity, cfg.threads)
    t_render = time.perf_counter() - t0
    anchors = {f.id: _anchor(rendered[f.id], np.asarray(f.cam_to_world, np.float64)) for f in frames}
    done = [0]

    def clip_done(i, n):
        done[0] = i
        if ctx.on_progress is not None:
            ctx.on_progress(i, n, {"loss": 0.0, "clips": i})

    refined = run_inverse_model(b, "train", anchors=anchors, sigma_tau=cfg.sigma_tau, steps=cfg.steps,
                                threads=cfg.threads, on_clip=clip_done)
    refined.save(ctx.out_dir / "priors.npz", {"sigma_tau": cfg.sigma_tau, "graph_stage": graph_stage})
    # how far the refinement moved: against the anchors and against the raw priors (non-sky)
    moved, from_raw = {}, {}
    for k in ("albedo", "roughness", "metallic"):
        a, r1 = [], []
        for f in frames:
            m = rendered[f.id]["opacity"][..., 0] > cfg.min_opacity
            a.append(np.abs(refined.layers[f.id][k] - rendered[f.id][k])[m].mean() if m.any() else 0.0)
            rl = raw.frame(f.id)
            if rl is not None and m.any():
                r1.append(np.abs(refined.layers[f.id][k] - rl[k])[m].mean())
        moved[k] = round(float(np.mean(a)), 4)
        if r1:
            from_raw[k] = round(float(np.mean(r1)), 4)
    mid = frames[len(frames) // 2]
    _preview(ctx.out_dir / "preview.png", b.load_image(mid), rendered[mid.id], refined.layers[mid.id])
    return {"graph_stage": graph_stage, "raw_prior_source": raw_source, "frames": len(frames),
            "sigma_tau": cfg.sigma_tau, "mean_abs_change_from_render": moved, "mean_abs_diff_from_raw_prior": from_raw,
            "seconds": round(time.perf_counter() - t0, 2), "render_seconds": round(t_render, 2)}


__all__ = ["RefineSettings", "render_intrinsics", "run_stage"]
