"""Objects for simulator edits (core.render.objects, core.relight.apply_edits): listing, box crop,
assets exported from one scene and inserted into another, trajectory edits, removal in every
frame, captured camera paths (core.render.scenario.views_from_capture)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.conventions import look_at
from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.pbr.envmap import EnvironmentMap
from core.synth.oracle import OracleSettings, oracle_gaussians
from core.camera import Camera
from core.pbr.render import ClipRenderer, PBRSettings
from core.relight import ObjectEdit, View, apply_edits
from core.render.objects import crop_to_box, describe_objects, export_asset, load_asset, retime_poses
from core.scene_graph import RigidNode, SceneGraph
from core.synth import geometry as geo
from core.synth.street import Material, Part

SIZE = (4.4, 1.8, 1.5)
XS = (3.0, 5.0, 7.0, 9.0)


def _graph(with_floaters: bool = True, road_y: float = 8.0):
    road = Part("road", *geo.quad([(-5, -road_y, 0), (35, -road_y, 0), (35, road_y, 0), (-5, road_y, 0)]),
                Material("asphalt", (0.3, 0.3, 0.3), 0.8, 0.0))
    body = Part("body", *geo.box((0, 0, 0), SIZE), Material("paint", (0.6, 0.1, 0.1), 0.4, 0.0))
    eye = np.array([-2.0, -2.0, 7.0])
    bg = oracle_gaussians([road], eye[None], 40.0, OracleSettings(spacing_px=1.5, max_spacing=0.25))
    car = oracle_gaussians([body], eye[None], 40.0, OracleSettings(spacing_px=1.5, max_spacing=0.15))
    if with_floaters:  # what optimisation leaves attached to a node: a column of blobs above the car
        fl = oracle_gaussians([Part("f", *geo.box((0.0, 0.0, 3.5), (0.4, 0.4, 2.5)),
                                    Material("f", (0.9, 0.9, 0.9), 0.5, 0.0))], eye[None], 40.0,
                              OracleSettings(spacing_px=1.5, max_spacing=0.2))
        car = Gaussians.cat([car, fl])
    t = len(XS)
    moving = torch.eye(4, dtype=torch.float64).repeat(t, 1, 1)
    moving[:, 0, 3] = torch.tensor(XS)
    moving[:, 1, 3], moving[:, 2, 3] = -2.0, 0.75
    graph = SceneGraph(bg, [RigidNode("car0", "car", car, torch.arange(t), moving, size=SIZE)],
                       torch.arange(t, dtype=torch.float64) * 0.5)
    c2w = look_at(eye, np.array([12.0, -1.0, 0.0]))
    views = [View(Camera.from_intrinsics(c2w, 40.0, 40.0, 40.0, 30.0, 80, 60), float(x), f"f{i}") for i, x in
             enumerate(graph.times.tolist())]
    return graph, views


@pytest.fixture(scope="module")
def street():
    return _graph()


def _gbuf(graph, views):
    r = ClipRenderer(graph, EnvironmentMap.constant(0.5, 16, 32), PBRSettings(rays_per_pixel=1, threads=2))
    return [r.render(v.camera, time_s=v.time_s, frame_index=i).gbuffers for i, v in enumerate(views)]


def test_removing_a_moving_car_removes_it_in_every_frame_and_shows_the_road(street):
    graph, views = street
    before = _gbuf(graph, views)
    gone = apply_edits(graph, [ObjectEdit("remove", "car0")])
    after = _gbuf(gone, views)
    # the road was observed everywhere: no ground fill, not past its ends either
    assert gone.background.num == graph.background.num
    for i, v in enumerate(views):
        assert gone.compose(v.time_s).num == gone.background.num
        albedo_b, albedo_a = before[i]["albedo"].numpy(), after[i]["albedo"].numpy()
        car = albedo_b[..., 0] > albedo_b[..., 1] + 0.2  # red paint in frame i
        assert car.sum() >= 30, i
        # where the car was: the grey road, opaque (background, not sky)
        assert (after[i]["opacity"].numpy()[car, 0] > 0.9).mean() > 0.95, i
        assert np.abs(albedo_a[car, 0] - albedo_a[car, 1]).max() < 0.05, i
        assert float(after[i]["depth"].numpy()[car].min()) > 0.0, i


def test_cropping_to_the_box_drops_the_floaters_of_an_inserted_car(street, tmp_path):
    graph, views = street
    node = graph.node("car0")
    kept = crop_to_box(node.gaussians, SIZE)
    assert kept.num < node.gaussians.num
    assert float(kept.means[:, 2].max()) <= SIZE[2] / 2 + 0.1 + 1e-6
    with pytest.raises(ConfigError, match="size"):
        crop_to_box(node.gaussians, (1.0, -1.0, 1.0))
    # inserted 6 m to the left: with the crop (the default) no column of depth stands above it
    empty = _graph(with_floaters=False)[0]
    base = SceneGraph(empty.background, [], empty.times)
    src = SceneGraph(empty.background, [node], empty.times)
    for crop, column in ((True, False), (False, True)):
        g = apply_edits(src, [ObjectEdit("insert", "car9", "car0", (0.0, 6.0, 0.0), crop=crop),
                              ObjectEdit("remove", "car0")])
        gb = _gbuf(g, views[:1])[0]
        sky_before = _gbuf(base, views[:1])[0]["opacity"].numpy()[..., 0] < 0.1
        opaque_now = gb["opacity"].numpy()[..., 0] > 0.5
        assert bool((sky_before & opaque_now).any()) is column, crop  # floaters against the sky


def test_cropping_leaves_the_road_under_the_object_behind():
    """A node learns the road patch it stands on (flat, facing up, at and just below the box's
    bottom face, its contact shadow in the colour): the crop leaves that behind and keeps the
    body, the wheels' undersides (facing down) and an upward face higher up (the bonnet)."""
    h = SIZE[2]
    rows = [((0.0, 0.0, -h / 2 - 0.04), (0, 0, 1), "road below the face"),
            ((1.0, 0.5, -h / 2 + 0.02), (0, 0, 1), "road at the face"),
            ((-1.5, 0.0, -h / 2 + 0.02), (0, 0, -1), "tyre underside"),
            ((0.0, 0.9, 0.0), (0, 1, 0), "door"),
            ((1.5, 0.0, 0.1), (0, 0, 1), "bonnet")]
    n = len(rows)
    g = Gaussians.from_activated(torch.tensor([r[0] for r in rows], dtype=torch.float64),
                                 torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
                                 torch.full((n, 3), 0.05, dtype=torch.float64), torch.full((n,), 0.9, dtype=torch.float64),
                                 torch.full((n, 3), 0.3, dtype=torch.float64),
                                 torch.tensor([r[1] for r in rows], dtype=torch.float64),
                                 torch.full((n, 3), 0.3, dtype=torch.float64), torch.full((n,), 0.5, dtype=torch.float64),
                                 torch.zeros(n, dtype=torch.float64))
    kept = crop_to_box(g, SIZE)
    kept_z = sorted(round(float(z), 3) for z in kept.means[:, 2])
    assert kept_z == sorted(round(r[0][2], 3) for r in rows[2:])
    assert crop_to_box(g, SIZE, ground_m=0.0).num == n  # 0: the road patch stays (the bottom margin too)
    with pytest.raises(ConfigError, match="ground_m"):
        crop_to_box(g, SIZE, ground_m=-0.1)


