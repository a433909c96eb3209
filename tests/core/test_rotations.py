from __future__ import annotations

import math

import pytest
import torch

from core.errors import ShapeError
from core.rotations import (
    axis_angle_to_quat, quat_mul, quat_normalize, quat_slerp, quat_to_rotmat, rotmat_to_quat,
)


def _rand_quats(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return quat_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64))


def test_rotmat_is_orthonormal_and_roundtrips():
    q = _rand_quats(200)
    r = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(200, 3, 3)
    torch.testing.assert_close(r @ r.transpose(-1, -2), eye)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(200, dtype=torch.float64))
    q2 = rotmat_to_quat(r)
    q_pos = torch.where(q[:, :1] < 0, -q, q)
    torch.testing.assert_close(q2, q_pos)


def test_rotmat_to_quat_near_180_degrees():
    # the trace branch is unstable near 180 degrees: the largest-component branch must be used
    for axis in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]):
        v = torch.tensor(axis, dtype=torch.float64)
        v = v / v.norm() * (math.pi - 1e-9)
        r = quat_to_rotmat(axis_angle_to_quat(v))
        torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(r)), r, atol=1e-9, rtol=0)


def test_product_composes_rotations():
    a, b = _rand_quats(50, 1), _rand_quats(50, 2)
    torch.testing.assert_close(quat_to_rotmat(quat_mul(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))


def test_zero_quaternion_is_identity_with_finite_gradient():
    q = torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)
    r = quat_to_rotmat(q)
    torch.testing.assert_close(r[0], torch.eye(3, dtype=torch.float64))
    r.sum().backward()
    assert torch.isfinite(q.grad).all()


def test_slerp_endpoints_and_midpoint():
    a = axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64))
    b = axis_angle_to_quat(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(quat_slerp(a, b, 0.0), a)
    torch.testing.assert_close(quat_slerp(a, b, 1.0), b)
    mid = axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64))
    torch.testing.assert_close(quat_slerp(a, b, 0.5), mid)
    # identical inputs take the nlerp branch without NaN, in value and gradient
    x = a.clone().requires_grad_(True)
    out = quat_slerp(x, a, 0.3)
    out.sum().backward()
    torch.testing.assert_close(out.detach(), a)
    assert torch.isfinite(x.grad).all()


def test_axis_angle_small_angles_are_smooth():
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    q = axis_angle_to_quat(v)
    torch.testing.assert_close(q.detach(), torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    q[1].backward()
    torch.testing.assert_close(v.grad, torch.tensor([0.5, 0, 0], dtype=torch.float64))
    assert torch.autograd.gradcheck(axis_angle_to_quat, (torch.tensor([1e-5, 2e-5, -1e-5], dtype=torch.float64,
                                                                        requires_grad=True),))


def test_shapes_are_checked():
    with pytest.raises(ShapeError, match="q"):
        quat_normalize(torch.zeros(3))
    with pytest.raises(ShapeError, match="m"):
        rotmat_to_quat(torch.zeros(4, 4))
