"""The material diagnostic's pooled metallic error split (``benchmarks/diagnose_materials.py``):
metal pixels (truth > 0.5) against the rest, summed over frames."""

from __future__ import annotations

import math

import torch

from benchmarks.diagnose_materials import _add, _finish, _split


def test_the_split_pools_frames_and_puts_the_error_where_it_is():
    # frame 1: two metal pixels predicted 0.5 (error 0.5 each), two plain pixels exact
    a = _split(torch.tensor([0.5, 0.5, 0.0, 0.0]), torch.tensor([1.0, 1.0, 0.0, 0.0]))
    # frame 2: no metal, one plain pixel predicted 0.2
    b = _split(torch.tensor([0.2, 0.0]), torch.tensor([0.0, 0.0]))
    r = _finish(_add(_add(None, a), b))
    se_metal, se_all = 2 * 0.25, 2 * 0.25 + 0.04
    assert math.isclose(r["metallic_rmse"], math.sqrt(se_all / 6), rel_tol=1e-6)
    assert math.isclose(r["metal_share_of_pixels"], 2 / 6)
    assert math.isclose(r["metal_share_of_error"], se_metal / se_all, rel_tol=1e-6)
    assert math.isclose(r["metallic_rmse_metal"], 0.5, rel_tol=1e-6)
    assert math.isclose(r["metallic_rmse_rest"], math.sqrt(0.04 / 4), rel_tol=1e-6)
    assert math.isclose(r["mean_pred_on_metal"], 0.5, rel_tol=1e-6)
    assert math.isclose(r["mean_pred_on_rest"], 0.2 / 4, rel_tol=1e-6)


def test_no_metal_pixels_leaves_the_metal_figures_at_zero_not_nan():
    r = _finish(_split(torch.tensor([0.1, 0.3]), torch.tensor([0.0, 0.0])))
    assert r["metal_share_of_pixels"] == 0 and r["metallic_rmse_metal"] == 0.0
    assert all(math.isfinite(v) for v in r.values())