def test_an_object_asset_exported_from_one_scene_goes_into_another(street, tmp_path):
    graph, views = street
    path = export_asset(graph, "car0", tmp_path / "car0.pt")
    cls, size, g = load_asset(path)
    assert cls == "car" and size == SIZE and g.num == crop_to_box(graph.node("car0").gaussians, SIZE).num
    other, other_views = _graph(with_floaters=False, road_y=12.0)
    other = SceneGraph(other.background, [], other.times)  # a scene with no car
    ins = apply_edits(other, [ObjectEdit("insert", "carX", asset=str(path), offset_m=(10.0, 3.0, 0.75),
                                         yaw_deg=90.0, solid=False)])
    node = ins.node("carX")
    assert node.size == SIZE and node.cls == "car" and ins.compose(0.0).num == other.background.num + g.num
    pose = ins.node_poses(1.0)["carX"].numpy()
    np.testing.assert_allclose(pose[:3, 3], [10.0, 3.0, 0.75], atol=1e-9)
    np.testing.assert_allclose(pose[:3, 0], [0.0, 1.0, 0.0], atol=1e-9)  # faces +y
    # it renders where it was put (its red paint around the projection of (10, 3))
    gb = _gbuf(ins, other_views[:1])[0]["albedo"].numpy()
    red = gb[..., 0] > gb[..., 1] + 0.2
    assert red.sum() >= 20
    with pytest.raises(ConfigError, match="exactly one of source_object_id or asset"):
        apply_edits(other, [ObjectEdit("insert", "carY")])
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(FormatError, match="asset"):
        apply_edits(other, [ObjectEdit("insert", "carY", asset=str(tmp_path / "bad.pt"))])
    with pytest.raises(ConfigError, match="object_id"):
        export_asset(graph, "nope", tmp_path / "x.pt")


