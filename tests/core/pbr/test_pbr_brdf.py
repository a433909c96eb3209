"""The paper's Cook-Torrance BRDF: formula, reciprocity, energy, samplers vs their pdfs,
degenerate inputs (values and gradients), property-based finiteness."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from core.numerics import GGX_ALPHA_MIN
from core.pbr import brdf
from core.pbr.brdf import (cook_torrance, dot, ggx_alpha, ggx_d, pdf_brdf, pdf_cosine, pdf_ggx_vndf, sample_brdf,
                           sample_cosine, sample_ggx_vndf)
from chi_square import chi_square_pvalue  # tests/chi_square.py

D64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _paper_reference(n, wi, wo, a, r, m):
    """A literal numpy transcription of the supplement's formulas (for one sample)."""
    n, wi, wo = _unit(n), _unit(wi), _unit(wo)
    nwi, nwo = n @ wi, n @ wo
    if nwi <= 0 or nwo <= 0:
        return np.zeros(3)
    h = _unit(wi + wo)
    alpha = max(r * r, GGX_ALPHA_MIN)
    d = alpha ** 2 / (math.pi * ((n @ h) ** 2 * (alpha ** 2 - 1) + 1) ** 2)
    k = (r + 1) ** 2 / 8
    g1 = lambda c: c / (c * (1 - k) + k)  # noqa: E731
    f0 = 0.04 * (1 - m) + m * np.asarray(a)
    f = f0 + (1 - f0) * (1 - wo @ h) ** 5
    return (1 - m) * np.asarray(a) / math.pi + d * g1(nwi) * g1(nwo) * f / (4 * nwi * nwo)


def _t(x, dtype=D64):
    return torch.as_tensor(np.asarray(x, np.float64), dtype=dtype)


def test_matches_a_literal_transcription_of_the_paper():
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = _unit(rng.normal(size=3))
        wi, wo = rng.normal(size=3), rng.normal(size=3)
        wi = wi if n @ wi > 0 else -wi
        wo = wo if n @ wo > 0 else -wo
        a = rng.uniform(0, 1, 3)
        r, m = rng.uniform(0.05, 1), rng.uniform(0, 1)
        got = cook_torrance(_t(n), _t(wi), _t(wo), _t(a), _t([r]), _t([m])).numpy()
        np.testing.assert_allclose(got, _paper_reference(n, wi, wo, a, r, m), rtol=1e-9, atol=1e-12)


def test_alpha_is_roughness_squared_and_d_is_normalised():
    r = torch.tensor([[0.0], [0.01], [0.2], [0.5], [1.0]], dtype=D64)
    np.testing.assert_allclose(ggx_alpha(r).numpy()[:, 0], [GGX_ALPHA_MIN, GGX_ALPHA_MIN, 0.04, 0.25, 1.0])
    # projected-area normalisation: integral of D(h) (n.h) over the hemisphere of h is 1
    from scipy.integrate import quad

    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    for alpha in (0.04, 0.25, 1.0):
        def integrand(c):
            h = torch.tensor([[math.sqrt(max(0.0, 1 - c * c)), 0.0, c]], dtype=D64)
            return float(ggx_d(n, h, torch.tensor([[alpha]], dtype=D64))) * c

        integral = 2 * math.pi * quad(integrand, 0.0, 1.0, points=[1 - alpha, 1 - alpha ** 2], limit=200)[0]
        assert integral == pytest.approx(1.0, rel=1e-6), alpha


def test_reciprocity():
    g = _gen(1)
    n = 4000
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D64), dim=-1)
    wi = torch.randn(n, 3, generator=g, dtype=D64)
    wo = torch.randn(n, 3, generator=g, dtype=D64)
    a = torch.rand(n, 3, generator=g, dtype=D64)
    r = torch.rand(n, 1, generator=g, dtype=D64)
    m = torch.rand(n, 1, generator=g, dtype=D64)
    f1 = cook_torrance(nrm, wi, wo, a, r, m)
    f2 = cook_torrance(nrm, wo, wi, a, r, m)
    np.testing.assert_allclose(f1.numpy(), f2.numpy(), rtol=1e-10, atol=1e-14)
    assert (f1 > 0).any()


