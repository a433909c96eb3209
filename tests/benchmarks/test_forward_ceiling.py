"""The forward-pass ceiling diagnostic's corrector (``benchmarks/forward_ceiling.py``): it starts
as the identity on the OIDN frame, learns a residual that is a function of its inputs, and cannot
learn one that is not (its held-out gain on noise stays near zero)."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.forward_ceiling import Corrector, apply, fit, gain


def _frames(n: int, seed: int, h: int = 32, w: int = 40) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        x = rng.uniform(0.1, 0.6, size=(h, w, 13)).astype(np.float32)
        out.append(x)
    return out


def test_the_corrector_starts_as_the_identity_on_the_oidn_frame():
    x = _frames(1, 0)[0]
    net = Corrector(x.shape[-1])
    np.testing.assert_allclose(apply(net, x), np.clip(x[..., :3], 0, 1), atol=1e-6)


def test_a_residual_that_is_a_function_of_the_inputs_is_learned():
    xs = _frames(4, 1)
    # the reference: the OIDN frame brightened where the 'albedo' channel (3) is high
    ys = [np.clip(x[..., :3] + 0.3 * x[..., 3:4], 0, 1) for x in xs]
    net = fit(xs[:3], ys[:3], steps=150, crop=24, seed=0, width=8)
    g = gain(net, xs[3:], ys[3:])
    assert g["psnr_gain_db"] > 3.0, g


def test_noise_the_inputs_do_not_predict_gives_no_held_out_gain():
    xs = _frames(4, 2)
    rng = np.random.default_rng(3)
    ys = [np.clip(x[..., :3] + rng.normal(0, 0.1, size=x[..., :3].shape), 0, 1).astype(np.float32) for x in xs]
    torch.manual_seed(0)
    net = fit(xs[:3], ys[:3], steps=150, crop=24, seed=0, width=8)
    g = gain(net, xs[3:], ys[3:])
    assert g["psnr_gain_db"] < 0.5, g
