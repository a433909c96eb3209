from __future__ import annotations

import numpy as np
import pytest
import torch

from core.bundle import open_bundle
from core.camera import Camera
from core.errors import ConfigError, ShapeError
from core.gaussians import Gaussians
from core.train.density import DensityConfig, DensityController, scene_extent
from core.train.init_lidar import LidarInitConfig, gaussians_from_lidar
from core.train.optim import GaussianAdam
from core.train.sky import SkyDome


@pytest.mark.mitsuba
def test_lidar_init_places_gaussians_on_surfaces(tiny_scene):
    b = open_bundle(tiny_scene)
    bg, nodes = gaussians_from_lidar(b, LidarInitConfig(max_background_points=2000))
    assert 100 < bg.num <= 2000  # only points some training camera sees
    assert nodes, "LiDAR hits on cars become object nodes"
    m = b.manifest
    # road points: upward normals, flat disks
    means = bg.means.detach().numpy()
    road = np.abs(means[:, 2]) < 0.01
    assert road.sum() > 20
    n = bg.unit_normals().detach().numpy()[road]
    assert np.median(n[:, 2]) > 0.95
    # object points sit inside their box in the object frame
    for oid, g in nodes.items():
        size = np.array(next(o.size for o in m.objects if o.id == oid))
        assert np.all(np.abs(g.means.detach().numpy()) <= size / 2 + 0.11)
    # colours come from the frames: the asphalt is dark
    assert np.median(bg.colors().detach().numpy()[road].mean(1)) < 0.45


def _blob(n=10):
    g = torch.Generator().manual_seed(0)
    return Gaussians.from_activated(
        means=torch.randn(n, 3, generator=g), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.05), opacities=torch.full((n,), 0.5), colors=torch.rand(n, 3, generator=g),
        normals=torch.tensor([[0.0, 0, 1]]).repeat(n, 1), albedo=torch.rand(n, 3, generator=g),
        roughness=torch.full((n,), 0.5), metallic=torch.zeros(n))


def test_density_clone_split_prune_and_cap():
    g = _blob(10)
    # make Gaussian 0 large (split), 1 small (clone), 2 transparent (prune)
    with torch.no_grad():
        g.log_scales[0] = np.log(2.0)
        g.opacity_logits[2] = -10.0
    opt = GaussianAdam(g)
    dc = DensityController(DensityConfig(grad_threshold=1e-3, max_gaussians=100), scene_extent=10.0, num=10)
    grad = torch.zeros(10, 3)
    grad[0, 0] = grad[1, 0] = 1.0
    cam = Camera.from_intrinsics(torch.eye(4, dtype=torch.float64), 100.0, 100.0, 32.0, 32.0, 64, 64)
    means = g.means.detach().clone()
    means[:, 2] = 5.0
    dc.accumulate(grad, means, cam)
    stats = dc.densify_and_prune(opt, prune_large=False)
    assert stats == {"cloned": 1, "split": 1, "pruned": 1, "total": 10 - 2 + 1 + 2}
    assert opt.g.num == 11 and opt.m["means"].shape == (11, 3)
    # split children are smaller than the parent
    assert float(opt.g.scales()[-1].max()) == pytest.approx(2.0 / 1.6, rel=1e-5)
    # the cap is respected
    dc2 = DensityController(DensityConfig(grad_threshold=1e-3, max_gaussians=11), 10.0, opt.g.num)
    dc2.accumulate(torch.ones(11, 3), torch.cat([means[:1]] * 11), cam)
    assert dc2.densify_and_prune(opt, prune_large=False)["total"] <= 11 + 1  # only splits may replace


def test_density_accumulate_is_the_screen_space_gradient_of_the_camera():
    """The accumulated statistic is |dL/dmean projected on the image| x depth / focal x half the
    image (3DGS's NDC mean2D gradient), with the camera's pose, fx, fy and image size."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    cam = Camera.from_intrinsics(c2w, 80.0, 120.0, 30.0, 20.0, 64, 48)
    means = torch.tensor([[1.0, -2.0, 4.5], [1.0, -2.0, 0.6]])  # 4 m and 0.1 m in front (the 2nd not counted)
    grad = torch.tensor([[0.3, -0.4, 2.0], [1.0, 1.0, 1.0]])
    dc = DensityController(DensityConfig(), scene_extent=1.0, num=2)
    dc.accumulate(grad, means, cam)
    want = float(np.hypot(0.3 * 4.0 / 80.0 * 32, -0.4 * 4.0 / 120.0 * 24))
    assert float(dc.grad_accum[0]) == pytest.approx(want, rel=1e-6)
    assert dc.count.tolist() == [1.0, 0.0]
    with pytest.raises(ConfigError, match="camera"):
        dc.accumulate(grad, means, torch.eye(4))
    with pytest.raises(ShapeError, match="camera"):
        dc.accumulate(grad, means, Camera.stack([cam, cam]))
    with pytest.raises(ShapeError, match="means_grad"):
        dc.accumulate(grad[:1], means, cam)


def test_adam_moves_parameters_and_survives_nan_gradients():
    g = _blob(4)
    opt = GaussianAdam(g)
    loss = (opt.g.means ** 2).sum()
    loss.backward()
    opt.g.colors().sum()  # untouched fields have no grad: skipped
    before = opt.g.means.detach().clone()
    opt.step()
    assert (opt.g.means.detach().abs() < before.abs()).all()
    opt.zero_grad()
    opt.g.means.grad = torch.full_like(opt.g.means, float("nan"))
    opt.step()
    assert torch.isfinite(opt.g.means).all()


def test_sky_dome_follows_the_envmap_convention():
    from core.conventions import pixel_to_direction

    sky = SkyDome(8, 16)
    with torch.no_grad():
        sky.logits.fill_(-5.0)
        sky.logits[2, 5] = 5.0
    d = torch.tensor(pixel_to_direction(2, 5, 8, 16), dtype=torch.float32)
    assert float(sky(d[None])[0].mean()) > 0.9
    # gradients reach the texture
    sky(d[None]).sum().backward()
    assert sky.logits.grad[2, 5].abs().sum() > 0
