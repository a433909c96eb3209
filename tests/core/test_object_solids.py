"""core.object_solids and SceneGraph.node_solid: tracked objects' insides filled, for shadow rays only
where the object was not edited."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.gaussians import Gaussians
from core.object_solids import solid_filler
from core.pbr.visibility import GaussianTracer, TraceSettings

SIZE = (4.0, 1.8, 1.5)  # a car-sized box, node frame centred on the origin


def _shell(opacity: float = 0.4, step: float = 0.1, faces=("top", "+y", "+x")) -> Gaussians:
    """Semi-transparent splats on some faces of the box (what a forward camera saw of a car: its
    roof, one side and its front)."""
    l, w, h = SIZE
    pts, nrm = [], []
    xs, ys, zs = (np.arange(-a / 2 + step / 2, a / 2, step) for a in (l, w, h))
    zs = zs[zs > -h / 2 + 0.3]  # the body stands 0.3 m off the ground
    if "top" in faces:
        pts += [(x, y, h / 2) for x in xs for y in ys]
        nrm += [(0.0, 0.0, 1.0)] * (len(xs) * len(ys))
    if "+y" in faces:
        pts += [(x, w / 2, z) for x in xs for z in zs]
        nrm += [(0.0, 1.0, 0.0)] * (len(xs) * len(zs))
    if "+x" in faces:
        pts += [(l / 2, y, z) for y in ys for z in zs]
        nrm += [(1.0, 0.0, 0.0)] * (len(ys) * len(zs))
    m = torch.tensor(pts, dtype=torch.float64)
    n = len(m)
    one = torch.ones(n, 1, dtype=torch.float64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(n, 4)
    return Gaussians.from_activated(m, q, torch.full((n, 3), 0.04, dtype=torch.float64), one * opacity,
                                    one.expand(n, 3) * 0.5, torch.tensor(nrm, dtype=torch.float64),
                                    one.expand(n, 3) * 0.5, one * 0.5, one * 0.0)


def _transmittance(g: Gaussians, origins: np.ndarray, d) -> np.ndarray:
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    tr = GaussianTracer.from_gaussians(g.to(torch.float64), TraceSettings(t_min=0.0))
    return tr(torch.from_numpy(origins - 6.0 * d), torch.from_numpy(np.tile(d, (len(origins), 1)))).numpy().reshape(-1)


def _cat(a: Gaussians, b: Gaussians) -> Gaussians:
    return Gaussians.cat([a.to(torch.float64), b.to(torch.float64)])


def test_a_thin_shell_lets_light_through_and_its_filled_inside_does_not():
    shell = _shell()
    solid = solid_filler(shell, SIZE)
    assert solid.num > 0 and torch.isfinite(solid.means).all()
    rng = np.random.default_rng(0)
    # rays through the middle of the box: straight down, sideways across, slanted
    mid = np.stack([rng.uniform(-1.2, 1.2, 300), rng.uniform(-0.4, 0.4, 300), rng.uniform(-0.1, 0.3, 300)], -1)
    for d in ((0, 0, -1.0), (0, 1.0, 0), (0.5, 0.5, -0.7)):
        t_shell = np.median(_transmittance(shell, mid, d))
        t_solid = np.median(_transmittance(_cat(shell, solid), mid, d))
        assert t_shell > 0.3, d
        assert t_solid < 0.01, d


def test_the_graph_fills_unedited_boxed_nodes_only():
    from core.relight import ObjectEdit, apply_edits
    from core.scene_graph import RigidNode, SceneGraph

    pose = torch.eye(4, dtype=torch.float64)[None]
    nodes = [RigidNode("car0", "car", _shell(), torch.tensor([0]), pose.clone(), size=SIZE),
             RigidNode("blob", "unknown", _shell(), torch.tensor([0]), pose.clone())]  # no tracked box
    graph = SceneGraph(_ground(), nodes, torch.tensor([0.0]))
    assert graph.node_solid(graph.node("car0")).num > 0 and graph.node_solid(graph.node("blob")).num == 0
    n_fill = graph.node_solid(graph.node("car0")).num
    assert graph.shadow_static(True).num == graph.shadow_static(False).num + n_fill
    assert graph.shadow_static_except(frozenset({"car0"}), True).num == graph.shadow_static_except(frozenset({"car0"})).num
    # an edited copy carries its filler among its own Gaussians: no second one for shadows
    edited = apply_edits(graph, [ObjectEdit("insert", "car9", "car0", (10.0, 0.0, 0.0), 0.0)])
    assert edited.node("car9").gaussians.num > graph.node("car0").gaussians.num
    assert edited.node_solid(edited.node("car9")).num == 0


def test_the_renderer_traces_the_fill_and_never_draws_it():
    from core.camera import Camera
    from core.conventions import look_at
    from core.pbr.render import ClipRenderer, PBRSettings
    from core.scene_graph import RigidNode, SceneGraph

    pose = np.eye(4)
    pose[2, 3] = SIZE[2] / 2
    node = RigidNode("car0", "car", _shell(faces=("top", "+y", "+x")), torch.tensor([0]),
                     torch.from_numpy(pose)[None], size=SIZE)
    graph = SceneGraph(_ground(), [node], torch.tensor([0.0]))
    # a sun 45 deg up along x: the car's shadow falls on the road beyond one of its ends (both
    # are in view)
    cam = Camera.from_intrinsics(look_at(np.array([0.0, 8.0, 10.0]), np.array([0.0, 0.0, 0.0])), 48.0, 48.0, 32.0,
                                 24.0, 64, 48)
    out = {}
    for solids in (False, True):
        out[solids] = ClipRenderer(graph, _sun_map((1.0, 0.0, 1.0)),
                                   PBRSettings(rays_per_pixel=64, threads=1, object_solids=solids)).render(cam)
    assert torch.equal(out[False].gbuffers["opacity"], out[True].gbuffers["opacity"])  # never rasterized
    lum = {k: out[k].hdr.mean(-1) for k in out}
    ends = [_ground_pixels(cam, lambda p, sx=sx: (p[..., 1].abs() < 0.5) & (sx * p[..., 0] > SIZE[0] / 2 + 0.2)
                           & (sx * p[..., 0] < SIZE[0] / 2 + 1.0)) for sx in (-1.0, 1.0)]
    assert all(int(e.sum()) >= 4 for e in ends)
    # the end in the car's shadow: darker with the fill; the lit end unchanged
    shade, lit = sorted(ends, key=lambda e: float(lum[False][e].mean()))
    assert float(lum[True][shade].mean()) < 0.5 * float(lum[False][shade].mean())
    assert float(lum[True][lit].mean()) == pytest.approx(float(lum[False][lit].mean()), rel=0.05)
    # the roof, facing the sun, is not shadowed by the fill beneath it
    roof = out[False].gbuffers["normal"][..., 2] > 0.9
    roof &= out[False].gbuffers["depth"][..., 0] < float(out[False].gbuffers["depth"][..., 0][roof].median())
    assert float(lum[True][roof].mean()) == pytest.approx(float(lum[False][roof].mean()), rel=0.1)


def _ground() -> Gaussians:
    from core.rotations import rotmat_to_quat

    xs = np.arange(-6.0, 6.0, 0.25)
    pts = np.array([[x, y, 0.0] for x in xs for y in xs])
    n = len(pts)
    one = torch.ones(n, 1, dtype=torch.float64)
    q = rotmat_to_quat(torch.eye(3, dtype=torch.float64))[None].expand(n, 4)
    return Gaussians.from_activated(torch.from_numpy(pts), q.clone(),
                                    torch.tensor([[0.2, 0.2, 0.01]]).double().expand(n, 3), one * 0.98,
                                    one.expand(n, 3) * 0.5, torch.tensor([[0.0, 0.0, 1.0]]).double().expand(n, 3),
                                    one.expand(n, 3) * 0.5, one * 0.9, one * 0.0)


def _sun_map(to_sun):
    """A dim sky with a 5 deg sun towards ``to_sun`` (world)."""
    from core.conventions import envmap_directions
    from core.pbr.envmap import EnvironmentMap

    d = envmap_directions(64, 128)
    s = np.asarray(to_sun, np.float64) / np.linalg.norm(to_sun)
    img = np.full((64, 128, 3), 0.02, np.float32)
    img[d @ s > np.cos(np.radians(5.0))] = 300.0
    return EnvironmentMap(img)


def _ground_pixels(cam, where) -> torch.Tensor:
    """[H, W] bool: pixels whose ray meets the ground plane z = 0 at a point ``where`` holds."""
    h, w = cam.height, cam.width
    d = torch.from_numpy(cam.ray_directions().reshape(h, w, 3))
    o = torch.from_numpy(cam.pose_numpy()[:3, 3])
    t = -o[2] / d[..., 2].clamp(max=-1e-6)
    return where(o + t[..., None] * d)
