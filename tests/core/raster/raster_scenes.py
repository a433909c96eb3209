"""Random small scenes shared by the rasterizer tests (imported by file name: unique basename)."""

from __future__ import annotations

import numpy as np
import torch

from core.conventions import look_at

NAMES = ("means", "quats", "scales", "opacities", "colors", "normals", "albedo", "roughness", "metallic")


def random_scene(n: int, seed: int = 0, dtype=torch.float64, spread: float = 1.0, scale=(0.05, 0.5),
                 opacity=(0.05, 0.95)) -> list[torch.Tensor]:
    """n Gaussians in front of a camera at the origin looking along +z (depth 2..6 m)."""
    g = torch.Generator().manual_seed(seed)

    def r(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    means = torch.stack([(r(n) * 4 - 2) * spread, (r(n) * 3 - 1.5) * spread, r(n) * 4 + 2], -1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = scale[0] + (scale[1] - scale[0]) * r(n, 3)
    opac = opacity[0] + (opacity[1] - opacity[0]) * r(n)
    colors = r(n, 3)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)
    return [means, quats, scales, opac, colors, normals, r(n, 3), r(n), r(n, 1)]


def camera(width: int, height: int, dtype=torch.float64, tilted: bool = True):
    """(cam_to_world, fx, fy, cx, cy, width, height), the arguments of
    :meth:`core.camera.Camera.from_intrinsics`: a slightly rotated, off-centre camera."""
    if tilted:
        c2w = torch.tensor(look_at(np.array([0.15, -0.1, -0.2]), np.array([0.1, 0.05, 4.0]),
                                   np.array([0.05, -1.0, 0.0])), dtype=dtype)
    else:
        c2w = torch.eye(4, dtype=dtype)
    return (c2w, 0.9 * width, 0.95 * width, 0.52 * width, 0.47 * height, width, height)


CHANNELS = ("color", "opacity", "depth", "normal", "albedo", "roughness", "metallic")