def _directional_albedo(configs, n_samples=8_000, seed=0, specular=1.0, diffuse="lambert", masking="schlick"):
    """Estimates (and standard errors) of the integral of f cos over wi for fixed wo, one per
    config ``(roughness, metallic, albedo, theta_o)``, with the mixture sampler; one batch."""
    g = _gen(seed)
    c = torch.tensor(configs, dtype=D64)  # [C, 4]
    k = c.shape[0]
    rep = lambda x: x.repeat_interleave(n_samples, 0)  # noqa: E731
    th = rep(c[:, 3:4])
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64).expand(k * n_samples, 3)
    wo = torch.cat([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
    al = rep(c[:, 2:3]).expand(-1, 3)
    rr, mm = rep(c[:, 0:1]), rep(c[:, 1:2])
    wi, pdf = sample_brdf(n, wo, al, rr, mm, torch.rand(k * n_samples, 3, generator=g, dtype=D64), specular)
    f = cook_torrance(n, wi, wo, al, rr, mm, specular, diffuse, masking)
    v = torch.where(pdf > 0, f[:, :1] * dot(n, wi).clamp_min(0) / pdf.clamp_min(1e-300), torch.zeros_like(pdf))
    v = v.reshape(k, n_samples)
    return v.mean(1).numpy(), (v.std(1) / math.sqrt(n_samples)).numpy()


ROUGH = (0.0, 0.1, 0.3, 0.6, 1.0)
THETAS = (0.0, 0.8, 1.3, 1.55)


def test_white_furnace_metal_and_specular_lobe_never_exceed_one():
    """M = 1, A = 1 (F0 = 1): the microfacet lobe alone. Energy <= 1.01 for every roughness."""
    configs = [(r, 1.0, 1.0, th) for r in ROUGH for th in THETAS]
    e, se = _directional_albedo(configs, seed=1)
    assert (e <= 1.01).all(), list(zip(configs, e))
    assert e.max() > 0.9  # not trivially dark: smooth metal at normal incidence reflects ~1
    assert (se < 0.01).all()


def test_energy_bounded_on_roughness_metallic_grid():
    """The full BRDF reflects <= 1.01 on a grid of roughness x metallic x view angle for albedo
    0.85 (about the brightest real albedo). With A = 1 the paper's model (diffuse not weighted by
    1 - F) exceeds 1 for dielectrics by its specular albedo: pinned below as a known property."""
    configs = [(r, m, 0.85, th) for r in ROUGH for m in (0.0, 0.5, 1.0) for th in THETAS]
    e, se = _directional_albedo(configs, seed=2)
    assert (e <= 1.01).all(), [(c, x) for c, x in zip(configs, e) if x > 1.01]
    assert (se < 0.01).all()
    excess, _ = _directional_albedo([(r, 0.0, 1.0, 1.3) for r in ROUGH], seed=3)
    assert ((excess > 1.0) & (excess < 1.16)).all(), excess


def test_white_lambertian_furnace_is_one():
    """specular = 0 is the pure Lambertian of ground-truth "lambert" materials: white albedo
    under a constant environment of 1 reflects exactly 1 (cosine sampling has zero variance)."""
    for th in (0.0, 1.0, 1.5):
        e, se = _directional_albedo([(1.0, 0.0, 1.0, th)], specular=0.0, n_samples=2000)
        assert e[0] == pytest.approx(1.0, abs=1e-9) and se[0] < 1e-9


def _hemisphere_bins_test(sample_fn, pdf_fn, n=60_000, nt=12, nphi=24, seed=0):
    """Chi-square of directions (over the whole sphere, binned in cos(theta) x phi) against the
    integral of the pdf over each bin (midpoint rule on 8x8 sub-cells)."""
    wi = sample_fn(n, _gen(seed))
    assert torch.isfinite(wi).all()
    z = wi[:, 2].numpy()
    phi = np.mod(np.arctan2(wi[:, 1].numpy(), wi[:, 0].numpy()), 2 * math.pi)
    bz = np.clip(((z + 1) / 2 * nt).astype(int), 0, nt - 1)
    bp = np.clip((phi / (2 * math.pi) * nphi).astype(int), 0, nphi - 1)
    observed = np.bincount(bz * nphi + bp, minlength=nt * nphi)
    sub = 8
    zc = -1 + (np.arange(nt * sub) + 0.5) * 2 / (nt * sub)
    pc = (np.arange(nphi * sub) + 0.5) * 2 * math.pi / (nphi * sub)
    zz, pp = np.meshgrid(zc, pc, indexing="ij")
    s = np.sqrt(1 - zz ** 2)
    dirs = torch.from_numpy(np.stack([s * np.cos(pp), s * np.sin(pp), zz], -1).reshape(-1, 3))
    p = pdf_fn(dirs).numpy().reshape(nt * sub, nphi * sub)
    cell = (2 / (nt * sub)) * (2 * math.pi / (nphi * sub))
    expected = p.reshape(nt, sub, nphi, sub).sum((1, 3)) * cell
    total = expected.sum()
    assert total == pytest.approx(1.0, abs=0.01)
    return chi_square_pvalue(observed, expected.ravel() * n / total)


@pytest.mark.parametrize("rough,theta", [(0.6, 0.9), (0.8, 0.2), (1.0, 1.4)])
def test_vndf_sampler_chi_square(rough, theta):
    wo1 = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=D64)
    n1 = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    r1 = torch.tensor([[rough]], dtype=D64)

    def sample(n, g):
        return sample_ggx_vndf(n1.expand(n, 3), wo1.expand(n, 3), r1.expand(n, 1), torch.rand(n, 2, generator=g, dtype=D64))

    def pdf(d):
        m = d.shape[0]
        return pdf_ggx_vndf(n1.expand(m, 3), d, wo1.expand(m, 3), r1.expand(m, 1))[:, 0]

    assert _hemisphere_bins_test(sample, pdf) > 1e-3


def test_vndf_sampler_chi_square_in_a_tilted_frame():
    """The same with a normal that is not +z (tests the tangent frame)."""
    nrm = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=D64), dim=-1)
    wo1 = torch.nn.functional.normalize(torch.tensor([[0.9, 0.1, 0.4]], dtype=D64), dim=-1)
    r1 = torch.tensor([[0.7]], dtype=D64)

    def sample(n, g):
        return sample_ggx_vndf(nrm.expand(n, 3), wo1.expand(n, 3), r1.expand(n, 1), torch.rand(n, 2, generator=g, dtype=D64))

    def pdf(d):
        m = d.shape[0]
        return pdf_ggx_vndf(nrm.expand(m, 3), d, wo1.expand(m, 3), r1.expand(m, 1))[:, 0]

    assert _hemisphere_bins_test(sample, pdf, seed=3) > 1e-3