def _in_box_shadow(pts, light, centre, size):
    """Road points whose segment to ``light`` crosses the axis-aligned box (slab test)."""
    d = light[None] - pts
    lo, hi = centre - np.asarray(size) / 2, centre + np.asarray(size) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - pts) / d, (hi - pts) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax >= np.maximum(tmin, 0)) & (tmin <= 1)


def test_a_filled_object_casts_a_solid_shadow_where_its_half_transparent_shell_does_not(street):
    from core.pbr.lights import PointLight
    from core.object_solids import solid_filler

    graph, views = street
    node = graph.node("car0")
    # a reconstructed car's shell: sparse small disks of opacity 0.5 (camera rays composite many of
    # them to a surface; a shadow ray crosses few)
    shell = crop_to_box(node.gaussians, SIZE)
    shell = shell.index(torch.arange(0, shell.num, 3)).clone()
    shell.opacity_logits.data[:] = 0.0
    shell.log_scales.data[:, :2] -= float(np.log(2.0))
    fill = solid_filler(shell, SIZE)
    assert fill.num > 50 and bool((fill.opacities() > 0.98).all())
    inner = np.asarray(SIZE) / 2
    assert bool((fill.means.abs() <= torch.as_tensor(inner, dtype=fill.dtype)).all())  # inside the box
    assert float(fill.means[:, 2].min()) >= -SIZE[2] / 2 + 0.3  # air under the body
    light = np.array([8.0, -6.0, 6.0])
    means = []
    for solid in (False, True):
        g = SceneGraph(graph.background, [RigidNode("car0", "car", shell, node.time_indices, node.poses, size=SIZE)],
                       graph.times)
        g = apply_edits(g, [ObjectEdit("move", "car0", solid=solid)])
        r = ClipRenderer(g, EnvironmentMap.constant(0.0, 16, 32), PBRSettings(rays_per_pixel=1, threads=2),
                         lights=[PointLight(tuple(light), intensity=500.0)])
        v = views[0]
        res = r.render(v.camera, time_s=v.time_s)
        from core.conventions import camera_ray_directions

        cam = v.camera
        c2w = cam.pose_numpy()
        d = camera_ray_directions(c2w, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height).reshape(-1, 3)
        z = res.gbuffers["depth"].numpy().reshape(-1)
        pts = c2w[:3, 3] + d * (z / (d @ c2w[:3, 2]))[:, None]
        centre = g.node_poses(v.time_s)["car0"].numpy()[:3, 3]
        road = (z > 0) & (pts[:, 2] < 0.3) & ~(np.abs(pts - centre) <= np.asarray(SIZE) / 2 + 0.3).all(1)
        # the umbra of the body: the box above the 0.3 m under the car, 0.15 m in from its sides
        body = np.asarray(SIZE) - np.array([0.3, 0.3, 0.45])
        shadow = road & _in_box_shadow(pts, light, centre + np.array([0.0, 0.0, 0.15]), body)
        lit = road & ~shadow & (np.linalg.norm(pts[:, :2] - centre[:2], axis=1) < 6.0)
        rad = res.hdr.numpy().reshape(-1, 3).sum(1)
        assert shadow.sum() >= 20
        means.append(float(rad[shadow].mean() / rad[lit].mean()))
    shell_ratio, solid_ratio = means
    assert solid_ratio < 0.5 * shell_ratio and solid_ratio < 0.15, means


