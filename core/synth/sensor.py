"""Lens distortion and the simulated sensor of the randomised streets (numpy).

Lens: Mitsuba renders pinhole images only, so a distorted frame is rendered as a pinhole image
on a canvas padded to cover the lens's field, and each distorted output pixel takes the canvas
at its undistorted position (OpenCV radial model, ``r_d = r_u (1 + k1 r_u^2)``, in normalised
coordinates): HDR beauty and relit frames are resampled bilinearly; the G-buffers and the sky
mask are not resampled but ray cast by Mitsuba exactly along each output pixel's lens ray
(``render_gbuffers(..., film_uv)``), so albedo, normal, depth (camera z) and mask are exact.

Sensor (LDR input frames only, never ground truth): exposure, noise on the exposed linear
signal, the gamma tone curve and an S-curve, 8-bit quantisation (JPEG is written by the caller).
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import ConfigError


def undistort_radius(r_d: np.ndarray, k1: float, iters: int = 20) -> np.ndarray:
    """Pinhole radius r_u with ``r_u (1 + k1 r_u^2) = r_d`` (Newton; the model is monotonic
    where it is used: ``1 + 3 k1 r_u^2 > 0``)."""
    r_d = np.asarray(r_d, np.float64)
    r = r_d.copy()
    for _ in range(iters):
        f = r * (1.0 + k1 * r * r) - r_d
        r = r - f / (1.0 + 3.0 * k1 * r * r)
    bad = ~(np.abs(r * (1.0 + k1 * r * r) - r_d) <= 1e-9 * (1.0 + r_d)) | (1.0 + 3.0 * k1 * r * r <= 0)
    if np.any(bad):
        raise ConfigError(f"r_d: {int(bad.sum())} radius/radii beyond the range of the lens k1 = {k1} "
                          f"(max {float(np.max(r_d)):.4g})")
    return r


def source_coords(width: int, height: int, fx: float, k1: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """For each pixel of a distorted ``width`` x ``height`` image (principal point at the centre,
    square pixels ``fx``): continuous coordinates (us, vs) [H, W] in the pinhole canvas padded by
    (pad_x, pad_y) on each side (pixel centres at i + 0.5). Returns (us, vs, pad_x, pad_y)."""
    u = (np.arange(width) + 0.5 - width / 2.0) / fx
    v = (np.arange(height) + 0.5 - height / 2.0) / fx
    xd, yd = np.meshgrid(u, v)
    rd = np.hypot(xd, yd)
    ru = undistort_radius(rd, k1)
    scale = np.where(rd > 0, ru / np.where(rd > 0, rd, 1.0), 1.0)
    xu, yu = xd * scale * fx, yd * scale * fx
    pad_x = max(0, math.ceil(np.abs(xu).max() - width / 2.0) + 1)
    pad_y = max(0, math.ceil(np.abs(yu).max() - height / 2.0) + 1)
    return xu + width / 2.0 + pad_x, yu + height / 2.0 + pad_y, pad_x, pad_y


def warp_bilinear(img: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """img [Hp, Wp, C] bilinearly sampled at (us, vs) (pixel centres at i + 0.5)."""
    x, y = us - 0.5, vs - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, img.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, img.shape[0] - 2)
    tx = np.clip(x - x0, 0.0, 1.0)[..., None]
    ty = np.clip(y - y0, 0.0, 1.0)[..., None]
    a = img[y0, x0] * (1 - tx) + img[y0, x0 + 1] * tx
    b = img[y0 + 1, x0] * (1 - tx) + img[y0 + 1, x0 + 1] * tx
    return (a * (1 - ty) + b * ty).astype(img.dtype)


def auto_exposure(hdr: np.ndarray, ev: float = 0.0) -> float:
    """Exposure that maps the median luminance of ``hdr`` to 0.18, times 2^ev."""
    lum = np.asarray(hdr, np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    med = float(np.median(lum))
    return float(0.18 / max(med, 1e-6) * 2.0 ** ev)


def apply_sensor(hdr: np.ndarray, exposure: float, gamma: float, contrast: float, shot_noise: float,
                 read_noise: float, rng: np.random.Generator) -> np.ndarray:
    """LDR uint8 [H, W, 3] of linear ``hdr``: x = exposure * hdr; x += N(0, shot_noise x +
    read_noise^2); y = clip(x, 0, 1)^(1/gamma); y -= contrast sin(2 pi y) / (2 pi); 8 bits."""
    if exposure <= 0 or gamma <= 0 or not 0 <= contrast < 1 or shot_noise < 0 or read_noise < 0:
        raise ConfigError(f"sensor: exposure, gamma > 0, contrast in [0, 1), noise >= 0 "
                          f"(got {exposure}, {gamma}, {contrast}, {shot_noise}, {read_noise})")
    x = exposure * np.asarray(hdr, np.float64)
    sigma = np.sqrt(shot_noise * np.maximum(x, 0.0) + read_noise ** 2)
    x = x + sigma * rng.standard_normal(x.shape)
    y = np.clip(x, 0.0, 1.0) ** (1.0 / gamma)
    y = y - contrast * np.sin(2 * math.pi * y) / (2 * math.pi)
    return np.clip(np.round(y * 255.0), 0, 255).astype(np.uint8)