def test_mixture_and_cosine_samplers_chi_square():
    nrm = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    wo1 = torch.nn.functional.normalize(torch.tensor([[0.5, 0.2, 0.8]], dtype=D64), dim=-1)
    a1 = torch.tensor([[0.6, 0.5, 0.4]], dtype=D64)
    r1 = torch.tensor([[0.7]], dtype=D64)
    m1 = torch.tensor([[0.3]], dtype=D64)

    def sample(n, g):
        wi, _ = sample_brdf(nrm.expand(n, 3), wo1.expand(n, 3), a1.expand(n, 3), r1.expand(n, 1), m1.expand(n, 1),
                            torch.rand(n, 3, generator=g, dtype=D64))
        return wi

    def pdf(d):
        m = d.shape[0]
        return pdf_brdf(nrm.expand(m, 3), d, wo1.expand(m, 3), a1.expand(m, 3), r1.expand(m, 1), m1.expand(m, 1))[:, 0]

    assert _hemisphere_bins_test(sample, pdf, seed=4) > 1e-3

    def sample_c(n, g):
        return sample_cosine(nrm.expand(n, 3), torch.rand(n, 2, generator=g, dtype=D64))

    assert _hemisphere_bins_test(sample_c, lambda d: pdf_cosine(nrm.expand(d.shape[0], 3), d)[:, 0], seed=5) > 1e-3


