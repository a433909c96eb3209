"""Night lighting (core.render.objects vehicle lights, core.render.streetlights, core.render.exposure)
on a small oracle street: a moving car and a parked one on a road, rendered by the PBR pass."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.conventions import camera_ray_directions, look_at
from core.errors import ConfigError
from core.pbr.envmap import EnvironmentMap
from core.synth.oracle import OracleSettings, oracle_gaussians
from core.camera import Camera
from core.pbr.render import ClipRenderer, PBRSettings
from core.relight import View
from core.render.objects import LAMP_CLEARANCE_M, object_box, vehicle_lights
from core.render.scenario import Scenario, render_scenario
from core.render.streetlights import StreetLightSettings, detect_poles, lamp_lights, lamps_along_path, lamps_at
from core.scene_graph import RigidNode, SceneGraph
from core.synth import geometry as geo
from core.synth.street import Material, Part

SIZE = (4.4, 1.8, 1.5)
CAR0_X = (3.0, 5.0, 7.0, 9.0)  # the moving car drives +x at y = -2


@pytest.fixture(scope="module")
def street():
    road = Part("road", *geo.quad([(-5, -8, 0), (35, -8, 0), (35, 8, 0), (-5, 8, 0)]),
                Material("asphalt", (0.3, 0.3, 0.3), 0.8, 0.0))
    body = Part("body", *geo.box((0, 0, 0), SIZE), Material("paint", (0.6, 0.1, 0.1), 0.4, 0.0))
    eye = np.array([-2.0, -2.0, 7.0])
    bg = oracle_gaussians([road], eye[None], 40.0, OracleSettings(spacing_px=1.5, max_spacing=0.25))
    car = oracle_gaussians([body], eye[None], 40.0, OracleSettings(spacing_px=1.5, max_spacing=0.15))
    t = len(CAR0_X)
    times = torch.arange(t, dtype=torch.float64) * 0.5
    moving = torch.eye(4, dtype=torch.float64).repeat(t, 1, 1)
    moving[:, 0, 3] = torch.tensor(CAR0_X)
    moving[:, 1, 3], moving[:, 2, 3] = -2.0, 0.75
    parked = torch.eye(4, dtype=torch.float64).repeat(t, 1, 1)
    parked[:, :3, :3] = torch.tensor([[-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]], dtype=torch.float64)
    parked[:, :3, 3] = torch.tensor([22.0, 3.0, 0.75], dtype=torch.float64)
    graph = SceneGraph(bg, [RigidNode("car0", "car", car, torch.arange(t), moving, size=SIZE),
                            RigidNode("car1", "car", car.clone(), torch.arange(t), parked, size=SIZE)], times)
    c2w = look_at(eye, np.array([12.0, -1.0, 0.0]))
    views = [View(Camera.from_intrinsics(c2w, 40.0, 40.0, 40.0, 30.0, 80, 60), float(x), f"f{i}")
             for i, x in enumerate(times)]
    return graph, views


def _world_points(view, depth):
    cam = view.camera
    d = camera_ray_directions(cam.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height).reshape(-1, 3)
    c2w = np.asarray(cam.cam_to_world)
    z = depth.reshape(-1)
    return c2w[:3, 3] + d * (z / (d @ c2w[:3, 2]))[:, None]


def _on_road(graph, time_s, pts):
    """Pixels showing the road: low (the G-buffer depth of a grazing thin road is biased a few
    decimetres up) and inside no car's box."""
    out = pts[:, 2] < 0.6
    for name, pose in graph.node_poses(time_s).items():
        pose = pose.numpy()
        local = (pts - pose[:3, 3]) @ pose[:3, :3]
        out &= ~(np.abs(local) <= np.asarray(SIZE) / 2 + 0.3).all(1)
    return out


def _render_one(graph, views, light):
    """Per frame: (world points [P, 3], radiance of that light alone [P]) of the visible pixels."""
    r = ClipRenderer(graph, EnvironmentMap.constant(0.0, 16, 32), PBRSettings(rays_per_pixel=2, threads=2),
                     lights=[light])
    out = []
    for i, v in enumerate(views):
        res = r.render(v.camera, time_s=v.time_s, frame_index=i)
        pts = _world_points(v, res.gbuffers["depth"].numpy())
        out.append((pts, res.hdr.numpy().reshape(-1, 3).sum(1), res.hdr.numpy().reshape(-1, 3)))
    return out


