"""Differentiable tile-based EWA splatting of 3D Gaussians into G-buffers (CPU).

Pipeline of :func:`rasterize`:

1. **Projection** (:func:`project_gaussians`, vectorised torch, differentiable by autograd):
   world means -> OpenCV camera (``world_to_cam`` = inverse of the rigid ``cam_to_world``),
   pinhole projection to pixels (pixel centres at +0.5, i.e. ``u = fx x / z + cx``), 3D covariance
   ``R(q) diag(s)^2 R(q)^T``, EWA 2D covariance ``J W Sigma W^T J^T`` with the Jacobian's
   ``x/z, y/z`` clamped to a ``guard_band`` (1.3x) field of view, ``+low_pass`` on the diagonal,
   conic = inverse 2D covariance (formed in float64 so extreme covariances cannot overflow).
   Gaussians with camera depth ``z <= near`` are culled.
2. **Binning** (C++): opacity-aware footprint: the ellipse where ``o * g >= alpha_min``
   (``q <= 2 ln(o / alpha_min)``); a Gaussian is listed in a 16x16 tile only if that ellipse
   overlaps the rectangle spanned by the tile's pixel centres (exact ellipse-rectangle test).
   Gaussians are sorted by depth once (stable), then bucketed per tile with a stable counting
   sort: the same order as a global sort by the key (tile, depth).
3. **Compositing** (C++, :class:`_RasterizeFn`): per pixel, front to back,
   ``alpha = min(alpha_max, o g)``, skipped when ``< alpha_min``, stop before the Gaussian that
   would bring the transmittance below ``transmittance_min``; 12 feature channels + opacity.
   The backward walks each tile's list back to front, recovering ``T_i`` by division.

Gradients reach every input, including ``cam_to_world`` and the intrinsics' tensors if they
require grad (through the torch projection), so scene-graph node poses composed in torch
before the call get gradients too.
"""

from __future__ import annotations

import ctypes
import math
from typing import Any

import torch

from core.errors import ConfigError, ShapeError
from core.numerics import EPS_NORM_SQ, require_finite
from core.raster import _native
from core.raster.settings import NUM_FEATURES, NUM_OUTPUTS, RasterOutput, RasterSettings

NG = 6 + NUM_FEATURES  # floats per Gaussian handed to the kernels
TILE = 16


# ---------------------------------------------------------------------------------------------
# helpers (torch) shared with core.gaussians
# ---------------------------------------------------------------------------------------------