def test_sample_brdf_pdf_matches_pdf_brdf():
    g = _gen(6)
    n = 2000
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D64), dim=-1)
    wo = torch.where(dot(nrm, wo) < 0, -wo, wo)
    a, r, m = (torch.rand(n, 3, generator=g, dtype=D64), torch.rand(n, 1, generator=g, dtype=D64),
               torch.rand(n, 1, generator=g, dtype=D64))
    wi, p = sample_brdf(nrm, wo, a, r, m, torch.rand(n, 3, generator=g, dtype=D64))
    np.testing.assert_allclose(p.numpy(), pdf_brdf(nrm, wi, wo, a, r, m).numpy(), rtol=1e-9)
    assert torch.isfinite(p).all() and (p >= 0).all()


# ---------------------------------------------------------------------------------------------
# degenerate inputs
# ---------------------------------------------------------------------------------------------

def _degenerate_batch(dtype=D64):
    z = [0.0, 0.0, 1.0]
    rows = []
    for r in (0.0, 1e-4, 0.5, 1.0):
        for m in (0.0, 1.0):
            for n, wi, wo in (
                (z, z, z),  # all aligned (GGX peak, alpha floor)
                (z, [1.0, 0.0, 0.0], z),  # grazing light, n.wi = 0
                (z, [1.0, 0.0, 1e-7], [-1.0, 0.0, 1e-7]),  # both grazing from above
                (z, [1.0, 0.0, -1e-7], [0.0, 1.0, 1e-7]),  # just below / above
                (z, [0.3, 0.0, 0.9], [-0.3, 0.0, 0.9]),  # mirror pair
                (z, [0.3, 0.1, 0.9], [-0.3, -0.1, -0.9]),  # wi = -wo (zero half vector)
                ([0.0, 0.0, 0.0], z, z),  # zero normal
                ([0.0, 0.0, -1.0], z, z),  # normal facing away
                (z, [0.0, 0.0, 0.0], z),  # zero light direction
            ):
                rows.append((n, wi, wo, r, m))
    n = torch.tensor([r[0] for r in rows], dtype=dtype)
    wi = torch.tensor([r[1] for r in rows], dtype=dtype)
    wo = torch.tensor([r[2] for r in rows], dtype=dtype)
    rough = torch.tensor([[r[3]] for r in rows], dtype=dtype)
    metal = torch.tensor([[r[4]] for r in rows], dtype=dtype)
    albedo = torch.full((len(rows), 3), 0.7, dtype=dtype)
    return n, wi, wo, albedo, rough, metal


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_inputs_give_finite_values_and_gradients(dtype):
    tensors = [t.clone().requires_grad_(True) for t in _degenerate_batch(dtype)]
    n, wi, wo, a, r, m = tensors
    f = cook_torrance(n, wi, wo, a, r, m)
    assert torch.isfinite(f).all() and (f >= 0).all()
    f.sum().backward()
    for name, t in zip(("n", "wi", "wo", "albedo", "roughness", "metallic"), tensors):
        assert torch.isfinite(t.grad).all(), name
    # zero normal and normal facing away reflect nothing
    assert (f[6::9] == 0).all() and (f[7::9] == 0).all()
    # samplers and pdfs on the same inputs
    u = torch.rand(n.shape[0], 3, generator=_gen(7), dtype=dtype)
    wi_s, p = sample_brdf(n.detach(), wo.detach(), a.detach(), r.detach(), m.detach(), u)
    assert torch.isfinite(wi_s).all() and torch.isfinite(p).all() and (p >= 0).all()
    p2 = pdf_brdf(n.detach(), wi.detach(), wo.detach(), a.detach(), r.detach(), m.detach())
    assert torch.isfinite(p2).all() and (p2 >= 0).all()


