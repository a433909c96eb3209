"""The material diagnostic's pooled metallic error split (``benchmarks/diagnose_materials.py``):
metal pixels (truth > 0.5) against the rest, and pixels near a metal boundary against the rest,
summed over frames."""

from __future__ import annotations

import math

import numpy as np
import torch

from benchmarks.diagnose_materials import _add, _finish, _split, boundary_mask


def test_the_split_pools_frames_and_puts_the_error_where_it_is():
    # frame 1: two metal pixels predicted 0.5 (error 0.5 each), two plain pixels exact
    # (the first metal pixel and the first plain one on a boundary)
    a = _split(torch.tensor([0.5, 0.5, 0.0, 0.0]), torch.tensor([1.0, 1.0, 0.0, 0.0]),
               torch.tensor([True, False, True, False]))
    # frame 2: no metal, one plain pixel predicted 0.2
    b = _split(torch.tensor([0.2, 0.0]), torch.tensor([0.0, 0.0]), torch.tensor([False, False]))
    r = _finish(_add(_add(None, a), b))
    se_metal, se_all = 2 * 0.25, 2 * 0.25 + 0.04
    assert math.isclose(r["metallic_rmse"], math.sqrt(se_all / 6), rel_tol=1e-6)
    assert math.isclose(r["metal_share_of_pixels"], 2 / 6)
    assert math.isclose(r["metal_share_of_error"], se_metal / se_all, rel_tol=1e-6)
    assert math.isclose(r["metallic_rmse_metal"], 0.5, rel_tol=1e-6)
    assert math.isclose(r["metallic_rmse_rest"], math.sqrt(0.04 / 4), rel_tol=1e-6)
    assert math.isclose(r["mean_pred_on_metal"], 0.5, rel_tol=1e-6)
    assert math.isclose(r["mean_pred_on_rest"], 0.2 / 4, rel_tol=1e-6)
    assert math.isclose(r["boundary_share_of_pixels"], 2 / 6)
    assert math.isclose(r["boundary_share_of_error"], 0.25 / se_all, rel_tol=1e-6)
    assert math.isclose(r["metallic_rmse_off_boundary"], math.sqrt((se_all - 0.25) / 4), rel_tol=1e-6)
    assert math.isclose(r["mean_pred_on_metal_interior"], 0.5, rel_tol=1e-6)


def test_no_metal_pixels_leaves_the_metal_figures_at_zero_not_nan():
    r = _finish(_split(torch.tensor([0.1, 0.3]), torch.tensor([0.0, 0.0]), torch.tensor([False, False])))
    assert r["metal_share_of_pixels"] == 0 and r["metallic_rmse_metal"] == 0.0
    assert all(math.isfinite(v) for v in r.values())


def test_the_boundary_band_is_the_pixels_near_a_metal_edge_only():
    m = np.zeros((12, 12), np.float32)
    m[2:10, 2:10] = 1.0  # an 8x8 metal square
    b = boundary_mask(m, px=2)
    assert b[6, 2] and b[6, 0] and b[6, 3]  # on the edge, 2 px outside, 1 px inside
    assert not b[6, 6]  # the interior, 4 px from the edge
    assert not boundary_mask(np.zeros((5, 5), np.float32)).any()  # no metal: no boundary
    assert not boundary_mask(np.ones((5, 5), np.float32)).any()  # all metal: the frame edge is no boundary


def test_thin_metal_mask_takes_poles_and_leaves_car_bodies():
    from benchmarks.diagnose_materials import thin_metal_mask

    m = np.zeros((30, 40), np.float32)
    m[2:28, 5] = 1.0          # a 1 px pole
    m[10:22, 20:36] = 1.0     # a car body, 12 x 16 px
    thin = thin_metal_mask(m)
    assert thin[15, 5] and thin[15, 7] and not thin[15, 8]   # the pole and 2 px around it
    assert not thin[16, 28] and not thin[10, 20]             # the body and its edge are not thin
    assert not thin_metal_mask(np.zeros((8, 8), np.float32)).any()


def test_split_counts_thin_pixels():
    r = _finish(_split(torch.tensor([0.4, 1.0, 0.0]), torch.tensor([1.0, 1.0, 0.0]),
                       torch.tensor([True, False, False]), torch.tensor([True, False, False])))
    assert math.isclose(r["thin_share_of_pixels"], 1 / 3)
    assert math.isclose(r["thin_share_of_error"], 1.0)
    assert math.isclose(r["mean_pred_on_thin_metal"], 0.4, rel_tol=1e-6)
