"""Randomised streets and the OOD protocol: ranges respected, held-out regions never drawn for
training, determinism, and a tiny randomised bundle (Mitsuba) that validates with consistent
ground truth."""

from __future__ import annotations

import itertools
import math
from dataclasses import fields, replace

import numpy as np
import pytest

from core.errors import ConfigError
from core.synth import profile
from core.synth.generate import ego_positions
from core.synth.random_street import make_random_street
from core.synth.randomise import (
    SUNSKY,
    RandomisationSettings,
    lens_k1,
    sample_spec,
    spec_config,
)
from core.synth.sensor import apply_sensor, source_coords, undistort_radius
from core.synth.sky import sun_direction, sun_sky_map
from core.synth.splits import (
    HELD_OUT,
    IN_DISTRIBUTION_SPLITS,
    SPLITS,
    check_split,
    held_out_axes,
    split_spec,
)
from core.synth.textures import AlbedoTexture, planar_uvs, texture_image

S = RandomisationSettings()
N = 150  # specs per split in the sampling tests (pure Python, ~ms each)


def _inside(v, r):
    return r[0] - 1e-9 <= v <= r[1] + 1e-9


@pytest.mark.parametrize("split", SPLITS)
def test_sampled_specs_respect_the_ranges(split):
    for i in range(N):
        s = split_spec(split, i)
        assert s.layout in S.layout_styles and s.palette in S.facade_palettes
        assert _inside(s.road_half_width_m, S.road_half_width_m) and _inside(s.sidewalk_width_m, S.sidewalk_width_m)
        assert _inside(s.tree_spacing_m, S.tree_spacing_m)
        assert S.parked_cars[0] <= s.num_parked_cars <= S.parked_cars[1]
        assert S.moving_cars[0] <= s.num_moving_cars <= S.moving_cars[1]
        assert _inside(s.camera_height_m, S.camera_height_m) and _inside(s.camera_pitch_deg, S.camera_pitch_deg)
        assert _inside(s.hfov_deg, S.hfov_deg) and (s.width, s.height) in S.resolutions
        assert s.edge_distortion == 0.0 or _inside(s.edge_distortion, S.edge_distortion)
        assert s.light == SUNSKY or (s.light in S.hdris and _inside(s.light_rotation_deg, S.hdri_rotation_deg))
        assert _inside(s.intensity, S.intensity)
        assert _inside(s.sun_elevation_deg, S.sun_elevation_deg) and _inside(s.turbidity, S.turbidity)
        assert len(s.relight_envmaps) == S.relight_count and s.light not in s.relight_envmaps
        assert set(s.relight_envmaps) <= set(S.hdris)
        for name in ("exposure_ev", "gamma", "contrast", "shot_noise", "read_noise"):
            assert _inside(getattr(s, name), getattr(S, name)), name
        assert s.jpeg_quality == 0 or _inside(s.jpeg_quality, S.jpeg_quality)


def test_the_draws_cover_the_ranges():
    """Training draws reach across each training range (not stuck at one value)."""
    specs = [split_spec("train", i) for i in range(300)]
    h = [s.camera_height_m for s in specs]
    assert min(h) < 1.3 and max(h) > 2.1
    fov = [s.hfov_deg for s in specs]
    assert min(fov) < 55 and max(fov) > 105
    pitch = [s.camera_pitch_deg for s in specs]
    assert min(pitch) < -9 and max(pitch) > 9
    elev = [s.sun_elevation_deg for s in specs if s.light == SUNSKY]
    assert len(elev) > 100 and min(elev) < 10 and max(elev) > 75
    assert {s.layout for s in specs} == set(S.layout_styles) - set(HELD_OUT["layout"].values)
    assert {s.palette for s in specs} == set(S.facade_palettes) - set(HELD_OUT["palette"].values)
    assert {s.light for s in specs} == (set(S.hdris) - set(HELD_OUT["hdri"].values)) | {SUNSKY}
    assert any(s.edge_distortion < 0 for s in specs) and any(s.edge_distortion > 0 for s in specs)
    assert any(s.jpeg_quality == 0 for s in specs) and any(s.jpeg_quality > 0 for s in specs)


@pytest.mark.parametrize("split", IN_DISTRIBUTION_SPLITS)
def test_held_out_regions_are_never_drawn_for_training(split):
    for i in range(3 * N):
        s = split_spec(split, i)
        assert held_out_axes(s) == set()
        assert s.camera_height_m <= 2.2
        assert "forest" not in (s.light, *s.relight_envmaps)
        assert s.palette != "pastel" and s.layout != "narrow"


