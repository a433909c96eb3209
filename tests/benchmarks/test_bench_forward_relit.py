"""The low-pass of the cleanup-pass benchmark (``benchmarks/bench_forward_relit.py``): it keeps
constants and means, removes fine detail, and its fused variant is OIDN where the model agrees."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_forward_relit import gaussian_lowpass


def test_lowpass_keeps_a_constant_and_the_shape():
    x = np.full((2, 17, 23, 3), 0.37, np.float32)
    y = gaussian_lowpass(x, 3.0)
    assert y.shape == x.shape
    assert np.allclose(y, 0.37, atol=1e-6)


def test_lowpass_removes_pixel_noise_but_keeps_a_smooth_ramp():
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.1, (1, 64, 64, 3)).astype(np.float32)
    assert gaussian_lowpass(noise, 4.0).std() < 0.2 * noise.std()
    ramp = np.broadcast_to(np.linspace(0, 1, 64, dtype=np.float32)[None, None, :, None], (1, 64, 64, 3)).copy()
    inner = (slice(None), slice(16, 48), slice(16, 48))  # away from the reflect-padded borders
    assert np.allclose(gaussian_lowpass(ramp, 2.0)[inner], ramp[inner], atol=1e-5)


def test_fused_variant_is_oidn_where_the_model_changes_nothing_at_low_frequency():
    rng = np.random.default_rng(1)
    oidn = rng.uniform(0.2, 0.8, (1, 32, 32, 3)).astype(np.float32)
    grain = rng.normal(0.0, 0.05, oidn.shape).astype(np.float32)  # the model's added grain, zero mean
    fused = oidn + gaussian_lowpass((oidn + grain) - oidn, 8.0)
    assert np.abs(fused - oidn).mean() < 0.1 * np.abs(grain).mean()


def test_masked_lowpass_ignores_the_sky_and_leaves_it_zero():
    from benchmarks.bench_forward_relit import masked_lowpass

    x = np.full((1, 24, 24, 3), 0.2, np.float32)
    x[:, :8] = 5.0  # the sky's difference, far off
    mask = np.ones((1, 24, 24), bool)
    mask[:, :8] = False
    y = masked_lowpass(x, mask, 4.0)
    assert np.allclose(y[:, 8:], 0.2, atol=1e-5)  # the surface's own constant, no sky bleeding in
    assert np.all(y[:, :8] == 0.0)
