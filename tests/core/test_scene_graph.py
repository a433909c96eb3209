from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.rotations import axis_angle_to_quat, quat_to_rotmat
from core.scene_graph import RigidNode, SceneGraph, transform_gaussians


def _gaussians(n, seed=0, dtype=torch.float64, offset=(0.0, 0.0, 0.0)):
    g = torch.Generator().manual_seed(seed)
    return Gaussians.from_activated(
        means=torch.randn(n, 3, generator=g, dtype=dtype) * 0.5 + torch.tensor(offset, dtype=dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.05,
        opacities=torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1,
        colors=torch.rand(n, 3, generator=g, dtype=dtype),
        normals=torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1),
        albedo=torch.rand(n, 3, generator=g, dtype=dtype),
        roughness=torch.rand(n, generator=g, dtype=dtype),
        metallic=torch.rand(n, generator=g, dtype=dtype),
    )


def _pose(x, y, yaw):
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = quat_to_rotmat(axis_angle_to_quat(torch.tensor([0.0, 0.0, yaw], dtype=torch.float64)))
    m[:3, 3] = torch.tensor([x, y, 0.75], dtype=torch.float64)
    return m


def _graph():
    times = torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=torch.float64)
    mover = RigidNode("car1", "car", _gaussians(20, 1), torch.tensor([0, 1, 2]),
                      torch.stack([_pose(5.0 + t, 0.0, 0.1 * t) for t in range(3)]))
    parked = RigidNode("car2", "car", _gaussians(10, 2), torch.tensor([0, 1, 2, 3]),
                       torch.stack([_pose(8.0, 4.0, math.pi)] * 4))
    return SceneGraph(_gaussians(30, 0), [mover, parked], times)


def test_compose_at_keyframe_matches_manual_transform():
    sg = _graph()
    world = sg.compose(0.1)
    assert world.num == 30 + 10 + 20
    mover = sg.node("car1")
    m = mover.poses[1]
    expect = mover.gaussians.means @ m[:3, :3].T + m[:3, 3]
    torch.testing.assert_close(world.means[40:], expect)
    torch.testing.assert_close(world.unit_normals()[40:], mover.gaussians.unit_normals() @ m[:3, :3].T)
    # rotations compose: R_world = R_pose @ R_local
    torch.testing.assert_close(quat_to_rotmat(world.quats[40:]), m[:3, :3] @ quat_to_rotmat(mover.gaussians.quats))
    torch.testing.assert_close(world.log_scales[40:], mover.gaussians.log_scales)


def test_interpolation_between_keyframes():
    sg = _graph()
    poses = sg.node_poses(0.15)  # halfway between keyframes 1 and 2
    torch.testing.assert_close(poses["car1"][:3, 3], torch.tensor([6.5, 0.0, 0.75], dtype=torch.float64))
    expect_r = quat_to_rotmat(axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.15], dtype=torch.float64)))
    torch.testing.assert_close(poses["car1"][:3, :3], expect_r)


def test_node_hidden_outside_its_observed_range():
    sg = _graph()
    assert set(sg.node_poses(0.3)) == {"car2"}  # car1 was last seen at t = 0.2 s
    assert sg.compose(0.3).num == 40
    assert sg.compose(0.1, hidden={"car1"}).num == 40


def test_static_nodes_are_composed_once():
    sg = _graph()
    assert sg.node("car2").is_static and not sg.node("car1").is_static
    a = sg._static_part()
    assert sg._static_part() is a  # cached: no per-frame work for nodes that do not move
    torch.testing.assert_close(sg.compose(0.0).means[:40], a.means)


def test_pose_refinement_receives_gradients():
    sg = _graph()
    params = sg.node("car1").enable_pose_refinement()
    world = sg.compose(0.15)
    world.means[40:].sum().backward()
    dt, dr = params
    assert dt.grad is not None and torch.isfinite(dt.grad).all()
    # halfway between keyframes 1 and 2: translation gradient splits 0.5 / 0.5 (20 Gaussians x 1)
    torch.testing.assert_close(dt.grad[:, 0], torch.tensor([0.0, 10.0, 10.0], dtype=torch.float64))
    assert torch.isfinite(dr.grad).all() and dr.grad.abs().sum() > 0


def test_transform_is_differentiable_in_pose():
    g = _gaussians(5, 3)
    q = axis_angle_to_quat(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)).requires_grad_(True)
    t = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q_, t_: transform_gaussians(g, q_, t_).means, (q, t))


