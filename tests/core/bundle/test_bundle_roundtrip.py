from __future__ import annotations

import json

import numpy as np
import pytest

from core.bundle import open_bundle, pack_bundle, read_manifest, unpack_bundle, validate_bundle
from core.bundle.schema import SCHEMA_VERSION
from core.errors import BundleError, ConfigError


def test_roundtrip_fields(small_bundle):
    assert validate_bundle(small_bundle) == []
    b = open_bundle(small_bundle)
    m = b.manifest
    assert m.version == SCHEMA_VERSION
    assert [f.id for f in m.frames] == ["f000", "f001", "f002"]
    assert [f.split for f in m.frames] == ["train", "train", "test"]
    np.testing.assert_allclose(m.frames[1].cam_to_world[:3, 3], [1.0, 0.0, 1.5])
    img = b.load_image(m.frames[0])
    assert img.shape == (24, 32, 3) and img.dtype == np.float32 and 0 <= img.min() and img.max() <= 1
    sky = b.load_sky_mask(m.frames[0])
    assert sky.dtype == bool and sky[:8].all() and not sky[8:].any()
    gt = b.load_ground_truth(m.frames[0])
    assert set(gt) == {"rgb", "albedo", "roughness", "metallic", "normal", "depth"}
    assert gt["normal"].shape == (24, 32, 3) and gt["depth"].shape == (24, 32, 1)
    pts = b.load_lidar(1)
    assert pts.shape == (50, 6) and pts.dtype == np.float32
    assert b.load_lidar().shape == (150, 6)
    (car,) = m.objects
    assert car.size == (4.4, 1.8, 1.5) and sorted(car.poses) == [0, 1, 2]
    np.testing.assert_allclose(car.poses[2][:3, 3], [7.0, 2.0, 0.75])
    assert b.load_envmap().shape == (16, 32, 3)
    np.testing.assert_allclose(b.load_envmap("const2"), 2.0)
    (rl,) = m.ground_truth.relit
    fid = next(iter(rl.frames))
    relit = b.load_relit_frame(rl.name, fid)
    assert relit.shape == (24, 32, 3) and relit.dtype == np.float32 and np.isfinite(relit).all()
    with pytest.raises(BundleError, match="no relit set named 'nope'"):
        b.load_relit_frame("nope", fid)
    with pytest.raises(BundleError, match="has no frame 'f999'"):
        b.load_relit_frame(rl.name, "f999")


@pytest.mark.parametrize("suffix", [".zip", ".tar.gz"])
def test_pack_unpack(small_bundle, tmp_path, suffix):
    arc = pack_bundle(small_bundle, tmp_path / f"scene{suffix}")
    root = unpack_bundle(arc, tmp_path / "unpacked")
    assert validate_bundle(root) == []
    assert read_manifest(root).to_dict() == read_manifest(small_bundle).to_dict()


def test_writer_refuses_to_clobber(small_bundle):
    from core.bundle import BundleWriter

    with pytest.raises(ConfigError, match="not empty"):
        BundleWriter(small_bundle, "again")


def test_failed_overwrite_keeps_previous_bundle(small_bundle):
    """A write that fails validation must leave the stored bundle untouched."""
    from core.bundle import BundleWriter, Camera

    before = (small_bundle / "bundle.json").read_text()
    w = BundleWriter(small_bundle, "broken", overwrite=True)
    w.set_times([0.0])
    w.add_camera(Camera("c", 8, 8, 8, 8, 4, 4))
    # no frame added: the manifest is invalid
    with pytest.raises(BundleError):
        w.finish()
    assert (small_bundle / "bundle.json").read_text() == before
    assert validate_bundle(small_bundle) == []
    leftovers = [p.name for p in small_bundle.parent.iterdir() if "staging" in p.name or ".old-" in p.name]
    assert leftovers == []


def test_writer_rejects_bad_calls(tmp_path):
    from core.bundle import BundleWriter, Camera

    w = BundleWriter(tmp_path / "b", "b")
    w.set_times([0.0, 0.1])
    w.add_camera(Camera("c", 8, 8, 8, 8, 4, 4))
    eye = np.eye(4)
    w.add_frame("a", "c", 0, eye, image=np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ConfigError, match="duplicate frame id"):
        w.add_frame("a", "c", 1, eye, image=np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ConfigError, match="unknown camera"):
        w.add_frame("b", "nope", 1, eye, image=np.zeros((8, 8, 3), np.uint8))
    bad = eye.copy()
    bad[0, 0] = 2.0
    with pytest.raises(ConfigError, match="cam_to_world.*rigid"):
        w.add_frame("b", "c", 1, bad, image=np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ConfigError, match="image_file: not found"):
        w.add_frame("b", "c", 1, eye, image_file=tmp_path / "missing.png")
    w.add_lidar(0, np.zeros((3, 6)))
    with pytest.raises(ConfigError, match="already added"):
        w.add_lidar(0, np.zeros((3, 6)))
    w.abort()
    assert not (tmp_path / "b").exists()
