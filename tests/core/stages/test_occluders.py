"""core.stages.occluders: facades completed above the captured view for shadow rays only."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.camera import Camera
from core.conventions import look_at
from core.errors import ConfigError
from core.gaussians import Gaussians
from core.pbr.envmap import EnvironmentMap
from core.pbr.render import ClipRenderer, PBRSettings
from core.scene_graph import SceneGraph
from core.stages.occluders import OccluderSettings, complete_occluders, facade_columns


def _flat(means: np.ndarray, normal, half: float = 0.3, opacity: float = 0.95) -> Gaussians:
    """Flat disks at ``means`` [N, 3] facing ``normal``, half-width ``half`` metres."""
    n = len(means)
    nz = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    helper = np.array([0.0, 0.0, 1.0]) if abs(nz[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, nz)
    x /= np.linalg.norm(x)
    y = np.cross(nz, x)
    from core.rotations import rotmat_to_quat

    q = rotmat_to_quat(torch.from_numpy(np.stack([x, y, nz], -1)))[None].expand(n, 4)
    one = torch.ones(n, 1, dtype=torch.float64)
    return Gaussians.from_activated(torch.from_numpy(means.astype(np.float64)), q.clone(),
                                    torch.tensor([[half, half, 0.01]], dtype=torch.float64).expand(n, 3).clone(),
                                    one * opacity, one.expand(n, 3) * 0.5, torch.from_numpy(np.tile(nz, (n, 1))),
                                    one.expand(n, 3) * 0.5, one * 0.8, one * 0.0)


def _wall(x0=0.0, x1=10.0, y=5.0, z1=4.0, step=0.25) -> Gaussians:
    """A wall at ``y`` facing -y (towards the street at y = 0), from z = 0 to ``z1``."""
    xs, zs = np.arange(x0 + step / 2, x1, step), np.arange(step / 2, z1, step)
    X, Z = np.meshgrid(xs, zs, indexing="ij")
    pts = np.stack([X.ravel(), np.full(X.size, y), Z.ravel()], -1)
    return _flat(pts, (0.0, -1.0, 0.0), half=step)


def _view(eye, target, w=32, h=24, fov_deg=60.0, sky=False, depth=0.0):
    c2w = look_at(np.asarray(eye, float), np.asarray(target, float))
    f = w / 2 / math.tan(math.radians(fov_deg) / 2)
    return (Camera.from_intrinsics(c2w, f, f, w / 2, h / 2, w, h), np.full((h, w), sky), np.full((h, w), depth))


#: the upward completion alone: one layer of disks, the observed wall not backed
UPWARD_ONLY = {"layers": 1, "fill_observed": False}


def test_an_unseen_wall_top_is_extended_to_the_cap_with_wall_disks():
    s = OccluderSettings(max_height_m=12.0, **UPWARD_ONLY)
    occ = complete_occluders(_wall(), [], s)  # no frame saw anything above the wall (no path: no continuation)
    centres, tops, _bottoms, normals = facade_columns(_wall(), s)
    assert len(centres) == 20 and np.allclose(normals, [0.0, -1.0, 0.0], atol=1e-6)
    z = occ.means[:, 2].numpy()
    assert occ.num > 0 and z.min() > tops.min() - 1e-9 and z.max() <= 12.0 + 1e-9
    # every column runs from its top to the cap in step_m steps
    assert occ.num == sum(int(np.floor((12.0 - t) / s.step_m)) for t in tops)
    assert np.allclose(occ.unit_normals().numpy(), [0.0, -1.0, 0.0], atol=1e-5)
    # on the wall's grid cells, inset_m behind the surface (inside the building)
    assert np.allclose(occ.means[:, 1].numpy(), 5.25 + s.inset_m, atol=0.26)
    assert torch.isfinite(occ.means).all() and (occ.opacities() > 0.9).all()


def test_sky_seen_above_the_wall_stops_the_columns_at_the_roof_line():
    wall = _wall(z1=4.0)
    # a camera far down the street looking at the wall's upper part: sky everywhere it looks
    sky_view = _view((-30.0, 0.0, 6.0), (5.0, 5.0, 8.0), sky=True)
    occ = complete_occluders(wall, [sky_view], OccluderSettings(max_height_m=12.0))
    free_all = complete_occluders(wall, [], OccluderSettings(max_height_m=12.0))
    assert occ.num < free_all.num
    # columns are contiguous from the wall top: no Gaussian above a carved step of its column
    m = occ.means.numpy()
    for key in {tuple(np.round(p[:2], 3)) for p in m}:
        z = np.sort(m[np.all(np.isclose(m[:, :2], key), 1), 2])
        assert np.allclose(np.diff(z), 0.5, atol=1e-6) if len(z) > 1 else True
    # a view that saw a surface far behind those points carves them too (seen through)
    behind = _view((-30.0, 0.0, 6.0), (5.0, 5.0, 8.0), depth=500.0)
    assert complete_occluders(wall, [behind], OccluderSettings(max_height_m=12.0)).num == occ.num


def _plane_view(eye, target, wall_y: float, w=320, h=240, fov_deg=60.0):
    """A frame whose rendered depth is the plane y = ``wall_y`` (optical-axis metres; 0 where a
    ray never meets it) and no sky: a facade seen down the street."""
    cam, sky, _ = _view(eye, target, w, h, fov_deg)
    d = cam.ray_directions().reshape(h, w, 3)
    fwd = cam.pose_numpy()[:3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wall_y - np.asarray(eye, float)[1]) / d[..., 1]
    depth = np.where(np.isfinite(t) & (t > 0), t * (d @ fwd), 0.0)
    return cam, sky, depth


def test_a_facade_seen_down_the_street_keeps_its_columns_grown_behind_the_surface():
    # the wall's surface at y = 4.9 lies in the grid cells [4.5, 5.0): their centres are 0.15 m in
    # front of it, in the street's free space
    wall = _wall(y=4.9, z1=4.0)
    graze = _plane_view((-25.0, 0.0, 1.5), (10.0, 4.9, 7.0), 4.9)
    cap = OccluderSettings(max_height_m=10.0, **UPWARD_ONLY)
    free = complete_occluders(wall, [], cap).num
    kept = complete_occluders(wall, [graze], cap)
    at_centres = complete_occluders(wall, [graze], OccluderSettings(max_height_m=10.0, grow_behind=False,
                                                                      **UPWARD_ONLY))
    # seen at a grazing angle, a point 0.15 m in front of the facade is > depth_margin_m in front
    # of its rendered depth: a frame "saw through" it and the columns stopped
    assert at_centres.num < 0.5 * free
    # behind the surface, nothing the frame saw is in front of them: every column grows to the cap
    assert kept.num == free
    assert (kept.means[:, 1].numpy() > 4.9).all()


def test_nothing_for_ground_kerbs_or_an_empty_scene():
    ground = _flat(np.array([[x, y, 0.0] for x in range(10) for y in range(5)], float), (0.0, 0.0, 1.0))
    assert complete_occluders(ground, []).num == 0
    low = _wall(z1=1.0)  # below min_wall_height_m: a kerb or a car, not a facade
    assert complete_occluders(low, []).num == 0
    assert complete_occluders(Gaussians.empty(torch.float64), []).num == 0
    assert complete_occluders(_wall(), [], OccluderSettings(enabled=False)).num == 0


@pytest.mark.parametrize("field,value", [("cell_m", 0.0), ("step_m", float("nan")), ("opacity", 1.0),
                                         ("min_count", 0), ("max_height_m", -1.0), ("layers", 0), ("layers", 2.0),
                                         ("inset_m", 0.0), ("layer_spacing_m", -0.1), ("fill_observed", 1), ("grow_behind", "yes"),
                                         ("wall_tolerance_m", 0.0), ("unseen_roof_radius_m", -1.0), ("wall_line_sky_only", 1),
                                         ("extend_m", float("inf"))])
def test_settings_are_validated_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        OccluderSettings(**{field: value})


def test_scene_graph_keeps_occluders_for_shadows_only(tmp_path):
    ground = _flat(np.array([[x, y, 0.0] for x in np.arange(0, 8, 0.4) for y in np.arange(-3, 3, 0.4)]),
                   (0.0, 0.0, 1.0), half=0.4)
    roof = _flat(np.array([[x, y, 3.0] for x in np.arange(0, 8, 0.4) for y in np.arange(-3, 3, 0.4)]),
                 (0.0, 0.0, -1.0), half=0.4)
    graph = SceneGraph(ground, [], torch.tensor([0.0]))
    graph.occluders = roof
    assert graph.compose(0.0).num == ground.num and graph.shadow_static().num == ground.num + roof.num
    graph.save(tmp_path / "g.pt")
    back = SceneGraph.load(tmp_path / "g.pt")
    assert back.occluders is not None and torch.equal(back.occluders.means, roof.means)
    # the PBR pass: the roof shadows the ground under a uniform sky; it is never drawn
    cam = Camera.from_intrinsics(look_at(np.array([-1.0, 0.0, 1.5]), np.array([4.0, 0.0, 0.0])), 20.0, 20.0, 16.0, 12.0,
                                 32, 24)
    env = EnvironmentMap.constant(1.0, 16, 32)
    s = PBRSettings(rays_per_pixel=16, threads=1)
    with_roof = ClipRenderer(back, env, s).render(cam)
    no_roof = SceneGraph(ground, [], torch.tensor([0.0]))
    without = ClipRenderer(no_roof, env, s).render(cam)
    o = with_roof.gbuffers["opacity"][..., 0] > 0.5
    assert torch.equal(with_roof.gbuffers["opacity"], without.gbuffers["opacity"])  # not rasterized
    assert float(with_roof.hdr[o].mean()) < 0.5 * float(without.hdr[o].mean())
    # edits keep the static scene's occluders
    from core.relight import apply_edits

    assert apply_edits(back, []).occluders is back.occluders


def test_walls_continue_along_the_path_beyond_what_was_seen():
    wall = _wall(x0=0.0, x1=10.0, z1=4.0)
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 5.0)]  # nothing seen through
    s = OccluderSettings(max_height_m=8.0, extend_m=3.0, **UPWARD_ONLY)
    occ = complete_occluders(wall, path, s).means.numpy()
    behind, ahead = occ[occ[:, 0] < 0.0], occ[occ[:, 0] > 10.0]
    assert len(behind) and len(ahead)
    assert behind[:, 0].min() >= -3.0 - 0.5 and ahead[:, 0].max() <= 13.0 + 0.5
    assert behind[:, 2].min() < 0.5 and behind[:, 2].max() > 7.0  # full height, from the wall's foot
    assert np.allclose(occ[:, 1], occ[0, 1])  # on the wall's own line
    assert (complete_occluders(wall, path, OccluderSettings(max_height_m=8.0, extend_m=0.0)).means[:, 0] > 0).all()
    # a frame that saw sky where the continuation would stand carves it
    seen = _view((-20.0, 5.0, 4.0), (-1.0, 5.0, 4.0), fov_deg=90.0, sky=True)
    carved = complete_occluders(wall, [path[0], seen, path[1]], s).means.numpy()
    assert (carved[:, 0] < 0.0).sum() < len(behind)


def test_continued_walls_are_as_tall_as_the_roof_line_their_side_showed():
    wall = _wall(x0=0.0, x1=10.0, z1=4.0)
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 5.0)]
    # a frame from across the street saw sky above z ~ 4.4 over the seen wall
    roofline = _view((5.0, -30.0, 9.0), (5.0, 5.0, 9.0), fov_deg=20.0, sky=True)
    # (the path direction runs from the first to the last frame: the odd one goes between)
    occ = complete_occluders(wall, [path[0], roofline, path[1]], OccluderSettings(max_height_m=12.0, extend_m=4.0))
    m = occ.means.numpy()
    far_behind = m[m[:, 0] < -1.6]  # outside that frame: only the cap stops these
    assert len(far_behind) and far_behind[:, 2].max() < 5.0
    assert m[(m[:, 0] > 0) & (m[:, 0] < 10), 2].max() < 5.0  # the seen wall stops at the roof line too


def test_the_observed_wall_is_backed_behind_its_surface_up_to_its_top():
    wall = _wall(z1=4.0)  # at y = 5, facing -y (the street)
    s = OccluderSettings(max_height_m=4.0, layers=1)  # nothing to complete above: the backing alone
    occ = complete_occluders(wall, [], s).means.numpy()
    up = complete_occluders(wall, [], OccluderSettings(max_height_m=4.0, **UPWARD_ONLY)).means.numpy()
    back = occ[len(up):] if len(up) else occ
    assert len(back) > 0
    _c, tops, bottoms, _n = facade_columns(wall, s)
    assert back[:, 2].min() >= bottoms.min() - 1e-9 and back[:, 2].max() <= tops.max() + 1e-9
    assert (back[:, 1] > 5.25 + 0.2).all()  # behind the cell centres, away from the street
    # a frame that saw far behind the wall (depth 500 m through it) carves the backing too
    through = _view((5.0, -10.0, 2.0), (5.0, 5.0, 2.0), fov_deg=90.0, depth=500.0)
    assert complete_occluders(wall, [through], s).num < len(occ)


def test_three_layers_stop_a_steep_shadow_ray_that_passes_one():
    from core.pbr.visibility import GaussianTracer, TraceSettings

    wall = _wall(z1=2.0)
    one = complete_occluders(wall, [], OccluderSettings(max_height_m=10.0, **UPWARD_ONLY))
    three = complete_occluders(wall, [], OccluderSettings(max_height_m=10.0, layers=3, fill_observed=False))
    assert three.num == 3 * one.num
    # rays from the street (y = 0) crossing the completed part of the wall face-on at heights
    # between and on the disks' centres
    zs = np.linspace(4.0, 8.0, 41)
    org = torch.from_numpy(np.stack([np.full_like(zs, 5.0), np.zeros_like(zs), zs], -1))
    dirs = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64).expand(len(zs), 3)
    v1 = GaussianTracer.from_gaussians(one, TraceSettings(t_min=0.01))(org, dirs)
    v3 = GaussianTracer.from_gaussians(three, TraceSettings(t_min=0.01))(org, dirs)
    assert float(v1.max()) > 0.03  # one layer leaks between its disks
    assert float(v3.max()) < 0.01


def test_a_tree_in_front_of_the_wall_is_not_continued_as_the_wall():
    # the wall from x = 2 to 10 at y = 5; a "tree" (a column of facade-like disks at y = 3, x = 0.5)
    # stands before its start: the continuation behind must follow the wall's line, not the tree's
    wall = _wall(x0=2.0, x1=10.0, z1=4.0)
    tree = _flat(np.array([[0.5, 3.0, z] for z in np.arange(2.0, 4.0, 0.25)]), (0.0, -1.0, 0.0), half=0.25)
    from core.gaussians import Gaussians as G

    scene = G.cat([wall, tree])
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 5.0)]
    s = OccluderSettings(max_height_m=8.0, extend_m=3.0, **UPWARD_ONLY)
    occ = complete_occluders(scene, path, s).means.numpy()
    behind = occ[occ[:, 0] < 0.0]
    assert len(behind) and np.allclose(behind[:, 1], 5.25 + s.inset_m, atol=0.26)  # on the wall's line, behind it
    loose = complete_occluders(scene, path, OccluderSettings(max_height_m=8.0, extend_m=3.0, wall_tolerance_m=100.0,
                                                             **UPWARD_ONLY)).means.numpy()
    assert (np.abs(loose[loose[:, 0] < 0.0, 1] - 3.25 - s.inset_m) < 0.26).any()  # without the line test the tree is continued


def test_a_side_of_two_far_apart_columns_still_continues():
    # two columns on one side, 3 m apart across the street: the median of their offsets lies
    # between them, more than wall_tolerance_m from each; the nearest stand for the wall line
    a = _flat(np.array([[4.0, 3.0, z] for z in np.arange(0.25, 3.0, 0.25)]), (0.0, -1.0, 0.0), half=0.25)
    b = _flat(np.array([[6.0, 6.0, z] for z in np.arange(0.25, 3.0, 0.25)]), (0.0, -1.0, 0.0), half=0.25)
    from core.gaussians import Gaussians as G

    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 5.0)]
    occ = complete_occluders(G.cat([a, b]), path, OccluderSettings(max_height_m=6.0, extend_m=2.0, **UPWARD_ONLY))
    m = occ.means.numpy()
    assert occ.num > 0 and np.isfinite(m).all() and (m[:, 0] < 4.0).any() and (m[:, 0] > 6.0).any()


def _column_tops(occ: Gaussians, x1: float = 30.0) -> np.ndarray:
    """[x1 / 0.5] highest completed Gaussian per 0.5 m cell along x (the wall runs along x; 0 where
    the column has none)."""
    m = occ.means.numpy()
    out = np.zeros(int(x1 / 0.5))
    np.maximum.at(out, np.clip(np.floor(m[:, 0] / 0.5).astype(int), 0, len(out) - 1), m[:, 2])
    return out


def test_an_unseen_column_is_capped_at_the_sky_seen_roof_line_of_its_neighbours():
    wall = _wall(x0=0.0, x1=30.0, z1=4.0)
    x = np.arange(0.0, 30.0, 0.5)
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 1.0)]  # never sees through anything
    # a frame from across the street saw sky above the far part of the wall (x ~ 19-31) only
    far_sky = _view((25.0, -30.0, 9.0), (25.0, 5.0, 9.0), fov_deg=20.0, sky=True)
    s = OccluderSettings(max_height_m=12.0, extend_m=0.0, **UPWARD_ONLY)
    tops = _column_tops(complete_occluders(wall, [path[0], far_sky, path[1]], s))
    assert tops[x >= 20.0].max() < 5.0  # the seen roof line
    assert tops[(x >= 6.0) & (x <= 15.0)].max() < 5.0  # unseen, capped by its neighbours
    assert tops[x < 3.0].min() > 11.0  # unseen, no sky-seen column within 15 m
    off = _column_tops(complete_occluders(wall, [path[0], far_sky, path[1]],
                                          OccluderSettings(max_height_m=12.0, extend_m=0.0, unseen_roof_radius_m=0.0,
                                                           **UPWARD_ONLY)))
    assert off[x < 15.0].min() > 11.0
    # a column the depth test stopped (a window read as free space) is not a roof line
    through = (far_sky[0], np.zeros_like(far_sky[1]), np.full_like(far_sky[2], 500.0))
    carved = _column_tops(complete_occluders(wall, [path[0], through, path[1]], s))
    assert carved[x >= 20.0].max() < 5.0
    assert carved[(x >= 6.0) & (x <= 15.0)].min() > 11.0


def test_continued_walls_can_take_the_sky_seen_roof_line_only():
    wall = _wall(x0=0.0, x1=10.0, z1=4.0)
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 5.0)]
    # one frame saw through the wall's upper part at a depth far behind it (a window's reflection
    # read as free space): the columns stop there, but that is no roof line
    through = _view((5.0, -30.0, 9.0), (5.0, 5.0, 9.0), fov_deg=20.0, depth=500.0)
    views = [path[0], through, path[1]]
    s_all = OccluderSettings(max_height_m=12.0, extend_m=4.0, **UPWARD_ONLY)
    s_sky = OccluderSettings(max_height_m=12.0, extend_m=4.0, continued_sky_roof=True, **UPWARD_ONLY)
    low = complete_occluders(wall, views, s_all).means.numpy()
    high = complete_occluders(wall, views, s_sky).means.numpy()
    # every stopped column counts: the continued wall is as low as the depth-stopped roof line;
    # sky only: no side showed a sky roof line, so the continuation goes to max_height_m
    assert low[low[:, 0] < -1.6, 2].max() < 5.0
    assert high[high[:, 0] < -1.6, 2].max() > 11.0


def test_wall_line_columns_can_be_carved_by_sky_pixels_only():
    # a facade at y = 5 and a tree-like patch 2.5 m in front of it; the frames' rendered depth lies
    # far behind both everywhere (a window's reflection read as free space), and no pixel is sky
    wall = _wall(x0=0.0, x1=20.0, y=5.0, z1=4.0)
    tree = _flat(np.array([[10.0 + dx, 2.5, z] for dx in (0.1, 0.3) for z in np.arange(0.2, 3.0, 0.2)]),
                 (0.0, -1.0, 0.0), half=0.2)
    scene = Gaussians.cat([wall, tree])
    views = [_view((x, 0.0, 1.5), (x + 10.0, 3.0, 4.0), w=64, h=48, depth=500.0) for x in (-20.0, -15.0, -10.0)]
    base = dict(max_height_m=12.0, extend_m=0.0, unseen_roof_radius_m=0.0, **UPWARD_ONLY)
    free = complete_occluders(scene, [], OccluderSettings(**base))
    depth_test = complete_occluders(scene, views, OccluderSettings(**base))
    sky_only = complete_occluders(scene, views, OccluderSettings(wall_line_sky_only=True, **base))
    on_tree = lambda g: int((g.means[:, 1].numpy() < 4.0).sum())  # noqa: E731
    assert on_tree(free) > 0
    # the depth test stops the columns it sees through, the wall's and the tree's
    assert depth_test.num < free.num and on_tree(depth_test) < on_tree(free)
    # on the wall line only the sky carves (none here): the wall grows as if unseen, and the tree,
    # off the line, keeps the depth test
    assert sky_only.num - on_tree(sky_only) == free.num - on_tree(free)
    assert on_tree(sky_only) == on_tree(depth_test)


def test_tall_unseen_lifts_the_guessed_heights_on_its_side_only():
    # the wall at y = 5 stands left of the path (which runs along +x)
    wall = _wall(x0=0.0, x1=30.0, z1=4.0)
    x = np.arange(0.0, 30.0, 0.5)
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 1.0)]
    far_sky = _view((25.0, -30.0, 9.0), (25.0, 5.0, 9.0), fov_deg=20.0, sky=True)
    views = [path[0], far_sky, path[1]]

    def tops(side: str, extend: float = 0.0) -> np.ndarray:
        s = OccluderSettings(max_height_m=12.0, extend_m=extend, tall_unseen=side, **UPWARD_ONLY)
        return _column_tops(complete_occluders(wall, views, s))

    for side in ("none", "right"):  # guessed: capped at the neighbours' sky-seen roof line
        assert tops(side)[(x >= 6.0) & (x <= 15.0)].max() < 5.0, side
    for side in ("left", "both"):  # the unseen columns stand max_height_m tall
        t = tops(side)
        assert t[(x >= 6.0) & (x <= 15.0)].min() > 11.0, side
        assert t[x >= 20.0].max() < 5.0, side  # a roof line the capture saw stays where it was seen
    # the continued walls beyond the path's ends: the side's roof line, or full height
    for side, lo, hi in (("none", 0.0, 5.0), ("left", 11.0, 12.5)):
        s = OccluderSettings(max_height_m=12.0, extend_m=4.0, tall_unseen=side, **UPWARD_ONLY)
        m = complete_occluders(wall, views, s).means.numpy()
        behind = m[m[:, 0] < -1.6, 2]
        assert len(behind) and lo < behind.max() < hi, (side, behind.max())
    with pytest.raises(ConfigError, match="tall_unseen"):
        OccluderSettings(tall_unseen="up")