def test_trajectory_edits_speed_lateral_offset_and_explicit_poses(street):
    graph, _ = street
    n = graph.node("car0")
    fast = retime_poses(n.poses, n.time_indices, graph.times, speed=2.0)
    np.testing.assert_allclose(fast[:, 0, 3].numpy(), [3.0, 7.0, 11.0, 15.0])  # extrapolated past the end
    stop = retime_poses(n.poses, n.time_indices, graph.times, speed=0.0)
    np.testing.assert_allclose(stop[:, 0, 3].numpy(), [3.0] * 4)
    lane = apply_edits(graph, [ObjectEdit("move", "car0", lateral_offset_m=3.5)]).node("car0")
    np.testing.assert_allclose(lane.poses[:, 1, 3].numpy(), [1.5] * 4)  # +y is the car's left
    m = np.eye(4)
    m[:3, 3] = [1.0, 2.0, 0.75]
    exp = apply_edits(graph, [ObjectEdit("move", "car0", poses=((1, m), (3, m)))]).node("car0")
    assert exp.time_indices.tolist() == [1, 3] and exp.pose_at(0.0, graph.times) is None  # hidden at t = 0
    with pytest.raises(ConfigError, match=r"edits\[0\].poses\[0\].time_index"):
        apply_edits(graph, [ObjectEdit("move", "car0", poses=((9, m),))])
    with pytest.raises(ConfigError, match=r"edits\[0\].speed"):
        apply_edits(graph, [ObjectEdit("move", "car0", speed=-1.0)])


def test_describe_objects_and_captured_camera_paths():
    from pathlib import Path

    from core.bundle import open_bundle
    from core.render.scenario import views_from_capture

    b = open_bundle(Path(__file__).resolve().parents[3] / "data" / "scenes" / "default", validate=False)
    objs = {o["id"]: o for o in describe_objects(b.manifest, nodes=["car0", "car4"])}
    assert not objs["car0"]["moving"] and objs["car4"]["moving"] and objs["car4"]["path_length_m"] > 5
    assert objs["car0"]["reconstructed"] and not objs["car1"]["reconstructed"]
    assert len(objs["car4"]["poses"]) == len(b.manifest.times) and objs["car4"]["size"] == [4.4, 1.8, 1.5]
    cap = views_from_capture(b)
    assert [v.name for v in cap] == [f"{i:05d}" for i in range(len(b.frames("train")))]
    moved = views_from_capture(b, lateral_shift_m=3.5, height_shift_m=1.0, start_s=0.2, stop_s=0.5, fps=20)
    assert [round(v.time_s, 6) for v in moved] == [0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5]
    orig = {round(v.time_s, 6): v.camera.pose_numpy() for v in cap}
    for v in moved:
        if round(v.time_s, 6) in orig:  # a captured time: the pose shifted 3.5 m left and 1 m up
            d = v.camera.pose_numpy()[:3, 3] - orig[round(v.time_s, 6)][:3, 3]
            np.testing.assert_allclose(d, [0.0, 3.5, 1.0], atol=1e-9)
            np.testing.assert_allclose(v.camera.pose_numpy()[:3, :3], orig[round(v.time_s, 6)][:3, :3], atol=1e-9)
    mid = next(v for v in moved if abs(v.time_s - 0.25) < 1e-9)  # interpolated between 0.2 and 0.3
    np.testing.assert_allclose(mid.camera.pose_numpy()[0, 3], (orig[0.2][0, 3] + orig[0.3][0, 3]) / 2, atol=1e-9)
    for kw, field in (({"start_s": 5.0}, "start_s"), ({"camera": "rear"}, "camera"), ({"split": "x"}, "split"),
                      ({"fps": 0.0}, "fps"), ({"lateral_shift_m": float("nan")}, "lateral_shift_m")):
        with pytest.raises(ConfigError, match=field):
            views_from_capture(b, **kw)


