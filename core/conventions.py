"""The project's coordinate conventions, decided once and used everywhere.

World
    Right-handed, z up, metres.
Cameras
    OpenCV axes: x right, y down, z forward. A pose is ``cam_to_world``: a rigid 4x4 matrix whose
    columns 0..2 are the camera axes in world coordinates and column 3 is the camera centre.
    Intrinsics are pinhole ``fx, fy, cx, cy`` in pixels; pixel (u, v) = (column, row), and the
    centre of the top-left pixel is (0.5, 0.5).
Environment maps
    Equirectangular, H rows x W columns (W = 2H), row 0 = zenith (+z). A world direction
    ``d = (x, y, z)`` has polar angle ``theta = acos(z)`` and azimuth ``phi = atan2(y, x)``
    (measured from +x toward +y). It maps to continuous image coordinates

        v = theta / pi * H                      (rows, 0 at the zenith)
        u = ((1/4 - phi / (2 pi)) mod 1) * W    (columns)

    so column c (centre c + 0.5) has azimuth ``phi = pi/2 - 2 pi (c + 0.5) / W``. This is exactly
    how Mitsuba 3's ``envmap`` emitter reads an image when given ``to_world = rotate(x, 90 deg)``
    (:data:`MITSUBA_ENVMAP_TO_WORLD_ROTATION_X_DEG`), so an HDRI passed to Mitsuba and read by
    this project lights the world from the same directions. ``tests/core/test_conventions.py``
    checks it against Mitsuba with a sun-lit plane.
Angles
    Radians inside the code, degrees in the API.
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import ShapeError
from core.numerics import clamped_acos, safe_normalize

#: Rotation about +x, in degrees, that makes Mitsuba's envmap emitter follow this convention.
MITSUBA_ENVMAP_TO_WORLD_ROTATION_X_DEG = 90.0

#: OpenCV camera axes -> OpenGL/nerfstudio camera axes (x right, y up, z backward) and back:
#: the matrix is its own inverse.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])

#: OpenCV camera axes -> Mitsuba camera axes (x left, y up, z forward); its own inverse.
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])

#: Waymo camera axes (x forward, y left, z up) -> OpenCV axes: ``cam_to_vehicle_opencv =
#: cam_to_vehicle_waymo @ WAYMO_TO_OPENCV`` (as drivestudio does).
WAYMO_TO_OPENCV = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def _check_dirs(d: np.ndarray, name: str) -> np.ndarray:
    d = np.asarray(d, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ShapeError(f"{name}: expected shape [..., 3], got {tuple(d.shape)}")
    return d


def direction_to_uv(dirs_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous equirect coordinates of world directions.

    dirs_world: [..., 3] world, need not be unit length (zero vectors map to the zenith).
    Returns (u, v): columns in [0, W), rows in [0, H], pixel centres at integer + 0.5.
    """
    d = _check_dirs(dirs_world, "dirs_world")
    n = np.linalg.norm(d, axis=-1)
    safe = np.where(n > 0, n, 1.0)
    z = np.where(n > 0, d[..., 2] / safe, 1.0)
    theta = np.arccos(np.clip(z, -1.0, 1.0))
    phi = np.arctan2(d[..., 1], d[..., 0])
    v = theta / math.pi * height
    u = np.mod(0.25 - phi / (2.0 * math.pi), 1.0) * width
    return u, v


def direction_to_pixel(dirs_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer (row, col) of the equirect pixel containing each direction. dirs: [..., 3] world."""
    u, v = direction_to_uv(dirs_world, height, width)
    row = np.clip(np.floor(v).astype(np.int64), 0, height - 1)
    col = np.clip(np.floor(u).astype(np.int64), 0, width - 1)
    return row, col


def pixel_to_direction(row: np.ndarray, col: np.ndarray, height: int, width: int) -> np.ndarray:
    """Unit world direction [..., 3] of equirect pixel centres (row, col) (may be fractional:
    the centre of pixel (r, c) is passed as (r, c), not r + 0.5)."""
    row = np.asarray(row, dtype=np.float64)
    col = np.asarray(col, dtype=np.float64)
    theta = (row + 0.5) / height * math.pi
    phi = math.pi / 2.0 - 2.0 * math.pi * (col + 0.5) / width
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def envmap_directions(height: int, width: int) -> np.ndarray:
    """World directions [H, W, 3] of every pixel centre of an H x W equirect map."""
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    return pixel_to_direction(rows, cols, height, width)


def envmap_solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle [H] of one pixel in each row (steradians); sums to 4 pi over the map."""
    theta0 = np.arange(height) / height * math.pi
    theta1 = (np.arange(height) + 1) / height * math.pi
    return (np.cos(theta0) - np.cos(theta1)) * (2.0 * math.pi / width)


def is_rigid(m: np.ndarray, tol: float = 1e-4) -> bool:
    """True when ``m`` is a finite 4x4 rigid transform (orthonormal rotation, det +1, last row
    0 0 0 1) within ``tol``."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        return False
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=tol):
        return False
    if abs(np.linalg.det(r) - 1.0) > tol:
        return False
    return bool(np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=tol))


def project_points(points_world: np.ndarray, cam_to_world: np.ndarray, fx: float, fy: float,
                   cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """Project world points with an OpenCV pinhole camera.

    points_world: [N, 3] world, metres. Returns (uv [N, 2] pixels, z [N] camera depth, metres).
    Points with z <= 0 get uv = NaN (they are behind the camera).
    """
    p = _check_dirs(points_world, "points_world").reshape(-1, 3)
    w2c = np.linalg.inv(np.asarray(cam_to_world, dtype=np.float64))
    pc = p @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(z > 0, fx * pc[:, 0] / np.where(z > 0, z, 1.0) + cx, np.nan)
        v = np.where(z > 0, fy * pc[:, 1] / np.where(z > 0, z, 1.0) + cy, np.nan)
    return np.stack([u, v], axis=-1), z


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV ``cam_to_world`` [4, 4] for a camera at ``eye`` looking at ``target`` (world)."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, fwd, eye
    return m


def direction_to_uv_torch(dirs_world, height: int, width: int):
    """torch twin of :func:`direction_to_uv` (differentiable in the directions away from the
    poles). dirs_world: [..., 3] world. Returns (u, v) in pixels, u in [0, W), v in [0, H]."""
    import torch

    d = safe_normalize(dirs_world)
    theta = clamped_acos(d[..., 2])
    phi = torch.atan2(d[..., 1], d[..., 0])
    v = theta / math.pi * height
    u = torch.remainder(0.25 - phi / (2.0 * math.pi), 1.0) * width
    return u, v


def camera_ray_directions(cam_to_world: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                          width: int, height: int) -> np.ndarray:
    """World directions [H, W, 3] (unit) of the rays through every pixel centre."""
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    uu, vv = np.meshgrid(u, v)
    d_cam = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1)
    c2w = np.asarray(cam_to_world, np.float64)
    d = d_cam @ c2w[:3, :3].T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
