"""core.numerics: each guard at its edges (zero, negative, huge, NaN/Inf), finite gradients at the
guarded points, and the numpy and torch twins agreeing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import NumericalError
from core.numerics import (ACOS_CLAMP, EPS_NORM_SQ, EPS_PDF, EPS_SQRT, clamped_acos, require_finite,
                           require_finite_np, safe_div, safe_normalize, safe_normalize_np, safe_sqrt, smoothstep)


def _grad(fn, x: torch.Tensor) -> torch.Tensor:
    """d sum(fn(x)) / dx, float64."""
    x = x.detach().to(torch.float64).requires_grad_()
    (g,) = torch.autograd.grad(fn(x).sum(), x)
    return g


def _random_vectors(n: int, dim: int = 3, seed: int = 0, scale: float = 1.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, dim)) * scale


# --- safe_sqrt ------------------------------------------------------------------------------------

def test_safe_sqrt_values_at_the_edges():
    x = torch.tensor([0.0, -1.0, -1e-30, EPS_SQRT, 4.0, 1e300, math.inf], dtype=torch.float64)
    got = safe_sqrt(x)
    assert got[:4].tolist() == [0.0] * 4  # zero, negative (rounding below 0) and x <= EPS_SQRT: 0
    assert got[4] == 2.0 and got[5] == pytest.approx(1e150) and math.isinf(got[6])
    # NaN is not > EPS_SQRT: the guard gives 0 (require_finite is the check that reports NaN)
    assert safe_sqrt(torch.tensor([math.nan])).tolist() == [0.0]


def test_safe_sqrt_matches_sqrt_above_the_guard():
    x = torch.from_numpy(np.random.default_rng(1).random(100) * 10 + 1e-6)
    torch.testing.assert_close(safe_sqrt(x), torch.sqrt(x), rtol=0, atol=0)
    assert safe_sqrt(x.float()).dtype == torch.float32


def test_safe_sqrt_gradient_finite_at_and_below_zero():
    g = _grad(safe_sqrt, torch.tensor([0.0, -2.0, EPS_SQRT, 4.0]))
    assert torch.isfinite(g).all()
    assert g[:3].tolist() == [0.0, 0.0, 0.0]
    assert float(g[3]) == pytest.approx(0.25)  # d sqrt(x) / dx = 1 / (2 sqrt x)


# --- safe_normalize / safe_normalize_np -----------------------------------------------------------

def test_safe_normalize_unit_length_and_zero_vectors():
    v = torch.from_numpy(_random_vectors(50))
    n = safe_normalize(v)
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(50, dtype=torch.float64))
    torch.testing.assert_close(n * v.norm(dim=-1, keepdim=True), v)
    zero = torch.zeros(2, 3, dtype=torch.float64)
    assert torch.equal(safe_normalize(zero), zero)
    tiny = torch.full((1, 3), math.sqrt(EPS_NORM_SQ) / 10, dtype=torch.float64)  # below the guard
    assert torch.equal(safe_normalize(tiny), torch.zeros_like(tiny))


def test_safe_normalize_huge_and_dim():
    huge = torch.from_numpy(_random_vectors(10, scale=1e100))
    torch.testing.assert_close(safe_normalize(huge).norm(dim=-1), torch.ones(10, dtype=torch.float64))
    v = torch.from_numpy(_random_vectors(4, dim=5, seed=2)).T  # normalise along dim 0
    torch.testing.assert_close(safe_normalize(v, dim=0).norm(dim=0), torch.ones(4, dtype=torch.float64))


def test_safe_normalize_does_not_hide_nan():
    out = safe_normalize(torch.tensor([[math.nan, 0.0, 1.0]]))
    assert torch.isnan(out).any()


def test_safe_normalize_gradient_finite_at_zero():
    v = torch.cat([torch.zeros(1, 3), torch.from_numpy(_random_vectors(3, seed=3)).float()])
    g = _grad(safe_normalize, v)
    assert torch.isfinite(g).all()
    assert g[0].tolist() == [0.0, 0.0, 0.0]  # a zero vector maps to zero with zero gradient


def test_safe_normalize_np_fallbacks_and_dtypes():
    v = np.zeros((2, 3))
    np.testing.assert_array_equal(safe_normalize_np(v), np.tile([0.0, 0.0, 1.0], (2, 1)))  # +z for 3-vectors
    np.testing.assert_array_equal(safe_normalize_np(np.zeros((2, 4))), np.zeros((2, 4)))  # else zeros
    fb = np.array([1.0, 0.0, 0.0])
    np.testing.assert_array_equal(safe_normalize_np(v, fallback=fb), np.tile(fb, (2, 1)))
    assert safe_normalize_np(v).dtype == np.float64
    assert safe_normalize_np(v.astype(np.float32)).dtype == np.float32
    assert safe_normalize_np(np.ones((1, 3), np.int64)).dtype == np.float32
    cols = safe_normalize_np(_random_vectors(6, seed=4).T, axis=0)
    np.testing.assert_allclose(np.linalg.norm(cols, axis=0), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(safe_normalize_np(_random_vectors(5, scale=1e100)), axis=-1), 1.0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_safe_normalize_numpy_and_torch_agree(dtype):
    v = _random_vectors(200, seed=5).astype(dtype)
    v[:3] = 0.0  # the twins differ on purpose only here: numpy falls back to +z, torch to zero
    got_np = safe_normalize_np(v)
    got_t = safe_normalize(torch.from_numpy(v)).numpy()
    tol = 1e-6 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(got_np[3:], got_t[3:], rtol=tol, atol=tol)
    np.testing.assert_array_equal(got_t[:3], 0.0)
    np.testing.assert_array_equal(got_np[:3], np.tile([0.0, 0.0, 1.0], (3, 1)))


# --- clamped_acos ---------------------------------------------------------------------------------

def test_clamped_acos_values():
    x = torch.linspace(-0.99, 0.99, 101, dtype=torch.float64)
    torch.testing.assert_close(clamped_acos(x), torch.acos(x))
    ends = clamped_acos(torch.tensor([1.0, -1.0, 5.0, -5.0], dtype=torch.float64))
    assert float(ends[0]) == float(ends[2]) == pytest.approx(math.acos(ACOS_CLAMP))
    assert float(ends[1]) == float(ends[3]) == pytest.approx(math.acos(-ACOS_CLAMP))
    assert 0.0 < float(ends[0]) < 1e-3 and math.pi - 1e-3 < float(ends[1]) < math.pi


def test_clamped_acos_gradient_finite_at_plus_minus_one():
    x = torch.tensor([1.0, -1.0, 1.5, -1.5, ACOS_CLAMP, 0.0], dtype=torch.float64)
    assert not torch.isfinite(_grad(torch.acos, x[:2])).any()  # what the clamp is for
    g = _grad(clamped_acos, x)
    assert torch.isfinite(g).all()
    assert float(g[5]) == pytest.approx(-1.0)  # d acos(x) / dx = -1 / sqrt(1 - x^2)
    assert float(g[4]) == pytest.approx(-1.0 / math.sqrt(1.0 - ACOS_CLAMP ** 2), rel=1e-6)


# --- require_finite / require_finite_np -----------------------------------------------------------

@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_require_finite_raises_naming_the_argument(bad):
    arr = np.array([0.0, bad, 1.0, bad])
    for fn, x in ((require_finite_np, arr), (require_finite, arr), (require_finite, torch.from_numpy(arr))):
        with pytest.raises(NumericalError, match=r"depth map: 2 non-finite value\(s\)"):
            fn(x, "depth map")


def test_require_finite_passes_finite_huge_and_integer_values_through():
    a = np.array([0.0, -1e308, 1e308])
    assert require_finite_np(a, "a") is a
    t = torch.from_numpy(a)
    assert require_finite(t, "t") is t
    assert require_finite(a, "a") is a
    ints = np.array([1, 2, 3])
    assert require_finite_np(ints, "ints") is ints
    assert require_finite(torch.arange(3), "ints") is not None
    np.testing.assert_array_equal(require_finite([1.0, 2.0], "list"), [1.0, 2.0])
    assert require_finite_np(np.zeros(0), "empty").size == 0


def test_require_finite_numpy_and_torch_agree():
    rng = np.random.default_rng(6)
    a = rng.normal(size=(8, 8))
    a[rng.random((8, 8)) < 0.2] = np.nan
    with pytest.raises(NumericalError) as e_np:
        require_finite_np(a, "x")
    with pytest.raises(NumericalError) as e_t:
        require_finite(torch.from_numpy(a), "x")
    assert str(e_np.value) == str(e_t.value)


# --- safe_div -------------------------------------------------------------------------------------

def test_safe_div_values_at_the_edges():
    a = torch.tensor([1.0, 1.0, 1.0, -6.0, 1e300, 1.0, 1.0], dtype=torch.float64)
    b = torch.tensor([0.0, EPS_PDF, -EPS_PDF / 2, -3.0, 1e-5, math.nan, math.inf], dtype=torch.float64)
    got = safe_div(a, b)
    assert got[:3].tolist() == [0.0, 0.0, 0.0]  # |b| <= eps: 0, never Inf
    assert float(got[3]) == 2.0 and float(got[4]) == pytest.approx(1e305)
    assert float(got[5]) == 0.0  # NaN is not > eps: 0 (require_finite reports NaN)
    assert float(got[6]) == 0.0  # 1 / Inf
    assert safe_div(torch.ones(1), torch.full((1,), 0.5), eps=1.0).tolist() == [0.0]  # the eps argument


def test_safe_div_broadcasts_and_gradient_finite_at_zero():
    a = torch.from_numpy(_random_vectors(4, seed=7))
    b = torch.tensor([[0.0], [2.0], [-1e-12], [4.0]], dtype=torch.float64)
    got = safe_div(a, b)
    assert got.shape == (4, 3)
    torch.testing.assert_close(got[[1, 3]], a[[1, 3]] / b[[1, 3]])
    a_, b_ = a.clone().requires_grad_(), b.clone().requires_grad_()
    ga, gb = torch.autograd.grad(safe_div(a_, b_).sum(), (a_, b_))
    assert torch.isfinite(ga).all() and torch.isfinite(gb).all()
    assert ga[0].tolist() == [0.0] * 3 and gb[0].tolist() == [0.0] and gb[2].tolist() == [0.0]
    torch.testing.assert_close(gb[1], -a[1].sum(0, keepdim=True) / 4.0)


# --- smoothstep -----------------------------------------------------------------------------------

def test_smoothstep_values():
    x = torch.linspace(-1.0, 3.0, 401, dtype=torch.float64)
    s = smoothstep(0.0, 2.0, x)
    assert float(s.min()) == 0.0 and float(s.max()) == 1.0
    assert (s[1:] >= s[:-1]).all()  # monotone
    t = (x / 2).clamp(0, 1)
    torch.testing.assert_close(s, t * t * (3 - 2 * t))
    ends = smoothstep(0.0, 2.0, torch.tensor([0.0, 1.0, 2.0, -1e300, 1e300, math.inf, -math.inf]))
    assert ends.tolist() == [0.0, 0.5, 1.0, 0.0, 1.0, 1.0, 0.0]


def test_smoothstep_empty_interval_is_a_hard_step():
    x = torch.tensor([-1.0, 0.5, 0.99, 1.0, 2.0])
    for e1 in (1.0, 0.0, 1.0 + EPS_PDF / 2):  # edge1 == edge0, edge1 < edge0, a width below the guard
        assert smoothstep(1.0, e1, x).tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]
    g = _grad(lambda v: smoothstep(1.0, 1.0, v), x)
    assert torch.isfinite(g).all() and g.abs().max() == 0.0


def test_smoothstep_tensor_edges_broadcast_and_finite_gradient():
    e0 = torch.tensor([[0.0], [1.0], [2.0]], dtype=torch.float64)
    e1 = torch.tensor([[1.0], [1.0], [4.0]], dtype=torch.float64)  # the middle row is empty: a step
    x = torch.linspace(-1.0, 5.0, 7, dtype=torch.float64)
    s = smoothstep(e0, e1, x)
    assert s.shape == (3, 7)
    assert s[1].tolist() == (x >= 1.0).double().tolist()
    torch.testing.assert_close(s[0], smoothstep(0.0, 1.0, x))
    g = _grad(lambda v: smoothstep(e0, e1, v), x)
    assert torch.isfinite(g).all()
    assert float(_grad(lambda v: smoothstep(0.0, 2.0, v), torch.tensor([1.0]))) == pytest.approx(0.75)  # 6t(1-t)/w
    assert smoothstep(0.0, 1.0, x.float()).dtype == torch.float32