def test_each_headlight_lights_the_road_in_front_of_its_car_in_every_frame(street):
    graph, views = street
    lights = [lt for lt in vehicle_lights(graph) if lt.node == "car0" and "headlight" in lt.name]
    assert len(lights) == 2
    centres = {}
    for lt in lights:
        side = 1.0 if lt.position[1] > 0 else -1.0  # headlight0 left (+y), headlight1 right
        xs = []
        for i, (pts, rad, _rgb) in enumerate(_render_one(graph, views, lt)):
            pose = graph.node_poses(views[i].time_s)["car0"].numpy()
            local = (pts - pose[:3, 3]) @ pose[:3, :3]  # world -> car frame
            lit = (rad > 0.05) & _on_road(graph, views[i].time_s, pts)  # (it lights the parked car too)
            assert lit.sum() >= 20, (lt.name, i)
            on_road_ahead = local[lit, 0] > SIZE[0] / 2
            assert on_road_ahead.mean() >= 0.9, (lt.name, i, on_road_ahead.mean())
            w = rad[lit][on_road_ahead]
            cy = float((local[lit][on_road_ahead, 1] * w).sum() / w.sum())
            centres.setdefault(lt.name, []).append(cy)
            xs.append(float((pts[lit][on_road_ahead, 0] * w).sum() / w.sum()))
            assert side * cy > -0.3, (lt.name, i, cy)  # on its own side of the car's axis (or near it)
        assert all(b > a for a, b in zip(xs, xs[1:])), (lt.name, xs)  # the lit patch follows the car
    left, right = (centres[lt.name] for lt in lights)
    assert all(a > b + 0.3 for a, b in zip(left, right)), (left, right)


def test_tail_lights_are_red_and_behind_the_car(street):
    graph, views = street
    tail = next(lt for lt in vehicle_lights(graph) if lt.node == "car0" and "tail" in lt.name)
    pts, rad, rgb = _render_one(graph, views[:1], tail)[0]
    pose = graph.node_poses(views[0].time_s)["car0"].numpy()
    local = (pts - pose[:3, 3]) @ pose[:3, :3]
    lit = rad > 0.01
    assert lit.sum() >= 10
    w = rad[lit]
    assert float((local[lit, 0] * w).sum() / w.sum()) < -SIZE[0] / 2 + 0.3  # at the rear face and behind it
    assert (local[lit, 0] < 0).mean() >= 0.9  # the car shades everything ahead of its middle
    assert rgb[lit, 0].sum() > 10 * rgb[lit, 1].sum()


def test_vehicle_lights_follow_the_box_and_switch_off_per_object(street):
    graph, _ = street
    all_lights = vehicle_lights(graph)
    assert sorted({lt.node for lt in all_lights}) == ["car0", "car1"] and len(all_lights) == 8
    off = vehicle_lights(graph, off=["car1"])
    assert {lt.node for lt in off} == {"car0"}
    head = [lt for lt in all_lights if "headlight" in lt.name]
    assert all(abs(lt.position[0] - (SIZE[0] / 2 + LAMP_CLEARANCE_M)) < 1e-9 for lt in head)
    with pytest.raises(ConfigError, match="vehicle_lights_off"):
        vehicle_lights(graph, off=["car7"])
    # a node without a tracked size gets its box from its Gaussians
    n = graph.node("car0")
    est = object_box(RigidNode("x", "car", n.gaussians, n.time_indices, n.poses))
    np.testing.assert_allclose(est, SIZE, atol=0.35)


def test_a_street_light_lights_the_road_below_it(street):
    graph, views = street
    spec = lamp_lights(lamps_at([[12.0, 3.0]]))[0]
    assert spec.position == (12.0, 3.0, StreetLightSettings().mount_height_m) and spec.direction == (0.0, 0.0, -1.0)
    from core.render.scenario import to_lights

    (light,) = to_lights([spec], graph)
    pts, rad, _ = _render_one(graph, views[:1], light)[0]
    road = _on_road(graph, views[0].time_s, pts)
    peak = pts[road][np.argmax(rad[road])]
    assert np.hypot(peak[0] - 12.0, peak[1] - 3.0) < 1.5, peak
    lit = road & (rad > 0.5 * rad[road].max())
    c = pts[lit, :2].mean(0)
    assert np.hypot(c[0] - 12.0, c[1] - 3.0) < 1.0, c
    far = road & (np.hypot(pts[:, 0] - 12.0, pts[:, 1] - 3.0) > 10.0)
    assert rad[far].max() < 0.25 * rad[road].max()  # it lights the road below, not the whole street


