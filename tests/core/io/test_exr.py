"""core.io.exr and core.io.envmap_file: round trips, half clamping, hostile files, real HDRIs."""

from __future__ import annotations

import glob
import os
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.io import exr_header, read_envmap, read_exr, write_envmap, write_exr

HDRI_DIR = Path(__file__).resolve().parents[3] / "data" / "hdri"
HDRIS = sorted(glob.glob(str(HDRI_DIR / "*.exr")))


def _layers(h=6, w=10, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "rgb": rng.random((h, w, 3)).astype(np.float32) * 4.0,
        "albedo": rng.random((h, w, 3)).astype(np.float32),
        "depth": rng.random((h, w)).astype(np.float32) * 100.0,
        "mask": rng.random((h, w, 1)).astype(np.float32),
        "flow": rng.standard_normal((h, w, 2)).astype(np.float32),
        "spec": rng.random((h, w, 4)).astype(np.float32),
    }


@pytest.mark.parametrize("precision", ["half", "float"])
def test_round_trip_multi_layer(tmp_path, precision):
    layers = _layers()
    path = tmp_path / "multi.exr"
    write_exr(path, layers, precision=precision)
    got = read_exr(path)
    assert set(got) == set(layers)
    tol = 1e-3 if precision == "half" else 0.0
    for name, value in layers.items():
        expect = value if value.ndim == 3 else value[:, :, None]
        assert got[name].dtype == np.float32
        assert got[name].shape == expect.shape, name
        np.testing.assert_allclose(got[name], expect, rtol=tol, atol=tol, err_msg=name)
    head = exr_header(path)
    assert (head.width, head.height) == (10, 6)
    assert {"R", "G", "B", "albedo.R", "depth.Y", "mask.Y", "flow.X", "flow.Y", "spec.A"} \
        <= set(head.channels)
    want = "half" if precision == "half" else "float"
    assert set(head.pixel_types) == {want}


def test_beauty_is_top_level_and_channel_names(tmp_path):
    rng = np.random.default_rng(1)
    beauty = rng.random((4, 5, 3)).astype(np.float32)
    normal = rng.standard_normal((4, 5, 3)).astype(np.float32)
    path = tmp_path / "b.exr"
    write_exr(path, {"beauty": beauty, "normal": normal}, precision={"normal": "float"},
              channel_names={"normal": ("X", "Y", "Z")})
    head = exr_header(path)
    assert {"R", "G", "B", "normal.X", "normal.Y", "normal.Z"} == set(head.channels)
    got = read_exr(path)
    assert set(got) == {"rgb", "normal"}
    np.testing.assert_array_equal(got["normal"], normal)  # float: exact, order X, Y, Z
    np.testing.assert_allclose(got["rgb"], beauty, atol=1e-3)


def test_unusual_channel_names_come_back_sorted(tmp_path):
    a = np.arange(2 * 3 * 2, dtype=np.float32).reshape(2, 3, 2)
    path = tmp_path / "uv.exr"
    write_exr(path, {"tex": a}, precision="float", channel_names={"tex": ("V", "U")})
    got = read_exr(path)["tex"]
    np.testing.assert_array_equal(got, a[:, :, ::-1])  # sorted: U, V


def test_half_clamps_instead_of_overflowing(tmp_path):
    img = np.full((3, 4, 3), 0.5, np.float32)
    img[1, 2] = (1e6, -1e6, 7e4)
    path = tmp_path / "clamp.exr"
    write_exr(path, {"rgb": img}, precision="half")
    got = read_exr(path)["rgb"]
    assert np.all(np.isfinite(got))
    assert got[1, 2, 0] == 65504.0 and got[1, 2, 1] == -65504.0 and got[1, 2, 2] == 65504.0


def test_float_keeps_large_values(tmp_path):
    img = np.full((2, 4, 3), 3.5e4, np.float32)
    img[0, 0, 0] = 1e6
    write_envmap(tmp_path / "env.exr", img)
    assert read_envmap(tmp_path / "env.exr")[0, 0, 0] == 1e6


def test_nan_raises_naming_layer(tmp_path):
    layers = _layers()
    layers["albedo"][2, 3, 1] = np.nan
    path = tmp_path / "nan.exr"
    with pytest.raises(NumericalError, match="albedo"):
        write_exr(path, layers)
    assert not path.exists()
    assert os.listdir(tmp_path) == []  # no temp file left behind


def test_inf_raises_naming_layer(tmp_path):
    with pytest.raises(NumericalError, match="depth"):
        write_exr(tmp_path / "inf.exr", {"depth": np.array([[1.0, np.inf]])})


