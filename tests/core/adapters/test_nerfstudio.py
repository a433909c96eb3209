"""nerfstudio (transforms.json) importer: OpenGL -> OpenCV poses, intrinsics, order and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.adapters import import_nerfstudio
from core.bundle import open_bundle, validate_bundle
from core.conventions import project_points
from core.errors import BundleError, ConfigError


def _import(scene, tmp_path, **kw):
    return open_bundle(import_nerfstudio(scene.root, tmp_path / "bundle", progress=False, **kw))


def test_known_point_projects_to_image_centre(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    b = _import(scene, tmp_path)
    assert validate_bundle(b.root) == []
    assert len(b.manifest.frames) == 3
    for f in b.manifest.frames:
        cam = b.camera(f)
        uv, z = project_points(scene.target[None], f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
        assert z[0] > 0
        np.testing.assert_allclose(uv[0], [cam.width / 2, cam.height / 2], atol=1e-6)
        # a point above the target is higher in the image (smaller row): OpenCV y is down
        uv_up, _ = project_points(scene.target[None] + [0, 0, 0.3], f.cam_to_world,
                                  cam.fx, cam.fy, cam.cx, cam.cy)
        assert uv_up[0, 1] < uv[0, 1]


def test_poses_are_opencv_and_ordered_by_file_name(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    b = _import(scene, tmp_path)
    m = b.manifest
    files = sorted(scene.c2w_opencv)
    assert [f.id for f in m.frames] == ["0000_frame_00001", "0001_frame_00002", "0002_frame_00003"]
    assert [f.time_index for f in m.frames] == [0, 1, 2]
    assert m.times == pytest.approx([0.0, 0.1, 0.2])
    for f, fp in zip(m.frames, files):
        np.testing.assert_allclose(f.cam_to_world, scene.c2w_opencv[fp], atol=1e-9)
        assert (b.root / f.image).read_bytes() == (scene.root / fp).read_bytes()
    assert m.source["kind"] == "nerfstudio"
    assert m.source["skipped"] == ["mask_path", "ply_file_path"]


def test_intrinsics_copied_one_camera_per_set(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    m = _import(scene, tmp_path).manifest
    assert sorted(m.cameras) == ["0", "1"]
    shared, override = m.cameras["0"], m.cameras["1"]
    assert (shared.width, shared.height, shared.fx, shared.fy, shared.cx, shared.cy) == (80, 60, 70, 72, 40, 30)
    assert shared.distortion == ()
    assert (override.fx, override.fy, override.cx, override.cy) == (90, 90, 40, 30)
    assert [f.camera for f in m.frames] == ["0", "0", "1"]


def test_defaults_and_distortion(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    meta = dict(scene.meta)
    for k in ("fl_y", "cx", "cy", "w", "h"):
        meta.pop(k)
    meta["k1"] = 0.05
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    m = _import(scene, tmp_path).manifest
    cam = m.cameras["0"]
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (80, 60, 70, 70, 40, 30)
    assert cam.distortion == (0.05, 0.0, 0.0, 0.0, 0.0)


def test_test_split(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    m = _import(scene, tmp_path, test_every=3, name="ns").manifest
    assert m.name == "ns"
    assert [f.split for f in m.frames] == ["train", "train", "test"]


def test_world_up_reorients_to_z(nerfstudio_scene, tmp_path, geom):
    """A y-up world (z-up scene rotated by -90 deg about x) comes back z-up with world_up."""
    rot = np.eye(4)
    rot[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # -90 deg about x: maps +z to +y
    scene = nerfstudio_scene(world=rot)
    b = _import(scene, tmp_path, world_up=(0, 1, 0))
    for f in b.manifest.frames:
        fp = next(k for k in scene.c2w_opencv if k.endswith(f.id.split("_", 1)[1] + ".png"))
        orig = rot.T @ scene.c2w_opencv[fp]  # the pose in the original z-up scene
        # the smallest rotation taking +y to +z is exactly rot's inverse
        np.testing.assert_allclose(f.cam_to_world, orig, atol=1e-9)
    assert b.manifest.source["world_rotation"] != np.eye(3).tolist()
    # orient=True uses the cameras' mean up vector: it is "up-ish", so the z of the up axis grows
    b2 = open_bundle(import_nerfstudio(scene.root, tmp_path / "b2", orient=True, progress=False))
    for f in b2.manifest.frames:
        assert -f.cam_to_world[2, 1] > 0.8
    with pytest.raises(ConfigError):
        import_nerfstudio(scene.root, tmp_path / "b3", orient=True, world_up=(0, 0, 1), progress=False)


# ---------------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------------
def test_missing_transforms(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(BundleError, match=r"transforms\.json.*missing transforms\.json"):
        import_nerfstudio(tmp_path / "empty", tmp_path / "out", progress=False)


def test_missing_image(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    (scene.root / "images" / "frame_00002.png").unlink()
    with pytest.raises(BundleError, match=r"transforms\.json \[frames\[2\]\.file_path\].*frame_00002\.png"):
        import_nerfstudio(scene.root, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_non_rigid_matrix(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    meta = dict(scene.meta)
    for row in meta["frames"][0]["transform_matrix"][:3]:
        row[0] *= 2.0  # stretch the camera x axis
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=r"transforms\.json \[frames\[0\]\.transform_matrix\].*rigid"):
        import_nerfstudio(scene.root, tmp_path / "out", progress=False)


def test_missing_intrinsics(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    meta = dict(scene.meta)
    meta.pop("fl_x")
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=r"transforms\.json \[fl_x\].*missing intrinsic 'fl_x'"):
        import_nerfstudio(scene.root, tmp_path / "out", progress=False)


def test_size_mismatch_and_unsupported_model(nerfstudio_scene, tmp_path):
    scene = nerfstudio_scene()
    meta = dict(scene.meta)
    meta["w"] = 160
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=r"is 80x60 but the intrinsics say w=160"):
        import_nerfstudio(scene.root, tmp_path / "out", progress=False)
    meta["w"] = 80
    meta["camera_model"] = "OPENCV_FISHEYE"
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=r"\[camera_model\].*unsupported camera_model"):
        import_nerfstudio(scene.root, tmp_path / "out", progress=False)


def test_invalid_json(tmp_path):
    (tmp_path / "ns").mkdir()
    (tmp_path / "ns" / "transforms.json").write_text("{\"frames\": [")
    with pytest.raises(BundleError, match="invalid JSON"):
        import_nerfstudio(tmp_path / "ns", tmp_path / "out", progress=False)