def test_removing_a_car_that_hid_the_road_in_every_frame_fills_the_road_from_around_it(street):
    """A car driving ahead of the camera hides the road under and beyond it in every frame: the
    reconstruction has no Gaussians there. Removed, its pixels show road coloured like the road
    around it (not sky); where the road was observed nothing is added."""
    graph, views = street
    m = graph.background.means
    hidden = ((m[:, 1] + 2.0).abs() < 1.2) & (m[:, 0] > 1.0) & (m[:, 0] < 30.0)
    holed = SceneGraph(graph.background.index(torch.nonzero(~hidden).reshape(-1)), list(graph.nodes), graph.times)
    before = _gbuf(holed, views)
    plain = _gbuf(apply_edits(holed, [ObjectEdit("remove", "car0", fill_ground=False)]), views)
    gone = apply_edits(holed, [ObjectEdit("remove", "car0")])
    after = _gbuf(gone, views)
    fill = gone.background.means[holed.background.num:]
    assert fill.shape[0] > 100
    # the fill lies in the hole, flat on the road
    in_hole = ((fill[:, 1] + 2.0).abs() < 1.3) & (fill[:, 0] > 0.8) & (fill[:, 0] < 30.2)
    assert bool(in_hole.all()) and float(fill[:, 2].abs().max()) < 1e-6
    for i in range(len(views)):
        albedo_b = before[i]["albedo"].numpy()
        car = albedo_b[..., 0] > albedo_b[..., 1] + 0.2
        assert car.sum() >= 30, i
        assert (plain[i]["opacity"].numpy()[car, 0] > 0.5).mean() < 0.9, i  # without the fill: sky
        assert (after[i]["opacity"].numpy()[car, 0] > 0.5).mean() > 0.95, i
        albedo_a = after[i]["albedo"].numpy()[car]
        assert np.abs(albedo_a[:, 0] - albedo_a[:, 1]).max() < 0.05, i  # grey road, not red paint


def _tinted(g, where, rgb):
    act = g.activated()
    c = torch.tensor(rgb, dtype=g.means.dtype)
    colors, albedo = act["colors"].clone(), act["albedo"].clone()
    colors[where], albedo[where] = c, c
    return Gaussians.from_activated(g.means, act["quats"], act["scales"], act["opacities"], colors, act["normals"],
                                    albedo, act["roughness"], act["metallic"])


def _holed(graph):
    m = graph.background.means
    hidden = ((m[:, 1] + 2.0).abs() < 1.2) & (m[:, 0] > 1.0) & (m[:, 0] < 30.0)
    return graph.background.index(torch.nonzero(~hidden).reshape(-1))


def test_the_ground_fill_takes_the_road_colour_not_the_objects_bleed(street, monkeypatch):
    """The road just beside a car in every frame carries the car's colour (its silhouette blurred
    into the road): the fill of the road it hid takes its colour from road farther from the car's
    footprint (``bleed_m``) and of a colour typical of the ground (GROUND_FILL_OUTLIER_MAD); either
    alone keeps a blue strip out of it, neither lets it in."""
    import core.render.removal as removal
    from core.render.objects import object_box

    graph, _ = street
    bg = _holed(graph)
    mm = bg.means
    strip = ((mm[:, 1] + 2.0).abs() < 1.8) & (mm[:, 0] > 0.4) & (mm[:, 0] < 11.8)  # within 0.6 m of the hole
    assert int(strip.sum()) > 50
    tinted = _tinted(bg, strip, (0.2, 0.25, 0.7))
    node = graph.node("car0")

    def blue_excess(bleed):
        fill = removal.ground_fill(tinted, node.poses, object_box(node), bleed_m=bleed)
        assert fill.num > 100
        a = fill.albedo()
        return float((a[:, 2] - 0.5 * (a[:, 0] + a[:, 1])).abs().max())

    assert blue_excess(removal.GROUND_FILL_BLEED_M) < 0.05
    assert blue_excess(0.0) < 0.05  # the colour test alone
    monkeypatch.setattr(removal, "GROUND_FILL_OUTLIER_MAD", 1e9)  # no colour test
    assert blue_excess(removal.GROUND_FILL_BLEED_M) < 0.05  # the distance alone
    assert blue_excess(0.0) > 0.2  # neither: blue by the strip
    with pytest.raises(ConfigError, match="bleed_m"):
        removal.ground_fill(tinted, node.poses, object_box(node), bleed_m=-1.0)


