"""The re-render diagnostic's edge classes (``benchmarks/diagnose_rerender.py`` regions): a small
synthetic G-buffer with one depth jump, one fold in the normals, one albedo step and some sky."""

from __future__ import annotations

import numpy as np

from benchmarks.diagnose_rerender import edge_classes


def _frame():
    h, w = 24, 40
    depth = np.full((h, w), 10.0)
    depth[:, 30:] = 20.0              # a silhouette at column 30
    depth[:4] = 0.0                   # sky rows 0-3
    normal = np.zeros((h, w, 3))
    normal[..., 2] = 1.0
    normal[:, 10:30] = [0.0, 1.0, 0.0]  # a fold at column 10 (same depth)
    albedo = np.full((h, w, 3), 0.3)
    albedo[14:, 20:30] = 0.8          # an albedo step at row 14 / column 20, inside the fold's face
    return albedo, depth, normal


def test_classes_are_disjoint_and_cover_the_frame():
    c = edge_classes(*_frame())
    stack = np.stack(list(c.values())).astype(int)
    assert set(c) == {"silhouette", "crease", "albedo_edge", "flat", "sky"}
    assert (stack.sum(0) == 1).all()


def test_each_edge_lands_in_its_class():
    c = edge_classes(*_frame())
    row = 18  # below the sky, away from its border
    assert c["silhouette"][row, 29] and c["silhouette"][row, 30]
    assert c["crease"][row, 9] and c["crease"][row, 10] and not c["silhouette"][row, 10]
    assert c["albedo_edge"][row, 19] and c["albedo_edge"][row, 20]
    assert c["albedo_edge"][13, 25] and c["albedo_edge"][14, 25]
    assert c["flat"][row, 4] and c["flat"][8, 25] and c["flat"][row, 36]
    assert c["sky"][1, 4] and not c["sky"][row, 4]
    # the sky's border with the street is a depth jump, not sky
    assert c["silhouette"][4, 4] and not c["sky"][4, 4]