def test_roughness_zero_peak_is_finite_and_bounded():
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float32)
    f = cook_torrance(n, n, n, torch.ones(1, 3), torch.zeros(1, 1), torch.ones(1, 1))
    # D peak 1/(pi alpha_min^2), G/(4 c c) = 1/4 at normal incidence, F = 1
    assert float(f[0, 0]) == pytest.approx(1.0 / (math.pi * GGX_ALPHA_MIN ** 2) / 4.0, rel=1e-4)


def test_face_forward_flips_back_facing_normals():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    wo = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.1, 1.0]])
    np.testing.assert_array_equal(brdf.face_forward(n, wo).numpy(), [[0, 0, -1.0], [0, 0, 1.0]])


vec = st.lists(st.floats(-1e3, 1e3, allow_nan=False, allow_subnormal=False), min_size=3, max_size=3)
unit_interval = st.floats(0.0, 1.0)


@settings(max_examples=150, deadline=None)
@given(n=vec, wi=vec, wo=vec, a=st.lists(unit_interval, min_size=3, max_size=3), r=unit_interval, m=unit_interval,
       u=st.lists(st.floats(0.0, 0.999999), min_size=3, max_size=3))
def test_property_random_inputs_finite_and_non_negative(n, wi, wo, a, r, m, u):
    t = lambda x: torch.tensor([x], dtype=torch.float32)  # noqa: E731
    args = [t(n).requires_grad_(), t(wi).requires_grad_(), t(wo).requires_grad_(), t(a).requires_grad_(),
            t([r]).requires_grad_(), t([m]).requires_grad_()]
    f = cook_torrance(*args)
    assert torch.isfinite(f).all() and (f >= 0).all()
    f.sum().backward()
    assert all(torch.isfinite(x.grad).all() for x in args)
    wi_s, p = sample_brdf(args[0].detach(), args[2].detach(), args[3].detach(), args[4].detach(), args[5].detach(), t(u))
    assert torch.isfinite(wi_s).all() and torch.isfinite(p).all() and (p >= 0).all()


# --- Burley's diffuse lobe (diffuse="burley") ----------------------------------------------------

def _dir(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


def test_burley_diffuse_matches_mitsubas_principled_bsdf():
    """The independent reference: Mitsuba 3's ``principled`` BSDF with ``specular`` 0 (no
    specular lobe: its dielectric Fresnel is 0 at eta 1) is Burley's diffuse alone. Ours with the
    microfacet term off must agree on a grid of roughness x light x view angles."""
    from core.synth.mitsuba_backend import mitsuba

    mi = mitsuba()
    ours, ref = [], []
    for rough in (0.0, 0.3, 0.84, 1.0):
        bsdf = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": [0.6, 0.4, 0.2]},
                             "roughness": rough, "metallic": 0.0, "specular": 0.0})
        for tho in (0, 30, 60, 80, 88):
            for thi, phi in ((10, 0), (42, 90), (42, 180), (70, 180), (70, 0), (85, 45)):
                wi, wo = _dir(thi, phi), _dir(tho, 180)
                si = mi.SurfaceInteraction3f()
                si.wi = mi.Vector3f(*wo)  # Mitsuba's wi is our view direction (both point away)
                si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
                v = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wi)))
                ref.append(v / wi[2])  # Mitsuba returns f cos(theta_light)
                ours.append(cook_torrance(_t([0, 0, 1]), _t(wi), _t(wo), _t([0.6, 0.4, 0.2]), _t([rough]),
                                          _t([0.0]), 0.0, "burley").numpy())
    np.testing.assert_allclose(np.array(ours), np.array(ref), rtol=1e-5)
    lam = cook_torrance(_t([0, 0, 1]), _t(_dir(42, 180)), _t(_dir(80, 180)), _t([0.6, 0.4, 0.2]), _t([0.84]),
                        _t([0.0]), 0.0)
    bur = cook_torrance(_t([0, 0, 1]), _t(_dir(42, 180)), _t(_dir(80, 180)), _t([0.6, 0.4, 0.2]), _t([0.84]),
                        _t([0.0]), 0.0, "burley")
    assert float(bur[0] / lam[0]) > 1.3  # a rough road at a grazing view, lit from behind: retro-reflection