def test_night_frames_at_the_automatic_exposure_are_neither_black_nor_clipped(street, tmp_path):
    graph, views = street
    lamps = lamp_lights(lamps_at([[6.0, 5.0], [18.0, -5.0]]))
    common = dict(views=tuple(views), envmap=np.full((16, 32, 3), 0.5, np.float32), sky_scale=0.02,
                  street_lights=tuple(lamps), headlights=True, rays_per_pixel=4, denoiser="none", outputs=("png",))
    auto = render_scenario(graph, Scenario(exposure_ev=None, **common), tmp_path / "auto")
    u8 = np.round(auto.result.frames * 255)
    for f in u8:
        assert (f.max(-1) >= 255).mean() < 0.02 and (f.max(-1) <= 0).mean() < 0.20
    assert auto.metrics["exposure"] == "auto" and auto.metrics["exposure_limited_by"] == "highlights"
    assert len(auto.metrics["street_lights"]) == 2 and auto.metrics["lights"] == 2 + 8
    # an explicit EV overrides it (here the old night default, EV 2: the lamps blow the road out)
    fixed = render_scenario(graph, Scenario(exposure_ev=2.0, **common), tmp_path / "fixed")
    assert fixed.metrics["exposure"] == "fixed" and fixed.metrics["exposure_ev"] == 2.0
    assert (np.round(fixed.result.frames * 255).max(-1) >= 255).mean() > 0.02
    # lights off for car0: its headlights and tail lights are gone
    off = render_scenario(graph, Scenario(exposure_ev=None, vehicle_lights_off=("car0",), **common), tmp_path / "o")
    assert off.metrics["lights"] == 2 + 4
    with pytest.raises(ConfigError, match="vehicle_lights_off"):
        render_scenario(graph, Scenario(vehicle_lights_off=("nope",), **common), tmp_path / "x")


def test_lamps_along_the_road_are_spaced_staggered_and_on_both_sides():
    path = np.array([[0.0, -1.75, 1.6], [8.0, -1.75, 1.6]])
    s = StreetLightSettings(spacing_m=20.0, side_offsets_m=(-4.0, 4.0), ahead_m=40.0, behind_m=0.0)
    lamps = lamps_along_path(path, settings=s)
    left = sorted(lp.position[0] for lp in lamps if lp.position[1] > 0)
    right = sorted(lp.position[0] for lp in lamps if lp.position[1] < 0)
    assert {round(lp.position[1], 6) for lp in lamps} == {-5.75, 2.25}  # 4 m either side of the path
    np.testing.assert_allclose(np.diff(right), 20.0)
    np.testing.assert_allclose(np.diff(left), 20.0)
    assert left[0] - right[0] == pytest.approx(10.0)  # staggered by half a spacing
    assert max(left + right) <= 48.0 + 1e-9 and min(left + right) >= 0.0
    assert all(lp.position[2] == pytest.approx(s.mount_height_m) for lp in lamps)  # ground 1.6 m under the camera
    with pytest.raises(ConfigError, match="street_light_positions"):
        lamps_at([[1.0]])
    with pytest.raises(ConfigError, match="spacing_m"):
        StreetLightSettings(spacing_m=0.0)


def _cloud(rng):
    """Ground, a 6 m pole at (5, 6) with an arm toward the road, a wall at y = 9, a tree, a car."""
    pts = [np.c_[rng.uniform(-10, 30, 6000), rng.uniform(-9, 9, 6000), rng.normal(0, 0.01, 6000)]]
    zp = rng.uniform(0.0, 6.0, 120)
    a = rng.uniform(0, 2 * np.pi, 120)
    pts.append(np.c_[5 + 0.08 * np.cos(a), 6 + 0.08 * np.sin(a), zp])
    pts.append(np.c_[np.full(20, 5.0), rng.uniform(4.6, 6.0, 20), np.full(20, 5.9)])  # the arm
    pts.append(np.c_[rng.uniform(-10, 30, 3000), np.full(3000, 9.0), rng.uniform(0, 8, 3000)])  # a wall
    zt = rng.uniform(0.0, 2.6, 60)
    pts.append(np.c_[15 + 0.12 * np.cos(zt * 9), 7 + 0.12 * np.sin(zt * 9), zt])  # a trunk
    d = rng.normal(size=(400, 3))
    pts.append(np.array([15, 7, 3.8]) + 1.4 * d / np.linalg.norm(d, axis=1, keepdims=True))  # its crown
    pts.append(np.c_[rng.uniform(8, 12.4, 500), rng.uniform(-3, -1.2, 500), rng.uniform(0, 1.5, 500)])  # a car
    return np.concatenate(pts)