@pytest.mark.parametrize("axis", sorted(HELD_OUT))
def test_ood_splits_lie_in_their_own_region_only(axis):
    for i in range(N):
        s = split_spec(f"test_ood_{axis}", i)
        assert held_out_axes(s) == {axis}
    if axis == "camera_height":
        assert all(split_spec("test_ood_camera_height", i).camera_height_m > 2.2 for i in range(N))


def test_a_spec_in_a_held_out_region_is_refused_for_training():
    s = split_spec("train", 0)
    check_split(s, "train")  # a training draw passes
    for bad in (replace(s, camera_height_m=2.3), replace(s, light="forest"), replace(s, palette="pastel"),
                replace(s, layout="narrow"), replace(s, relight_envmaps=("forest",))):
        with pytest.raises(ConfigError, match="held-out"):
            check_split(bad, "train")
        with pytest.raises(ConfigError, match="held-out"):
            check_split(bad, "val")
    with pytest.raises(ConfigError, match="held-out axis 'camera_height'"):
        check_split(s, "test_ood_camera_height")


def test_specs_are_deterministic_and_splits_disjoint():
    assert split_spec("train", 5) == split_spec("train", 5)
    assert split_spec("train", 5) != split_spec("train", 6)
    seeds = {split_spec(sp, i).seed for sp in SPLITS for i in range(40)}
    assert len(seeds) == 40 * len(SPLITS)  # no scene shared between splits
    a = [split_spec("train", i) for i in range(20)]
    b = [split_spec("val", i) for i in range(20)]
    assert all(x.camera_height_m != y.camera_height_m for x, y in zip(a, b))
    # the street itself is a function of the spec
    sa = make_random_street(a[0], ego_positions(profile("tiny")), 60.0, 0.1, 8.0)
    sb = make_random_street(a[0], ego_positions(profile("tiny")), 60.0, 0.1, 8.0)
    assert [p.name for p in sa.static_parts] == [p.name for p in sb.static_parts]
    assert all(np.array_equal(p.vertices, q.vertices) and p.material == q.material
               for p, q in zip(sa.static_parts, sb.static_parts))


def test_pinhole_settings_change_only_the_lens():
    pin = RandomisationSettings(distortion_prob=0.0)
    for i in range(30):
        a, b = split_spec("train", i), split_spec("train", i, pin)
        assert b.edge_distortion == 0.0
        assert replace(a, edge_distortion=0.0, settings=pin) == b


def test_bad_settings_and_arguments_are_named():
    with pytest.raises(ConfigError, match="camera_height_m"):
        RandomisationSettings(camera_height_m=(2.0, 1.0))
    with pytest.raises(ConfigError, match="sky_prob"):
        RandomisationSettings(sky_prob=1.5)
    with pytest.raises(ConfigError, match="layout_styles"):
        RandomisationSettings(layout_styles=("suburb",))
    with pytest.raises(ConfigError, match="split"):
        split_spec("test", 0)
    with pytest.raises(ConfigError, match="index"):
        split_spec("train", -1)
    with pytest.raises(ConfigError, match="scene_spec"):
        profile("tiny", scene_spec={"layout": "narrow"})
    with pytest.raises(ConfigError, match="overrides"):
        sample_spec(S, 0, overrides={"no_such_axis": 1})
    with pytest.raises(ConfigError, match="elevation_deg"):
        sun_sky_map(95.0, 0.0, 3.0, height=16)
    with pytest.raises(ConfigError, match="turbidity"):
        sun_sky_map(30.0, 0.0, 0.5, height=16)


def test_every_setting_has_a_docstring():
    import inspect

    from core.synth import randomise

    src = inspect.getsource(randomise.RandomisationSettings)
    for f in fields(RandomisationSettings):
        head = src.split(f"    {f.name}:", 1)[1]
        assert head.split("\n", 2)[1].strip().startswith('"""'), f.name


