"""The post-hoc diagnostic of the inverse model (``benchmarks/diagnose_inverse_posthoc.py``): the
monotone calibration and the colour guided filter."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.diagnose_inverse_posthoc import BINS, apply_monotone, box, fit_monotone, guided_filter, pava


def test_pava_pools_violators_into_their_weighted_mean():
    out = pava(np.array([0.1, 0.5, 0.3, 0.9]), np.array([1.0, 1.0, 3.0, 1.0]))
    assert np.allclose(out, [0.1, 0.35, 0.35, 0.9])
    assert np.all(np.diff(out) >= 0)


def test_calibration_learns_a_shrinkage_and_keeps_order():
    rng = np.random.default_rng(0)
    pred = rng.uniform(0, 1, 20000)
    true = 0.5 * pred  # an over-confident model: the truth is half of what it says
    table = fit_monotone(pred, true)
    assert table.shape == (BINS,) and np.all(np.diff(table) >= -1e-12)
    q = apply_monotone(table, torch.tensor([0.2, 0.8], dtype=torch.float64)).numpy()
    assert np.allclose(q, [0.1, 0.4], atol=0.01)


def test_box_mean_is_normalised_at_the_border():
    x = torch.ones(1, 1, 5, 6, dtype=torch.float64)
    assert torch.allclose(box(x, 2), x)


def test_guided_filter_snaps_a_blurred_edge_to_the_guide_edge():
    # guide: a sharp vertical colour edge; p: the same edge blurred over 4 px (a soft prediction)
    w = 16
    guide = torch.zeros(1, 3, 8, w, dtype=torch.float64)
    guide[..., w // 2:] = torch.tensor([0.8, 0.6, 0.4], dtype=torch.float64)[:, None, None]
    ramp = torch.clamp((torch.arange(w, dtype=torch.float64) - (w // 2 - 2) + 0.5) / 4, 0, 1)
    p = ramp.expand(1, 1, 8, w).clone()
    truth = (torch.arange(w) >= w // 2).double().expand(1, 1, 8, w)
    q = guided_filter(guide, p, r=2, eps=1e-4)
    assert torch.isfinite(q).all()
    assert float(((q - truth) ** 2).mean()) < 0.5 * float(((p - truth) ** 2).mean())
    # a flat guide leaves the box mean of p (no edge to follow)
    flat = guided_filter(torch.full_like(guide, 0.5), p, r=1, eps=1e-3)
    assert torch.allclose(flat, box(box(p, 1), 1), atol=1e-9)