def test_pole_detection_finds_the_pole_and_nothing_else():
    lamps = detect_poles(_cloud(np.random.default_rng(0)), path_xyz=np.array([[0, -1.75, 1.6], [20, -1.75, 1.6]]))
    assert len(lamps) == 1
    (lp,) = lamps
    assert np.hypot(lp.pole_base[0] - 5, lp.pole_base[1] - 6) < 0.2 and abs(lp.pole_base[2]) < 0.1
    assert lp.position[1] < 5.0 and abs(lp.position[2] - 5.65) < 0.2  # under the arm tip, over the road
    assert detect_poles(np.zeros((5, 3))) == []
    with pytest.raises(Exception, match="points"):
        detect_poles(np.zeros((10, 2)))


def test_pole_detection_on_the_default_scene_lidar_finds_every_pole():
    """The bundled street's 9 lamp posts (the generator's geometry, rebuilt from the bundle's
    recorded config) against the poles detected in its LiDAR."""
    import json
    from pathlib import Path

    from core.bundle import open_bundle
    from core.synth import profile
    from core.synth.generate import ego_positions
    from core.synth.street import make_street

    root = Path(__file__).resolve().parents[3] / "data" / "scenes" / "default"
    b = open_bundle(root, validate=False)
    cfg = json.loads((root / "bundle.json").read_text())["source"]["config"]
    cfg = profile("quick", **{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()})
    poles = [np.asarray(p.vertices) for p in make_street(cfg, ego_positions(cfg)).static_parts
             if p.name.startswith("pole")]
    truth = np.array([[(v[:, 0].min() + v[:, 0].max()) / 2, np.sign(v[:, 1].mean()) * 6.2] for v in poles])
    path = np.array([np.asarray(f.cam_to_world)[:3, 3] for f in b.frames("train")])
    lamps = detect_poles(b.load_lidar(), path_xyz=path)
    found = np.array([lp.pole_base[:2] for lp in lamps])
    d = np.linalg.norm(found[:, None] - truth[None], axis=2)
    assert len(lamps) == len(truth) == 9
    assert d.min(1).max() < 0.3 and d.min(0).max() < 0.3  # one to one within 0.3 m
    # the lamp heads: over the road at the arm's tip (x, +-4.7), hanging under the 6 m top
    tips = truth * np.array([1.0, 4.7 / 6.2])
    heads = np.array([lp.position for lp in lamps])
    assert np.linalg.norm(heads[:, None, :2] - tips[None], axis=2).min(1).max() < 0.3
    assert all(5.0 < lp.position[2] - lp.pole_base[2] < 6.0 for lp in lamps)


def test_without_lidar_the_poles_are_found_in_the_reconstruction_and_spacing_is_the_fallback(small_bundle):
    """``street_lights_for``: a bundle without LiDAR looks for poles in the reconstruction's opaque
    background Gaussians; with no pole there either, the lamps go in rows along the road."""
    from core.bundle import open_bundle
    from core.gaussians import Gaussians
    from core.render.scenario import street_lights_for

    from dataclasses import replace

    b = open_bundle(small_bundle)
    b = type(b)(b.root, replace(b.manifest, lidar=()))  # the same capture without its LiDAR
    road = Part("road", *geo.quad([(-10, -9, 0), (30, -9, 0), (30, 9, 0), (-10, 9, 0)]),
                Material("a", (0.3, 0.3, 0.3), 0.8, 0.0))
    pole = Part("pole", *geo.cylinder((6.0, 6.2, 0.0), 0.08, 6.0, 12), Material("p", (0.5, 0.5, 0.5), 0.4, 1.0))
    eye = np.array([[0.0, 0.0, 1.5]])
    bg = oracle_gaussians([road], eye, 30.0, OracleSettings(spacing_px=1.5, max_spacing=0.4))
    pg = oracle_gaussians([pole], eye, 30.0, OracleSettings(spacing_px=1.5, max_spacing=0.1))
    times = torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64)
    specs, lamps, note = street_lights_for(b, SceneGraph(Gaussians.cat([bg, pg]), [], times))
    assert "the reconstruction's Gaussians" in note and len(lamps) == 1
    assert np.hypot(lamps[0].pole_base[0] - 6.0, lamps[0].pole_base[1] - 6.2) < 0.2
    assert specs[0].direction == (0.0, 0.0, -1.0) and specs[0].intensity == StreetLightSettings().intensity_cd
    specs, lamps, note = street_lights_for(b, SceneGraph(bg, [], times), intensity_cd=500.0)
    assert "0 detected" in note and "along the road" in note and lamps and {lp.source for lp in lamps} == {"spacing"}
    assert all(sp.intensity == 500.0 for sp in specs)
    specs, lamps, note = street_lights_for(b, None, positions=[[1.0, 2.0]])
    assert [lp.position for lp in lamps] == [(1.0, 2.0, StreetLightSettings().mount_height_m)]
    with pytest.raises(ConfigError, match="street_light_placement"):
        street_lights_for(b, None, placement="random")
