"""core.io.images and core.io.video."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.io import image_size, read_image, read_mask, read_mp4_frames, write_mp4, write_png


def _gradient(h, w, shift=0):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x * 255 // max(w - 1, 1) + shift) % 256,
                     y * 255 // max(h - 1, 1),
                     np.full_like(x, 128)], axis=-1).astype(np.uint8)


def test_png_round_trip_rgb_gray_rgba(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    write_png(tmp_path / "rgb.png", rgb)
    np.testing.assert_array_equal(read_image(tmp_path / "rgb.png"), rgb)
    assert image_size(tmp_path / "rgb.png") == (9, 7)

    gray = rgb[:, :, 0]
    write_png(tmp_path / "g.png", gray)
    np.testing.assert_array_equal(read_image(tmp_path / "g.png"), np.repeat(gray[..., None], 3, 2))

    rgba = np.concatenate([rgb, np.full((7, 9, 1), 7, np.uint8)], axis=2)
    write_png(tmp_path / "a.png", rgba)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), rgb)


def test_float_png_is_rounded(tmp_path):
    f = np.array([[0.0, 0.5, 1.0, 0.2 / 255 + 0.5 / 255]])
    write_png(tmp_path / "f.png", f)
    assert read_image(tmp_path / "f.png")[0, :, 0].tolist() == [0, 128, 255, 1]
    with pytest.raises(ConfigError):
        write_png(tmp_path / "x.png", np.array([[1.5]]))
    with pytest.raises(NumericalError):
        write_png(tmp_path / "x.png", np.array([[np.nan]]))
    with pytest.raises(ShapeError):
        write_png(tmp_path / "x.png", np.zeros((2, 2), np.uint16))
    with pytest.raises(ShapeError):
        write_png(tmp_path / "x.png", np.zeros((2, 2, 2), np.uint8))


def test_mask(tmp_path):
    m = np.zeros((5, 6), bool)
    m[1:3, 2:5] = True
    write_png(tmp_path / "m.png", m)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), m)
    Image.fromarray(m).save(tmp_path / "m1.png")  # 1-bit PNG
    np.testing.assert_array_equal(read_mask(tmp_path / "m1.png"), m)
    rgb = np.zeros((5, 6, 3), np.uint8)
    rgb[m, 1] = 3
    write_png(tmp_path / "mc.png", rgb)
    np.testing.assert_array_equal(read_mask(tmp_path / "mc.png"), m)


def test_jpeg_and_palette(tmp_path):
    img = _gradient(16, 24)
    Image.fromarray(img).save(tmp_path / "a.jpg", quality=95)
    got = read_image(tmp_path / "a.jpg")
    assert got.shape == (16, 24, 3) and np.abs(got.astype(int) - img).mean() < 5
    Image.fromarray(img).convert("P").save(tmp_path / "p.png")
    assert read_image(tmp_path / "p.png").shape == (16, 24, 3)


def test_unreadable_images(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"definitely not a png")
    for fn in (read_image, read_mask, image_size):
        with pytest.raises(FormatError, match="junk.png"):
            fn(junk)
    write_png(tmp_path / "ok.png", np.random.default_rng(1).integers(0, 256, (64, 64, 3),
                                                                      dtype=np.uint8))
    data = (tmp_path / "ok.png").read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="cut.png"):
        read_image(cut)
    with pytest.raises(FormatError, match="max_pixels"):
        read_image(tmp_path / "ok.png", max_pixels=100)


def test_mp4_odd_size_round_trip(tmp_path):
    frames = [_gradient(21, 33, shift=8 * i) for i in range(5)]
    p = tmp_path / "v.mp4"
    write_mp4(p, frames, fps=10, crf=18)
    got = read_mp4_frames(p)
    assert got.shape == (5, 22, 34, 3)  # padded to even by edge replication
    for i in range(5):
        diff = np.abs(got[i, :21, :33].astype(int) - frames[i].astype(int)).mean()
        assert diff < 10, (i, diff)


def test_mp4_from_array_and_validation(tmp_path):
    arr = np.stack([_gradient(16, 16)] * 3)
    write_mp4(tmp_path / "a.mp4", arr, fps=24)
    assert read_mp4_frames(tmp_path / "a.mp4").shape == (3, 16, 16, 3)
    with pytest.raises(ConfigError, match="frame"):
        write_mp4(tmp_path / "e.mp4", [])
    with pytest.raises(ConfigError, match="fps"):
        write_mp4(tmp_path / "e.mp4", arr, fps=0)
    with pytest.raises(ConfigError, match="crf"):
        write_mp4(tmp_path / "e.mp4", arr, crf=99)
    with pytest.raises(ShapeError, match=r"frames\[1\]"):
        write_mp4(tmp_path / "e.mp4", [arr[0], arr[0, :8]])
    with pytest.raises(ShapeError):
        write_mp4(tmp_path / "e.mp4", [arr[0].astype(np.float32)])
    assert not (tmp_path / "e.mp4").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mp4"]


def test_read_mp4_not_video(tmp_path):
    p = tmp_path / "junk.mp4"
    p.write_bytes(b"\0" * 100)
    with pytest.raises(FormatError, match="junk.mp4"):
        read_mp4_frames(p)
