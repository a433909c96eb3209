"""Differentiable tile-based EWA splatting of 3D Gaussians into G-buffers (CPU, C++ kernels).

Pipeline of :func:`rasterize` (all of it in ``_kernels.cpp``, called through ctypes with the
GIL released, on ``settings.threads`` threads):

1. **Projection** (per Gaussian, computed in float64 whatever the input dtype): world means ->
   OpenCV camera with ``world_to_cam = inv(cam_to_world)``; pinhole projection to pixels
   ``u = fx x/z + cx`` (pixel centres at +0.5); 3D covariance ``R(q) diag(s)^2 R(q)^T`` with
   ``q`` safely normalised (zero -> identity) and ``s`` clamped to ``[0, max_scale]``; EWA 2D
   covariance ``J W Sigma W^T J^T`` with the Jacobian's ``x/z, y/z`` clamped to a
   ``guard_band`` (1.3x) field of view; ``+low_pass`` on the diagonal; conic = its inverse.
   Gaussians with camera depth ``z <= near`` are culled. Also checks every input is finite.
2. **Binning**: opacity-aware footprint, the ellipse where ``o * g >= alpha_min``
   (``q <= 2 ln(o / alpha_min)``, no fixed 3 sigma); a Gaussian is listed in a 16x16 tile only
   if that ellipse meets the rectangle spanned by the tile's pixel centres (exact, per row of
   tiles). Visible Gaussians are radix-sorted by depth, then the (tile, depth-rank) keys of all
   pairs are radix-sorted: the global sort by (tile, depth) of 3DGS.
3. **Compositing**: per pixel, front to back, ``alpha = min(alpha_max, o g)``, skipped when
   ``< alpha_min``; a pixel stops before the Gaussian that would bring its transmittance below
   ``transmittance_min``; 12 feature channels + opacity (``O = 1 - T_final``), background
   added to color. 16 pixels of a tile row are one SIMD vector.
4. **Backward**: each tile's list back to front, recovering ``T_i = T_{i+1} / (1 - alpha_i)``;
   per-thread gradient buffers reduced at the end; then the chain rule through the projection
   (hand-written, checked against the dense PyTorch twin and finite differences).

Gradients reach means, quats, scales, opacities, colors, normals, albedo, roughness,
metallic, background and ``cam_to_world`` (through ``torch.linalg.inv``), so scene-graph node
poses composed in torch before the call (transforming means/quats/normals) get gradients by
ordinary autograd. The camera is a :class:`core.camera.Camera`; its intrinsics ``K`` get no gradient.
"""

from __future__ import annotations

import ctypes
from typing import Any

import torch

from core.camera import Camera, require_one_camera
from core.errors import ConfigError, NumericalError, ShapeError
from core.numerics import require_finite
from core.rotations import quat_normalize, quat_to_rotmat  # noqa: F401 - re-exported
from core.raster import _native
from core.raster.settings import NUM_FEATURES, NUM_OUTPUTS, RasterOutput, RasterSettings

NG = 6 + NUM_FEATURES  # floats per Gaussian handed to the kernels
TILE = 16
_INPUT_NAMES = ("means", "quats", "scales", "opacities", "colors", "normals", "albedo", "roughness", "metallic")


# Quaternion helpers live in core.rotations (one home for rotation maths); re-exported here.
safe_normalize_quat = quat_normalize


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _suffix(dtype: torch.dtype) -> str:
    return "f64" if dtype == torch.float64 else "f32"


