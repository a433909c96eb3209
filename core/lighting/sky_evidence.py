"""The sky the capture saw, as a fixed part of the recovered environment map.

A pixel of a frame that sees sky sees the environment map itself: its radiance *is* ``E`` in
that direction (``ldr^gamma / exposure`` below the clip). The pbr stage's lighting prior fits a
low-order parametric sky to those pixels, and its photometric loss uses non-sky pixels only, so
the recovered map showed a smooth gradient where the frames see distant skyline, clouds and
trees; re-rendered under the recovered lighting, the default scene's sky pixels scored 13.6 dB
against 18.3 dB elsewhere.

This module turns the reconstruction's sky dome (:class:`core.train.sky.SkyDome`, fitted by the
volume stages to the frames' sky pixels behind the Gaussians) into evidence on the map:

* **coverage**: the directions of the sky pixels of the given frames (their sky masks, else the
  render's uncovered pixels), counted on a ``grid_height`` x 2 ``grid_height`` equirect grid;
* **radiance**: the dome at every texel of the map, linearised (``dome^gamma / exposure``);
* **weight** in [0, 1]: 1 on covered texels whose dome value is below ``clip`` in every channel
  (a clipped value only bounds the radiance from below: the sun and its glare stay the fit's),
  eroded by ``erode_texels`` and feathered over ``feather_texels`` of the grid (a soft seam).

The pbr and joint stages then hold the map at ``log E = w log E_obs + (1 - w) log E_fit``: the
fit moves only what the frames did not see. Inputs are the capture's (frames' sky masks, poses)
and the reconstruction's (dome, opacity), never ground truth. Not in the paper (its
environment map is fitted to every pixel, sky included, over many more steps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from core.camera import Camera
from core.conventions import direction_to_pixel, envmap_directions
from core.errors import ConfigError, FormatError, ShapeError
from core.numerics import LOG_RADIANCE_FLOOR, require_finite_np
from core.pbr.envmap import resample


@dataclass(frozen=True)
class SkyEvidenceSettings:
    """How the observed sky is fixed in the recovered map."""

    enabled: bool = True
    """Fix the observed sky (False: the map is fitted everywhere, as before)."""
    grid_height: int = 128
    """Rows of the coverage grid (columns = 2 x rows) at most: a texel counts as seen when a sky
    pixel's ray falls in it. Coarser than the map (512 rows), and coarser still for coarse
    frames: at most ``pi f / 3`` rows for the smallest focal length ``f`` (pixels), so a texel
    spans about 3 x 3 pixels and the covered region has no pinholes (a 240-pixel frame with a
    70 deg field of view: 128 rows, 1.4 deg a texel)."""
    min_pixels: int = 2
    """Sky pixels a grid texel needs to count as seen."""
    clip: float = 0.98
    """LDR value (gamma-encoded, [0, 1]) at or above which a dome channel counts as clipped."""
    erode_texels: int = 0
    """Grid texels taken off the covered region's border (mixed sky / object pixels there)."""
    feather_texels: int = 1
    """Half-width, in grid texels, of the box blur that softens the weight's edge."""

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ConfigError(f"enabled: expected true or false, got {self.enabled!r}")
        for name, lo, hi in (("grid_height", 4, 2048), ("min_pixels", 1, 10 ** 6), ("erode_texels", 0, 64),
                             ("feather_texels", 0, 64)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(f"{name}: expected an int in [{lo}, {hi}], got {v!r}")
        if not (isinstance(self.clip, (int, float)) and 0.0 < self.clip <= 1.0):
            raise ConfigError(f"clip: expected a number in (0, 1], got {self.clip!r}")


def _box(x: np.ndarray, r: int) -> np.ndarray:
    """Box blur of half-width ``r`` (wrapping in azimuth, clamped at the poles)."""
    if r <= 0:
        return x
    k = 2 * r + 1
    p = np.pad(x, ((r, r), (0, 0)), mode="edge")
    p = np.concatenate([p[:, -r:], p, p[:, :r]], 1)
    c = np.cumsum(np.cumsum(np.pad(p, ((1, 0), (1, 0))), 0), 1)
    return (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)


def _erode(m: np.ndarray, r: int) -> np.ndarray:
    return m if r <= 0 else _box(m.astype(np.float64), r) > 1.0 - 1e-9


def observed_sky(dome, cameras, sky_masks, *, height: int, exposure: float, gamma: float,
                 settings: SkyEvidenceSettings | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The observed sky on an ``height`` x 2 ``height`` map (module docstring).

    Args:
        dome: the reconstruction's :class:`core.train.sky.SkyDome` (LDR values in [0, 1]).
        cameras: sequence of one-frame :class:`core.camera.Camera` (world, metres).
        sky_masks: one [H, W] bool per camera (True = sky), H x W the camera's image size.
        height: rows of the output map (columns = 2 x rows).
        exposure, gamma: the frames' tone map (bundle ``ldr``).
        settings: :class:`SkyEvidenceSettings`.
    Returns:
        ``(radiance [height, 2 height, 3] float64 linear, weight [height, 2 height] float64 in
        [0, 1], floor [height, 2 height] float64 linear (the clip level where the sky was seen
        clipped, else 0), stats)``; weight and floor are all zero when nothing was seen or
        ``enabled`` is False.
    """
    s = settings or SkyEvidenceSettings()
    if not isinstance(height, int) or height < 4:
        raise ConfigError(f"height: expected an int >= 4, got {height!r}")
    if not (exposure > 0 and gamma > 0):
        raise ConfigError(f"exposure, gamma: expected > 0, got {exposure!r}, {gamma!r}")
    cams = list(cameras)
    masks = list(sky_masks)
    if len(cams) != len(masks):
        raise ShapeError(f"sky_masks: expected one per camera ({len(cams)}), got {len(masks)}")
    cams = [Camera.of(c) for c in cams]
    f_min = min((min(float(c.fx), float(c.fy)) for c in cams), default=1e9)
    gh = int(max(4, min(s.grid_height, math.floor(math.pi * f_min / 3.0))))
    count = np.zeros((gh, 2 * gh), np.int64)
    for i, (cam, m) in enumerate(zip(cams, masks)):
        m = np.asarray(m, bool)
        if m.shape != (cam.height, cam.width):
            raise ShapeError(f"sky_masks[{i}]: expected [{cam.height}, {cam.width}], got {list(m.shape)}")
        if not m.any():
            continue
        rows, cols = direction_to_pixel(cam.ray_directions()[m], gh, 2 * gh)
        np.add.at(count, (rows, cols), 1)
    h2 = 2 * height
    dirs = envmap_directions(height, h2)
    with torch.no_grad():
        ldr = dome(torch.from_numpy(dirs).to(torch.float32)).double().numpy()
    ldr = require_finite_np(ldr, "dome")
    radiance = np.power(np.clip(ldr, 0.0, 1.0), gamma) / exposure
    gdirs = envmap_directions(gh, 2 * gh)
    with torch.no_grad():
        gldr = dome(torch.from_numpy(gdirs).to(torch.float32)).double().numpy()
    covered = _erode((count >= s.min_pixels) & (gdirs[..., 2] > 0.0), s.erode_texels)
    seen = covered & (gldr < s.clip).all(-1)
    weight_g = _box(seen.astype(np.float64), s.feather_texels) * seen  # soft inside, zero outside
    if not s.enabled:
        weight_g[:] = 0.0
    # grid -> map: nearest grid texel of every map texel (the feather already smooths the edge)
    r, c = direction_to_pixel(dirs, gh, 2 * gh)
    weight = weight_g[r, c]
    # seen but clipped: the radiance is at least the clip level (a floor, not a value)
    floor_mask = (covered & ~seen)[r, c] if s.enabled else np.zeros_like(weight, bool)
    floor = np.where(floor_mask, (s.clip ** gamma) / exposure, 0.0)
    stats = {"enabled": s.enabled, "grid_height": gh, "grid_texels_seen": int(seen.sum()),
             "grid_texels_clipped": int((covered & ~seen).sum()),
             "solid_angle_fixed_sr": float((weight * np.sin((np.arange(height)[:, None] + 0.5) / height * np.pi)).sum()
                                            * (np.pi / height) * (2 * np.pi / h2))}
    return radiance, weight, floor, stats


def hold_observed(log_fit: torch.Tensor, log_obs: torch.Tensor, weight: torch.Tensor,
                  log_floor: torch.Tensor | None = None) -> torch.Tensor:
    """``w log E_obs + (1 - w) max(log E_fit, log E_floor)`` ([H, W, 3] log radiance; ``weight``
    and ``log_floor`` [H, W]): the fit's gradient reaches only the unseen part, and a texel seen
    clipped never falls below the clip level."""
    if log_fit.shape != log_obs.shape or weight.shape != log_fit.shape[:2] \
            or (log_floor is not None and log_floor.shape != weight.shape):
        raise ShapeError(f"log_fit {list(log_fit.shape)}, log_obs {list(log_obs.shape)}, weight "
                         f"{list(weight.shape)}, log_floor {None if log_floor is None else list(log_floor.shape)}: "
                         "expected [H, W, 3], [H, W, 3], [H, W], [H, W]")
    w = weight[..., None].to(log_fit.dtype)
    if log_floor is not None:
        log_fit = torch.maximum(log_fit, log_floor[..., None].to(log_fit.dtype))
    return w * log_obs.to(log_fit.dtype) + (1.0 - w) * log_fit


@dataclass(frozen=True)
class SkyEvidence:
    """The observed sky of :func:`observed_sky` as log radiance, for one map size (the pbr stage
    writes it beside its map, the joint stage holds it too)."""

    log_radiance: torch.Tensor
    """[H, 2H, 3] float64, log of the linear radiance seen."""
    weight: torch.Tensor
    """[H, 2H] float64 in [0, 1]: how firmly each texel is held."""
    log_floor: torch.Tensor
    """[H, 2H] float64: log of the clip level where the sky was seen clipped, else the log floor."""

    @classmethod
    def from_observed(cls, radiance: np.ndarray, weight: np.ndarray, floor: np.ndarray) -> "SkyEvidence":
        def log(x):
            return torch.log(torch.from_numpy(np.asarray(x, np.float64)).clamp_min(LOG_RADIANCE_FLOOR))
        return cls(log(radiance), torch.from_numpy(np.asarray(weight, np.float64)), log(floor))

    @property
    def empty(self) -> bool:
        """Nothing held: no texel seen, none clipped."""
        return not bool((self.weight > 0).any()) and not bool((self.log_floor > math.log(LOG_RADIANCE_FLOOR) + 1e-6).any())

    def at(self, height: int) -> "SkyEvidence":
        """The same evidence on a ``height`` x 2 ``height`` map (area average when shrinking)."""
        if height == self.weight.shape[0]:
            return self

        def rs(x):
            return resample(x if x.dim() == 3 else x[..., None].expand(*x.shape, 3), height, 2 * height)
        rad = rs(torch.exp(self.log_radiance))
        return SkyEvidence(torch.log(rad.clamp_min(LOG_RADIANCE_FLOOR)), rs(self.weight)[..., 0].clamp(0, 1),
                           torch.log(rs(torch.exp(self.log_floor))[..., 0].clamp_min(LOG_RADIANCE_FLOOR)))

    def hold(self, log_fit: torch.Tensor) -> torch.Tensor:
        """:func:`hold_observed` of ``log_fit`` [H, 2H, 3] with this evidence (same size)."""
        return hold_observed(log_fit, self.log_radiance, self.weight, self.log_floor)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, log_radiance=self.log_radiance.float().numpy(), weight=self.weight.float().numpy(),
                            log_floor=self.log_floor.float().numpy())

    @classmethod
    def load(cls, path: str | Path) -> "SkyEvidence":
        try:
            with np.load(path, allow_pickle=False) as z:
                ev = cls(*(torch.from_numpy(z[k].astype(np.float64)) for k in ("log_radiance", "weight", "log_floor")))
        except (OSError, KeyError, ValueError) as exc:
            raise FormatError(f"{path}: unreadable sky evidence ({exc})") from exc
        h = ev.weight.shape[0]
        if ev.log_radiance.shape != (h, 2 * h, 3) or ev.weight.shape != (h, 2 * h) or ev.log_floor.shape != (h, 2 * h):
            raise FormatError(f"{path}: sky evidence of inconsistent shapes")
        for k in ("log_radiance", "weight", "log_floor"):
            require_finite_np(getattr(ev, k).numpy(), f"{path}: {k}")
        return ev


__all__ = ["SkyEvidenceSettings", "SkyEvidence", "observed_sky", "hold_observed"]