def test_street_follows_the_spec():
    ego = ego_positions(profile("tiny"))
    base = split_spec("train", 2)
    terr = replace(base, layout="terraced", num_parked_cars=3, num_moving_cars=2)
    street = make_random_street(terr, ego, 80.0, 0.1, 8.0)
    facades = [p for p in street.static_parts if p.name.startswith("buildingR")]
    assert len(facades) >= 3
    # terraced: the facades stand on the building line and touch their neighbours
    B = terr.road_half_width_m + 0.2 + terr.sidewalk_width_m
    for p, q in itertools.pairwise(facades):
        assert abs(p.vertices[:, 0].max() - q.vertices[:, 0].min()) < 1e-3
    for p in facades:
        assert abs(-p.vertices[:, 1].max() - B) < 1e-3
        assert p.material.texture is not None and p.uvs is not None and len(p.uvs) == len(p.vertices)
        h = p.vertices[:, 2].max()
        assert _inside(h, S.building_height_m)
    road = next(p for p in street.static_parts if p.name == "road")
    assert np.isclose(road.vertices[:, 1].max(), terr.road_half_width_m)
    assert len(street.cars) == 5 and sum(c.moving for c in street.cars) == 2
    for c in street.cars:
        assert _inside(c.size[0], S.vehicle_length_m)
        paint = c.parts[0].material
        assert _inside(paint.roughness, S.paint_roughness) and _inside(paint.metallic, S.paint_metallic)
    # detached: gaps and setbacks appear
    det = make_random_street(replace(base, layout="detached"), ego, 80.0, 0.1, 8.0)
    fl = [p for p in det.static_parts if p.name.startswith("buildingR")]
    gaps = [q.vertices[:, 0].min() - p.vertices[:, 0].max() for p, q in itertools.pairwise(fl)]
    assert max(gaps) > 0.5


def test_textures_vary_and_stay_in_range():
    for pattern in ("noise", "bricks", "blocks", "panels", "tiles", "asphalt"):
        img = texture_image(AlbedoTexture(pattern, (0.4, 0.3, 0.2), 0.2, 2.0, seed=3))
        assert img.shape == (64, 64, 3) and img.min() >= 0.01 and img.max() <= 0.95
        assert img.std(axis=(0, 1)).min() > 0.005, pattern
    a = texture_image(AlbedoTexture("bricks", (0.4, 0.3, 0.2), 0.2, 2.0, seed=3))
    assert np.array_equal(a, texture_image(AlbedoTexture("bricks", (0.4, 0.3, 0.2), 0.2, 2.0, seed=3)))
    from core.synth import geometry as geo

    v, f, uv = planar_uvs(*geo.box((0, 0, 0), (2.0, 2.0, 2.0)), repeat_m=2.0)
    assert uv.shape == (len(v), 2) and np.ptp(uv[f[0]], axis=0).max() <= 1.0 + 1e-6


def test_sky_puts_the_sun_where_asked():
    from core.conventions import envmap_directions, envmap_solid_angles

    for elev, az, turb in ((8.0, 30.0, 2.0), (45.0, 200.0, 5.0), (70.0, 300.0, 9.0)):
        env = sun_sky_map(elev, az, turb, height=128)
        assert env.shape == (128, 256, 3) and np.isfinite(env).all() and env.min() >= 0
        d = envmap_directions(128, 256)
        r, c = np.unravel_index(np.argmax(env.sum(-1)), env.shape[:2])
        ang = math.degrees(math.acos(np.clip(d[r, c] @ sun_direction(elev, az), -1, 1)))
        assert ang < 1.5, (elev, az, ang)
        # the clear sky at 45 degrees elevation opposite the sun is bluer than it is red
        from core.conventions import direction_to_pixel

        rr, cc = direction_to_pixel(sun_direction(45.0, az + 180.0), 128, 256)
        assert env[rr, cc, 2] > env[rr, cc, 0]
    # a clearer sky gives the sun a larger share of the light
    sa = envmap_solid_angles(128, 256)[:, None]

    def sun_share(turb):
        env = sun_sky_map(40.0, 0.0, turb, height=128).mean(-1)
        tot = (env * sa).sum()
        return float(np.sort((env * sa).ravel())[-20:].sum() / tot)

    assert sun_share(2.0) > sun_share(9.0)


def test_lens_model_round_trips():
    r = np.linspace(0.0, 1.3, 50)
    for k1 in (-0.08, 0.03):
        ru = undistort_radius(r, k1)
        np.testing.assert_allclose(ru * (1 + k1 * ru * ru), r, atol=1e-9)
    with pytest.raises(ConfigError, match="r_d"):  # barrel k1 = -0.08 never reaches r_d = 1.5
        undistort_radius(np.array([1.5]), -0.08)
    k1 = lens_k1(-0.1, 90.0, 64, 48)
    us, vs, px, py = source_coords(64, 48, 32.0, k1)
    assert px > 0 and py > 0  # barrel: the pinhole canvas must reach further out
    # the corner lands at edge_distortion relative displacement
    xc, yc = us[0, 0] - (32 + px), vs[0, 0] - (24 + py)
    assert np.isclose(math.hypot(31.5, 23.5) / math.hypot(xc, yc) - 1.0, -0.1, atol=0.01)
    assert abs(us[24, 32] - (32.5 + px)) < 1e-3  # near the centre, pixels barely move


