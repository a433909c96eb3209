"""HDR environment maps: bilinear lookup, rotation, exposure and importance sampling (torch).

Frames and units
    An :class:`EnvironmentMap` holds ``[H, W, 3]`` linear RGB radiance (W / (m^2 sr), any scale)
    laid out by :mod:`core.conventions` (equirectangular, row 0 = zenith +z, column ``c`` at
    azimuth ``pi/2 - 2 pi (c + 0.5) / W``). Every direction <-> pixel mapping below goes through
    :func:`core.conventions.direction_to_uv` / :func:`core.conventions.pixel_to_direction`.
    Directions are world-space ``[..., 3]`` (z up), pointing *away* from the shading point
    toward the light; they need not be unit length.

Rotation and exposure
    ``rotation_deg`` (degrees in the API, radians inside) turns the map about +z: the light stored
    at map direction ``m`` arrives from world direction ``Rz(rotation) m``. ``exposure`` scales the
    returned radiance (not the sampling pdf).

Sampling
    A 2D piecewise-constant distribution over pixels (marginal over rows, conditional over
    columns) with pixel weight ``luminance * Omega_row`` (by default the luminance is the maximum
    over the pixel's 3x3 neighbourhood, which bounds the bilinearly interpolated radiance inside
    the pixel: without it a dim pixel next to a 3.5e4 sun returns half the sun's radiance with a
    tiny pdf, a firefly; ``sampling_filter="none"`` uses the pixel's own luminance), where ``Omega_row`` is the exact solid
    angle of a pixel of that row (:func:`core.conventions.envmap_solid_angles`, which is
    ``2 pi / W * (cos theta_0 - cos theta_1)``, the integral of ``sin theta`` over the row).
    Inside the chosen pixel the direction is uniform in *solid angle* (uniform in ``cos theta``
    and in azimuth), so the density over solid angle is constant per pixel::

        pdf(w) = P_pixel / Omega_row = p(u, v) * H * W / (2 pi^2 * sinbar(theta_row))

    with ``p(u, v)`` the density over the unit square of image coordinates and ``sinbar`` the mean
    of ``sin theta`` over the row. This is the usual ``p(u,v) H W / (2 pi^2 sin theta)`` with the
    row's mean ``sin theta`` in place of the pointwise one: it stays finite at the poles, and a
    constant map is sampled exactly uniformly over the sphere (``pdf = 1 / (4 pi)``), so
    ``L / pdf`` is the same number for every sample.

    ``uniform_fraction`` mixes in a uniform-over-the-sphere density (useful while optimising the
    map, whose values move away from the ones the sampler was built from). A map whose luminance
    sums to zero (all black) falls back to uniform sampling over the sphere: pdf ``1 / (4 pi)``,
    radiance 0, no NaN. The sampler is built from the values at construction time (detached);
    call :meth:`EnvironmentMap.rebuild_sampler` after changing the map.

Differentiability
    :meth:`lookup` and the radiance returned by :meth:`sample` are differentiable with respect to
    the map parameter :attr:`EnvironmentMap.param` (directions, pdfs and sampling are not: for a
    fixed sampling density, ``E_p[grad(L) f cos / p]`` is an unbiased gradient). With
    ``log_space=True`` the parameter is ``log(max(radiance, LOG_RADIANCE_FLOOR))`` and radiance is
    ``exp(param)``, as the PBR stage's log-space prior wants.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
import torch.nn.functional as F

from core import conventions
from core.errors import ConfigError, ShapeError
from core.io.envmap_file import read_envmap
from core.numerics import ENV_RADIANCE_MAX, LOG_RADIANCE_FLOOR, require_finite

#: Default size of the resampled map (rows, columns), as in the paper.
DEFAULT_SIZE = (512, 1024)
#: Rec. 709 luminance weights of linear RGB.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 709 luminance of linear RGB ``[..., 3]`` -> ``[...]``."""
    w = torch.tensor(LUMINANCE_WEIGHTS, dtype=rgb.dtype, device=rgb.device)
    return (rgb * w).sum(-1)