def test_burley_factor_is_one_head_on_and_symmetric():
    f = brdf.burley_diffuse_factor(_t([1.0]), _t([1.0]), _t([1.0]), _t([0.7]))
    assert float(f) == pytest.approx(1.0, abs=1e-12)
    g = _gen(3)
    a, b, c, r = (torch.rand(500, 1, generator=g, dtype=D64) for _ in range(4))
    np.testing.assert_allclose(brdf.burley_diffuse_factor(a, b, c, r).numpy(),
                               brdf.burley_diffuse_factor(b, a, c, r).numpy(), rtol=1e-12)
    # smooth surfaces at grazing angles reflect less than Lambert (the Fresnel factors)
    assert float(brdf.burley_diffuse_factor(_t([0.1]), _t([0.1]), _t([0.5]), _t([0.0]))) < 0.5


def test_burley_reciprocity_and_gradients():
    g = _gen(11)
    m = 64
    n = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=D64), dim=-1)
    wi = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=D64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=D64), dim=-1)
    wi = torch.where(dot(n, wi) < 0, -wi, wi)
    wo = torch.where(dot(n, wo) < 0, -wo, wo)
    a = torch.rand(m, 3, generator=g, dtype=D64)
    r = torch.rand(m, 1, generator=g, dtype=D64) * 0.8 + 0.1
    mm = torch.rand(m, 1, generator=g, dtype=D64)
    f1 = cook_torrance(n, wi, wo, a, r, mm, 1.0, "burley")
    f2 = cook_torrance(n, wo, wi, a, r, mm, 1.0, "burley")
    # the Fresnel term of the specular lobe uses wo.h = wi.h, so the whole BRDF is reciprocal
    np.testing.assert_allclose(f1.numpy(), f2.numpy(), rtol=1e-10)
    a.requires_grad_(True)
    r.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a_, r_: cook_torrance(n, wi, wo, a_, r_, mm, 1.0, "burley"), (a, r))


def test_burley_energy_is_pinned():
    """Burley's diffuse is not energy-bounded: rough white surfaces at grazing view reflect more
    than they receive (retro-reflection). Pinned: <= 1.01 up to 45 deg for every roughness, and
    the excess at R = 1, 75 deg stays below 1.2 (a street's road is seen at 70-86 deg)."""
    configs = [(r, 0.0, 1.0, th) for r in ROUGH for th in (0.0, 0.8)]
    e, se = _directional_albedo(configs, seed=5, specular=0.0, diffuse="burley")
    assert (e <= 1.04).all() and (se < 0.01).all(), list(zip(configs, e))
    excess, _ = _directional_albedo([(1.0, 0.0, 1.0, 1.3)], seed=6, specular=0.0, diffuse="burley")
    assert 1.1 < excess[0] < 1.2, excess
    lam, _ = _directional_albedo([(1.0, 0.0, 1.0, 1.3)], seed=6, specular=0.0)
    assert lam[0] == pytest.approx(1.0, abs=0.02)


