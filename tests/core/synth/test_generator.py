"""The synthetic benchmark generator: valid bundles, deterministic, consistent ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from core.bundle import open_bundle, validate_bundle
from core.conventions import project_points
from core.errors import ConfigError
from core.synth import generate_scene, profile
from core.synth.street import ROAD_HALF_WIDTH

pytestmark = pytest.mark.mitsuba


def test_tiny_scene_is_valid_and_complete(tiny_scene):
    assert validate_bundle(tiny_scene) == []
    b = open_bundle(tiny_scene)
    m = b.manifest
    cfg = profile("tiny")
    assert len(m.split("train")) == cfg.num_frames == len(m.split("test"))
    assert len(m.lidar) == cfg.num_frames
    assert {o.id for o in m.objects} and all(len(o.poses) == cfg.num_frames for o in m.objects)
    assert m.ground_truth.envmap_name == "city"
    assert [r.name for r in m.ground_truth.relit] == list(cfg.relight_envmaps)
    # train and test trajectories are parallel, offset laterally by test_offset_m
    for tr, te in zip(m.split("train"), m.split("test")):
        off = te.cam_to_world[:3, 3] - tr.cam_to_world[:3, 3]
        np.testing.assert_allclose(off, [0, cfg.test_offset_m, 0], atol=1e-9)
        np.testing.assert_allclose(te.cam_to_world[:3, :3], tr.cam_to_world[:3, :3])


def test_ground_truth_layers_are_consistent(tiny_scene):
    b = open_bundle(tiny_scene)
    for f in b.frames():
        gt = b.load_ground_truth(f)
        sky = b.load_sky_mask(f)
        hit = ~sky
        assert sky.any() and hit.any()
        assert np.all(gt["depth"][..., 0][hit] > 0) and np.all(gt["depth"][..., 0][sky] == 0)
        n = gt["normal"][hit]
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=2e-3)  # half precision
        for k in ("albedo", "roughness", "metallic"):
            assert gt[k].min() >= 0 and gt[k].max() <= 1
        assert np.all(np.isfinite(gt["rgb"])) and gt["rgb"].min() >= 0
        # the bottom rows see the road: upward normals, asphalt albedo
        bottom = gt["normal"][-1]
        assert np.all(bottom[:, 2] > 0.99)
        np.testing.assert_allclose(gt["albedo"][-1], 0.09, atol=0.011)
        # unprojected depth of the bottom rows lies on the road plane z = 0
        cam = b.camera(f)
        v = gt["depth"].shape[0] - 0.5
        u = np.arange(cam.width) + 0.5
        z = gt["depth"][-1, :, 0]
        p_cam = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1)
        p_world = p_cam @ f.cam_to_world[:3, :3].T + f.cam_to_world[:3, 3]
        np.testing.assert_allclose(p_world[:, 2], 0.0, atol=0.02)
        # the LDR image is the tone-mapped HDR beauty
        ldr = b.load_image(f)
        expect = np.clip(gt["rgb"] * b.manifest.ldr_exposure, 0, 1) ** (1 / b.manifest.ldr_gamma)
        assert np.abs(ldr - expect).max() <= 1 / 255 + 1e-6


def test_lidar_hits_scene_surfaces(tiny_scene):
    """LiDAR points lie on the road (z = 0) or on objects above it; points inside a car's box
    project inside that car's image region."""
    b = open_bundle(tiny_scene)
    m = b.manifest
    for s in m.lidar:
        pts = b.load_lidar(s.time_index)
        assert len(pts) > 100
        origin, hit = pts[:, :3], pts[:, 3:]
        assert np.all(np.linalg.norm(hit - origin, axis=1) <= profile("tiny").lidar_range_m + 1e-3)
        assert hit[:, 2].min() > -0.01
        on_road = np.abs(hit[:, 2]) < 0.01
        assert np.all(np.abs(hit[on_road, 1]) <= ROAD_HALF_WIDTH + 1e-3)
        frame = next(f for f in m.split("train") if f.time_index == s.time_index)
        cam = m.cameras[frame.camera]
        for obj in m.objects:
            pose = obj.poses[s.time_index]
            local = (hit - pose[:3, 3]) @ pose[:3, :3]
            inside = np.all(np.abs(local) <= np.array(obj.size) / 2 + 0.02, axis=1)
            if not inside.any():
                continue
            corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)]) * obj.size
            corners_w = corners @ pose[:3, :3].T + pose[:3, 3]
            uv_c, z_c = project_points(corners_w, frame.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
            if np.any(z_c <= 0):
                continue
            uv_p, z_p = project_points(hit[inside], frame.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
            ok = z_p > 0
            assert np.all(uv_p[ok] >= uv_c.min(0) - 1e-6) and np.all(uv_p[ok] <= uv_c.max(0) + 1e-6)


def test_generator_is_deterministic(tiny_scene, tmp_path):
    from core.io.images import read_image

    again = generate_scene(profile("tiny"), tmp_path / "again", progress=False, workers=1)
    for rel in ("images/train_000.png", "images/test_001.png", "sky_masks/train_001.png"):
        assert np.array_equal(read_image(tiny_scene / rel), read_image(again / rel)), rel
    assert np.array_equal(np.load(tiny_scene / "lidar/0001.npy"), np.load(again / "lidar/0001.npy"))


def test_seed_changes_the_scene(tmp_path):
    from core.synth.generate import ego_positions
    from core.synth.street import make_street

    a = make_street(profile("tiny", seed=1), ego_positions(profile("tiny")))
    b = make_street(profile("tiny", seed=2), ego_positions(profile("tiny")))
    assert [p.material for p in a.static_parts] != [p.material for p in b.static_parts]


def test_bad_settings_are_named():
    with pytest.raises(ConfigError, match="width"):
        profile("tiny", width=2)
    with pytest.raises(ConfigError, match="unknown profile"):
        profile("huge")
    with pytest.raises(ConfigError, match="envmap"):
        generate_scene(profile("tiny", envmap="no_such_sky"), "/tmp/never_written", progress=False)


def test_relit_references_get_more_samples_than_the_inputs(monkeypatch):
    """Relit frames are references: 4 x spp by default (their noise would cap the score of a
    perfect render), ``relight_spp`` when set; the input frames keep ``spp``."""
    import core.synth.generate as gen

    seen = []
    monkeypatch.setattr(gen, "render_beauty", lambda parts, env, cam, *, spp, max_depth, seed: seen.append(spp) or np.zeros((2, 2, 3)))
    cfg = profile("tiny", spp=8)
    c2w = gen.camera_pose(cfg, 0.0, 0.0)
    gen._render_job(("beauty", "train_000", cfg, 0, c2w, "city", 0.0, 0))
    gen._render_job(("relit:sunset", "test_000", cfg, 0, c2w, "sunset", 0.0, 0))
    gen._render_job(("relit:sunset", "test_000", profile("tiny", spp=8, relight_spp=100), 0, c2w, "sunset", 0.0, 0))
    assert seen == [8, 32, 100]
    with pytest.raises(ConfigError, match="relight_spp"):
        profile("tiny", relight_spp=-1)
