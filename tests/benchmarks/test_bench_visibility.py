"""The visibility benchmark's estimator (``benchmarks/bench_visibility.py``): light directions drawn
from a map in proportion to radiance x solid angle, and the light-weighted visibility."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_visibility import light_weighted, sample_directions
from core.conventions import direction_to_pixel


def test_directions_come_from_the_bright_texels_of_the_map():
    env = np.full((16, 32, 3), 1e-6, np.float32)
    env[4, 7] = 1e4  # one bright texel in the upper hemisphere
    d = sample_directions(env, 50, seed=3)
    assert d.shape == (50, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    rows, cols = zip(*(direction_to_pixel(v, 16, 32) for v in d))
    assert np.mean((np.floor(rows) == 4) & (np.floor(cols) == 7)) > 0.9


def test_a_constant_map_gives_directions_uniform_over_the_sphere():
    env = np.ones((32, 64, 3), np.float32)
    d = sample_directions(env, 4000, seed=0)
    # uniform on the sphere: z uniform in [-1, 1] (Archimedes), mean direction near 0
    assert abs(float(d[:, 2].mean())) < 0.05 and abs(float(np.mean(d[:, 2] > 0.5)) - 0.25) < 0.03
    assert np.linalg.norm(d.mean(0)) < 0.06


def test_light_weighted_visibility_weights_by_the_cosine():
    cos = np.array([[1.0, 0.5, 0.0], [0.0, 0.0, 0.0]])
    vis = np.array([[1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    e = light_weighted(vis, cos)
    assert np.allclose(e, [1.0 / 1.5, 0.0])  # the blocked sample carries a third of the light; none above point 2
    assert np.allclose(light_weighted(np.ones_like(cos[:1]), cos[:1]), 1.0)
