"""Differentiable tile-based EWA splatting rasterizer of 3D Gaussians into G-buffers.

Public API: :func:`rasterize` (activated, world-space tensors), :func:`rasterize_gaussians`
(a :class:`core.gaussians.Gaussians`), :class:`RasterSettings`, :class:`RasterOutput`.
The dense PyTorch twin used by the tests is :mod:`core.raster.reference`.
"""

from core.raster.splat import quat_to_rotmat, rasterize, safe_normalize_quat
from core.raster.settings import FEATURE_CHANNELS, RasterOutput, RasterSettings


def rasterize_gaussians(gaussians, cam_to_world, fx, fy, cx, cy, width, height, background=None,
                        settings=None):
    """:func:`rasterize` for a :class:`core.gaussians.Gaussians` (its activated attributes)."""
    a = gaussians.activated()
    return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["colors"], a["normals"],
                     a["albedo"], a["roughness"], a["metallic"], cam_to_world, fx, fy, cx, cy,
                     width, height, background=background, settings=settings)


__all__ = [
    "FEATURE_CHANNELS",
    "RasterOutput",
    "RasterSettings",
    "quat_to_rotmat",
    "rasterize",
    "rasterize_gaussians",
    "safe_normalize_quat",
]
