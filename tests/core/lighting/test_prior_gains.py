"""core.lighting.prior_gains: the prior's sun / sky split refitted by two gains."""

from __future__ import annotations

import numpy as np
import pytest

from core.conventions import envmap_directions
from core.errors import ConfigError, NumericalError, ShapeError
from core.lighting.prior_gains import PriorGainSettings, search_gains, split_map


def _map(h=32, seed=0):
    return np.random.default_rng(seed).uniform(0.1, 2.0, (h, 2 * h, 3))


def test_split_parts_sum_to_the_map_and_follow_the_sun_cap_and_the_held_sky():
    env = _map()
    sun = np.array([0.0, 0.6, 0.8])
    held = np.zeros((32, 64))
    held[20:, :] = 1.0  # everything below a row is seen (held)
    p = split_map(env, sun, held, 10.0)
    np.testing.assert_allclose(p["sun"] + p["sky"] + p["held"], env, rtol=0, atol=0)
    d = envmap_directions(32, 64)
    in_cap = d @ sun > np.cos(np.radians(10.0))
    assert in_cap.any()
    assert (p["sun"][~in_cap] == 0).all() and (p["sun"][in_cap & (held < 0.5)] > 0).all()
    assert (p["held"][20:] == env[20:]).all() and (p["held"][:20] == 0).all()
    assert (p["sky"][in_cap] == 0).all()


def test_the_search_recovers_known_gains():
    rng = np.random.default_rng(1)
    n = 5000
    r = {"sun": rng.uniform(0, 0.8, (n, 3)) * (rng.uniform(size=(n, 1)) > 0.4),
         "sky": rng.uniform(0.02, 0.2, (n, 3)), "held": rng.uniform(0, 0.02, (n, 3))}
    target = np.clip(0.4 * r["sun"] + 2.5 * r["sky"] + r["held"], 0, 1) ** (1 / 2.2)
    res = search_gains(r, target, 1.0, 2.2, PriorGainSettings())
    assert res["applied"]
    assert abs(np.log(res["gain_sun"] / 0.4)) < 0.08 and abs(np.log(res["gain_sky"] / 2.5)) < 0.08
    assert res["l1_best"] < 0.1 * res["l1_prior"]


def test_a_prior_already_right_is_kept():
    rng = np.random.default_rng(2)
    r = {k: rng.uniform(0, 0.3, (2000, 3)) for k in ("sun", "sky", "held")}
    target = np.clip(r["sun"] + r["sky"] + r["held"], 0, 1) ** (1 / 2.2)
    res = search_gains(r, target, 1.0, 2.2, PriorGainSettings())
    assert not res["applied"] and res["gain_sun"] == 1.0 and res["gain_sky"] == 1.0
    assert res["l1_prior"] == pytest.approx(0.0, abs=1e-12)


def test_bad_inputs_name_what_is_wrong():
    r = {k: np.zeros((10, 3)) for k in ("sun", "sky", "held")}
    t = np.zeros((10, 3))
    with pytest.raises(ConfigError, match="held"):
        search_gains({"sun": r["sun"], "sky": r["sky"]}, t, 1.0, 2.2, PriorGainSettings())
    with pytest.raises(ShapeError, match="sky"):
        search_gains({**r, "sky": np.zeros((9, 3))}, t, 1.0, 2.2, PriorGainSettings())
    bad = np.zeros((10, 3))
    bad[0, 0] = np.nan
    with pytest.raises(NumericalError, match="sun"):
        search_gains({**r, "sun": bad}, t, 1.0, 2.2, PriorGainSettings())
    with pytest.raises(ConfigError, match="exposure"):
        search_gains(r, t, 0.0, 2.2, PriorGainSettings())
    with pytest.raises(ShapeError, match="env"):
        split_map(np.zeros((8, 8, 3)), np.array([0, 0, 1.0]), None, 10.0)
    with pytest.raises(ConfigError, match="sun_dir"):
        split_map(_map(8), np.array([np.nan, 0, 1.0]), None, 10.0)
    with pytest.raises(ConfigError, match="steps"):
        PriorGainSettings(steps=2)