def test_unknown_diffuse_model_is_a_config_error():
    from core.errors import ConfigError
    from core.pbr.render import PBRSettings

    with pytest.raises(ConfigError, match="diffuse"):
        cook_torrance(_t([0, 0, 1]), _t([0, 0, 1]), _t([0, 0, 1]), _t([0.5] * 3), _t([0.5]), _t([0.0]), 1.0, "oren")
    with pytest.raises(ConfigError, match="diffuse"):
        PBRSettings(diffuse="oren")


# --- the exact Smith masking term (masking="smith") -------------------------------------------------

def test_smith_masking_matches_mitsubas_principled_metal_exactly():
    """Metals (M = 1: Schlick Fresnel of the base colour in both) isolate D and G: with the exact
    Smith term ours equals Mitsuba's principled evaluation; the paper's Schlick-Smith is several
    times darker at grazing views."""
    from core.synth.mitsuba_backend import mitsuba

    mi = mitsuba()
    ours, ref, paper = [], [], []
    for rough in (0.05, 0.3, 0.7):
        bsdf = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": [0.9, 0.6, 0.3]},
                             "roughness": rough, "metallic": 1.0})
        for tho in (0, 30, 60, 80, 88):
            for thi, phi in ((tho, 0), (min(tho + 5, 89), 0), (42, 90), (70, 180), (20, 0)):
                wi, wo = _dir(thi, phi), _dir(tho, 180)
                si = mi.SurfaceInteraction3f()
                si.wi = mi.Vector3f(*wo)
                si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
                ref.append(np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wi))) / wi[2])
                args = (_t([0, 0, 1]), _t(wi), _t(wo), _t([0.9, 0.6, 0.3]), _t([rough]), _t([1.0]), 1.0, "burley")
                ours.append(cook_torrance(*args, "smith").numpy())
                paper.append(cook_torrance(*args).numpy())
    ref, ours, paper = np.array(ref), np.array(ours), np.array(paper)
    np.testing.assert_allclose(ours, ref, rtol=2e-4, atol=1e-7)
    assert (ref / np.maximum(paper, 1e-12)).max() > 2.0  # what the paper's term loses at grazing


def test_smith_masking_is_finite_bounded_and_differentiable_at_the_extremes():
    g = _gen(21)
    m = 400
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64).expand(m, 3)
    th = torch.rand(m, 2, generator=g, dtype=D64) * (math.pi / 2)  # up to exactly grazing
    th[:8] = math.pi / 2
    wi = torch.stack([torch.sin(th[:, 0]), torch.zeros(m, dtype=D64), torch.cos(th[:, 0])], -1)
    wo = torch.stack([-torch.sin(th[:, 1]), torch.zeros(m, dtype=D64), torch.cos(th[:, 1])], -1)
    a = torch.rand(m, 3, generator=g, dtype=D64).requires_grad_(True)
    r = torch.rand(m, 1, generator=g, dtype=D64)
    r[:50] = 0.0
    r.requires_grad_(True)
    mm = torch.rand(m, 1, generator=g, dtype=D64)
    f = cook_torrance(n, wi, wo, a, r, mm, 1.0, "burley", "smith")
    assert torch.isfinite(f).all() and (f >= 0).all()
    f.sum().backward()
    assert torch.isfinite(a.grad).all() and torch.isfinite(r.grad).all()
    # the white furnace of the specular lobe alone (M = 1, A = 1) stays <= 1.01 (G <= 1)
    e, se = _directional_albedo([(rr, 1.0, 1.0, tt) for rr in ROUGH for tt in THETAS], seed=9, masking="smith")
    assert (e <= 1.01).all() and (se < 0.01).all(), e


def test_unknown_masking_model_is_a_config_error():
    from core.errors import ConfigError
    from core.pbr.render import PBRSettings

    with pytest.raises(ConfigError, match="masking"):
        cook_torrance(_t([0, 0, 1]), _t([0, 0, 1]), _t([0, 0, 1]), _t([0.5] * 3), _t([0.5]), _t([0.0]), 1.0,
                      "lambert", "beckmann")
    with pytest.raises(ConfigError, match="masking"):
        PBRSettings(masking="beckmann")
