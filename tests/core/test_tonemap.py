"""core.tonemap: the paper's clip-then-gamma tone map and its inverse."""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import ConfigError, NumericalError
from core.tonemap import hdr_to_ldr, ldr_to_hdr, ldr_to_uint8


def test_values():
    hdr = np.array([0.0, 0.25, 1.0, 4.0], np.float32)
    got = hdr_to_ldr(hdr, exposure=1.0, gamma=2.0)
    np.testing.assert_allclose(got, [0.0, 0.5, 1.0, 1.0], rtol=1e-6)
    assert got.dtype == np.float32
    np.testing.assert_allclose(hdr_to_ldr(np.array([0.5]), exposure=0.5, gamma=2.2),
                               [0.25 ** (1 / 2.2)], rtol=1e-12)


def test_clip_happens_before_power():
    # exposure pushes 0.8 to 1.6: clipped to 1, not 1.6 ** (1/2.2)
    assert hdr_to_ldr(np.array([0.8]), exposure=2.0)[0] == 1.0
    assert hdr_to_ldr(np.array([1e30]))[0] == 1.0


def test_uint8_and_inverse_round_trip():
    rng = np.random.default_rng(0)
    hdr = rng.random(1000) * 0.5  # exposure 2 keeps everything below the clip
    ldr = hdr_to_ldr(hdr, exposure=2.0, gamma=2.2)
    np.testing.assert_allclose(ldr_to_hdr(ldr, exposure=2.0, gamma=2.2), hdr, rtol=1e-10)
    q = ldr_to_uint8(ldr)
    assert q.dtype == np.uint8
    np.testing.assert_array_equal(q, np.round(ldr * 255).astype(np.uint8))
    back = ldr_to_hdr(q, exposure=2.0, gamma=2.2)
    assert back.dtype == np.float32
    np.testing.assert_allclose(hdr_to_ldr(back, exposure=2.0, gamma=2.2), ldr,
                               atol=0.5 / 255 + 1e-6)
    assert ldr_to_hdr(np.array([255], np.uint8), exposure=4.0)[0] == pytest.approx(0.25)


@pytest.mark.parametrize("bad", [np.array([-1.0]), np.array([np.nan]), np.array([np.inf])])
def test_bad_inputs(bad):
    with pytest.raises(NumericalError):
        hdr_to_ldr(bad)
    with pytest.raises(NumericalError):
        ldr_to_uint8(bad)
    with pytest.raises(NumericalError):
        ldr_to_hdr(bad)


def test_bad_parameters():
    with pytest.raises(ConfigError, match="exposure"):
        hdr_to_ldr(np.ones(2), exposure=0.0)
    with pytest.raises(ConfigError, match="gamma"):
        hdr_to_ldr(np.ones(2), gamma=float("nan"))
    with pytest.raises(NumericalError):
        ldr_to_uint8(np.array([1.5]))
