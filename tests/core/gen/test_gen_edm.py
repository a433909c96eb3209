"""EDM preconditioning, schedule, solvers, SDEdit, windows and flicker."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import ConfigError, NumericalError, ShapeError
from core.gen.edm import (OnnxDenoiser, SamplerSettings, TorchDenoiser, WindowedDenoiser, flicker, generate, sdedit,
                          sigma_schedule, tau_to_sigma, window_starts)
from core.gen.nets import edm_coefficients, example_inputs
from core.gen.runtime import load_model


def test_schedule_and_tau():
    s = sigma_schedule(8, 0.002, 80.0, 7.0)
    assert s.shape == (9,) and s[-1] == 0
    assert math.isclose(float(s[0]), 80.0, rel_tol=1e-12) and math.isclose(float(s[7]), 0.002, rel_tol=1e-9)
    assert torch.all(s[1:] < s[:-1])
    assert math.isclose(tau_to_sigma(1.0), 80.0) and math.isclose(tau_to_sigma(0.0), 0.002)
    with pytest.raises(ConfigError, match="tau"):
        tau_to_sigma(1.5)


def test_edm_coefficients_values():
    sd = 0.5
    sig = torch.tensor([0.1, 0.5, 2.0], dtype=torch.float64)
    c_skip, c_out, c_in, c_noise = edm_coefficients(sig, sd)
    assert torch.allclose(c_skip, sd ** 2 / (sig ** 2 + sd ** 2))
    assert torch.allclose(c_out, sig * sd / torch.sqrt(sig ** 2 + sd ** 2))
    assert torch.allclose(c_in ** 2 * (sd ** 2 + sig ** 2), torch.ones(3, dtype=torch.float64))  # unit input variance
    assert torch.allclose(c_noise, torch.log(sig) / 4)


def _gauss_denoiser(mu, s):
    """Ideal denoiser of data ~ N(mu, s^2): E[x0 | x] = mu + s^2 / (s^2 + sigma^2) (x - mu)."""
    def d(x, sigma, cond):
        sg = sigma.reshape(-1, 1, 1, 1, 1).double()
        return (mu + s ** 2 / (s ** 2 + sg ** 2) * (x.double() - mu)).float()
    return d


def test_ode_converges_to_analytic_gaussian_flow():
    """For Gaussian data the probability-flow ODE is x(sigma) = mu + (x_T - mu) sqrt(s^2 + sigma^2)
    / sqrt(s^2 + sigma_T^2): SDEdit from sigma_tau must converge to it, Heun at second order."""
    mu, s = 0.3, 0.2
    x_in = torch.full((1, 1, 8, 8), 0.9)
    g = torch.Generator().manual_seed(0)
    eps = torch.randn((1, 1, 1, 8, 8), generator=g)[0]
    expect = mu + (x_in + eps - mu) * s / math.sqrt(s ** 2 + 1.0)
    err = {}
    for solver in ("euler", "heun"):
        for steps in (8, 32, 128):
            out = sdedit(_gauss_denoiser(mu, s), x_in, {}, SamplerSettings(sigma_tau=1.0, steps=steps, solver=solver))
            err[solver, steps] = float((out - expect).abs().max())
    assert err["heun", 128] < 1e-3 and err["euler", 128] < 2e-2
    assert err["euler", 32] < err["euler", 8] / 2.5 and err["heun", 32] < err["heun", 8] / 10
    assert all(err["heun", n] < err["euler", n] for n in (8, 32, 128))


def test_sdedit_with_perfect_denoiser_returns_clean():
    clean = torch.rand(3, 3, 16, 16)
    out = sdedit(lambda x, s, c: clean[None].expand_as(x), clean, {}, SamplerSettings(sigma_tau=2.0))
    assert torch.allclose(out, clean, atol=1e-5)


def test_windows_blend_like_one_pass_and_shared_noise_gives_no_flicker():
    """A per-frame denoiser gives the same result with or without windows; with shared noise a
    static clip stays static (flicker 0)."""
    starts = window_starts(7, 3, 1)
    assert starts[0] == 0 and starts[-1] == 4 and all(b - a <= 2 for a, b in zip(starts, starts[1:]))
    den = _gauss_denoiser(0.0, 0.5)
    clip = torch.rand(7, 3, 8, 8)
    a = sdedit(den, clip, {}, SamplerSettings(window=3, overlap=1))
    b = sdedit(den, clip, {}, SamplerSettings(window=7))
    assert torch.allclose(a, b, atol=1e-5)
    static = clip[:1].expand(7, -1, -1, -1).contiguous()
    out = sdedit(den, static, {}, SamplerSettings(window=3, overlap=1, shared_noise=True))
    assert flicker(out) < 1e-6
    out_indep = sdedit(den, static, {}, SamplerSettings(window=3, overlap=1, shared_noise=False))
    assert flicker(out_indep) > 1e-3


def test_windowed_denoiser_batches_windows():
    calls = []

    def den(x, s, c):
        calls.append(tuple(x.shape))
        return x
    w = WindowedDenoiser(den, 4, 2)
    w(torch.zeros(1, 9, 3, 8, 8), torch.ones(1), {})
    assert calls == [(4, 4, 3, 8, 8)]  # starts 0, 2, 4, 5 in one batch


def test_flicker_value_and_errors():
    f = np.zeros((3, 2, 2, 1))
    f[1] = 1.0
    assert flicker(f) == pytest.approx(1.0)
    with pytest.raises(ShapeError):
        flicker(np.zeros((1, 4)))
    f[2, 0, 0, 0] = np.inf
    with pytest.raises(NumericalError, match="frames"):
        flicker(f)


def test_nonfinite_inputs_raise():
    x = torch.rand(2, 3, 8, 8)
    x[0, 0, 0, 0] = float("nan")
    with pytest.raises(NumericalError, match="x_in"):
        sdedit(lambda x, s, c: x, x, {})
    with pytest.raises(NumericalError, match="denoiser output"):
        sdedit(lambda x, s, c: x * float("inf"), torch.rand(1, 3, 8, 8), {})


def test_torch_and_onnx_denoisers_agree_through_the_sampler(small_models):
    model, path = small_models["fwd_a"]
    ex = example_inputs("forward_denoiser", 1, 5, 16, 24, seed=3)
    x = ex.pop("x_t")[0]
    ex.pop("sigma")
    cond = {k: v[0] for k, v in ex.items()}
    st = SamplerSettings(steps=3, solver="heun", window=2, overlap=1)
    a = sdedit(TorchDenoiser(model), x, cond, st)
    b = sdedit(OnnxDenoiser(load_model(path, threads=1)), x, cond, st)
    assert a.shape == (5, 3, 16, 24)
    assert float((a - b).abs().max()) < 1e-4
    g = generate(OnnxDenoiser(load_model(small_models["inv"][1], threads=1)), (2, 9, 16, 16),
                 {"rgb": torch.rand(2, 3, 16, 16)}, SamplerSettings(steps=2))
    assert g.shape == (2, 9, 16, 16) and torch.isfinite(g).all()
