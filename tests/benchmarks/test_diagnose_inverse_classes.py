"""The inverse model's class-floor diagnostic (``benchmarks/diagnose_inverse_classes.py``): class
names, the match of true values to materials, and the pooled model and floor errors."""

from __future__ import annotations

import math

import numpy as np

from benchmarks.diagnose_inverse_classes import assign_classes, floor_rows, material_class, pooled


def test_material_classes_drop_side_and_index():
    assert material_class("wallL3", 0.0) == "wall"
    assert material_class("wallR12", 0.8) == "wall_metal"
    assert material_class("car_glass2", 0.0) == "glass"
    assert material_class("paint4", 0.6) == "paint"
    assert material_class("asphalt", 0.0) == "asphalt"


def test_pixels_match_their_material_and_the_rest_stays_unassigned():
    mats = {"wallL0": ("wall", 0.7, 0.0), "paint0": ("paint", 0.3, 0.9)}
    r = np.array([0.7, 0.3001, 0.5], np.float32)
    m = np.array([0.0, 0.9, 0.0], np.float32)
    assert list(assign_classes(r, m, mats)) == ["wall", "paint", "?"]


def test_pooled_errors_weigh_classes_by_their_pixels():
    true = np.array([0.4, 1.0, 0.4, 1.0, 0.1, 0.1])
    cls = np.array(["wall"] * 4 + ["glass"] * 2, dtype=object)
    pred = np.array([0.7, 0.7, 0.7, 0.7, 0.5, 0.5])
    rows = floor_rows(pred, true, cls, {"wall": 0.7, "glass": 0.1})
    p = pooled(rows)
    # walls: model = floor (both 0.7, errors 0.3); glass: model 0.4 off, floor exact
    assert math.isclose(p["classes"]["wall"]["model"], 0.3) and math.isclose(p["classes"]["wall"]["floor"], 0.3)
    assert math.isclose(p["classes"]["glass"]["model"], 0.4) and p["classes"]["glass"]["floor"] == 0.0
    assert math.isclose(p["model"], math.sqrt((4 * 0.09 + 2 * 0.16) / 6))
    assert math.isclose(p["floor"], math.sqrt(4 * 0.09 / 6))
    assert math.isclose(p["classes"]["wall"]["share"], 4 / 6)
    assert math.isnan(pooled({})["model"])
