"""core.pbr.render.indirect_light: the approximate diffuse bounce of the PBR pass."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.errors import ConfigError, NumericalError
from core.pbr.render import PBRSettings, indirect_light

UP = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)


def _blocked(_org, dirs, _t_max=None):
    return torch.zeros(dirs.shape[0], dtype=torch.float64)


def _open(_org, dirs, _t_max=None):
    return torch.ones(dirs.shape[0], dtype=torch.float64)


def _inputs(p=1, albedo=0.5, metallic=0.0, direct=(0.2, 0.3, 0.4)):
    pts = torch.zeros(p, 3, dtype=torch.float64)
    n = UP.expand(p, 3).clone()
    a = torch.full((p, 3), albedo, dtype=torch.float64)
    m = torch.full((p, 1), metallic, dtype=torch.float64)
    d = torch.tensor([direct], dtype=torch.float64).expand(p, 3).clone()
    return pts, n, a, m, d


def test_off_by_default_and_validated_naming_the_field():
    assert PBRSettings().indirect_bounces == 0
    with pytest.raises(ConfigError, match="indirect_bounces"):
        PBRSettings(indirect_bounces=-1)
    with pytest.raises(ConfigError, match="indirect_rays"):
        PBRSettings(indirect_rays=0)
    with pytest.raises(ConfigError, match="bounces"):
        indirect_light(*_inputs(), [_open], bounces=0)


def test_nothing_bounces_onto_an_open_point_nor_onto_a_zero_normal():
    pts, n, a, m, d = _inputs(p=3)
    assert torch.equal(indirect_light(pts, n, a, m, d, [_open]), torch.zeros(3, 3, dtype=torch.float64))
    n[1] = 0.0
    out = indirect_light(pts, n, a, m, d, [_blocked])
    assert torch.equal(out[1], torch.zeros(3, dtype=torch.float64)) and bool((out[0] > 0).all())


def test_a_closed_hemisphere_gets_the_bounce_series():
    # every direction blocked: L = rho * L_b * (1 + r + r^2), r = rho (one point: the mean is itself)
    pts, n, a, m, d = _inputs(albedo=0.5, metallic=0.2)
    rho = 0.5 * (1 - 0.2)
    out = indirect_light(pts, n, a, m, d, [_blocked], bounces=3)
    expect = rho * d[0] * (1 + rho + rho ** 2)
    assert torch.allclose(out[0], expect, rtol=1e-12)
    # energy: with rho < 1 the series stays below the closed form 1 / (1 - rho)
    many = indirect_light(pts, n, a, m, d, [_blocked], bounces=16)
    assert bool((many[0] < rho * d[0] / (1 - rho)).all())
    # a metal reflects no diffuse bounce
    assert torch.equal(indirect_light(*_inputs(metallic=1.0), [_blocked]), torch.zeros(1, 3, dtype=torch.float64))


def test_visibility_is_cosine_weighted():
    # a cap above 60 deg elevation (z > sin 60) blocked: under cosine sampling z = sqrt(1 - u),
    # so P(z > s) = 1 - s^2 = 0.25 of the cosine-weighted hemisphere is blocked
    s = math.sin(math.radians(60))

    def cap(_org, dirs, _t_max=None):
        return (dirs[:, 2] <= s).to(torch.float64)

    pts, n, a, m, d = _inputs(p=400, albedo=1.0)
    g = torch.Generator().manual_seed(1)
    out = indirect_light(pts, n, a, m, d, [cap], bounces=1, rays=64, generator=g)
    blocked = out[:, 0] / d[0, 0]  # rho = 1, one bounce: out = (1 - V) L_b
    assert abs(float(blocked.mean()) - (1 - s ** 2)) < 0.01  # 25600 rays: 3 standard errors ~ 0.008
    assert float(blocked.std()) > 0  # per point, not one number


def test_gradients_reach_the_albedo_and_the_direct_light_and_nan_is_caught():
    pts, n, a, m, d = _inputs(p=4)
    a.requires_grad_(True)
    d.requires_grad_(True)
    out = indirect_light(pts, n, a, m, d, [_blocked])
    out.sum().backward()
    assert a.grad is not None and bool(torch.isfinite(a.grad).all()) and float(a.grad.abs().sum()) > 0
    assert d.grad is not None and float(d.grad.abs().sum()) > 0
    bad = d.detach().clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NumericalError, match="indirect"):
        indirect_light(pts, n, a.detach(), m, bad, [_blocked])


def test_the_pass_adds_light_under_a_roof_only():
    # G-buffers of ground at z = 0, a roof of Gaussians over x < 0 at z = 1: the shaded ground
    # under the roof gets the bounce, the open ground little or none
    from core.gaussians import Gaussians
    from core.pbr import EnvironmentMap, GaussianTracer
    from core.pbr.render import render_pbr

    w = 16
    roof_xy = np.array([[x, y] for x in np.arange(-6.0, 0.0, 0.2) for y in np.arange(-4.0, 4.0, 0.2)])
    k = len(roof_xy)
    one = torch.ones(k, 1, dtype=torch.float64)
    roof = Gaussians.from_activated(torch.from_numpy(np.c_[roof_xy, np.ones(k)]), torch.tensor([[1.0, 0, 0, 0]]).expand(k, 4).double(),
                                    torch.tensor([[0.15, 0.15, 0.02]], dtype=torch.float64).expand(k, 3), one * 0.99,
                                    one.expand(k, 3) * 0.5, torch.tensor([[0.0, 0, -1]]).expand(k, 3).double(),
                                    one.expand(k, 3) * 0.5, one * 0.9, one * 0.0)
    tracer = GaussianTracer.from_gaussians(roof)
    h = 1
    gb = {"opacity": torch.ones(h, w, 1, dtype=torch.float64),
          "normal": torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(h, w, 3).clone(),
          "albedo": torch.full((h, w, 3), 0.5, dtype=torch.float64),
          "roughness": torch.full((h, w, 1), 0.9, dtype=torch.float64),
          "metallic": torch.zeros(h, w, 1, dtype=torch.float64)}
    # a camera 3 m above the ground looking straight down: pixel i sees (xs[i], 0, 0)
    from core.camera import Camera

    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    c2w[:3, 3] = [0.0, 0.0, 3.0]
    f = 4.0
    cam = Camera.from_intrinsics(c2w, f, f, w / 2, 0.5, w, h)
    dirs = torch.from_numpy(cam.ray_directions()).reshape(h, w, 3)
    gb["depth"] = (3.0 / (-dirs[..., 2:3])) * (-dirs[..., 2:3])  # z-depth 3 m everywhere
    env = EnvironmentMap.constant(1.0, 16, 32)
    base = PBRSettings(rays_per_pixel=32, backend="torch", threads=1, normal_offset=0.02)
    off = render_pbr(gb, cam, env, settings=base, tracers=(tracer,), generator=torch.Generator().manual_seed(0))
    on = render_pbr(gb, cam, env, settings=PBRSettings(**{**base.__dict__, "indirect_bounces": 2, "indirect_rays": 256}),
                    tracers=(tracer,),
                    generator=torch.Generator().manual_seed(0))
    from core.pbr.render import shading_inputs

    gx = shading_inputs(gb, cam).points[:, 0]  # the ground x each pixel sees
    assert float(gx.min()) < -3.0 and float(gx.max()) > 3.0
    under, open_ = gx < -1.0, gx > 2.0
    add = (on.hdr - off.hdr)[0, :, 0]
    # (the open ground near the roof's edge still sees it low on its horizon: a little bounce)
    assert bool((add[under] > 0).all()) and float(add[open_].abs().max()) < 0.2 * float(add[under].mean())
    assert float(add[gx > 4.0].abs().max()) < 0.02 * float(add[under].mean())
    # the same roof as an edited object (a tracer built with objects=True): it still blocks the
    # direct light, but the bounce does not see it (an inserted car's shadowed side adds nothing)
    obj = GaussianTracer.from_gaussians(roof, objects=True)
    on_obj = render_pbr(gb, cam, env, settings=PBRSettings(**{**base.__dict__, "indirect_bounces": 2,
                                                               "indirect_rays": 256}),
                        tracers=(obj,), generator=torch.Generator().manual_seed(0))
    off_obj = render_pbr(gb, cam, env, settings=base, tracers=(obj,), generator=torch.Generator().manual_seed(0))
    assert float((off.hdr - off_obj.hdr).abs().max()) < 0.05 * float(off.hdr.mean())  # blocks the light alike
    np.testing.assert_allclose(on_obj.hdr.numpy(), off_obj.hdr.numpy(), atol=1e-9)


# --- the specular bounce (indirect_specular_rays) ---------------------------------------------

def _view(p, theta_deg):
    t = math.radians(theta_deg)
    return torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64).expand(p, 3).clone()


def _directional_albedo(albedo, roughness, metallic, theta_deg, n_theta=400, n_phi=400):
    """Reference twin: the specular lobe's directional albedo int f_s (n.wi) dwi by midpoint
    quadrature over the hemisphere (no sampling), channel 0."""
    from core.pbr.brdf import specular_lobe
    th = (torch.arange(n_theta, dtype=torch.float64) + 0.5) * (math.pi / 2) / n_theta
    ph = (torch.arange(n_phi, dtype=torch.float64) + 0.5) * 2 * math.pi / n_phi
    tt, pp = torch.meshgrid(th, ph, indexing="ij")
    wi = torch.stack([tt.sin() * pp.cos(), tt.sin() * pp.sin(), tt.cos()], -1).reshape(-1, 3)
    k = wi.shape[0]
    f = specular_lobe(UP.expand(k, 3), wi, _view(k, theta_deg), torch.full((k, 3), albedo, dtype=torch.float64),
                      torch.full((k, 1), roughness, dtype=torch.float64),
                      torch.full((k, 1), metallic, dtype=torch.float64), "smith")
    dw = (math.pi / 2 / n_theta) * (2 * math.pi / n_phi) * tt.sin().reshape(-1)
    return float((f[:, 0] * wi[:, 2] * dw).sum())


@pytest.mark.parametrize("albedo,roughness,metallic,theta", [(1.0, 0.3, 1.0, 30.0), (0.8, 0.6, 1.0, 70.0),
                                                             (0.05, 0.35, 0.0, 60.0)])
def test_specular_bounce_of_a_closed_hemisphere_is_the_lobe_directional_albedo(albedo, roughness, metallic, theta):
    # every direction blocked, one bounce, L_b = 1: the specular part is the lobe's directional
    # albedo (GGX samples against a quadrature of the same lobe), the diffuse part rho
    p = 3000
    pts, n, a, m, _ = _inputs(p=p, albedo=albedo, metallic=metallic)
    d = torch.ones(p, 3, dtype=torch.float64)
    r = torch.full((p, 1), roughness, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    out = indirect_light(pts, n, a, m, d, [_blocked], bounces=1, wo=_view(p, theta), roughness=r,
                         specular_rays=8, generator=g)
    spec = float(out[:, 0].mean()) - albedo * (1 - metallic)
    ref = _directional_albedo(albedo, roughness, metallic, theta)
    assert abs(spec - ref) < 0.01 * max(ref, 0.05), (spec, ref)
    assert spec <= 1.0 + 1e-9  # energy: the lobe reflects at most what arrives


def test_specular_bounce_needs_blocked_directions_and_its_inputs():
    p = 50
    pts, n, a, m, d = _inputs(p=p, albedo=0.9, metallic=1.0)
    r = torch.full((p, 1), 0.2, dtype=torch.float64)
    wo = _view(p, 40.0)
    assert torch.equal(indirect_light(pts, n, a, m, d, [_open], wo=wo, roughness=r, specular_rays=4),
                       torch.zeros(p, 3, dtype=torch.float64))
    # off (0 rays): a metal gets nothing, as before
    assert torch.equal(indirect_light(pts, n, a, m, d, [_blocked], wo=wo, roughness=r, specular_rays=0),
                       torch.zeros(p, 3, dtype=torch.float64))
    assert bool((indirect_light(pts, n, a, m, d, [_blocked], wo=wo, roughness=r, specular_rays=4) > 0).all())
    with pytest.raises(Exception, match="wo, roughness"):
        indirect_light(pts, n, a, m, d, [_blocked], specular_rays=4)
    with pytest.raises(ConfigError, match="specular_rays"):
        indirect_light(pts, n, a, m, d, [_blocked], wo=wo, roughness=r, specular_rays=-1)
    with pytest.raises(ConfigError, match="indirect_specular_rays"):
        PBRSettings(indirect_specular_rays=-2)


def test_specular_bounce_gradients_reach_albedo_metallic_and_roughness():
    p = 16
    pts, n, a, m, d = _inputs(p=p, albedo=0.6, metallic=0.5)
    r = torch.full((p, 1), 0.3, dtype=torch.float64)
    for t in (a, m, r):
        t.requires_grad_(True)
    out = indirect_light(pts, n, a, m, d, [_blocked], wo=_view(p, 50.0), roughness=r, specular_rays=4,
                         generator=torch.Generator().manual_seed(0))
    out.sum().backward()
    for name, t in (("albedo", a), ("metallic", m), ("roughness", r)):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all()) and float(t.grad.abs().sum()) > 0, name
