"""Shadow rays through Gaussians: C++ BVH kernel vs the brute-force twin, early stop bound,
self-shadowing offset, analytic single-Gaussian cases, segments, degenerate inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import ConfigError, ShapeError
from core.gaussians import Gaussians
from core.pbr.lights import PointLight, direct_lighting, lights_to_world
from core.pbr.visibility import GaussianTracer, TraceSettings, visibility_reference

D64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _cloud(n=400, seed=0, extent=4.0, flat=False):
    g = _gen(seed)
    means = (torch.rand(n, 3, generator=g, dtype=D64) - 0.5) * extent
    quats = torch.randn(n, 4, generator=g, dtype=D64)
    scales = torch.rand(n, 3, generator=g, dtype=D64) * 0.3 + 0.02
    if flat:
        scales[:, 2] = 1e-3
    op = torch.rand(n, generator=g, dtype=D64)
    return means, quats, scales, op


def _rays(m=3000, seed=1, extent=4.0, axis_parallel=False):
    g = _gen(seed)
    o = (torch.rand(m, 3, generator=g, dtype=D64) - 0.5) * extent * 1.5
    d = torch.randn(m, 3, generator=g, dtype=D64)
    if axis_parallel:
        k = torch.randint(0, 3, (m,), generator=g)
        d = torch.nn.functional.one_hot(k, 3).to(D64) * torch.sign(torch.randn(m, 1, generator=g, dtype=D64))
    return o, d


@pytest.mark.parametrize("flat,axis_parallel", [(False, False), (True, False), (False, True)])
def test_kernel_matches_brute_force_reference(flat, axis_parallel):
    cloud = _cloud(flat=flat)
    o, d = _rays(axis_parallel=axis_parallel)
    s = TraceSettings(early_stop=0.0, t_min=0.0)
    tr = GaussianTracer(*cloud, settings=s)
    v = tr(o, d)
    ref = visibility_reference(*cloud, o, d, settings=s)
    np.testing.assert_allclose(v.numpy(), ref.numpy(), atol=2e-7)
    assert v.dtype == D64 and (ref < 0.5).any() and (ref > 0.99).any()
    assert tr.last_stats["gaussian_tests"] < 0.25 * 3000 * tr.num_kept  # the BVH culls


def test_segments_with_t_max_and_t_min():
    cloud = _cloud(seed=2)
    o, d = _rays(seed=3)
    t_max = torch.rand(o.shape[0], generator=_gen(4), dtype=D64) * 3.0
    s = TraceSettings(early_stop=0.0, t_min=0.05)
    v = GaussianTracer(*cloud, settings=s)(o, d, t_max)
    ref = visibility_reference(*cloud, o, d, t_max, settings=s)
    np.testing.assert_allclose(v.numpy(), ref.numpy(), atol=2e-7)
    full = visibility_reference(*cloud, o, d, settings=s)
    assert (ref >= full - 1e-12).all() and (ref > full + 1e-3).any()
    # a segment shorter than t_min sees nothing
    short = GaussianTracer(*cloud, settings=s)(o, d, torch.full((o.shape[0],), 0.01, dtype=D64))
    assert (short == 1).all()


def test_object_tracers_start_their_rays_at_t_min_objects():
    """A tracer of edited objects (``objects=True``) traces from ``TraceSettings.t_min_objects``
    (the kernel and its brute-force twin agree); None falls back to ``t_min``."""
    cloud = _cloud(seed=4)
    o, d = _rays(seed=5)
    s = TraceSettings(early_stop=0.0, t_min=0.8, t_min_objects=0.1)
    obj, scene = GaussianTracer(*cloud, settings=s, objects=True), GaussianTracer(*cloud, settings=s)
    assert (obj.t_min, scene.t_min) == (0.1, 0.8)
    ref = visibility_reference(*cloud, o, d, settings=s, objects=True)
    np.testing.assert_allclose(obj(o, d).numpy(), ref.numpy(), atol=2e-7)
    np.testing.assert_allclose(scene(o, d).numpy(), visibility_reference(*cloud, o, d, settings=s).numpy(), atol=2e-7)
    # the objects' rays are the rays of a tracer with t_min 0.1, and differ from t_min 0.8's
    assert torch.equal(ref, visibility_reference(*cloud, o, d, settings=TraceSettings(early_stop=0.0, t_min=0.1)))
    assert float((ref - visibility_reference(*cloud, o, d, settings=s)).abs().max()) > 0.1
    # segments shorter than the objects' t_min are fully visible there, not before
    tm = torch.full((o.shape[0],), 0.5, dtype=D64)
    np.testing.assert_allclose(obj(o, d, tm).numpy(), visibility_reference(*cloud, o, d, tm, settings=s,
                                                                           objects=True).numpy(), atol=2e-7)
    assert bool((scene(o, d, tm) == 1.0).all())
    unset = TraceSettings(t_min=0.3)
    assert GaussianTracer(*cloud, settings=unset, objects=True).t_min == 0.3
    assert torch.equal(visibility_reference(*cloud, o, d, settings=unset, objects=True),
                       visibility_reference(*cloud, o, d, settings=unset))


def test_early_stop_error_is_bounded():
    cloud = _cloud(n=1500, seed=5, extent=3.0)
    cloud = (cloud[0], cloud[1], cloud[2], cloud[3].clamp_min(0.5))
    o, d = _rays(seed=6, extent=3.0)
    s = TraceSettings(early_stop=1e-3, t_min=0.0)
    tr = GaussianTracer(*cloud, settings=s)
    v = tr(o, d).numpy()
    ref = visibility_reference(*cloud, o, d, settings=s).numpy()
    assert (ref < 1e-3).mean() > 0.2  # many rays are blocked
    assert (v >= ref - 2e-7).all() and (v - ref).max() < 1e-3
    # where the exact V stays above the threshold the ray can never stop early: exact there
    assert np.abs(v[ref >= 1e-3] - ref[ref >= 1e-3]).max() < 2e-7
    counted_early = tr.last_stats["gaussians_counted"]
    no_stop = GaussianTracer(*cloud, settings=TraceSettings(early_stop=0.0, t_min=0.0))
    no_stop(o, d)
    assert counted_early < no_stop.last_stats["gaussians_counted"]


def test_single_gaussian_analytic_response():
    # isotropic sigma = 0.1 at the origin, opacity 0.8; rays along +x at perpendicular offset b
    mu = torch.zeros(1, 3, dtype=D64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D64)
    sc = torch.full((1, 3), 0.1, dtype=D64)
    op = torch.tensor([0.8], dtype=D64)
    b = torch.tensor([0.0, 0.05, 0.1, 0.2, 0.25], dtype=D64)
    o = torch.stack([torch.full_like(b, -1.0), b, torch.zeros_like(b)], -1)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=D64).expand_as(o)
    s = TraceSettings(t_min=0.0, early_stop=0.0)
    v = GaussianTracer(mu, q, sc, op, s)(o, d).numpy()
    expected = 1 - 0.8 * np.exp(-0.5 * (b.numpy() / 0.1) ** 2)
    np.testing.assert_allclose(v, expected, atol=2e-7)
    # max_alpha clamps an opaque Gaussian at 0.99
    v1 = GaussianTracer(mu, q, sc, torch.tensor([1.0], dtype=D64), s)(o[:1], d[:1])
    assert float(v1) == pytest.approx(0.01, abs=1e-6)
    # beyond 3 sigma (b = 0.35) the Gaussian is truncated
    far = GaussianTracer(mu, q, sc, op, s)(torch.tensor([[-1.0, 0.35, 0.0]], dtype=D64), d[:1])
    assert float(far) == 1.0
    # a ray starting past the Gaussian and leaving it sees only the clamped tail
    behind = GaussianTracer(mu, q, sc, op, s)(torch.tensor([[0.5, 0.0, 0.0]], dtype=D64), d[:1])
    assert float(behind) == 1.0


def test_ray_offset_prevents_self_shadowing_on_a_flat_gaussian():
    # a disc Gaussian (0.5 m x 0.5 m x 1 mm) in the z = 0 plane; rays start at its centre
    mu = torch.zeros(1, 3, dtype=D64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D64)
    sc = torch.tensor([[0.5, 0.5, 1e-3]], dtype=D64)
    op = torch.tensor([0.99], dtype=D64)
    ang = np.radians(np.array([0.0, 30.0, 60.0, 75.0]))
    d = torch.from_numpy(np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], -1))
    o = torch.zeros_like(d)
    with_offset = GaussianTracer(mu, q, sc, op, TraceSettings(t_min=0.02))(o, d)
    assert (with_offset == 1.0).all()
    without = GaussianTracer(mu, q, sc, op, TraceSettings(t_min=0.0))(o, d)
    np.testing.assert_allclose(without.numpy(), 0.01, atol=1e-6)


def test_order_of_gaussians_does_not_matter_and_containers_work():
    cloud = _cloud(n=300, seed=7)
    o, d = _rays(m=1000, seed=8)
    s = TraceSettings(early_stop=0.0)
    v1 = GaussianTracer(*cloud, settings=s)(o, d)
    perm = torch.randperm(300, generator=_gen(9))
    v2 = GaussianTracer(*(c[perm] for c in cloud), settings=s)(o, d)
    np.testing.assert_allclose(v1.numpy(), v2.numpy(), atol=1e-6)
    means, quats, scales, op = cloud
    g = Gaussians.from_activated(means, quats, scales, op, torch.rand(300, 3, dtype=D64), torch.zeros(300, 3, dtype=D64),
                                 torch.rand(300, 3, dtype=D64), torch.rand(300, dtype=D64), torch.rand(300, dtype=D64))
    v3 = GaussianTracer.from_gaussians(g, s)(o, d)
    np.testing.assert_allclose(v3.numpy(), v1.numpy(), atol=1e-5)


def test_empty_transparent_and_degenerate_inputs():
    o, d = _rays(m=100, seed=10)
    empty = GaussianTracer(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0))
    assert (empty(o.float(), d.float()) == 1).all()
    cloud = _cloud(n=50, seed=11)
    clear = GaussianTracer(cloud[0], cloud[1], cloud[2], torch.full((50,), 1e-3, dtype=D64))
    assert clear.num_kept == 0 and (clear(o, d) == 1).all()
    # zero quaternions, zero scales, zero directions
    q0 = torch.zeros(50, 4, dtype=D64)
    tr = GaussianTracer(cloud[0], q0, torch.zeros(50, 3, dtype=D64), cloud[3])
    v = tr(o, torch.zeros_like(d))
    assert (v == 1).all()
    v = tr(o, d)
    assert torch.isfinite(v).all() and ((v >= 0) & (v <= 1)).all()
    many = GaussianTracer(torch.zeros(5000, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(5000, 4),
                          torch.full((5000, 3), 0.1), torch.full((5000,), 0.5))
    assert many.depth < 40
    assert float(many(torch.tensor([[-1.0, 0, 0]]), torch.tensor([[1.0, 0, 0]]))) < 1e-3


def test_invalid_inputs_raise_named_errors():
    cloud = _cloud(n=10)
    with pytest.raises(ShapeError, match="quats"):
        GaussianTracer(cloud[0], cloud[1][:, :3], cloud[2], cloud[3])
    with pytest.raises(ConfigError, match="scales"):
        GaussianTracer(cloud[0], cloud[1], -cloud[2], cloud[3])
    with pytest.raises(ConfigError, match="t_min"):
        TraceSettings(t_min=-1.0)
    for bad in (-0.1, float("nan"), True, "0.1"):
        with pytest.raises(ConfigError, match="t_min_objects"):
            TraceSettings(t_min_objects=bad)
    tr = GaussianTracer(*cloud)
    with pytest.raises(ShapeError, match="dirs"):
        tr(torch.zeros(4, 3), torch.zeros(3, 3))
    with pytest.raises(ShapeError, match="t_max"):
        tr(torch.zeros(4, 3), torch.ones(4, 3), torch.ones(3))


def test_local_light_inside_a_gaussian_with_the_tracer():
    # an opaque-ish Gaussian around the light (a headlight inside its car's Gaussians) and one
    # between the light and the floor
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]], dtype=D64)
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=D64).expand(2, 4)
    sc = torch.tensor([[0.3, 0.3, 0.3], [0.2, 0.2, 0.2]], dtype=D64)
    op = torch.tensor([0.9, 0.5], dtype=D64)
    tr = GaussianTracer(means, q, sc, op, TraceSettings(t_min=0.01, early_stop=0.0))
    pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]], dtype=D64)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64).expand(2, 3)
    ls = lights_to_world([PointLight((0.0, 0.0, 2.0), intensity=10.0)], dtype=D64)
    args = (pts, n, n, torch.ones(2, 3, dtype=D64), torch.ones(2, 1, dtype=D64), torch.zeros(2, 1, dtype=D64))
    lit = direct_lighting(*args, ls, specular=0.0)
    shadowed = direct_lighting(*args, ls, visibility=tr, specular=0.0)
    assert torch.isfinite(shadowed).all() and (shadowed >= 0).all()
    # the point under both Gaussians: (1 - 0.9) (1 - 0.5) of the light passes
    assert float(shadowed[0, 0] / lit[0, 0]) == pytest.approx(0.1 * 0.5, rel=1e-5)
    assert 0 < float(shadowed[1, 0] / lit[1, 0]) < 1