def test_sensor_without_noise_is_the_tone_map():
    from core.tonemap import hdr_to_ldr, ldr_to_uint8

    hdr = np.random.default_rng(0).uniform(0, 3, (8, 8, 3)).astype(np.float32)
    plain = apply_sensor(hdr, 0.5, 2.2, 0.0, 0.0, 0.0, np.random.default_rng(1))
    assert np.abs(plain.astype(int) - ldr_to_uint8(hdr_to_ldr(hdr, 0.5, 2.2)).astype(int)).max() <= 1
    noisy = apply_sensor(hdr, 0.5, 2.2, 0.3, 0.01, 0.01, np.random.default_rng(1))
    assert noisy.dtype == np.uint8 and np.abs(noisy.astype(int) - plain.astype(int)).mean() > 1


def test_profiles_are_untouched():
    for name in ("tiny", "quick", "benchmark"):
        assert profile(name).scene_spec is None
    cfg = spec_config(split_spec("train", 0), profile("tiny"))
    assert cfg.scene_spec is not None and cfg.num_frames == profile("tiny").num_frames


# ------------------------------------------------------------------------------------------------
# Mitsuba: tiny renders only (48x32 or smaller, 2 frames, 4 spp)
# ------------------------------------------------------------------------------------------------
def _tiny_spec():
    """A training spec with a barrel lens, JPEG frames, the sky, no cars, looking down the road."""
    for i in range(200):
        s = split_spec("train", i)
        if s.edge_distortion < -0.05 and s.jpeg_quality > 0 and s.light == SUNSKY:
            return replace(s, num_parked_cars=0, num_moving_cars=0, camera_pitch_deg=6.0,
                           relight_envmaps=s.relight_envmaps[:1])
    raise AssertionError("no such spec in 200 draws")


@pytest.fixture(scope="module")
def tiny_random_scene(tmp_path_factory):
    from core.synth import generate_scene

    spec = _tiny_spec()
    cfg = spec_config(spec, profile("tiny"), width=48, height=32, spp=4, lidar_beams=4, lidar_azimuth_steps=30)
    return spec, cfg, generate_scene(cfg, tmp_path_factory.mktemp("rnd") / "b", progress=False, workers=1)


@pytest.mark.mitsuba
def test_tiny_randomised_bundle_validates(tiny_random_scene):
    from core.bundle import open_bundle, validate_bundle

    spec, cfg, root = tiny_random_scene
    assert validate_bundle(root) == []
    b = open_bundle(root)
    m = b.manifest
    cam = next(iter(m.cameras.values()))
    assert cam.distortion[0] == pytest.approx(lens_k1(spec.edge_distortion, cfg.hfov_deg, 48, 32), rel=1e-6)
    assert all(f.image.endswith(".jpg") for f in m.frames)
    assert m.ground_truth.envmap_name == SUNSKY and [r.name for r in m.ground_truth.relit] == list(spec.relight_envmaps)
    assert m.ldr_gamma == pytest.approx(spec.gamma)
    assert m.source["config"]["scene_spec"]["palette"] == spec.palette
    for f in b.frames():
        ldr = b.load_image(f)
        assert ldr.shape[:2] == (32, 48)


@pytest.mark.mitsuba
def test_distorted_ground_truth_is_consistent(tiny_random_scene):
    """Unprojecting the warped depth through the bundle's lens puts road pixels on z = 0."""
    from core.bundle import open_bundle

    spec, cfg, root = tiny_random_scene
    b = open_bundle(root)
    n_checked = 0
    for f in b.frames():
        gt = b.load_ground_truth(f)
        cam = b.camera(f)
        k1 = cam.distortion[0]
        H, W = gt["depth"].shape[:2]
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        xd, yd = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
        rd = np.hypot(xd, yd)
        s = np.where(rd > 0, undistort_radius(rd, k1) / np.where(rd > 0, rd, 1), 1.0)
        z = gt["depth"][..., 0]
        p_cam = np.stack([xd * s * z, yd * s * z, z], -1)
        p = p_cam @ f.cam_to_world[:3, :3].T + f.cam_to_world[:3, 3]
        road = (z > 0) & (gt["normal"][..., 2] > 0.99) & (np.abs(p[..., 1]) < spec.road_half_width_m - 0.3)
        assert road.sum() > 20
        np.testing.assert_allclose(p[..., 2][road], 0.0, atol=0.03)
        n_checked += 1
        assert np.isfinite(gt["rgb"]).all() and gt["rgb"].min() >= 0
    assert n_checked == 2 * cfg.num_frames


