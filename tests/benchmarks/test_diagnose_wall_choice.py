"""The wall-choice diagnostic's paired test (``benchmarks/diagnose_wall_choice.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.diagnose_wall_choice import paired
from core.errors import ShapeError


def test_a_constant_gain_on_noisy_samples_is_measured_with_its_standard_error():
    rng = np.random.default_rng(0)
    b = rng.uniform(0.1, 0.5, 10_000)
    a = b + 0.01 + rng.normal(0, 0.1, b.shape)  # a is worse by 0.01 on average, noise 0.1 per sample
    r = paired(a, b)
    assert abs(r["mean_diff"] - 0.01) < 3 * r["se"]
    assert math.isclose(r["se"], 0.1 / math.sqrt(len(b)), rel_tol=0.05)
    assert 7 < r["z"] < 13 and math.isclose(r["rel"], r["mean_diff"] / b.mean())


def test_identical_residuals_have_no_z_and_bad_shapes_are_named():
    b = np.linspace(0, 1, 10)
    assert paired(b, b)["z"] is None and paired(b, b)["mean_diff"] == 0
    with pytest.raises(ShapeError, match="paired"):
        paired(b, b[:5])