def test_write_validation(tmp_path):
    p = tmp_path / "x.exr"
    with pytest.raises(ShapeError, match="a"):
        write_exr(p, {"a": np.zeros((2, 2, 5))})
    with pytest.raises(ShapeError, match="b"):
        write_exr(p, {"a": np.zeros((2, 2)), "b": np.zeros((3, 2))})
    with pytest.raises(ConfigError, match="precision"):
        write_exr(p, {"a": np.zeros((2, 2))}, precision="double")
    with pytest.raises(ConfigError, match="compression"):
        write_exr(p, {"a": np.zeros((2, 2))}, compression="lzma")
    with pytest.raises(ConfigError, match="channel_names"):
        write_exr(p, {"a": np.zeros((2, 2, 3))}, channel_names={"a": ("X", "Y")})
    with pytest.raises(ConfigError):
        write_exr(p, {})
    with pytest.raises(ShapeError, match="rgb"):
        write_exr(p, {"rgb": np.zeros((2, 2))})
    assert not p.exists()


def test_failed_write_keeps_old_file(tmp_path):
    p = tmp_path / "keep.exr"
    write_exr(p, {"a": np.ones((2, 2))})
    before = p.read_bytes()
    with pytest.raises(NumericalError):
        write_exr(p, {"a": np.full((2, 2), np.nan)})
    assert p.read_bytes() == before


def test_non_contiguous_input_written_correctly(tmp_path):
    base = np.random.default_rng(2).random((5, 6, 4)).astype(np.float32)
    view = base[:, ::-1, :3]  # non-contiguous view
    write_exr(tmp_path / "v.exr", {"rgb": view}, precision="float")
    np.testing.assert_array_equal(read_exr(tmp_path / "v.exr")["rgb"], view)


# --------------------------------------------------------------------------------------------
# hostile files
# --------------------------------------------------------------------------------------------

def _attr(name: str, type_name: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) \
        + value


def _exr_header_bytes(width: int, height: int, channels=("R",)) -> bytes:
    """A syntactically valid single-part scanline EXR header (no pixel data follows)."""
    chlist = b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1)
                      for c in channels) + b"\0"
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    return (b"\x76\x2f\x31\x01" + struct.pack("<I", 2)
            + _attr("channels", "chlist", chlist)
            + _attr("compression", "compression", b"\0")
            + _attr("dataWindow", "box2i", box)
            + _attr("displayWindow", "box2i", box)
            + _attr("lineOrder", "lineOrder", b"\0")
            + _attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
            + _attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
            + _attr("screenWindowWidth", "float", struct.pack("<f", 1.0))
            + b"\0")


def test_absurd_size_refused_before_allocation(tmp_path):
    p = tmp_path / "huge.exr"
    p.write_bytes(_exr_header_bytes(100_000, 100_000) + b"\0" * 64)
    head = exr_header(p)
    assert (head.width, head.height, head.channels) == (100_000, 100_000, ("R",))
    t0 = time.perf_counter()
    with pytest.raises(FormatError, match="100000 x 100000") as info:
        read_exr(p)
    assert time.perf_counter() - t0 < 1.0
    assert str(p) in str(info.value)


def test_too_many_channels_refused(tmp_path):
    p = tmp_path / "chans.exr"
    p.write_bytes(_exr_header_bytes(4, 4, channels=[f"c{i:03d}.Y" for i in range(100)]))
    with pytest.raises(FormatError, match="channels"):
        read_exr(p)


def test_empty_data_window_refused(tmp_path):
    p = tmp_path / "empty.exr"
    p.write_bytes(_exr_header_bytes(0, 5))
    with pytest.raises(FormatError, match="data window"):
        exr_header(p)


def test_oversized_attribute_refused(tmp_path):
    p = tmp_path / "attr.exr"
    p.write_bytes(b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + b"comment\0string\0"
                  + struct.pack("<i", 50_000_000))
    with pytest.raises(FormatError, match="size"):
        exr_header(p)


