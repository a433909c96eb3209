"""Training data of the generative models (paper Sec. 3.2-3.3): synthetic scenes and the PBR renders of
imperfect Gaussian scenes that the forward model learns to clean.

For a synthetic bundle (``core.synth``; its ``bundle.json`` records the generator config), the
*oracle* Gaussian scene of its street (:func:`core.synth.oracle.street_scene_graph`: thin flat
Gaussians on the mesh surfaces with the ground-truth materials, moving cars as rigid nodes) is
made imperfect the way a reconstruction is (:class:`PerturbSettings`: jittered positions and
normals, blurred and dropped Gaussians, noisy albedo / roughness / metallic), then rendered by
the PBR pass at few rays per pixel under the bundle's own environment map, frame by frame with
the bundle's cameras and times. Each frame goes to ``<bundle>/derived/pbr/<frame id>.exr``
(beauty + G-buffers, :func:`core.pbr.render.write_frame_exr`), where
:func:`core.synth.gen_data.load_clips` (``forward_source="pbr"``) finds it. The Mitsuba path-traced
ground truth of the bundle is the target; it also carries the indirect light the PBR pass lacks.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from core.bundle import open_bundle
from core.camera import Camera
from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.numerics import safe_normalize
from core.pbr.envmap import EnvironmentMap
from core.pbr.render import ClipRenderer, PBRSettings, write_frame_exr
from core.synth.config import SynthConfig
from core.synth.oracle import OracleSettings, street_scene_graph


@dataclass(frozen=True)
class PerturbSettings:
    """How an oracle scene is made imperfect (a reconstruction's typical errors) and rendered."""

    budget: int = 40_000
    """Gaussians spread over the street at time 0 (the oracle's density budget)."""
    position_sigma_m: float = 0.01
    """Std of the Gaussian jitter of every mean along its normal (metres)."""
    normal_sigma_deg: float = 6.0
    """Std of the per-Gaussian normal perturbation (degrees)."""
    scale_jitter: float = 0.3
    """Scales are multiplied by ``exp(U(0, scale_jitter))`` (blur: reconstructions are soft)."""
    drop_fraction: float = 0.03
    """Fraction of Gaussians removed (holes)."""
    albedo_log_sigma: float = 0.12
    """Std of the multiplicative log-normal albedo noise per Gaussian."""
    albedo_bias_log_sigma: float = 0.08
    """Std of one multiplicative log-normal albedo factor per scene and channel (a global bias)."""
    roughness_sigma: float = 0.08
    """Std of the additive roughness noise (clamped to [0.02, 1])."""
    metallic_sigma: float = 0.05
    """Std of the additive metallic noise (clamped to [0, 1])."""
    rays_per_pixel: int = 16
    """Rays per pixel of the PBR render (the forward model's input quality)."""
    seed: int = 0
    """Seed of the perturbation and of the renders (mixed with the bundle's generator seed)."""
    threads: int = 2
    """CPU threads of the render."""

    def __post_init__(self) -> None:
        for name in ("position_sigma_m", "normal_sigma_deg", "scale_jitter", "drop_fraction", "albedo_log_sigma",
                     "albedo_bias_log_sigma", "roughness_sigma", "metallic_sigma"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"PerturbSettings.{name}: must be a finite number >= 0, got {v!r}")
        if self.drop_fraction >= 0.5:
            raise ConfigError(f"PerturbSettings.drop_fraction: must be < 0.5, got {self.drop_fraction}")
        if self.budget < 100 or self.rays_per_pixel < 1 or self.threads < 1:
            raise ConfigError(f"PerturbSettings: budget >= 100, rays_per_pixel >= 1, threads >= 1 ({self})")


def perturb_gaussians(g, s: PerturbSettings, rng: np.random.Generator, albedo_bias: np.ndarray):
    """A perturbed copy of :class:`core.gaussians.Gaussians` ``g`` (see :class:`PerturbSettings`)."""
    n = g.num
    if n == 0:
        return g
    keep = torch.from_numpy(rng.random(n) >= s.drop_fraction)
    g = g.index(keep)
    n = g.num
    dt = g.means.dtype
    t = lambda a: torch.as_tensor(a, dtype=dt)  # noqa: E731
    nrm = g.unit_normals()
    means = g.means + nrm * t(rng.normal(0, s.position_sigma_m, (n, 1)))
    nn = safe_normalize(nrm + t(rng.normal(0, math.radians(s.normal_sigma_deg), (n, 3))))
    scales = g.scales() * t(np.exp(rng.uniform(0, s.scale_jitter, (n, 1))))
    alb = (g.albedo() * t(np.exp(rng.normal(0, s.albedo_log_sigma, (n, 1)))) * t(albedo_bias)).clamp(0.0, 1.0)
    rough = (g.roughness() + t(rng.normal(0, s.roughness_sigma, (n, 1)))).clamp(0.02, 1.0)
    metal = (g.metallic() + t(rng.normal(0, s.metallic_sigma, (n, 1)))).clamp(0.0, 1.0)
    return Gaussians.from_activated(means=means, quats=g.quats, scales=scales, opacities=g.opacities(),
                                    colors=g.colors(), normals=nn, albedo=alb, roughness=rough, metallic=metal)


def synth_config_of(bundle):
    """The :class:`core.synth.config.SynthConfig` a synthetic bundle was generated from."""
    src = getattr(bundle.manifest, "source", None) or {}
    cfg = src.get("config") if isinstance(src, dict) else None
    if src.get("generator") != "core.synth" or not isinstance(cfg, dict):
        raise FormatError(f"{bundle.root}: not a core.synth bundle (bundle.json source.config missing); "
                          "PBR training inputs are made from synthetic scenes")
    if cfg.get("scene_spec"):
        # core.synth.oracle rebuilds the fixed generator's street (lane, pinhole, flat albedo): for a
        # randomised street it would be the wrong scene, so refuse rather than train on it
        raise FormatError(f"{bundle.root}: a randomised street (core.synth.randomise); its PBR oracle "
                          "inputs are not supported yet (use DataSettings(forward_source='degrade'))")
    known = {f for f in SynthConfig.__dataclass_fields__}
    vals = {k: (tuple(v) if isinstance(v, list) else v) for k, v in cfg.items() if k in known}
    return SynthConfig(**vals)


def render_pbr_inputs(bundle_dir: str | Path, settings: PerturbSettings | None = None, *,
                      out_dir: str | Path | None = None, splits=("train", "test"),
                      on_frame: Callable[[int, int], None] | None = None) -> dict:
    """Render the perturbed oracle scene of a synthetic bundle at every frame of ``splits``.

    Writes ``<out_dir or bundle/derived/pbr>/<frame id>.exr`` and ``meta.json`` (settings, counts,
    times). Returns the meta dict. ``on_frame(done, total)`` after each frame.
    """
    s = settings or PerturbSettings()
    b = open_bundle(bundle_dir, validate=False)
    cfg = synth_config_of(b)
    out = Path(out_dir) if out_dir is not None else Path(bundle_dir) / "derived" / "pbr"
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    graph, _, _ = street_scene_graph(cfg, tuple(range(cfg.num_frames)), settings=OracleSettings(max_spacing=1.0),
                                     budget=s.budget)
    rng = np.random.default_rng([s.seed, int(cfg.seed)])
    bias = np.exp(rng.normal(0, s.albedo_bias_log_sigma, 3))
    graph.background = perturb_gaussians(graph.background, s, rng, bias)
    for node in graph.nodes:
        node.gaussians = perturb_gaussians(node.gaussians, s, rng, bias)
    graph.invalidate()
    t_scene = time.perf_counter() - t0
    m = b.manifest
    env = EnvironmentMap(b.load_envmap())
    r = ClipRenderer(graph, env, PBRSettings(rays_per_pixel=s.rays_per_pixel, exposure=m.ldr_exposure,
                                             gamma=m.ldr_gamma, threads=s.threads, seed=s.seed * 7919 + int(cfg.seed)))
    frames = [f for f in m.frames if f.split in splits]
    for k, fr in enumerate(frames):
        res = r.render(Camera.from_bundle(b.camera(fr), fr), time_s=float(m.times[fr.time_index]), frame_index=k)
        if not torch.isfinite(res.hdr).all():
            raise ConfigError(f"{bundle_dir}: frame {fr.id}: non-finite PBR render")
        write_frame_exr(out / f"{fr.id}.exr", res)
        if on_frame is not None:
            on_frame(k + 1, len(frames))
    meta = {"settings": asdict(s), "bundle": b.name, "generator_seed": cfg.seed, "frames": len(frames),
            "gaussians": int(graph.compose(0.0).num), "albedo_bias": bias.tolist(),
            "seconds": {"scene": round(t_scene, 2), "total": round(time.perf_counter() - t0, 2)}}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return meta


__all__ = ["PerturbSettings", "perturb_gaussians", "render_pbr_inputs", "synth_config_of"]
