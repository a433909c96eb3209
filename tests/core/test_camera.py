"""core.camera.Camera: validation (the project's errors, naming the argument), batches, the
bundle's stored camera format, and equality with the constructions it replaced."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.bundle import BundleWriter, open_bundle
from core.bundle.testing import write_fake_bundle
from core.camera import Camera
from core.conventions import camera_ray_directions, look_at, project_points
from core.errors import ConfigError, NumericalError, ShapeError

C2W = look_at(np.array([0.5, -2.0, 1.5]), np.array([3.0, 1.0, 1.0]))


def _cam(c2w=C2W, fx=30.0, fy=32.0, cx=16.5, cy=11.0, w=32, h=24) -> Camera:
    return Camera.from_intrinsics(c2w, fx, fy, cx, cy, w, h)


def _k(fx=30.0, fy=32.0, cx=16.5, cy=11.0) -> torch.Tensor:
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)


# -- construction and the views of its parameters ----------------------------------------------

def test_fields_shapes_units_and_dtypes():
    cam = _cam()
    assert cam.K.shape == (3, 3) and cam.K.dtype == torch.float64
    torch.testing.assert_close(cam.K, _k(), rtol=0, atol=0)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (30.0, 32.0, 16.5, 11.0)
    assert all(type(v) is float for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    assert (cam.width, cam.height) == (32, 24)
    assert cam.cam_to_world.dtype == torch.float64 and cam.cam_to_world.shape == (4, 4)
    np.testing.assert_array_equal(cam.pose_numpy(), C2W)
    np.testing.assert_array_equal(cam.center.numpy(), C2W[:3, 3])
    assert not cam.is_batched
    same = Camera(_k(), C2W, 32, 24)  # the K constructor, equal to from_intrinsics
    assert torch.equal(same.K, cam.K) and torch.equal(same.cam_to_world, cam.cam_to_world)


def test_a_pose_tensor_keeps_its_dtype_and_autograd_graph():
    c2w = torch.tensor(C2W, dtype=torch.float32, requires_grad=True)
    cam = _cam(c2w)
    assert cam.cam_to_world is c2w
    assert cam.to(torch.float32) is cam
    c64 = cam.to(torch.float64)
    assert c64.cam_to_world.dtype == torch.float64 and c64.cam_to_world.requires_grad
    c64.center.sum().backward()
    assert torch.equal(c2w.grad[:3, 3], torch.ones(3))
    assert cam.pose_numpy().dtype == np.float64  # detached


def test_scaled_multiplies_the_intrinsics_and_the_size():
    cam = _cam().scaled(2)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (60.0, 64.0, 33.0, 22.0, 64, 48)
    assert float(cam.K[2, 2]) == 1.0
    with pytest.raises(ConfigError, match="factor"):
        _cam().scaled(0.3)


def test_of_reads_any_object_with_the_attributes():
    class Old:
        cam_to_world, fx, fy, cx, cy, width, height = C2W.astype(np.float32), 30.0, 32.0, 16.5, 11.0, 32, 24

    cam = Camera.of(Old())
    assert cam.cam_to_world.dtype == torch.float64 and (cam.fx, cam.width) == (30.0, 32)
    assert Camera.of(cam) is cam


# -- validation ---------------------------------------------------------------------------------

@pytest.mark.parametrize("kw,name,err", [
    ({"fx": 0.0}, "fx", ConfigError), ({"fy": -1.0}, "fy", ConfigError), ({"fx": "a"}, "fx", ConfigError),
    ({"cx": math.nan}, "cx", NumericalError), ({"cy": math.inf}, "cy", NumericalError),
    ({"fx": torch.ones(2)}, "fx", ShapeError), ({"w": 0}, "width", ConfigError), ({"h": 2.5}, "height", ConfigError),
    ({"w": True}, "width", ConfigError),
])
def test_bad_intrinsics_name_the_argument(kw, name, err):
    with pytest.raises(err, match=name):
        _cam(**kw)


def test_bad_matrices_name_the_argument():
    with pytest.raises(ShapeError, match="cam_to_world"):
        _cam(C2W[:3])
    with pytest.raises(ShapeError, match="cam_to_world"):
        _cam(torch.eye(4, dtype=torch.int64))
    with pytest.raises(ShapeError, match="cam_to_world"):
        _cam(np.array([["a"] * 4] * 4))
    bad = C2W.copy()
    bad[0, 3] = math.nan
    with pytest.raises(NumericalError, match="cam_to_world"):
        _cam(bad)
    for change in (lambda m: m[:3, :3].__imul__(2.0), lambda m: m[:3, 0].__imul__(-1.0),
                   lambda m: m[3].__setitem__(0, 0.5)):
        m = C2W.copy()
        change(m)
        with pytest.raises(ConfigError, match="cam_to_world"):
            _cam(m)
    with pytest.raises(ShapeError, match="K"):
        Camera(torch.eye(2, dtype=torch.float64), C2W, 8, 8)
    skew = _k()
    skew[0, 1] = 0.1
    with pytest.raises(ConfigError, match="K"):
        Camera(skew, C2W, 8, 8)
    neg = _k(fx=-1.0)
    with pytest.raises(ConfigError, match="K"):
        Camera(neg, C2W, 8, 8)
    with pytest.raises(ShapeError, match="K"):
        Camera(_k().expand(3, 3, 3), np.stack([C2W, C2W]), 8, 8)


def test_the_rasterizer_takes_one_camera_only():
    from core.raster import rasterize

    t = [torch.zeros(1, 3, dtype=torch.float64)] * 9
    with pytest.raises(ConfigError, match="camera"):
        rasterize(*t, (C2W, 30.0, 30.0, 16.0, 12.0, 32, 24))
    with pytest.raises(ShapeError, match="camera"):
        rasterize(*t, Camera.stack([_cam(), _cam()]))


# -- batches ------------------------------------------------------------------------------------

def test_batches_stack_index_iterate_and_broadcast():
    poses = [look_at(np.array([x, 0.0, 1.5]), np.array([x + 10.0, 0.0, 1.0])) for x in (0.0, 1.0, 2.0)]
    cams = [_cam(p, fx=30.0 + i) for i, p in enumerate(poses)]
    batch = Camera.stack(cams)
    assert batch.is_batched and len(batch) == 3
    assert batch.K.shape == (3, 3, 3) and batch.cam_to_world.shape == (3, 4, 4)
    assert batch.fx.tolist() == [30.0, 31.0, 32.0] and batch.cx.shape == (3,)
    assert batch.center.shape == (3, 3)
    for i, c in enumerate(batch):
        assert not c.is_batched and c.fx == 30.0 + i
        np.testing.assert_array_equal(c.pose_numpy(), poses[i])
    assert len(batch[1:]) == 2 and batch[-1].fx == 32.0
    assert len(Camera.stack([batch, cams[0]])) == 4
    with pytest.raises(IndexError):
        batch[3]
    # one K broadcast to every pose, and one pose to every K
    one_k = Camera(_k(), np.stack(poses), 32, 24)
    assert one_k.K.shape == (3, 3, 3) and torch.equal(one_k.K[2], _k())
    one_pose = Camera(torch.stack([_k(), _k(fx=40.0)]), C2W, 32, 24)
    assert len(one_pose) == 2 and one_pose[1].fx == 40.0 and torch.equal(one_pose[1].cam_to_world, one_pose[0].cam_to_world)


def test_batch_errors():
    cam = _cam()
    with pytest.raises(TypeError):
        len(cam)
    with pytest.raises(TypeError):
        cam[0]
    with pytest.raises(ConfigError, match="cameras"):
        Camera.stack([cam, _cam(w=16)])
    with pytest.raises(ConfigError, match="cameras"):
        Camera.stack([])
    bad = np.stack([C2W, C2W])
    bad[1, :3, :3] *= 3.0
    with pytest.raises(ConfigError, match="cam_to_world"):
        Camera(_k(), bad, 32, 24)
    with pytest.raises(ShapeError, match="camera"):
        Camera.stack([cam, cam]).to_bundle("front")


# -- the bundle's stored camera format ------------------------------------------------------------

def test_round_trip_through_a_bundle_on_disk(tmp_path):
    """Bundle on disk -> Camera -> the bundle's records -> a new bundle on disk: the same camera
    record and poses (the stored format is unchanged), and the same values every caller used to
    pass as loose arguments."""
    b = open_bundle(write_fake_bundle(tmp_path / "a", frames=2, test_frames=0, with_gt=False, focal=30.0))
    cams = [Camera.from_bundle(b.camera(f), f) for f in b.frames()]
    w = BundleWriter(tmp_path / "b", "copy")
    w.set_times(b.manifest.times)
    w.add_camera(cams[0].to_bundle("front"))
    for f, cam in zip(b.frames(), cams):
        c = b.camera(f)
        old = (np.asarray(f.cam_to_world, np.float64), c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        np.testing.assert_array_equal(cam.pose_numpy(), old[0])
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == old[1:]
        assert cam.to_bundle(c.id) == c
        w.add_frame(f.id, "front", f.time_index, cam.pose_numpy(), image=b.load_image(f), split=f.split)
    copy = open_bundle(w.finish())
    assert copy.manifest.cameras == b.manifest.cameras
    for f, g in zip(b.frames(), copy.frames()):
        np.testing.assert_array_equal(g.cam_to_world, f.cam_to_world)
        assert Camera.from_bundle(copy.camera(g), g).to_bundle("front") == b.camera(f)
    assert cams[0].to_bundle("front", (0.1,)).distortion == (0.1,)


def test_rays_and_projection_equal_the_old_loose_argument_helpers():
    cam = _cam()
    np.testing.assert_array_equal(cam.ray_directions(), camera_ray_directions(C2W, 30.0, 32.0, 16.5, 11.0, 32, 24))
    pts = np.array([[3.0, 1.0, 1.0], [2.0, 0.5, 1.2], [-5.0, -8.0, 1.0]])
    uv, z = cam.project(pts)
    uv_old, z_old = project_points(pts, C2W, 30.0, 32.0, 16.5, 11.0)
    np.testing.assert_array_equal(uv, uv_old)
    np.testing.assert_array_equal(z, z_old)
    # K applied by hand to the camera-frame points gives the same pixels
    pc = (pts[:2] - C2W[:3, 3]) @ C2W[:3, :3]
    hom = pc @ cam.K.numpy().T
    np.testing.assert_allclose(hom[:, :2] / hom[:, 2:], uv[:2], rtol=1e-12)
    # the ray through a projected point's pixel passes through the point
    u, v = uv[0]
    d = cam.ray_directions()[int(v), int(u)]
    assert float(d @ (pts[0] - C2W[:3, 3]) / np.linalg.norm(pts[0] - C2W[:3, 3])) > 0.99
    with pytest.raises(ShapeError, match="camera"):
        Camera.stack([cam, cam]).ray_directions()


def test_the_rasterizer_renders_bit_identically_to_the_old_float32_construction():
    """Callers used to pass ``torch.as_tensor(c2w, dtype=g.dtype)`` and four numbers;
    :func:`core.raster.rasterize_gaussians` casts the camera to the Gaussians' dtype itself."""
    from core.gaussians import Gaussians
    from core.raster import rasterize, rasterize_gaussians

    gen = torch.Generator().manual_seed(3)
    n = 60
    means = torch.stack([torch.rand(n, generator=gen) * 4 - 2, torch.rand(n, generator=gen) * 3 - 1.5,
                         torch.rand(n, generator=gen) * 4 + 2], -1)
    g = Gaussians.from_activated(means, torch.randn(n, 4, generator=gen), 0.05 + 0.3 * torch.rand(n, 3, generator=gen),
                                 torch.rand(n, generator=gen), torch.rand(n, 3, generator=gen),
                                 torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1),
                                 torch.rand(n, 3, generator=gen), torch.rand(n, generator=gen),
                                 torch.rand(n, generator=gen))
    c2w = look_at(np.array([0.1, -0.1, -0.2]), np.array([0.0, 0.1, 4.0]), np.array([0.0, -1.0, 0.0]))
    cam = Camera.from_intrinsics(c2w, 20.0, 21.0, 12.0, 9.5, 24, 18)
    a = rasterize_gaussians(g, cam)
    old = Camera.from_intrinsics(torch.as_tensor(c2w, dtype=torch.float32), 20.0, 21.0, 12.0, 9.5, 24, 18)
    act = g.activated(cam_center=old.cam_to_world[:3, 3])
    b = rasterize(*[act[k] for k in ("means", "quats", "scales", "opacities", "colors", "normals", "albedo",
                                     "roughness", "metallic")], old)
    assert a.opacity.max() > 0.1 and torch.equal(a.packed, b.packed)