def test_a_removal_takes_the_objects_remnants_in_the_background_and_leaves_the_road(street):
    """Blobs of the red car's paint that the background holds on the road along its path go with
    it; a yellow line in its lane, grey road and red paint off its path stay; a grey car has no
    remnants a colour could tell."""
    from core.render.objects import object_box
    from core.render.removal import clear_removed, object_remnants

    graph, _ = street
    bg = graph.background
    mm = bg.means
    lane = (mm[:, 1] + 2.0).abs() < 0.9
    red = lane & (mm[:, 0] > 14.0) & (mm[:, 0] < 15.0)  # 2.8 m ahead of its last pose, in its lane
    yellow = (mm[:, 1] + 2.0).abs() < 0.1
    yellow &= (mm[:, 0] > 0.0) & (mm[:, 0] < 12.0) & ~red
    off_path = ((mm[:, 1] - 6.0).abs() < 0.5) & (mm[:, 0] > 14.0) & (mm[:, 0] < 15.0)  # 8 m to the side
    assert int(red.sum()) > 10 and int(yellow.sum()) > 10 and int(off_path.sum()) > 5
    g = _tinted(_tinted(_tinted(bg, red, (0.55, 0.1, 0.1)), yellow, (0.8, 0.7, 0.1)), off_path, (0.55, 0.1, 0.1))
    node = graph.node("car0")
    rem = object_remnants(g, node.gaussians, node.poses, object_box(node))
    assert bool(rem[red].all()) and not bool(rem[~red].any())
    scene = SceneGraph(g, list(graph.nodes), graph.times)
    cleared, dropped, _filled = clear_removed(g, node)
    assert dropped == int(red.sum())
    gone = apply_edits(scene, [ObjectEdit("remove", "car0")])
    assert gone.background.num == cleared.num
    alb = gone.background.albedo()
    assert int(((alb[:, 0] > 0.5) & (alb[:, 1] < 0.2)).sum()) == int(off_path.sum())  # the red off its path stays
    assert int(((alb[:, 0] > 0.7) & (alb[:, 2] < 0.2)).sum()) == int(yellow.sum())  # the yellow line stays
    # a grey car: nothing told by colour
    act = node.gaussians.activated()
    grey = Gaussians.from_activated(act["means"], act["quats"], act["scales"], act["opacities"],
                                    torch.full_like(act["colors"], 0.3), act["normals"], torch.full_like(act["albedo"], 0.3),
                                    act["roughness"], act["metallic"])
    assert not bool(object_remnants(g, grey, node.poses, object_box(node)).any())
    with pytest.raises(ConfigError, match="size"):
        object_remnants(g, node.gaussians, node.poses, (1.0, 0.0, 1.0))