def test_save_load_roundtrip(tmp_path):
    sg = _graph()
    sg.save(tmp_path / "sg.pt")
    sg2 = SceneGraph.load(tmp_path / "sg.pt")
    torch.testing.assert_close(sg2.compose(0.15).means, sg.compose(0.15).means)
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(FormatError, match="bad.pt"):
        SceneGraph.load(tmp_path / "bad.pt")


def test_from_bundle_objects(small_bundle):
    from core.bundle import open_bundle

    m = open_bundle(small_bundle).manifest
    sg = SceneGraph.from_bundle_objects(m, _gaussians(5, 0), {"car0": _gaussians(3, 1)})
    poses = sg.node_poses(m.times[2])
    np.testing.assert_allclose(poses["car0"][:3, 3].numpy(), [7.0, 2.0, 0.75])


def test_bad_graphs_are_named():
    times = torch.tensor([0.0, 0.1])
    with pytest.raises(ConfigError, match="duplicate node names"):
        n = RigidNode("a", "car", _gaussians(2), torch.tensor([0]), _pose(0, 0, 0)[None])
        SceneGraph(_gaussians(2), [n, n], times)
    with pytest.raises(ConfigError, match="time index outside"):
        SceneGraph(_gaussians(2), [RigidNode("a", "car", _gaussians(2), torch.tensor([5]), _pose(0, 0, 0)[None])], times)
    with pytest.raises(ConfigError, match="no node"):
        _graph().node("bus")


def test_moved_node_renders_like_moved_world_gaussians():
    """A rigid node moved by a pose renders exactly like the same Gaussians moved in world space."""
    from core.camera import Camera
    from core.conventions import look_at
    from core.raster import rasterize_gaussians

    local = _gaussians(40, 5, dtype=torch.float32)
    pose = _pose(6.0, 0.5, 0.4).float()
    node = RigidNode("car", "car", local, torch.tensor([0]), pose[None].double())
    sg = SceneGraph(Gaussians.empty(torch.float32), [node], torch.tensor([0.0]))
    via_graph = sg.compose(0.0)
    r, t = pose[:3, :3], pose[:3, 3]
    a = local.activated()
    from core.rotations import rotmat_to_quat, quat_mul

    by_hand = Gaussians.from_activated(
        means=a["means"] @ r.T + t, quats=quat_mul(rotmat_to_quat(r).expand(40, 4), a["quats"]),
        scales=a["scales"], opacities=a["opacities"], colors=a["colors"], normals=a["normals"] @ r.T,
        albedo=a["albedo"], roughness=a["roughness"], metallic=a["metallic"])
    cam = Camera.from_intrinsics(torch.tensor(look_at([0.0, 0.0, 1.5], [6.0, 0.5, 0.75]), dtype=torch.float32), 60.0,
                                 60.0, 32.0, 24.0, 64, 48)
    o1 = rasterize_gaussians(via_graph, cam)
    o2 = rasterize_gaussians(by_hand, cam)
    assert o1.opacity.max() > 0.5
    torch.testing.assert_close(o1.packed, o2.packed, atol=2e-5, rtol=1e-4)


def test_view_dependent_colour_moves_with_the_node():
    """A node's Gaussian seen from a camera looks the same before and after a rigid motion that
    moves the camera with it (the view-dependent matrix rotates with the node)."""
    g = _gaussians(6, 7)
    with torch.no_grad():
        g.view_dep.copy_(torch.randn(6, 9, dtype=torch.float64))
    q = axis_angle_to_quat(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64))
    t = torch.tensor([4.0, -1.0, 0.5], dtype=torch.float64)
    moved = transform_gaussians(g, q, t)
    cam_local = torch.tensor([-3.0, 1.0, 2.0], dtype=torch.float64)
    cam_world = quat_to_rotmat(q) @ cam_local + t
    torch.testing.assert_close(moved.colors(cam_world), g.colors(cam_local))
    # and the view-dependent term really depends on the view
    assert (g.colors(cam_local) - g.colors(-cam_local)).abs().max() > 1e-3


def test_version_1_gaussians_file_loads(tmp_path):
    g = _gaussians(4, 8)
    payload = {"format": "brdfusion.gaussians", "version": 1, "num": 4}
    payload.update({k: v for k, v in g.tensors().items() if k != "view_dep"})
    torch.save(payload, tmp_path / "v1.pt")
    g1 = Gaussians.load(tmp_path / "v1.pt")
    assert torch.equal(g1.view_dep, torch.zeros(4, 9, dtype=torch.float64))
    torch.testing.assert_close(g1.colors(torch.zeros(3, dtype=torch.float64)), g.colors())