def rotate_z(dirs: torch.Tensor, angle_rad: float) -> torch.Tensor:
    """Rotate world directions ``[..., 3]`` by ``angle_rad`` about +z (counter-clockwise seen
    from above, i.e. azimuth increases by ``angle_rad``)."""
    if angle_rad == 0.0:
        return dirs
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    x, y, z = dirs.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], -1)


def _as_map(rgb, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(rgb, np.ndarray):
        if rgb.dtype.kind not in "fiu":
            raise ShapeError(f"rgb: dtype {rgb.dtype} is not a real number type")
        t = torch.from_numpy(np.ascontiguousarray(rgb)).to(dtype)
    elif isinstance(rgb, torch.Tensor):
        if not (rgb.is_floating_point() or rgb.dtype in (torch.uint8, torch.int32, torch.int64)):
            raise ShapeError(f"rgb: dtype {rgb.dtype} is not a real number type")
        t = rgb.detach().to(dtype)
    else:
        raise ShapeError(f"rgb: expected a numpy array or torch tensor, got {type(rgb).__name__}")
    if t.dim() != 3 or t.shape[2] != 3 or t.shape[0] < 1 or t.shape[1] < 1:
        raise ShapeError(f"rgb: expected [H, W, 3] with H, W >= 1, got {list(t.shape)}")
    require_finite(t, "rgb")
    if bool((t < 0).any()):
        raise ConfigError(f"rgb: {int((t < 0).sum())} negative value(s); radiance must be >= 0")
    # finite but near float32's end overflows to Inf in lookups and exp(log(x)) (stress tests)
    if bool((t > ENV_RADIANCE_MAX).any()):
        raise ConfigError(f"rgb: {int((t > ENV_RADIANCE_MAX).sum())} value(s) above {ENV_RADIANCE_MAX:g} "
                          f"(core.numerics.ENV_RADIANCE_MAX); max {float(t.max()):.3g}")
    return t


def resample(rgb: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Resample ``[H, W, 3]`` to ``[height, width, 3]``: area averaging when shrinking by integer
    factors (keeps the integral of the map), bilinear otherwise (azimuth wraps)."""
    h, w = rgb.shape[:2]
    if (h, w) == (height, width):
        return rgb.clone()
    x = rgb.permute(2, 0, 1)[None]
    if h % height == 0 and w % width == 0:
        y = F.avg_pool2d(x, (h // height, w // width))
    else:
        # pad one column on each side so azimuth interpolation wraps around
        xp = torch.cat([x[..., -1:], x, x[..., :1]], -1)
        # sample positions of the target pixel centres in source pixel units (centre = i + 0.5)
        ys = (torch.arange(height, dtype=x.dtype) + 0.5) * h / height
        xs = (torch.arange(width, dtype=x.dtype) + 0.5) * w / width + 1.0  # +1 for the pad
        gy = ys / h * 2.0 - 1.0
        gx = xs / (w + 2) * 2.0 - 1.0
        grid = torch.stack(torch.meshgrid(gx, gy, indexing="xy"), -1)[None]
        y = F.grid_sample(xp, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return y[0].permute(1, 2, 0).contiguous().clamp_min(0.0)


class EnvironmentMap:
    """An HDR equirectangular environment map with bilinear lookup and importance sampling.

    Args:
        rgb: ``[H, W, 3]`` non-negative finite linear radiance (numpy or torch), any size.
        rotation_deg: rotation about +z in degrees (see the module docstring).
        exposure: finite multiplier > 0 of the returned radiance.
        resample_to: ``(rows, cols)`` to resample to (e.g. :data:`DEFAULT_SIZE`), or None to keep.
        log_space: store the parameter as log radiance (see module docstring).
        requires_grad: make :attr:`param` a leaf that requires grad (for the PBR stage).
        uniform_fraction: in [0, 1), the weight of a uniform-sphere density in the sampler.
        sampling_filter: ``"max3x3"`` (default) samples pixels by the maximum luminance of their
            3x3 neighbourhood, a bound of the bilinear radiance inside the pixel (no fireflies
            next to a sun); ``"none"`` by the pixel's own luminance.
        dtype: floating dtype of the map and of every returned tensor.

    Raises:
        ShapeError: ``rgb`` is not ``[H, W, 3]`` of real numbers.
        ConfigError: negative radiance, bad exposure/rotation/uniform_fraction/resample_to.
        NumericalError: ``rgb`` holds NaN or Inf.
    """

    def __init__(self, rgb, *, rotation_deg: float = 0.0, exposure: float = 1.0,
                 resample_to: tuple[int, int] | None = None, log_space: bool = False,
                 requires_grad: bool = False, uniform_fraction: float = 0.0,
                 dtype: torch.dtype = torch.float32, sampling_filter: str = "max3x3"):
        if dtype not in (torch.float32, torch.float64):
            raise ConfigError(f"dtype: must be torch.float32 or torch.float64, got {dtype}")
        self.dtype = dtype
        t = _as_map(rgb, dtype)
        if resample_to is not None:
            if (not isinstance(resample_to, (tuple, list)) or len(resample_to) != 2
                    or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in resample_to)):
                raise ConfigError(f"resample_to: expected (rows, cols) of positive ints, got {resample_to!r}")
            t = resample(t, int(resample_to[0]), int(resample_to[1]))
        self.log_space = bool(log_space)
        p = torch.log(t.clamp_min(LOG_RADIANCE_FLOOR)) if self.log_space else t.clone()
        self.param = p.requires_grad_(bool(requires_grad))
        self.rotation_deg = rotation_deg
        self.exposure = exposure
        if sampling_filter not in ("max3x3", "none"):
            raise ConfigError(f"sampling_filter: must be 'max3x3' or 'none', got {sampling_filter!r}")
        self.sampling_filter = sampling_filter
        uf = float(uniform_fraction) if isinstance(uniform_fraction, (int, float)) and not isinstance(uniform_fraction, bool) else None
        if uf is None or not math.isfinite(uf) or not 0.0 <= uf < 1.0:
            raise ConfigError(f"uniform_fraction: must be a number in [0, 1), got {uniform_fraction!r}")
        self.uniform_fraction = uf
        self.rebuild_sampler()

    # -- construction helpers ------------------------------------------------------------------
    @classmethod
    def from_file(cls, path: str | os.PathLike, **kwargs) -> "EnvironmentMap":
        """Read ``.exr`` / ``.hdr`` with :func:`core.io.read_envmap` and wrap it (kwargs as
        :class:`EnvironmentMap`)."""
        return cls(read_envmap(path), **kwargs)

    @classmethod
    def constant(cls, value=1.0, height: int = 16, width: int = 32, **kwargs) -> "EnvironmentMap":
        """A map of constant radiance ``value`` (a number or an RGB triple)."""
        v = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
        if v.numel() == 1:
            v = v.expand(3)
        if v.numel() != 3:
            raise ShapeError(f"value: expected a number or 3 values, got {v.numel()}")
        return cls(v.reshape(1, 1, 3).expand(height, width, 3).clone(), **kwargs)

    # -- properties ----------------------------------------------------------------------------
    @property
    def height(self) -> int:
        return int(self.param.shape[0])

    @property
    def width(self) -> int:
        return int(self.param.shape[1])

    @property
    def rotation_deg(self) -> float:
        """Rotation about +z in degrees."""
        return math.degrees(self._rotation_rad)

    @rotation_deg.setter
    def rotation_deg(self, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not math.isfinite(value):
            raise ConfigError(f"rotation_deg: must be a finite number of degrees, got {value!r}")
        self._rotation_rad = math.radians(float(value) % 360.0)

    @property
    def exposure(self) -> float:
        return self._exposure

    @exposure.setter
    def exposure(self, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
                or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"exposure: must be finite and > 0, got {value!r}")
        self._exposure = float(value)

    def radiance_map(self) -> torch.Tensor:
        """``[H, W, 3]`` radiance including exposure (differentiable w.r.t. :attr:`param`)."""
        base = torch.exp(self.param) if self.log_space else self.param
        return base * self._exposure if self._exposure != 1.0 else base

    # -- lookup --------------------------------------------------------------------------------
    def _check_dirs(self, dirs: torch.Tensor, name: str = "dirs_world") -> torch.Tensor:
        if not isinstance(dirs, torch.Tensor) or not dirs.is_floating_point():
            raise ShapeError(f"{name}: expected a floating torch tensor [..., 3]")
        if dirs.shape[-1:] != (3,):
            raise ShapeError(f"{name}: expected shape [..., 3], got {list(dirs.shape)}")
        require_finite(dirs.detach(), name)
        return dirs

    def _map_uv(self, dirs: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (u, v) of world directions in the *unrotated* map (float64 numpy)."""
        d = rotate_z(dirs.detach().to(torch.float64), -self._rotation_rad)
        return conventions.direction_to_uv(d.cpu().numpy(), self.height, self.width)

    def lookup(self, dirs_world: torch.Tensor) -> torch.Tensor:
        """Radiance ``[..., 3]`` arriving from world directions ``[..., 3]`` (bilinear between
        pixel centres; wraps in azimuth, clamps at the poles). Differentiable w.r.t. the map;
        zero-length directions read the zenith."""
        dirs = self._check_dirs(dirs_world)
        h, w = self.height, self.width
        u, v = self._map_uv(dirs)
        x = u - 0.5
        y = v - 0.5
        c0 = np.floor(x)
        fx = x - c0
        r0 = np.floor(y)
        fy = y - r0
        c0 = c0.astype(np.int64)
        r0 = r0.astype(np.int64)
        ca, cb = np.mod(c0, w), np.mod(c0 + 1, w)
        ra, rb = np.clip(r0, 0, h - 1), np.clip(r0 + 1, 0, h - 1)
        idx = np.stack([ra * w + ca, ra * w + cb, rb * w + ca, rb * w + cb], -1)
        wt = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
        flat = self.radiance_map().reshape(-1, 3)
        idx_t = torch.from_numpy(idx.reshape(-1))
        wt_t = torch.from_numpy(wt.reshape(-1, 4, 1)).to(self.dtype)
        vals = flat[idx_t].reshape(-1, 4, 3)
        out = (vals * wt_t).sum(1)
        return out.reshape(dirs.shape[:-1] + (3,))

    __call__ = lookup

    # -- sampling ------------------------------------------------------------------------------
    def rebuild_sampler(self) -> None:
        """(Re)build the sampling distribution from the current (detached) map values."""
        h, w = self.height, self.width
        with torch.no_grad():
            lum = luminance(self.radiance_map().detach().to(torch.float64)).clamp_min(0.0)
            if self.sampling_filter == "max3x3":
                # the bilinear radiance inside a pixel is bounded by the max over its 3x3
                # neighbourhood (azimuth wraps, rows clamp): sampling by that bound keeps L / pdf
                # bounded next to a sun, where a piecewise-constant pdf gives fireflies
                x = torch.cat([lum[:, -1:], lum, lum[:, :1]], 1)
                x = torch.cat([x[:1], x, x[-1:]], 0)[None, None]
                lum = F.max_pool2d(x, 3, stride=1)[0, 0]
        omega = torch.from_numpy(conventions.envmap_solid_angles(h, w))  # [H] sr, float64
        weight = lum * omega[:, None]
        total = float(weight.sum())
        self.fallback_uniform = not (math.isfinite(total) and total > 0.0)
        uniform = omega[:, None].expand(h, w) / (4.0 * math.pi)  # sums to 1
        if self.fallback_uniform:
            prob = uniform.clone()
        else:
            prob = weight / total
            if self.uniform_fraction > 0:
                prob = (1.0 - self.uniform_fraction) * prob + self.uniform_fraction * uniform
        self._omega = omega
        self._prob = prob  # [H, W] probability of each pixel, float64, sums to 1
        row_p = prob.sum(1)
        self._row_cdf = torch.cumsum(row_p, 0)
        self._row_cdf = self._row_cdf / self._row_cdf[-1]
        cond = prob / torch.where(row_p > 0, row_p, torch.ones_like(row_p))[:, None]
        cond = torch.where(row_p[:, None] > 0, cond, torch.full_like(cond, 1.0 / w))
        col_cdf = torch.cumsum(cond, 1)
        col_cdf = col_cdf / col_cdf[:, -1:]
        # conditional cdfs of all rows in one increasing array: row r occupies (r, r + 1]
        self._col_cdf_flat = (col_cdf + torch.arange(h, dtype=torch.float64)[:, None]).reshape(-1).contiguous()
        #: density over solid angle of each pixel [H, W] (float64)
        self._pdf_pixel = prob / omega[:, None]

    def pixel_probabilities(self) -> torch.Tensor:
        """``[H, W]`` float64 probability that a sample lands in each pixel (sums to 1)."""
        return self._prob.clone()

    def pdf(self, dirs_world: torch.Tensor) -> torch.Tensor:
        """Sampling density over solid angle (1/sr) of world directions ``[..., 3]`` -> ``[...]``
        (not differentiable; dtype of the map)."""
        dirs = self._check_dirs(dirs_world)
        d = rotate_z(dirs.detach().to(torch.float64), -self._rotation_rad)
        row, col = conventions.direction_to_pixel(d.cpu().numpy(), self.height, self.width)
        p = self._pdf_pixel[torch.from_numpy(row), torch.from_numpy(col)]
        return p.to(self.dtype).reshape(dirs.shape[:-1])

    def sample(self, n: int, generator: torch.Generator | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw ``n`` world directions.

        Returns:
            dirs ``[n, 3]`` unit world directions (no grad), pdf ``[n]`` over solid angle (1/sr,
            > 0, finite), radiance ``[n, 3]`` = :meth:`lookup` of dirs (differentiable).
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ConfigError(f"n: must be an int >= 0, got {n!r}")
        h, w = self.height, self.width
        uvs = torch.rand(n, 4, generator=generator, dtype=torch.float64)
        row = torch.searchsorted(self._row_cdf, uvs[:, 0].contiguous(), right=True).clamp_(0, h - 1)
        key = (row.to(torch.float64) + uvs[:, 1]).contiguous()
        flat = torch.searchsorted(self._col_cdf_flat, key, right=True)
        col = (flat - row * w).clamp_(0, w - 1)
        # uniform in solid angle inside the pixel: cos(theta) uniform between the row's edges
        theta0 = row.to(torch.float64) / h * math.pi
        theta1 = (row.to(torch.float64) + 1.0) / h * math.pi
        cos_t = torch.cos(theta0) + uvs[:, 2] * (torch.cos(theta1) - torch.cos(theta0))
        theta = torch.acos(cos_t.clamp(-1.0, 1.0))
        # fractional row/col in pixel_to_direction's convention (pixel centre = integer index)
        row_f = (theta / math.pi * h - 0.5).clamp(row.to(torch.float64) - 0.5, row.to(torch.float64) + 0.5)
        col_f = col.to(torch.float64) + uvs[:, 3] - 0.5
        d_map = torch.from_numpy(conventions.pixel_to_direction(row_f.numpy(), col_f.numpy(), h, w))
        dirs = rotate_z(d_map, self._rotation_rad).to(self.dtype)
        pdf = self._pdf_pixel[row, col].to(self.dtype)
        return dirs, pdf, self.lookup(dirs)
