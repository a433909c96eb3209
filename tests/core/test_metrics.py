from __future__ import annotations

import math

import pytest
import torch

from core.errors import ShapeError
from core.metrics import angular_error_deg, psnr, si_psnr, ssim


def test_psnr_known_value():
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)
    assert abs(float(psnr(a, b)) - 20.0) < 1e-4  # mse 0.01 -> 20 dB
    assert float(psnr(a, a)) == pytest.approx(100.0)  # capped, not inf
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:2] = True
    b2 = b.clone()
    b2[2:] = 0.0
    assert float(psnr(a, b2, mask)) == pytest.approx(20.0, abs=1e-4)


def test_ssim_identity_and_noise():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(32, 40, 3, generator=g)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    y = (x + 0.2 * torch.randn(32, 40, 3, generator=g)).clamp(0, 1)
    assert 0.0 < float(ssim(x, y)) < 0.9


def test_si_psnr_ignores_scale():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(16, 16, 3, generator=g) * 0.5
    assert float(si_psnr(x * 0.3, x)) > 60
    assert float(psnr(x * 0.3, x)) < 30


def test_angular_error():
    a = torch.tensor([[0.0, 0.0, 1.0]])
    b = torch.tensor([[0.0, 1.0, 1.0]])
    assert float(angular_error_deg(a, b)) == pytest.approx(45.0, abs=1e-3)
    assert math.isfinite(float(angular_error_deg(torch.zeros(1, 3), b)))


def test_shapes_named():
    with pytest.raises(ShapeError, match="pred"):
        psnr(torch.zeros(3), torch.zeros(3))
