"""Differentiable tile-based EWA splatting rasterizer of 3D Gaussians into G-buffers (CPU).

Public API
    :func:`rasterize` (activated, world-space tensors) and :func:`rasterize_gaussians` (a
    :class:`core.gaussians.Gaussians`), :class:`RasterSettings`, :class:`RasterOutput`.
    The dense PyTorch twin used by the tests is :mod:`core.raster.reference`.

Files
    ``splat.py``      the entry point, input validation and the ``torch.autograd.Function``
    ``settings.py``   ``RasterSettings`` (frozen, one docstring per field) and ``RasterOutput``
    ``_kernels.cpp``  projection, binning, forward and backward kernels (C++, SIMD, threads)
    ``_native.py``    builds ``_kernels.cpp`` once per machine (cached) and loads it via ctypes;
                      its docstring says why this is C++ rather than NVIDIA Warp
    ``reference.py``  dense per-pixel PyTorch twin (float64-capable), for tests only

Typical use::

    from core.raster import RasterSettings, rasterize
    camera = Camera.from_intrinsics(cam_to_world, fx, fy, cx, cy, width, height)  # core.camera
    out = rasterize(means, quats, scales, opacities, colors, normals, albedo, roughness, metallic,
                    camera, background=bg)
    loss = (out.color - target).abs().mean() + 0.1 * (out.opacity - mask).square().mean()
    loss.backward()   # gradients for every Gaussian attribute, background and cam_to_world

Performance notes: one call uses ``settings.threads`` threads (default: every core this process
may use). PyTorch's own OpenMP threads spin-wait for a while after each parallel torch op and
then compete with the kernels for the cores; on 2-core machines ``OMP_WAIT_POLICY=PASSIVE`` in
the worker's environment avoids that (the benchmark runs with the default environment).
"""

from core.camera import Camera
from core.errors import ConfigError
from core.raster.settings import FEATURE_CHANNELS, RasterOutput, RasterSettings
from core.raster.splat import quat_to_rotmat, rasterize, safe_normalize_quat


def rasterize_gaussians(gaussians, camera: Camera, background=None, settings=None):
    """:func:`rasterize` for a :class:`core.gaussians.Gaussians` (its activated attributes, the
    colour as seen from this camera's centre) and one :class:`core.camera.Camera`, whose
    ``cam_to_world`` is used in the Gaussians' dtype (``camera.to(gaussians.dtype)``: a float64
    pose is rounded for float32 Gaussians, as every caller did); gradients flow to the Gaussians'
    unconstrained parameters and to a pose that requires grad."""
    if not isinstance(camera, Camera):
        raise ConfigError(f"camera: expected a core.camera.Camera, got {type(camera).__name__}")
    camera = camera.to(gaussians.dtype)
    a = gaussians.activated(cam_center=camera.cam_to_world[:3, 3].detach())
    return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["colors"], a["normals"],
                     a["albedo"], a["roughness"], a["metallic"], camera, background=background,
                     settings=settings)


__all__ = [
    "FEATURE_CHANNELS",
    "RasterOutput",
    "RasterSettings",
    "quat_to_rotmat",
    "rasterize",
    "rasterize_gaussians",
    "safe_normalize_quat",
]