def safe_normalize_quat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (wxyz) ``[N, 4]``; (near-)zero quaternions become the identity (1,0,0,0)
    with zero gradient, never NaN. Same rule as the kernels (|q|^2 <= EPS_NORM_SQ -> identity)."""
    n2 = (q * q).sum(-1, keepdim=True)
    ok = n2 > EPS_NORM_SQ
    unit = q * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    return torch.where(ok, unit, ident)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[N, 3, 3]`` of unit quaternions ``[N, 4]`` (wxyz)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


# ---------------------------------------------------------------------------------------------
# the autograd function (C++ kernels)
# ---------------------------------------------------------------------------------------------

def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _suffix(dtype: torch.dtype) -> str:
    return "f64" if dtype == torch.float64 else "f32"


class _Binning:
    """Sorted per-tile Gaussian lists (and the per-Gaussian footprint data) for one frame."""

    def __init__(self, lib, suf: str, gdata: torch.Tensor, valid: torch.Tensor, width: int,
                 height: int, settings: RasterSettings, threads: int):
        n = gdata.shape[0]
        self.n_tiles = ((width + TILE - 1) // TILE) * ((height + TILE - 1) // TILE)
        self.aux = torch.empty(n, 2, dtype=gdata.dtype)
        counts = torch.empty(n, dtype=torch.int32)
        order = torch.empty(n, dtype=torch.int32)
        goff = torch.empty(n, dtype=torch.int64)
        n_vis = ctypes.c_int64(0)
        total = getattr(lib, f"br_bin_prepare_{suf}")(
            _ptr(gdata), _ptr(valid), n, width, height, settings.alpha_min, threads,
            _ptr(self.aux), _ptr(counts), _ptr(order), _ptr(goff), ctypes.byref(n_vis))
        self.num_visible = int(n_vis.value)
        self.total = int(total)
        self.tile_offsets = torch.empty(self.n_tiles + 1, dtype=torch.int64)
        self.tile_ids = torch.empty(self.total, dtype=torch.int32)
        self.tile_order = torch.empty(self.n_tiles, dtype=torch.int32)
        getattr(lib, f"br_bin_fill_{suf}")(
            _ptr(gdata), _ptr(valid), width, height, settings.alpha_min, threads, _ptr(order),
            _ptr(goff), self.num_visible, self.total, _ptr(self.tile_offsets), _ptr(self.tile_ids),
            _ptr(self.tile_order))


class _SplatFn(torch.autograd.Function):
    """Projection + binning + compositing in C++.

    Inputs: means, quats, scales, opacities [N], colors, normals, albedo, roughness [N],
    metallic [N], world_to_cam [4, 4], background [3] (differentiable), then non-tensor
    arguments. Outputs: packed [H, W, 13], T_final [H, W], stats (non-differentiable).
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opac, colors, normals, albedo, rough, metal, w2c,
                background, intrinsics, width: int, height: int, settings: RasterSettings, info: dict):
        lib = _native.lib()
        dtype = means.dtype
        suf = _suffix(dtype)
        n = means.shape[0]
        threads = settings.num_threads
        fx, fy, cx, cy = intrinsics
        cam = torch.cat([w2c.detach().double().reshape(16), torch.tensor(
            [fx, fy, cx, cy, settings.near, settings.guard_band, settings.low_pass, settings.max_scale],
            dtype=torch.float64)])
        ins = [t.detach().contiguous() for t in (means, quats, scales, opac, colors, normals, albedo, rough, metal)]
        gdata = torch.empty(n, NG, dtype=dtype)
        valid = torch.empty(n, dtype=torch.uint8)
        getattr(lib, f"br_project_{suf}")(*[_ptr(t) for t in ins], _ptr(cam), width, height, n, threads,
                                          _ptr(gdata), _ptr(valid))
        binning = _Binning(lib, suf, gdata, valid, width, height, settings, threads)
        out = torch.empty(height, width, NUM_OUTPUTS, dtype=dtype)
        tfinal = torch.empty(height, width, dtype=dtype)
        last = torch.empty(height, width, dtype=torch.int32)
        stats = torch.empty(height, width, 2, dtype=torch.int32) if settings.collect_stats else None
        bg = background.detach().contiguous()
        getattr(lib, f"br_forward_{suf}")(
            _ptr(gdata), _ptr(binning.aux), _ptr(binning.tile_offsets), _ptr(binning.tile_ids),
            _ptr(binning.tile_order), binning.n_tiles, width, height, _ptr(bg),
            settings.alpha_min, settings.alpha_max, settings.transmittance_min,
            threads, _ptr(out), _ptr(tfinal), _ptr(last), _ptr(stats))
        ctx.save_for_backward(*ins[:4], bg, tfinal, last, gdata)
        ctx.binning = binning
        ctx.cam = cam
        ctx.dims = (width, height)
        ctx.settings = settings
        info["num_visible"] = binning.num_visible
        info["num_tile_pairs"] = binning.total
        if stats is None:
            stats = torch.empty(0, dtype=torch.int32)
        ctx.mark_non_differentiable(tfinal, stats)
        return out, tfinal, stats

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out, _grad_tfinal, _grad_stats):
        means, quats, scales, opac, bg, tfinal, last, gdata = ctx.saved_tensors
        binning: _Binning = ctx.binning
        settings: RasterSettings = ctx.settings
        width, height = ctx.dims
        lib = _native.lib()
        dtype = gdata.dtype
        suf = _suffix(dtype)
        n = gdata.shape[0]
        threads = max(1, min(settings.num_threads, binning.n_tiles))
        grad_out = grad_out.to(dtype).contiguous()
        buf = torch.zeros(threads, n, NG, dtype=dtype)
        getattr(lib, f"br_backward_{suf}")(
            _ptr(gdata), _ptr(binning.aux), _ptr(binning.tile_offsets), _ptr(binning.tile_ids),
            _ptr(binning.tile_order), binning.n_tiles, width, height, _ptr(bg),
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, threads,
            _ptr(tfinal), _ptr(last), _ptr(grad_out), n, _ptr(buf))
        gg = buf[0]
        g_means = torch.empty(n, 3, dtype=dtype)
        g_quats = torch.empty(n, 4, dtype=dtype)
        g_scales = torch.empty(n, 3, dtype=dtype)
        pose = torch.zeros(12, dtype=torch.float64)
        getattr(lib, f"br_project_backward_{suf}")(
            _ptr(means), _ptr(quats), _ptr(scales), _ptr(ctx.cam), width, height, n,
            settings.num_threads, _ptr(gg), _ptr(g_means), _ptr(g_quats), _ptr(g_scales), _ptr(pose))
        g_opac = torch.where((opac >= 0) & (opac <= 1), gg[:, 5], torch.zeros_like(gg[:, 5]))
        g_w2c = None
        if ctx.needs_input_grad[9]:
            g_w2c = torch.zeros(4, 4, dtype=torch.float64)
            g_w2c[:3, :3] = pose[:9].reshape(3, 3)
            g_w2c[:3, 3] = pose[9:]
        grad_bg = None
        if ctx.needs_input_grad[10]:
            grad_bg = (tfinal[..., None] * grad_out[..., :3]).sum(dim=(0, 1))
        return (g_means, g_quats, g_scales, g_opac, gg[:, 6:9], gg[:, 10:13], gg[:, 13:16], gg[:, 16],
                gg[:, 17], g_w2c, grad_bg, None, None, None, None, None)