def test_object_t_min_changes_the_edited_objects_only_and_a_scene_without_edits_not_at_all(street):
    """``TraceSettings.t_min_objects`` (``Scenario.object_shadow_t_min_m``): without edits every
    frame renders to the bit as without it (a static node in the static BVH, the moving car's
    BVH, the visibility cache, the BVH rebuilt every frame); once an edit moves a node, that node
    alone goes to a third BVH traced from ``t_min_objects``: the road under a plate 0.3 m above
    it darkens (the contact shadow a 0.5 m ``t_min`` cuts off), the road away from it does not."""
    from core.pbr.lights import PointLight
    from core.pbr.visibility import TraceSettings

    graph, views = street
    eye = np.array([-2.0, -2.0, 7.0])
    plate_size = (2.0, 2.0, 0.04)
    plate = oracle_gaussians([Part("plate", *geo.box((0, 0, 0), plate_size), Material("p", (0.5, 0.5, 0.5), 0.6, 0.0))],
                             eye[None], 40.0, OracleSettings(spacing_px=1.5, max_spacing=0.1))
    pose = torch.eye(4, dtype=torch.float64)[None].clone()
    centre = np.array([6.0, 2.0, 0.3])
    pose[0, :3, 3] = torch.from_numpy(centre)
    g = SceneGraph(graph.background, [graph.node("car0"), RigidNode("plate", "sign", plate, torch.tensor([0]), pose,
                                                                    size=plate_size)], graph.times)
    env = EnvironmentMap.constant(0.3, 16, 32)
    lights = [PointLight((6.0, 2.0, 6.0), intensity=500.0)]

    # a low camera that sees the road under the plate
    low = View(Camera.from_intrinsics(look_at(np.array([2.0, 2.0, 1.2]), np.array([6.0, 2.0, 0.0])), 40.0, 40.0, 40.0,
                                      30.0, 80, 60), 0.0, "low")

    def render(gr, t_obj, static_reuse=True, reuse=False, vs=(*views[:2], low)):
        # one thread: the visibility cache's fill order (so a frame's cache hits) follows the threads
        s = PBRSettings(rays_per_pixel=8, threads=1, normal_offset=0.1, reuse_visibility=reuse,
                        trace=TraceSettings(leaf_size=16, t_min=0.5, t_min_objects=t_obj))
        r = ClipRenderer(gr, env, s, lights=lights, static_reuse=static_reuse)
        return r, [r.render(v.camera, time_s=v.time_s, frame_index=i).hdr for i, v in enumerate(vs)]

    for static_reuse, reuse in ((True, False), (True, True), (False, False)):
        _, base = render(g, None, static_reuse, reuse)
        for t_obj in (0.0, 0.05, 2.0):
            r, got = render(g, t_obj, static_reuse, reuse)
            assert r.objects == frozenset()
            assert all(torch.equal(a, b) for a, b in zip(base, got)), (static_reuse, reuse, t_obj)

    moved = apply_edits(g, [ObjectEdit("move", "plate")])  # edited where it stood
    assert moved.edited_nodes() == {"plate"} and not moved.node("car0").edited
    _, off = render(moved, None)
    _, same = render(moved, 0.5)  # t_min_objects == t_min: the BVHs of before
    assert all(torch.equal(a, b) for a, b in zip(off, same))
    _, off = render(moved, None, vs=(low,))  # (the same frame index, so the same samples)
    for static_reuse in (True, False):
        r, near = render(moved, 0.05, static_reuse, vs=(low,))
        assert r.objects == {"plate"}
        if static_reuse:  # the static BVH holds the background, not the plate
            assert r.context.static_tracer.num_gaussians == graph.background.num
        # the pixels that darken see the road within 1 m of the plate (or the plate): the
        # pixels where the road is 3 m or more from it keep their mean within 2%
        cam = low.camera
        c2w = cam.pose_numpy()
        d = cam.ray_directions().reshape(-1, 3)
        with np.errstate(divide="ignore"):
            t = -c2w[2, 3] / d[:, 2]  # where each pixel's ray meets the road plane
        pts = c2w[:3, 3] + d * t[:, None]
        out = np.where(t > 0, (np.abs(pts - centre)[:, :2] - np.asarray(plate_size[:2]) / 2).max(1), np.inf)
        lum_off, lum_near = (x[-1].numpy().reshape(-1, 3).sum(1) for x in (off, near))
        darker = lum_near < 0.8 * lum_off
        assert darker.sum() >= 10 and bool((out[darker] < 1.0).all())
        far = (out > 3.0) & np.isfinite(out)
        assert far.sum() >= 100
        assert abs(lum_near[far].mean() / lum_off[far].mean() - 1.0) < 0.02


def test_points_on_an_edited_object_are_inside_its_box_above_its_floor():
    from core.pbr.render import OBJECT_FLOOR_M, OBJECT_MARGIN_M, on_objects

    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # turned 90 deg
    pose[:3, 3] = [10.0, 2.0, 0.75]
    pts = torch.tensor([[10.0, 2.0, 1.4],  # on the roof
                        [10.0, 2.0 + 2.2 + OBJECT_MARGIN_M / 2, 0.75],  # just past the front (x: 4.4 long)
                        [10.0, 2.0 + 2.2 + 2 * OBJECT_MARGIN_M, 0.75],  # in front of it
                        [10.0 + 0.9 + OBJECT_MARGIN_M / 2, 2.0, 0.5],  # its side (y: 1.8 wide)
                        [10.0, 2.0, OBJECT_FLOOR_M / 2],  # the road under it
                        [10.0, 2.0, 0.0]], dtype=torch.float64)
    assert on_objects(pts, [(pose, SIZE)]).tolist() == [True, True, False, True, False, False]
    assert not on_objects(pts, []).any()
