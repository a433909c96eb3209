"""drivestudio (processed Waymo) importer: poses, intrinsics, LiDAR, boxes and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.adapters import WAYMO_CAMERA_NAMES, import_drivestudio
from core.bundle import open_bundle, validate_bundle
from core.conventions import WAYMO_TO_OPENCV, project_points
from core.errors import BundleError, ConfigError


@pytest.fixture
def imported(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    out = import_drivestudio(scene.root, tmp_path / "bundle", progress=False)
    return scene, open_bundle(out)


def _frame(bundle, t, cam):
    return bundle.manifest.frame(f"{t:03d}_{cam}")


def test_bundle_is_valid_and_complete(imported, tmp_path):
    scene, b = imported
    assert validate_bundle(b.root) == []
    m = b.manifest
    assert len(m.frames) == len(scene.times) * len(scene.cams)
    assert m.times == pytest.approx([0.0, 0.1, 0.2])
    assert sorted(m.cameras) == ["0", "3"]
    assert all(f.split == "train" for f in m.frames)
    assert m.source["kind"] == "drivestudio"
    assert m.source["camera_names"] == {"0": WAYMO_CAMERA_NAMES[0], "3": WAYMO_CAMERA_NAMES[3]}
    assert all(f.image.endswith(".jpg") for f in m.frames)
    # images are copied byte for byte
    assert (b.root / _frame(b, 1, 3).image).read_bytes() == (scene.root / "images" / "001_3.jpg").read_bytes()
    # the only staging directory left behind would sit next to the bundle
    assert not [p for p in tmp_path.iterdir() if "staging" in p.name]


def test_intrinsics_copied(imported):
    scene, b = imported
    for c in scene.cams:
        cam = b.manifest.cameras[str(c)]
        fx, fy, cx, cy, *dist = scene.intrinsics[c]
        assert (cam.width, cam.height) == (64, 48)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((fx, fy, cx, cy))
        if any(dist):
            assert list(cam.distortion) == pytest.approx(dist)
        else:
            assert cam.distortion == ()


def test_front_camera_looks_along_ego_forward(imported, geom):
    scene, b = imported
    for t in scene.times:
        f = _frame(b, t, 0)
        ego = scene.ego[t]
        c2w = f.cam_to_world
        assert f.time_index == t
        np.testing.assert_allclose(c2w[:3, 2], ego[:3, 0], atol=1e-9)    # OpenCV z = ego forward
        np.testing.assert_allclose(c2w[:3, 1], -ego[:3, 2], atol=1e-9)   # OpenCV y = ego down
        np.testing.assert_allclose(c2w[:3, 0], -ego[:3, 1], atol=1e-9)   # OpenCV x = ego right
        centre = geom.apply(ego, scene.extrinsic[0][:3, 3][None])[0]
        np.testing.assert_allclose(c2w[:3, 3], centre, atol=1e-9)
    # heading turns left by 0.04 rad per step
    z0 = _frame(b, 0, 0).cam_to_world[:3, 2]
    z2 = _frame(b, 2, 0).cam_to_world[:3, 2]
    assert np.degrees(np.arctan2(z2[1], z2[0]) - np.arctan2(z0[1], z0[0])) == pytest.approx(np.degrees(0.08))


def test_side_camera_pose(imported, geom):
    scene, b = imported
    for t in scene.times:
        c2w = _frame(b, t, 3).cam_to_world
        np.testing.assert_allclose(c2w, scene.ego[t] @ scene.extrinsic[3] @ WAYMO_TO_OPENCV, atol=1e-9)
        left = scene.ego[t][:3, 1]
        assert c2w[:3, 2] @ left > 0.99           # looks to the vehicle's left
        assert c2w[:3, 2] @ scene.ego[t][:3, 2] < 0  # pitched slightly down


def test_lidar_transformed_to_world(imported, geom):
    scene, b = imported
    assert [s.time_index for s in b.manifest.lidar] == scene.times
    for t in scene.times:
        got = b.load_lidar(t)
        rows = scene.lidar_rows[t].astype(np.float64)
        want = np.concatenate([geom.apply(scene.ego[t], rows[:, :3]), geom.apply(scene.ego[t], rows[:, 3:6])],
                              axis=1)
        assert got.shape == (len(rows), 6) and got.dtype == np.float32
        np.testing.assert_allclose(got, want, atol=1e-4)


def test_boxes_land(imported):
    scene, b = imported
    objs = {o.id: o for o in b.manifest.objects}
    assert set(objs) == {"0", "1"}
    car = objs["0"]
    assert car.cls == "Vehicle"
    assert car.size == pytest.approx(scene.box_size_median)
    assert sorted(car.poses) == scene.times
    for t in scene.times:
        np.testing.assert_allclose(car.poses[t], scene.box_pose[t], atol=1e-9)
    assert sorted(objs["1"].poses) == [1, 2] and objs["1"].size == pytest.approx((0.8, 0.8, 1.8))


def test_lidar_point_on_box_projects_inside_box_region(imported, geom):
    """The issue's key check: a LiDAR hit on a tracked box's surface lands inside the box's image
    region, using only what the bundle stores (cam_to_world, intrinsics, lidar, object poses)."""
    scene, b = imported
    car = next(o for o in b.manifest.objects if o.id == "0")
    for t in scene.times:
        pts = b.load_lidar(t)[scene.box_surface_idx[t], 3:6].astype(np.float64)
        # the points really are on the box surface (in the bundle's own box frame)
        local = geom.apply(np.linalg.inv(car.poses[t]), pts)
        half = np.asarray(car.size) / 2
        assert np.all(np.abs(local) <= half + 1e-3)
        assert np.all(np.min(half - np.abs(local), axis=1) < 1e-3)
        for cam_id in ("0",):
            f = _frame(b, t, cam_id)
            cam = b.camera(f)
            corners = geom.apply(car.poses[t], geom.box_corners(car.size))
            cuv, cz = project_points(corners, f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
            assert np.all(cz > 0)
            puv, pz = project_points(pts, f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
            assert np.all(pz > 0)
            lo, hi = cuv.min(axis=0), cuv.max(axis=0)
            assert np.all(puv >= lo - 1e-6) and np.all(puv <= hi + 1e-6), (t, puv, lo, hi)
            assert np.all((puv >= 0) & (puv <= [cam.width, cam.height]))
            # the box is not degenerate in the image (so "inside" means something)
            assert np.all(hi - lo > 2.0)


def test_sky_mask_imported(imported):
    scene, b = imported
    mask = b.load_sky_mask(_frame(b, 0, 0))
    assert mask.shape == (48, 64) and mask[:16].all() and not mask[16:].any()
    assert b.load_sky_mask(_frame(b, 1, 0)) is None


def test_frame_and_camera_selection_and_test_split(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    out = import_drivestudio(scene.root, tmp_path / "b2", cameras=["FRONT"], frames=range(1, 3),
                             test_every=2, name="sel", progress=True)
    b = open_bundle(out)
    m = b.manifest
    assert m.name == "sel"
    assert list(m.cameras) == ["0"]
    assert m.times == pytest.approx([0.1, 0.2])
    assert [(f.id, f.time_index, f.split) for f in m.frames] == [("001_0", 0, "train"), ("002_0", 1, "test")]
    assert m.source["source_time_indices"] == [1, 2]
    np.testing.assert_allclose(m.frame("002_0").cam_to_world[:3, 3],
                               (scene.ego[2] @ scene.extrinsic[0])[:3, 3], atol=1e-9)
    car = next(o for o in m.objects if o.id == "0")
    np.testing.assert_allclose(car.poses[1], scene.box_pose[2], atol=1e-9)  # renumbered time index
    np.testing.assert_allclose(b.load_lidar(0)[:, 3:6],
                               (scene.lidar_rows[1][:, 3:6].astype(np.float64) @ scene.ego[1][:3, :3].T
                                + scene.ego[1][:3, 3]), atol=1e-4)


def test_recenter_keeps_relative_geometry(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    b = open_bundle(import_drivestudio(scene.root, tmp_path / "rc", recenter=True, progress=False))
    off = np.asarray(b.manifest.source["world_offset"])
    np.testing.assert_allclose(off, scene.ego[0][:3, 3])
    np.testing.assert_allclose(b.manifest.frame("000_0").cam_to_world[:3, 3], [1.5, 0.0, 2.0], atol=1e-9)
    car = next(o for o in b.manifest.objects if o.id == "0")
    np.testing.assert_allclose(car.poses[2][:3, 3], scene.box_pose[2][:3, 3] - off, atol=1e-9)
    np.testing.assert_allclose(b.load_lidar(1)[:, :3], np.broadcast_to(
        scene.ego[1][:3, :3] @ [0.0, 0.0, 2.1] + scene.ego[1][:3, 3] - off, (len(scene.lidar_rows[1]), 3)),
        atol=1e-4)


def test_optional_parts_missing(drivestudio_scene, tmp_path):
    scene = drivestudio_scene(with_instances=False, with_lidar=False, with_sky=False)
    b = open_bundle(import_drivestudio(scene.root, tmp_path / "bare", progress=False))
    assert b.manifest.objects == () and b.manifest.lidar == ()
    assert all(f.sky_mask is None for f in b.manifest.frames)


def test_out_dir_not_empty_needs_overwrite(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    out = import_drivestudio(scene.root, tmp_path / "b", progress=False)
    with pytest.raises(ConfigError):
        import_drivestudio(scene.root, out, progress=False)
    import_drivestudio(scene.root, out, cameras=[3], overwrite=True, progress=False)
    assert list(open_bundle(out).manifest.cameras) == ["3"]


# ---------------------------------------------------------------------------------------------
# errors name the offending file
# ---------------------------------------------------------------------------------------------
def test_missing_ego_pose(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    (scene.root / "ego_pose" / "001.txt").unlink()
    with pytest.raises(BundleError, match=r"ego_pose[/\\]001\.txt.*missing ego pose"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_bad_lidar_size(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    p = scene.root / "lidar" / "002.bin"
    p.write_bytes(p.read_bytes()[:-4])
    with pytest.raises(BundleError, match=r"lidar[/\\]002\.bin.*multiple of 56"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
    assert not [q for q in tmp_path.iterdir() if "staging" in q.name]


def test_non_rigid_extrinsic(drivestudio_scene, tmp_path, geom):
    scene = drivestudio_scene()
    bad = scene.extrinsic[3].copy()
    bad[:3, :3] *= 1.1
    geom.write_matrix(scene.root / "extrinsics" / "3.txt", bad)
    with pytest.raises(BundleError, match=r"extrinsics[/\\]3\.txt.*not a rigid transform"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)


def test_unparsable_intrinsics(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    (scene.root / "intrinsics" / "0.txt").write_text("60 58 32 oops 0 0 0 0 0\n")
    with pytest.raises(BundleError, match=r"intrinsics[/\\]0\.txt.*unparsable"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)
    (scene.root / "intrinsics" / "0.txt").write_text("60 58 32 24\n")
    with pytest.raises(BundleError, match=r"intrinsics[/\\]0\.txt.*expected 9 numbers"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)


def test_missing_folder(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    for f in (scene.root / "extrinsics").iterdir():
        f.unlink()
    (scene.root / "extrinsics").rmdir()
    with pytest.raises(BundleError, match=r"extrinsics.*missing folder 'extrinsics/'"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)
    with pytest.raises(BundleError, match="not found"):
        import_drivestudio(tmp_path / "nowhere", tmp_path / "out", progress=False)


def test_bad_instances(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    p = scene.root / "instances" / "instances_info.json"
    info = json.loads(p.read_text())
    info["0"]["frame_annotations"]["obj_to_world"][1][0][0] = 3.0
    p.write_text(json.dumps(info))
    with pytest.raises(BundleError, match=r"instances_info\.json \[0\.frame_annotations\.obj_to_world\[1\]\]"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)


def test_frame_instances_mismatch_warns(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    (scene.root / "instances" / "frame_instances.json").write_text(json.dumps({"0": [0, 1]}))
    with pytest.warns(UserWarning, match="frame_instances.json disagrees"):
        import_drivestudio(scene.root, tmp_path / "out", progress=False)


def test_bad_arguments(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    with pytest.raises(ConfigError, match="cameras"):
        import_drivestudio(scene.root, tmp_path / "o", cameras=["REAR"], progress=False)
    with pytest.raises(BundleError, match="camera 1"):
        import_drivestudio(scene.root, tmp_path / "o", cameras=[1], progress=False)
    with pytest.raises(BundleError, match=r"time indices \[7\]"):
        import_drivestudio(scene.root, tmp_path / "o", frames=[0, 7], progress=False)
    with pytest.raises(ConfigError, match="test_every"):
        import_drivestudio(scene.root, tmp_path / "o", test_every=1, progress=False)


def test_camera_without_images_at_selected_times(drivestudio_scene, tmp_path):
    scene = drivestudio_scene()
    (scene.root / "images" / "001_3.jpg").unlink()
    m = open_bundle(import_drivestudio(scene.root, tmp_path / "o", frames=[1], progress=False)).manifest
    assert list(m.cameras) == ["0"] and [f.id for f in m.frames] == ["001_0"]
    with pytest.raises(BundleError, match=r"camera\(s\) \[3\] have no images"):
        import_drivestudio(scene.root, tmp_path / "o2", frames=[1], cameras=[0, 3], progress=False)
    # a frame missing for one camera at one time is simply absent
    m = open_bundle(import_drivestudio(scene.root, tmp_path / "o3", progress=False)).manifest
    assert len(m.frames) == 5 and "001_3" not in {f.id for f in m.frames}
