"""Rotations in torch: quaternions (wxyz, Hamilton product), matrices, interpolation.

All functions are differentiable and NaN-free for any finite input: a (near-)zero quaternion is
treated as the identity.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError
from core.numerics import EPS_NORM_SQ


def _check(q: torch.Tensor, name: str, last: int) -> None:
    if not isinstance(q, torch.Tensor) or q.shape[-1:] != (last,):
        raise ShapeError(f"{name}: expected a tensor of shape [..., {last}], got "
                         f"{tuple(q.shape) if isinstance(q, torch.Tensor) else type(q).__name__}")


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] wxyz; (near-)zero quaternions become the identity (1, 0, 0, 0)."""
    _check(q, "q", 4)
    n2 = (q * q).sum(-1, keepdim=True)
    ok = n2 > EPS_NORM_SQ
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    inv = torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    return torch.where(ok, q * inv, ident)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of quaternions [..., 4] wxyz (rotation b first, then a)."""
    _check(a, "a", 4)
    _check(b, "b", 4)
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] wxyz (normalised first)."""
    w, x, y, z = quat_normalize(q).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(m: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] wxyz (w >= 0) of rotation matrices [..., 3, 3].

    Uses the numerically stable branch (largest of w, x, y, z) per matrix."""
    if not isinstance(m, torch.Tensor) or m.shape[-2:] != (3, 3):
        raise ShapeError(f"m: expected [..., 3, 3], got {tuple(getattr(m, 'shape', ()))}")
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    cands = torch.stack([
        1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22,
    ], -1)
    k = cands.argmax(-1, keepdim=True)
    s = torch.sqrt(torch.clamp(cands.gather(-1, k), min=1e-12)) * 2.0  # s = 4 * |component|
    s = s[..., 0]
    qw = torch.stack([s / 4, (m[..., 2, 1] - m[..., 1, 2]) / s, (m[..., 0, 2] - m[..., 2, 0]) / s,
                      (m[..., 1, 0] - m[..., 0, 1]) / s], -1)
    qx = torch.stack([(m[..., 2, 1] - m[..., 1, 2]) / s, s / 4, (m[..., 0, 1] + m[..., 1, 0]) / s,
                      (m[..., 0, 2] + m[..., 2, 0]) / s], -1)
    qy = torch.stack([(m[..., 0, 2] - m[..., 2, 0]) / s, (m[..., 0, 1] + m[..., 1, 0]) / s, s / 4,
                      (m[..., 1, 2] + m[..., 2, 1]) / s], -1)
    qz = torch.stack([(m[..., 1, 0] - m[..., 0, 1]) / s, (m[..., 0, 2] + m[..., 2, 0]) / s,
                      (m[..., 1, 2] + m[..., 2, 1]) / s, s / 4], -1)
    q = torch.where(k == 0, qw, torch.where(k == 1, qx, torch.where(k == 2, qy, qz)))
    q = torch.where(q[..., :1] < 0, -q, q)
    return quat_normalize(q)


def quat_slerp(a: torch.Tensor, b: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Spherical interpolation between unit quaternions a (t=0) and b (t=1), shortest arc."""
    a = quat_normalize(a)
    b = quat_normalize(b)
    t = torch.as_tensor(t, dtype=a.dtype, device=a.device)
    dot = (a * b).sum(-1, keepdim=True)
    b = torch.where(dot < 0, -b, b)
    dot = dot.abs().clamp(max=1.0)
    # nearly parallel: fall back to normalised lerp (sin(theta) -> 0); guard both branches
    near = dot > 0.9995
    theta = torch.acos(torch.where(near, torch.zeros_like(dot), dot))
    sin_t = torch.sin(theta)
    safe_sin = torch.where(near, torch.ones_like(sin_t), sin_t)
    tt = t.reshape(t.shape + (1,) * 0) if t.dim() else t
    wa = torch.where(near, 1 - tt, torch.sin((1 - tt) * theta) / safe_sin)
    wb = torch.where(near, tt, torch.sin(tt * theta) / safe_sin)
    return quat_normalize(wa * a + wb * b)


def axis_angle_to_quat(v: torch.Tensor) -> torch.Tensor:
    """Quaternions [..., 4] of rotation vectors [..., 3] (axis * angle, radians); smooth at 0."""
    _check(v, "v", 3)
    th2 = (v * v).sum(-1, keepdim=True)
    small = th2 < 1e-8
    th = torch.sqrt(torch.where(small, torch.ones_like(th2), th2))
    half = 0.5 * th
    # sin(th/2)/th -> 1/2 - th^2/48 near zero (Taylor), exact formula elsewhere
    k = torch.where(small, 0.5 - th2 / 48.0, torch.sin(half) / th)
    w = torch.where(small, 1.0 - th2 / 8.0, torch.cos(half))
    return torch.cat([w, v * k], -1)
