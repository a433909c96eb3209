"""core.io.hdr: RGBE round trip, RLE / flat / old-RLE decoding, hostile files."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.io import read_envmap, read_hdr, write_envmap, write_hdr
from core.io.hdr import _decode_rle_component, _encode_rle_component, float_to_rgbe


def _rel_err(got, want):
    """Error relative to each pixel's brightest channel (RGBE shares one exponent)."""
    return np.abs(got - want) / np.maximum(want.max(axis=-1, keepdims=True), 1e-30)


def test_round_trip_within_rgbe_precision(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((20, 48, 3)) ** 3 * 100).astype(np.float32)
    img[5, 7] = (3.5e4, 1e-3, 0.0)
    img[6, :] = 0.0
    p = tmp_path / "rt.hdr"
    write_hdr(p, img)
    got = read_hdr(p)
    assert got.shape == img.shape and got.dtype == np.float32
    assert _rel_err(got, img).max() < 0.01
    assert np.all(got[6] == 0.0)


def test_rle_is_used_and_decoded(tmp_path):
    img = np.ones((8, 64, 3), np.float32)
    img[:, 20:40] = (5.0, 0.25, 2.0)
    p = tmp_path / "rle.hdr"
    write_hdr(p, img)
    data = p.read_bytes()
    body = data[data.index(b"+X 64\n") + 6:]
    assert body[:4] == bytes((2, 2, 0, 64))  # new-style RLE scanline marker
    assert len(body) < 8 * 64 * 4 / 4  # runs compress the flat regions a lot
    assert _rel_err(read_hdr(p), img).max() < 0.01


def _raw_hdr(height, width, body: bytes, res=None) -> bytes:
    res = res or f"-Y {height} +X {width}"
    return b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n" + res.encode() + b"\n" + body


def test_flat_and_old_rle_scanlines(tmp_path):
    px = [(128, 64, 32, 129), (10, 20, 30, 130)]
    # row 0 flat; row 1: pixel, then an old-style run repeating it 3 more times
    body = bytes(px[0] + px[1] + px[0] + px[1]) + bytes(px[1] + (1, 1, 1, 3))
    p = tmp_path / "flat.hdr"
    p.write_bytes(_raw_hdr(2, 4, body))
    got = read_hdr(p)
    want = np.array([(c + 0.5) * 2.0 ** (e - 136) for c in (128, 64, 32) for e in [129]])
    np.testing.assert_allclose(got[0, 0], want, rtol=1e-6)
    np.testing.assert_allclose(got[1], np.repeat(got[0, 1:2], 4, axis=0), rtol=1e-6)


def test_orientation_flips(tmp_path):
    rgbe = float_to_rgbe(np.arange(2 * 3 * 3, dtype=np.float64).reshape(2, 3, 3) + 1.0)
    a = tmp_path / "a.hdr"
    b = tmp_path / "b.hdr"
    a.write_bytes(_raw_hdr(2, 3, rgbe.tobytes()))
    b.write_bytes(_raw_hdr(2, 3, rgbe.tobytes(), res="+Y 2 -X 3"))
    np.testing.assert_array_equal(read_hdr(b), read_hdr(a)[::-1, ::-1])


def test_truncated_hdr(tmp_path):
    rng = np.random.default_rng(1)
    p = tmp_path / "full.hdr"
    write_hdr(p, (rng.random((16, 32, 3)) * 10).astype(np.float32))
    data = p.read_bytes()
    for cut in (len(data) // 2, len(data) - 1, 30):
        bad = tmp_path / f"cut{cut}.hdr"
        bad.write_bytes(data[:cut])
        with pytest.raises(FormatError, match="truncated") as info:
            read_hdr(bad)
        assert str(bad) in str(info.value)


@pytest.mark.parametrize("payload,match", [
    (b"P6\n2 2\n255\n" + bytes(12), "not a Radiance"),
    (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 1\n\0\0\0\0", "xyze"),
    (b"#?RADIANCE\n\n+X 2 +Y 2\n" + bytes(16), "resolution"),
    (b"#?RADIANCE\n\n-Y two +X 2\n" + bytes(16), "resolution"),
    (b"#?RADIANCE\n\n-Y 1 +X 8\n" + bytes((2, 2, 0, 9)) + bytes(40), "width"),
    (b"#?RADIANCE\n\n-Y 1 +X 8\n" + bytes((2, 2, 0, 8, 0)) + bytes(40), "run length"),
])
def test_malformed_hdr(tmp_path, payload, match):
    p = tmp_path / "bad.hdr"
    p.write_bytes(payload)
    with pytest.raises(FormatError, match=match):
        read_hdr(p)


def test_size_checked_before_allocation(tmp_path):
    p = tmp_path / "huge.hdr"
    p.write_bytes(_raw_hdr(100_000, 100_000, b""))
    with pytest.raises(FormatError, match="max_pixels"):
        read_hdr(p)
    with pytest.raises(ConfigError):
        read_hdr(p, max_pixels=0)


def test_write_validation(tmp_path):
    with pytest.raises(ShapeError):
        write_hdr(tmp_path / "a.hdr", np.ones((4, 4)))
    with pytest.raises(NumericalError, match="negative"):
        write_hdr(tmp_path / "a.hdr", -np.ones((4, 4, 3)))
    with pytest.raises(NumericalError):
        write_hdr(tmp_path / "a.hdr", np.full((4, 4, 3), np.nan))
    assert not (tmp_path / "a.hdr").exists()


def test_envmap_via_hdr(tmp_path):
    env = (np.random.default_rng(2).random((16, 32, 3)) * 5e4).astype(np.float32)
    p = tmp_path / "env.hdr"
    write_envmap(p, env)
    got = read_envmap(p)
    assert got.shape == (16, 32, 3)
    assert _rel_err(got, env).max() < 0.01


@pytest.mark.mitsuba
def test_cross_check_with_mitsuba(tmp_path):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(3)
    img = (rng.random((12, 40, 3)) ** 4 * 50).astype(np.float32)
    img[:, 10:30] = 2.0
    ours = tmp_path / "ours.hdr"
    write_hdr(ours, img)
    theirs_read = np.array(mi.Bitmap(str(ours)))
    assert _rel_err(theirs_read, img).max() < 0.01
    theirs = tmp_path / "theirs.hdr"
    mi.Bitmap(img).write(str(theirs))
    assert _rel_err(read_hdr(theirs), img).max() < 0.01


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), st.integers(1, 300)), min_size=1, max_size=40))
def test_rle_component_round_trip(runs):
    row = np.concatenate([np.full(n, v, np.uint8) for v, n in runs])
    encoded = _encode_rle_component(row)
    out = np.zeros_like(row)
    end = _decode_rle_component(encoded, 0, row.shape[0], out, "mem", 0)
    assert end == len(encoded)
    np.testing.assert_array_equal(out, row)