def test_truncated_file(tmp_path):
    good = tmp_path / "good.exr"
    write_exr(good, _layers(h=64, w=64), precision="float")
    data = good.read_bytes()
    for cut in (len(data) // 2, len(data) - 1, 100):
        bad = tmp_path / f"cut{cut}.exr"
        bad.write_bytes(data[:cut])
        with pytest.raises(FormatError) as info:
            read_exr(bad)
        assert str(bad) in str(info.value)


@pytest.mark.parametrize("compression", ["zip", "none", "piz"])
def test_garbled_pixel_data_says_what_and_where(tmp_path, compression):
    """A truncated or garbled file names the chunk and byte that are wrong (the OpenEXR binding
    alone says "file has 0 parts"); damage inside a chunk's compressed data is named as such."""
    good = tmp_path / "good.exr"
    write_exr(good, _layers(h=64, w=64), precision="float", compression=compression)
    data = good.read_bytes()
    head = exr_header(good)
    table_end = head.table_offset + 8 * (-(-64 // {"zip": 16, "none": 1, "piz": 32}[compression]))
    rng = np.random.default_rng(0)
    cases = {"cut": (data[:table_end + (len(data) - table_end) // 2], r"truncated (or corrupt )?EXR: scanline chunk \d+ of \d+"),
             "table": (data[:table_end - 3], r"truncated EXR: the table of \d+ chunk offsets ends at byte"),
             "leaders": (data[:table_end] + rng.integers(0, 256, len(data) - table_end, dtype=np.uint8).tobytes(),
                         r"corrupt EXR: scanline chunk 0 of \d+ \(lines 0...\) at byte \d+ is labelled line")}
    if compression == "zip":  # zlib data carries a checksum: damage inside a chunk is detected
        first = struct.unpack("<Q", data[head.table_offset:head.table_offset + 8])[0]
        body = bytearray(data)
        body[first + 8:first + 8 + 64] = b"\xff" * 64
        cases["inside"] = (bytes(body), r"corrupt EXR pixel data: the OpenEXR library could not decode part 0 "
                                        rf"\(64x64, {compression} compression\)")
    for name, (payload, msg) in cases.items():
        bad = tmp_path / f"{name}.exr"
        bad.write_bytes(payload)
        with pytest.raises(FormatError, match=msg) as info:
            read_exr(bad)
        assert str(bad) in str(info.value) and "0 parts" not in str(info.value), (name, info.value)


@pytest.mark.parametrize("payload", [b"", b"not an exr file at all", b"\x89PNG\r\n\x1a\n" * 8])
def test_not_exr(tmp_path, payload):
    p = tmp_path / "junk.exr"
    p.write_bytes(payload)
    with pytest.raises(FormatError, match="junk.exr"):
        read_exr(p)


def test_envmap_shape_and_sign_checks(tmp_path):
    p = tmp_path / "square.exr"
    write_exr(p, {"rgb": np.ones((4, 4, 3))}, precision="float")
    with pytest.raises(FormatError, match="W == 2 H"):
        read_envmap(p)
    neg = np.ones((4, 8, 3), np.float32)
    neg[1, 1, 1] = -0.5
    p2 = tmp_path / "neg.exr"
    write_exr(p2, {"rgb": neg}, precision="float")
    with pytest.raises(FormatError, match="negative"):
        read_envmap(p2)
    with pytest.raises(ConfigError):
        read_envmap(tmp_path / "env.png")
    with pytest.raises(ShapeError):
        write_envmap(tmp_path / "e.exr", np.ones((4, 4, 3)))


def test_envmap_nonfinite_names_file(tmp_path):
    # write with the raw library so the bad value reaches the disk
    import OpenEXR

    r = np.ones((4, 8), np.float32)
    r[0, 0] = np.inf
    p = tmp_path / "inf_env.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"R": r, "G": np.ones_like(r), "B": np.ones_like(r)}).write(str(p))
    with pytest.raises(NumericalError, match="inf_env.exr"):
        read_envmap(p)


def test_envmap_small_codec_noise_is_zeroed(tmp_path):
    env = np.ones((4, 8, 3), np.float32)
    env[0, 0, 2] = -1e-4
    p = tmp_path / "noise.exr"
    write_exr(p, {"rgb": env}, precision="float")
    got = read_envmap(p)
    assert got[0, 0, 2] == 0.0 and got.min() >= 0.0


@pytest.mark.parametrize("path", HDRIS, ids=[os.path.basename(h) for h in HDRIS])
def test_real_hdris_load(path):
    env = read_envmap(path)
    assert env.shape == (512, 1024, 3)
    assert env.dtype == np.float32
    assert np.all(np.isfinite(env))
    assert env.min() >= 0.0
    if os.path.basename(path) == "city.exr":
        assert env.max() > 50.0
        assert 3.0e4 < env.max() < 4.0e4


def test_six_hdris_present():
    assert len(HDRIS) == 6


def test_multi_part_reads_part_zero(tmp_path):
    import OpenEXR

    z0 = np.full((3, 4), 1.5, np.float32)
    z1 = np.full((3, 4), 2.5, np.float32)
    p = tmp_path / "parts.exr"
    OpenEXR.File([OpenEXR.Part({}, {"depth.Y": z0}, "a"),
                  OpenEXR.Part({}, {"depth.Y": z1}, "b")]).write(str(p))
    head = exr_header(p)
    assert head.num_parts == 2 and (head.width, head.height) == (4, 3)
    got = read_exr(p)
    np.testing.assert_array_equal(got["depth"], z0[:, :, None])