@pytest.mark.mitsuba
def test_facade_albedo_varies_within_one_facade():
    """The albedo G-buffer of one facade, seen head-on, varies spatially (texture, not a flat
    colour) and stays inside the texture's values."""
    from core.conventions import look_at
    from core.camera import Camera
    from core.synth.mitsuba_backend import render_gbuffers

    spec = replace(split_spec("train", 4), layout="terraced", palette="brick")
    street = make_random_street(spec, ego_positions(profile("tiny")), 60.0, 0.1, 8.0)
    wall = next(p for p in street.static_parts if p.name == "buildingR1")
    c = (wall.vertices.min(0) + wall.vertices.max(0)) / 2
    y_face = -wall.vertices[:, 1].max()  # the facade facing the road, at y = -B
    target = np.array([c[0], -y_face, 2.0])
    eye = target + np.array([0.0, 3.0, 0.0])
    cam = Camera.from_intrinsics(look_at(eye, target), 12.0, 12.0, 12.0, 12.0, 24, 24)
    g = render_gbuffers([wall], cam)
    hit = ~g["sky"]
    assert hit.sum() > 300
    alb = g["albedo"][hit]
    assert alb.std(axis=0).max() > 0.01
    img = texture_image(wall.material.texture)
    assert alb.min() >= img.min() - 1e-4 and alb.max() <= img.max() + 1e-4


@pytest.mark.mitsuba
def test_randomised_generation_is_deterministic(tiny_random_scene, tmp_path):
    from core.io.exr import read_exr
    from core.io.images import read_image
    from core.synth import generate_scene

    _, cfg, root = tiny_random_scene
    again = generate_scene(cfg, tmp_path / "again", progress=False, workers=1)
    for rel in ("images/train_000.jpg", "images/test_001.jpg", "sky_masks/train_001.png"):
        assert np.array_equal(read_image(root / rel), read_image(again / rel)), rel
    a = read_exr(root / "ground_truth/frames/train_001.exr")
    b = read_exr(again / "ground_truth/frames/train_001.exr")
    assert all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.mitsuba
def test_cli_writes_a_held_out_scene(tmp_path, capsys):
    from core.bundle import open_bundle, validate_bundle
    from core.cli import main

    out = tmp_path / "ood"
    assert main(["generate", "--split", "test_ood_camera_height", "--seed", "2", "--profile", "tiny",
                 "--out", str(out), "--quiet", "--workers", "1", "--set", "width=16", "--set", "height=12",
                 "--set", "num_frames=1", "--set", "relight_envmaps=[]", "--set", "lidar_beams=0"]) == 0
    assert validate_bundle(out) == []
    m = open_bundle(out).manifest
    spec = m.source["config"]["scene_spec"]
    assert spec["split"] == "test_ood_camera_height" and spec == _jsonable_spec(split_spec("test_ood_camera_height", 2))
    assert spec["camera_height_m"] > 2.2 and m.name == "test_ood_camera_height_000002"
    assert main(["generate", "--split", "test_ood_weather", "--out", str(tmp_path / "x"), "--quiet"]) != 0
    assert "unknown split 'test_ood_weather'" in capsys.readouterr().err


def _jsonable_spec(spec):
    import json
    from dataclasses import asdict

    return json.loads(json.dumps(asdict(spec)))


@pytest.mark.mitsuba
def test_training_loader_reads_a_randomised_bundle(tiny_random_scene):
    """The priors' data loader takes randomised bundles (JPEG frames, distorted camera); the PBR
    oracle inputs, which rebuild the fixed street, refuse them by name."""
    from core.bundle import open_bundle
    from core.errors import FormatError
    from core.synth.gen_data import DataSettings, load_clips
    from core.synth.prepare import synth_config_of

    _, cfg, root = tiny_random_scene
    clips = load_clips(root, DataSettings(forward_source="degrade"), kinds=("inverse",))
    assert len(clips) == 2 and len(clips[0]) == cfg.num_frames
    rec = clips[0][0]
    assert rec["rgb"].shape == (3, 32, 48) and np.isfinite(rec["gbuffer"]).all()
    with pytest.raises(FormatError, match="randomised street"):
        synth_config_of(open_bundle(root))