# ---------------------------------------------------------------------------------------------
# validation and the public entry point
# ---------------------------------------------------------------------------------------------

def _check_tensor(x: Any, name: str, shape: tuple, dtype: torch.dtype | None) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise ShapeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if dtype is not None and x.dtype != dtype:
        raise ShapeError(f"{name}: dtype {x.dtype} does not match means.dtype {dtype}")
    if x.device.type != "cpu":
        raise ShapeError(f"{name}: the rasterizer runs on the CPU, got device {x.device}")
    if x.dim() != len(shape) or any(s is not None and x.shape[i] != s for i, s in enumerate(shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ShapeError(f"{name}: expected shape {want}, got {list(x.shape)}")
    require_finite(x, name)
    return x


def _check_scalar(v: Any, name: str, positive: bool = False):
    if isinstance(v, torch.Tensor):
        if v.numel() != 1:
            raise ShapeError(f"{name}: expected a scalar, got shape {list(v.shape)}")
        val = float(v.detach())
    else:
        try:
            val = float(v)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{name}: expected a number, got {v!r}") from exc
    if not math.isfinite(val):
        from core.errors import NumericalError

        raise NumericalError(f"{name}: non-finite value {val}")
    if positive and val <= 0:
        raise ConfigError(f"{name}: must be > 0, got {val}")
    return val


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    normals: torch.Tensor,
    albedo: torch.Tensor,
    roughness: torch.Tensor,
    metallic: torch.Tensor,
    cam_to_world: torch.Tensor,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    settings: RasterSettings | None = None,
) -> RasterOutput:
    """Render the G-buffers of world-space Gaussians seen by an OpenCV pinhole camera.

    All Gaussian inputs are *activated* values, ``N`` rows, one float dtype (float32 for speed,
    float64 for exact checks), on the CPU:
    means [N, 3] world metres; quats [N, 4] wxyz (need not be normalised; zero -> identity);
    scales [N, 3] metres (>= 0); opacities [N] or [N, 1] in [0, 1] (clamped); colors [N, 3];
    normals [N, 3] world, unit; albedo [N, 3]; roughness [N] or [N, 1]; metallic [N] or [N, 1].
    cam_to_world: [4, 4] rigid (tensor, may require grad). fx, fy, cx, cy: pixels (floats or 0-d
    tensors). background: [3] color behind the Gaussians (default black).

    Returns a :class:`RasterOutput` of ``[H, W, C]`` tensors; gradients flow to every tensor
    input. Raises ShapeError / ConfigError / NumericalError naming the offending argument.
    """
    settings = settings if settings is not None else RasterSettings()
    if not isinstance(settings, RasterSettings):
        raise ConfigError(f"settings: expected RasterSettings, got {type(settings).__name__}")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"{name}: expected an int >= 1, got {v!r}")
    means = _check_tensor(means, "means", (None, 3), None)
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ShapeError(f"means: dtype must be float32 or float64, got {dtype}")
    n = means.shape[0]
    quats = _check_tensor(quats, "quats", (n, 4), dtype)
    scales = _check_tensor(scales, "scales", (n, 3), dtype)

    def col(x, name):
        if isinstance(x, torch.Tensor) and x.dim() == 2 and x.shape[1:] == (1,):
            x = x[:, 0]
        return _check_tensor(x, name, (n,), dtype)

    opacities = col(opacities, "opacities")
    colors = _check_tensor(colors, "colors", (n, 3), dtype)
    normals = _check_tensor(normals, "normals", (n, 3), dtype)
    albedo = _check_tensor(albedo, "albedo", (n, 3), dtype)
    roughness = col(roughness, "roughness")
    metallic = col(metallic, "metallic")
    cam_to_world = _check_tensor(torch.as_tensor(cam_to_world) if not isinstance(cam_to_world, torch.Tensor)
                                 else cam_to_world, "cam_to_world", (4, 4), None)
    c2w_d = cam_to_world.detach().double()
    r = c2w_d[:3, :3]
    if (not torch.allclose(r.T @ r, torch.eye(3, dtype=torch.float64), atol=1e-3)
            or abs(float(torch.linalg.det(r)) - 1.0) > 1e-3
            or not torch.allclose(c2w_d[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6)):
        raise ConfigError("cam_to_world: expected a rigid transform (orthonormal rotation, det +1, "
                          "last row 0 0 0 1)")
    fx = _check_scalar(fx, "fx", positive=True)
    fy = _check_scalar(fy, "fy", positive=True)
    cx = _check_scalar(cx, "cx")
    cy = _check_scalar(cy, "cy")
    if background is None:
        background = torch.zeros(3, dtype=dtype)
    else:
        background = _check_tensor(background, "background", (3,), None).to(dtype)

    w2c = torch.linalg.inv(cam_to_world.to(torch.float64))
    info: dict = {}
    packed, tfinal, stats = _SplatFn.apply(
        means, quats, scales, opacities, colors, normals, albedo, roughness, metallic, w2c,
        background, (fx, fy, cx, cy), width, height, settings, info)
    return RasterOutput(
        color=packed[..., 0:3],
        depth=packed[..., 3:4],
        normal=packed[..., 4:7],
        albedo=packed[..., 7:10],
        roughness=packed[..., 10:11],
        metallic=packed[..., 11:12],
        opacity=packed[..., 12:13],
        packed=packed,
        transmittance=tfinal,
        num_visible=info["num_visible"],
        num_tile_pairs=info["num_tile_pairs"],
        stats=stats if settings.collect_stats else None,
    )