class _Binning:
    """Sorted per-tile Gaussian lists (and the per-Gaussian footprint data) for one frame."""

    #: Initial capacity of the pair list per Gaussian; grows (with a second kernel call) when a
    #: frame has more pairs, and remembers the largest ratio seen.
    pairs_per_gaussian = 8.0

    def __init__(self, lib, suf: str, gdata: torch.Tensor, valid: torch.Tensor, width: int,
                 height: int, settings: RasterSettings, threads: int):
        n = gdata.shape[0]
        self.n_tiles = ((width + TILE - 1) // TILE) * ((height + TILE - 1) // TILE)
        self.aux = torch.empty(n, 2, dtype=gdata.dtype)
        self.tile_offsets = torch.empty(self.n_tiles + 1, dtype=torch.int64)
        self.tile_order = torch.empty(self.n_tiles, dtype=torch.int32)
        n_vis = ctypes.c_int64(0)
        cap = int(_Binning.pairs_per_gaussian * n) + 1024
        while True:
            tile_ids = torch.empty(cap, dtype=torch.int32)
            total = getattr(lib, f"br_bin_{suf}")(
                _ptr(gdata), _ptr(valid), n, width, height, settings.alpha_min, threads,
                _ptr(self.aux), cap, _ptr(self.tile_offsets), _ptr(tile_ids), _ptr(self.tile_order),
                ctypes.byref(n_vis))
            if total <= cap:
                break
            cap = int(total * 1.25) + 1024
            _Binning.pairs_per_gaussian = max(_Binning.pairs_per_gaussian, 1.25 * total / max(n, 1))
        self.tile_ids = tile_ids[:total]
        self.total = int(total)
        self.num_visible = int(n_vis.value)


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
        bad = getattr(lib, f"br_project_{suf}")(*[_ptr(t) for t in ins], _ptr(cam), width, height, n,
                                                threads, _ptr(gdata), _ptr(valid))
        if bad:
            name = _INPUT_NAMES[(bad & -bad).bit_length() - 1]
            raise NumericalError(f"{name}: non-finite value(s) (NaN or Inf)")
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
        buf = torch.empty(threads, n, NG, dtype=dtype)  # zeroed by the kernel
        getattr(lib, f"br_backward_{suf}")(
            _ptr(gdata), _ptr(binning.aux), _ptr(binning.tile_offsets), _ptr(binning.tile_ids),
            _ptr(binning.tile_order), binning.n_tiles, width, height, _ptr(bg),
            settings.alpha_min, settings.alpha_max, settings.transmittance_min, threads,
            _ptr(tfinal), _ptr(last), _ptr(grad_out), n, _ptr(buf))
        gg = buf[0]
        g_means = torch.empty(n, 3, dtype=dtype)
        g_quats = torch.empty(n, 4, dtype=dtype)
        g_scales = torch.empty(n, 3, dtype=dtype)
        g_opac = torch.empty(n, dtype=dtype)
        g_feat = [torch.empty(n, 3, dtype=dtype) for _ in range(3)] + [torch.empty(n, dtype=dtype) for _ in range(2)]
        pose = torch.zeros(12, dtype=torch.float64)
        getattr(lib, f"br_project_backward_{suf}")(
            _ptr(means), _ptr(quats), _ptr(scales), _ptr(opac), _ptr(ctx.cam), width, height, n,
            settings.num_threads, _ptr(gg), _ptr(g_means), _ptr(g_quats), _ptr(g_scales), _ptr(g_opac),
            *[_ptr(t) for t in g_feat], _ptr(pose))
        g_w2c = None
        if ctx.needs_input_grad[9]:
            g_w2c = torch.zeros(4, 4, dtype=torch.float64)
            g_w2c[:3, :3] = pose[:9].reshape(3, 3)
            g_w2c[:3, 3] = pose[9:]
        grad_bg = None
        if ctx.needs_input_grad[10]:
            grad_bg = (tfinal[..., None] * grad_out[..., :3]).sum(dim=(0, 1))
        return (g_means, g_quats, g_scales, g_opac, *g_feat, g_w2c, grad_bg, None, None, None, None, None)


# ---------------------------------------------------------------------------------------------
# validation and the public entry point
# ---------------------------------------------------------------------------------------------

def _check_tensor(x: Any, name: str, shape: tuple, dtype: torch.dtype | None,
                  check_finite: bool = True) -> torch.Tensor:
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
    if check_finite:  # the Gaussian attributes are checked by the projection kernel instead
        require_finite(x, name)
    return x


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
    camera: Camera,
    background: torch.Tensor | None = None,
    settings: RasterSettings | None = None,
) -> RasterOutput:
    """Render the G-buffers of world-space Gaussians seen by an OpenCV pinhole camera.

    All Gaussian inputs are *activated* values, ``N`` rows, one float dtype (float32 for speed,
    float64 for exact checks), on the CPU:
    means [N, 3] world metres; quats [N, 4] wxyz (need not be normalised; zero -> identity);
    scales [N, 3] metres (>= 0); opacities [N] or [N, 1] in [0, 1] (clamped); colors [N, 3];
    normals [N, 3] world, unit; albedo [N, 3]; roughness [N] or [N, 1]; metallic [N] or [N, 1].
    camera: one :class:`core.camera.Camera` (not a batch): ``cam_to_world`` [4, 4] rigid OpenCV
    camera-to-world, metres (any float dtype, may require grad: it gets a gradient); ``K`` in
    pixels (no gradient); ``width`` x ``height`` pixels, the output size. background: [3] color
    behind the Gaussians (default black; gets a gradient if it requires one).

    Returns a :class:`RasterOutput` of ``[H, W, C]`` tensors; gradients flow to every tensor
    input. Raises ShapeError / ConfigError / NumericalError naming the offending argument.
    """
    settings = settings if settings is not None else RasterSettings()
    if not isinstance(settings, RasterSettings):
        raise ConfigError(f"settings: expected RasterSettings, got {type(settings).__name__}")
    require_one_camera(camera)
    width, height = camera.width, camera.height
    means = _check_tensor(means, "means", (None, 3), None, False)
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ShapeError(f"means: dtype must be float32 or float64, got {dtype}")
    n = means.shape[0]
    quats = _check_tensor(quats, "quats", (n, 4), dtype, False)
    scales = _check_tensor(scales, "scales", (n, 3), dtype, False)

    def col(x, name):
        if isinstance(x, torch.Tensor) and x.dim() == 2 and x.shape[1:] == (1,):
            x = x.reshape(-1)
        return _check_tensor(x, name, (n,), dtype, False)

    opacities = col(opacities, "opacities")
    colors = _check_tensor(colors, "colors", (n, 3), dtype, False)
    normals = _check_tensor(normals, "normals", (n, 3), dtype, False)
    albedo = _check_tensor(albedo, "albedo", (n, 3), dtype, False)
    roughness = col(roughness, "roughness")
    metallic = col(metallic, "metallic")
    cam_to_world = _check_tensor(camera.cam_to_world, "cam_to_world", (4, 4), None)  # rigid: Camera checked
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
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
