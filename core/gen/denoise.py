"""Denoiser backends of the rendering pipeline, selectable per render: ``none``, ``oidn``,
``diffusion`` (paper Sec. 3.2, Eq. 5).

    res = denoise(frames, albedo, normal, backend="diffusion", fallback="oidn",
                  gbuffer={"depth": d, "roughness": r, "metallic": m}, cam_to_world=poses, env=env)
    res.frames            # [T, H, W, 3] float32, same range as the input
    res.backend           # the backend that produced res.frames ("oidn" here if the model was missing)
    res.fallback_reason   # None, or why the requested backend was replaced

Inputs (channels-last, numpy or torch, float)
    frames   [T, H, W, 3] (or one frame [H, W, 3]): LDR display values in [0, 1] (``hdr=False``)
             or linear HDR radiance >= 0 (``hdr=True``).
    albedo   same shape, [0, 1]: the G-buffer albedo (noise-free guide).
    normal   same shape, unit normals (world or camera frame: OIDN accepts either; the diffusion
             backend needs ``cam_to_world`` to move world normals to the camera frame), 0 on sky.

Backends
    ``none``       the input, unchanged (validated).
    ``oidn``       Intel Open Image Denoise (``pyoidn``), filter ``RT`` with the albedo and normal
                   guides (``cleanAux``: G-buffer guides are noise-free), ``hdr`` as given,
                   quality "high", on its own OIDN CPU device with ``numThreads`` = ``threads``.
                   Sky pixels (zero normal) get the clipped colour as albedo guide (OIDN's advice
                   for primary rays that miss: the background's own colour), so the sky is kept.
    ``diffusion``  SDEdit with the ``forward_denoiser`` ONNX model (:mod:`core.gen.edm`,
                   :mod:`core.gen.runtime`) of OIDN's result, its change low-passed over the
                   surface pixels and the sky kept (``DenoiseSettings``: ``diffusion_start``,
                   ``correction_sigma_px``, ``keep_sky``): needs LDR frames, ``gbuffer`` (depth,
                   roughness, metallic), ``cam_to_world`` [T, 4, 4] and ``env`` [He, We, 3] (HDR map).

Failure policy: a missing, corrupt or contract-mismatching model raises
:class:`core.errors.ModelLoadError` naming the file unless ``fallback`` ("none" or "oidn") is
given, in which case the fallback runs and the result says so. Bad input (NaN/Inf, shapes) is
never "fallen back" from: it raises :class:`NumericalError` / :class:`ShapeError` naming the input.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import ConfigError, DependencyError, ModelLoadError, NumericalError, ShapeError
from core.gen.edm import OnnxDenoiser, SamplerSettings, sdedit
from core.gen.encoding import data_to_ldr, encode_env, forward_conditioning, ldr_to_data
from core.gen.runtime import load_model

BACKENDS = ("none", "oidn", "diffusion")
FALLBACKS = ("none", "oidn")
#: Where the committed forward model lives (models/ at the repository root).
DEFAULT_FORWARD_MODEL = Path(__file__).resolve().parents[2] / "models" / "forward_denoiser.onnx"


@dataclass(frozen=True)
class DenoiseSettings:
    """Settings of :func:`denoise` shared by the backends."""

    threads: int = 2
    """CPU threads of OIDN and onnxruntime."""
    oidn_quality: str = "high"
    """OIDN quality: ``high``, ``balanced`` or ``fast``."""
    model_path: str | None = None
    """ONNX file of the ``forward_denoiser`` contract; None = :data:`DEFAULT_FORWARD_MODEL`."""
    sampler: SamplerSettings = field(default_factory=lambda: SamplerSettings(sigma_tau=0.2))
    """SDEdit settings of the diffusion backend (sigma_tau, steps, solver, windows). ``sigma_tau``
    0.2: from OIDN's result with the other defaults, 0.4 scored 21.09 dB / SSIM 0.675 against
    0.2's 21.52 / 0.681 on the development scenes' relit frames (``forward_relit.json``)."""
    diffusion_start: str = "oidn"
    """Diffusion backend: the frames SDEdit starts from. ``"oidn"``: OIDN's result of the input
    (the model corrects a clean frame); ``"input"``: the input itself (the paper's forward pass
    on the raw render). On relit reconstructions the model cannot remove 64-ray noise: from the
    input, the relit frames were coloured grain (SSIM 0.41 against OIDN's 0.68)."""
    correction_sigma_px: float = 8.0
    """Diffusion backend: Gaussian sigma (pixels) of the low-pass applied to the model's change
    to its start frame, over surface pixels only (normalised convolution); 0 = the model's output
    as is. The model's corrections of tone and colour stay, its grain goes: from OIDN at
    sigma_tau 0.2, 0 / 4 / 8 px scored 20.92 / 21.50 / 21.52 dB and SSIM 0.526 / 0.680 / 0.681
    (OIDN alone 21.51 / 0.684; development scenes, ``benchmarks/bench_forward_relit.py``)."""
    keep_sky: bool = True
    """Diffusion backend: sky pixels (zero normal, the rule OIDN's guide uses) keep the start
    frame's value. There the PBR pass shows the map itself, without noise, and the forward model
    only changed the lighting: on relit reconstructions it brightened the courtyard sky from 0.25
    to 0.48 (mean LDR; dev2, quick). Measured on the development scenes' relit frames
    (``benchmarks/bench_forward_relit.py``, ``benchmarks/results/forward_relit.json``), SDEdit of
    the input without low-pass, off -> on: 18.69 -> 19.38 dB / SSIM 0.383 -> 0.443 (default
    scene), 19.76 -> 20.75 / 0.441 -> 0.506 (dev2)."""

    def __post_init__(self) -> None:
        if isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1:
            raise ConfigError(f"threads: must be an int >= 1, got {self.threads!r}")
        if self.oidn_quality not in ("high", "balanced", "fast"):
            raise ConfigError(f"oidn_quality: must be high, balanced or fast, got {self.oidn_quality!r}")
        if not isinstance(self.keep_sky, bool):
            raise ConfigError(f"keep_sky: must be a bool, got {self.keep_sky!r}")
        if self.diffusion_start not in ("oidn", "input"):
            raise ConfigError(f"diffusion_start: must be 'oidn' or 'input', got {self.diffusion_start!r}")
        if (isinstance(self.correction_sigma_px, bool) or not isinstance(self.correction_sigma_px, (int, float))
                or not math.isfinite(self.correction_sigma_px) or not 0 <= self.correction_sigma_px <= 64):
            raise ConfigError(f"correction_sigma_px: must be a number in [0, 64], got {self.correction_sigma_px!r}")


@dataclass(frozen=True)
class DenoiseResult:
    """Output of :func:`denoise`."""

    frames: np.ndarray
    """[T, H, W, 3] float32 (a single input frame comes back as [1, H, W, 3])."""
    backend: str
    """Backend that produced ``frames``."""
    requested: str
    """Backend that was asked for."""
    fallback_reason: str | None = None
    """Why ``backend`` differs from ``requested`` (the ModelLoadError message), else None."""


def _as_clip(x, name: str, ref_shape=None) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        raise ShapeError(f"{name}: dtype {a.dtype} is not numeric")
    a = a.astype(np.float32, copy=False)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[-1] != 3:
        raise ShapeError(f"{name}: expected [T, H, W, 3] or [H, W, 3], got {a.shape}")
    if ref_shape is not None and a.shape != ref_shape:
        raise ShapeError(f"{name}: shape {a.shape} differs from frames {ref_shape}")
    if not np.all(np.isfinite(a)):
        raise NumericalError(f"{name}: {int(a.size - np.count_nonzero(np.isfinite(a)))} non-finite value(s) (NaN or Inf)")
    return np.ascontiguousarray(a)


# ---------------------------------------------------------------------------------------------
# OIDN
# ---------------------------------------------------------------------------------------------

def surface_mask(normal: np.ndarray) -> np.ndarray:
    """[..., H, W] bool from unit normals [..., H, W, 3]: True on surfaces, False on the sky
    (the renderers write a zero normal there; partly covered edge pixels count as sky below
    half a unit)."""
    return np.linalg.norm(np.clip(normal, -1.0, 1.0), axis=-1) >= 0.5


class _Oidn:
    """One OIDN CPU device (with an explicit thread count) and one RT filter, reused."""

    _instances: dict[int, "_Oidn"] = {}
    _lock = threading.Lock()

    def __init__(self, threads: int):
        try:
            import pyoidn
        except ImportError as e:  # pragma: no cover - hard dependency
            raise DependencyError(f"the oidn backend needs pyoidn ({e})") from None
        self.pyoidn = pyoidn
        self.device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        self.device.set_int("numThreads", int(threads))
        self.device.set_bool("setAffinity", False)
        self.device.commit()
        self._check("device creation")
        self.filter = pyoidn.Filter(self.device, "RT")
        self._check("filter creation")
        self.lock = threading.Lock()

    def _check(self, what: str) -> None:
        err = self.device.get_error()
        if err:
            raise RuntimeError(f"OIDN {what} failed: {err}")

    @classmethod
    def get(cls, threads: int) -> "_Oidn":
        with cls._lock:
            if threads not in cls._instances:
                cls._instances[threads] = cls(threads)
            return cls._instances[threads]

    def run(self, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, hdr: bool, quality: str) -> np.ndarray:
        p = self.pyoidn
        q = {"high": p.OIDN_QUALITY_HIGH, "balanced": p.OIDN_QUALITY_BALANCED, "fast": p.OIDN_QUALITY_FAST}[quality]
        out = np.empty_like(color)
        with self.lock:
            f = self.filter
            f.set_image(p.OIDN_IMAGE_COLOR, color, p.OIDN_FORMAT_FLOAT3)
            f.set_image(p.OIDN_IMAGE_ALBEDO, albedo, p.OIDN_FORMAT_FLOAT3)
            f.set_image(p.OIDN_IMAGE_NORMAL, normal, p.OIDN_FORMAT_FLOAT3)
            f.set_image(p.OIDN_IMAGE_OUTPUT, out, p.OIDN_FORMAT_FLOAT3)
            f.set_bool("hdr", bool(hdr))
            f.set_bool("cleanAux", True)
            f.set_quality(q)
            f.commit()
            self._check("filter commit")
            f.execute()
            self._check("filter execution")
        return out


def denoise_oidn(frames: np.ndarray, albedo: np.ndarray, normal: np.ndarray, *, hdr: bool = False,
                 threads: int = 2, quality: str = "high") -> np.ndarray:
    """OIDN on each frame of a clip ([T, H, W, 3] float32, validated by :func:`denoise`)."""
    dev = _Oidn.get(threads)
    out = np.empty_like(frames)
    for t in range(frames.shape[0]):
        n = np.clip(normal[t], -1.0, 1.0)
        sky = ~surface_mask(n)
        a = np.clip(albedo[t], 0.0, 1.0)
        if sky.any():
            bg = frames[t] / (1.0 + frames[t]) if hdr else frames[t]
            a = np.where(sky[..., None], np.clip(bg, 0.0, 1.0), a)
        c = np.maximum(frames[t], 0.0)
        out[t] = dev.run(np.ascontiguousarray(c), np.ascontiguousarray(a, np.float32),
                         np.ascontiguousarray(n, np.float32), hdr, quality)
    if not np.all(np.isfinite(out)):
        raise NumericalError("OIDN output: non-finite values")
    if not hdr:
        out = np.clip(out, 0.0, 1.0)
    return np.maximum(out, 0.0)


# ---------------------------------------------------------------------------------------------
# diffusion
# ---------------------------------------------------------------------------------------------

def denoise_diffusion(frames: np.ndarray, albedo: np.ndarray, normal: np.ndarray, gbuffer: dict,
                      cam_to_world: np.ndarray, env: np.ndarray, settings: DenoiseSettings) -> np.ndarray:
    """SDEdit of the LDR clip ``frames`` with the ``forward_denoiser`` ONNX model, from its start
    (OIDN's result or ``frames`` itself, :attr:`DenoiseSettings.diffusion_start`); the model's
    change to the start low-passed over the surface pixels and the sky pixels kept as in the
    start (:class:`DenoiseSettings`). Raises ModelLoadError (naming the file) when the model
    cannot be used, before any denoising work."""
    import torch

    path = Path(settings.model_path) if settings.model_path else DEFAULT_FORWARD_MODEL
    sess = load_model(path, kind="forward_denoiser", threads=settings.threads)
    if settings.diffusion_start == "oidn":
        frames = denoise_oidn(frames, albedo, normal, threads=settings.threads, quality=settings.oidn_quality)
    t, h, w, _ = frames.shape
    poses = np.asarray(cam_to_world, np.float64)
    if poses.shape == (4, 4):
        poses = np.broadcast_to(poses, (t, 4, 4))
    if poses.shape != (t, 4, 4) or not np.all(np.isfinite(poses)):
        raise ShapeError(f"cam_to_world: expected finite [T={t}, 4, 4], got {poses.shape}")
    for k in ("depth", "roughness", "metallic"):
        if k not in gbuffer:
            raise ShapeError(f"gbuffer: the diffusion backend needs {k!r} (has {sorted(gbuffer)})")
    layers = {}
    for k in ("depth", "roughness", "metallic"):
        a = np.asarray(gbuffer[k], np.float32)
        if a.ndim == 3:
            a = a[..., None]
        if a.shape != (t, h, w, 1):
            raise ShapeError(f"gbuffer[{k!r}]: expected [T, H, W] or [T, H, W, 1] = ({t}, {h}, {w}, 1), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise NumericalError(f"gbuffer[{k!r}]: non-finite values")
        layers[k] = a
    env = np.asarray(env, np.float32)
    if not np.all(np.isfinite(env)):
        raise NumericalError("env: non-finite values")
    cond_frames = []
    for i in range(t):
        cond_frames.append(forward_conditioning(albedo[i], layers["roughness"][i], layers["metallic"][i],
                                                normal[i], layers["depth"][i], poses[i],
                                                env_encoded=encode_env(env, poses[i])))
    cond = {k: torch.from_numpy(np.stack([c[k] for c in cond_frames])) for k in cond_frames[0]}
    x = torch.from_numpy(ldr_to_data(frames).transpose(0, 3, 1, 2).copy())
    out = data_to_ldr(sdedit(OnnxDenoiser(sess), x, cond, settings.sampler).numpy().transpose(0, 2, 3, 1))
    surface = surface_mask(normal)  # [T, H, W]
    if settings.correction_sigma_px > 0:
        out = frames + surface_lowpass(out - frames, surface, settings.correction_sigma_px)
    if settings.keep_sky:
        out = np.where(surface[..., None], out, frames)
    out = np.clip(out, 0.0, 1.0).astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise NumericalError("diffusion output: non-finite values")
    return out


def surface_lowpass(x: np.ndarray, surface: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian low-pass (``sigma_px`` pixels, reflected at the borders) of ``x`` [T, H, W, C]
    over each frame's pixels where ``surface`` [T, H, W] is true (normalised convolution: the
    other pixels neither contribute nor receive); 0 elsewhere. float32."""
    from scipy.ndimage import gaussian_filter

    x = np.asarray(x, np.float32)
    m = np.asarray(surface, bool)
    if x.ndim != 4 or m.shape != x.shape[:3]:
        raise ShapeError(f"x / surface: expected [T, H, W, C] / [T, H, W], got {x.shape} / {m.shape}")
    if not (math.isfinite(sigma_px) and sigma_px > 0):
        raise ConfigError(f"sigma_px: must be finite and > 0, got {sigma_px!r}")
    w = m[..., None].astype(np.float32)
    num = gaussian_filter(x * w, (0, sigma_px, sigma_px, 0), mode="reflect")
    den = gaussian_filter(w, (0, sigma_px, sigma_px, 0), mode="reflect")
    # den > 0 wherever w = 1 (the pixel's own weight); elsewhere the result is 0 by definition
    return np.where(w > 0, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def denoise(frames, albedo, normal, backend: str = "none", fallback: str | None = None, *,
            hdr: bool = False, gbuffer: dict | None = None, cam_to_world=None, env=None,
            settings: DenoiseSettings | None = None) -> DenoiseResult:
    """Denoise a clip with the chosen backend (module docstring).

    Raises:
        ConfigError: unknown backend/fallback, or ``hdr`` with the diffusion backend.
        ShapeError / NumericalError: bad input (names it).
        ModelLoadError: diffusion model missing/corrupt/mismatching and no ``fallback``.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"backend: must be one of {BACKENDS}, got {backend!r}")
    if fallback is not None and fallback not in FALLBACKS:
        raise ConfigError(f"fallback: must be None or one of {FALLBACKS}, got {fallback!r}")
    s = settings or DenoiseSettings()
    f = _as_clip(frames, "frames")
    if hdr and (f < 0).any():
        raise NumericalError(f"frames: {int((f < 0).sum())} negative HDR value(s)")
    if not hdr and (f.min() < 0 or f.max() > 1):
        raise NumericalError(f"frames: LDR values must be in [0, 1] (min {f.min():.4g}, max {f.max():.4g}); "
                             "pass hdr=True for linear radiance")
    a = _as_clip(albedo, "albedo", f.shape)
    n = _as_clip(normal, "normal", f.shape)

    def run(name: str) -> np.ndarray:
        if name == "none":
            return f.copy()
        if name == "oidn":
            return denoise_oidn(f, a, n, hdr=hdr, threads=s.threads, quality=s.oidn_quality)
        if hdr:
            raise ConfigError("backend 'diffusion' denoises LDR frames (the forward_denoiser contract's "
                              "data space): tone-map first, or use 'oidn' for HDR")
        if gbuffer is None or cam_to_world is None or env is None:
            raise ShapeError("backend 'diffusion' needs gbuffer (depth, roughness, metallic), "
                             "cam_to_world and env")
        return denoise_diffusion(f, a, n, gbuffer, cam_to_world, env, s)

    try:
        return DenoiseResult(run(backend), backend, backend)
    except ModelLoadError as e:
        if fallback is None:
            raise
        return DenoiseResult(run(fallback), fallback, backend, str(e))
