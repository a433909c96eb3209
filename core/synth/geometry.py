"""Triangle-mesh primitives for the procedural street (numpy; world z-up, metres).

Every primitive returns ``(vertices [V, 3] float32, faces [F, 3] uint32)`` with faces wound
counter-clockwise seen from outside, so face normals point outward.
"""

from __future__ import annotations

import math

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def box(center, size, yaw: float = 0.0) -> Mesh:
    """Axis-aligned box of ``size`` (sx, sy, sz) centred at ``center``, rotated by ``yaw`` (radians
    about +z). Each face has its own 4 vertices so shading normals stay flat."""
    c = np.asarray(center, np.float64)
    hx, hy, hz = (np.asarray(size, np.float64) / 2.0)
    # (normal axis, sign) -> 4 corners CCW seen from outside
    quads = [
        [(+hx, -hy, -hz), (+hx, +hy, -hz), (+hx, +hy, +hz), (+hx, -hy, +hz)],  # +x
        [(-hx, +hy, -hz), (-hx, -hy, -hz), (-hx, -hy, +hz), (-hx, +hy, +hz)],  # -x
        [(+hx, +hy, -hz), (-hx, +hy, -hz), (-hx, +hy, +hz), (+hx, +hy, +hz)],  # +y
        [(-hx, -hy, -hz), (+hx, -hy, -hz), (+hx, -hy, +hz), (-hx, -hy, +hz)],  # -y
        [(-hx, -hy, +hz), (+hx, -hy, +hz), (+hx, +hy, +hz), (-hx, +hy, +hz)],  # +z
        [(-hx, +hy, -hz), (+hx, +hy, -hz), (+hx, -hy, -hz), (-hx, -hy, -hz)],  # -z
    ]
    v = np.array([p for q in quads for p in q], np.float64)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rot = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    v = v @ rot.T + c
    f = np.array([[4 * i, 4 * i + 1, 4 * i + 2] for i in range(6)] + [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(6)])
    return v.astype(np.float32), f.astype(np.uint32)


def quad(corners) -> Mesh:
    """A planar quad from 4 corners given CCW seen from the side the normal points to."""
    v = np.asarray(corners, np.float32).reshape(4, 3)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def cylinder(base, radius: float, height: float, segments: int = 16, axis: str = "z") -> Mesh:
    """Capped cylinder; ``base`` is the centre of the bottom cap; ``axis`` 'z' (upright) or 'y'
    (a wheel: then ``base`` is the centre and the cylinder spans +-height/2 along y)."""
    ang = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang) * radius, np.sin(ang) * radius], -1)
    verts, faces = [], []
    n = segments
    # side: separate ring vertices for bottom and top
    bottom = np.concatenate([ring, np.zeros((n, 1))], 1)
    top = np.concatenate([ring, np.full((n, 1), height)], 1)
    verts += [bottom, top, [[0, 0, 0]], [[0, 0, height]]]
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
        faces += [[2 * n, j, i], [2 * n + 1, n + i, n + j]]
    v = np.concatenate([np.asarray(x, np.float64) for x in verts], 0)
    f = np.asarray(faces)
    if axis == "y":
        v = v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0]) + np.array([0.0, height / 2.0, 0.0])
        f = f[:, ::-1]  # the axis swap mirrors: flip winding back to outward
    elif axis != "z":
        raise ValueError(axis)
    return (v + np.asarray(base, np.float64)).astype(np.float32), f.astype(np.uint32)


def sphere(center, radius: float, rings: int = 8, segments: int = 12) -> Mesh:
    """UV sphere (low poly: foliage)."""
    verts = []
    for i in range(rings + 1):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            verts.append((math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)))
    faces = []
    for i in range(rings):
        for j in range(segments):
            a = i * segments + j
            b = i * segments + (j + 1) % segments
            c = (i + 1) * segments + (j + 1) % segments
            d = (i + 1) * segments + j
            faces += [[a, d, c], [a, c, b]]
    v = np.asarray(verts) * radius + np.asarray(center, np.float64)
    return v.astype(np.float32), np.asarray(faces, np.uint32)


def merge(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes into one."""
    vs, fs, off = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs, 0).astype(np.float32), np.concatenate(fs, 0).astype(np.uint32)


def transform(mesh: Mesh, m: np.ndarray) -> Mesh:
    """Apply a 4x4 rigid transform to a mesh."""
    v, f = mesh
    m = np.asarray(m, np.float64)
    return (v.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32), f
