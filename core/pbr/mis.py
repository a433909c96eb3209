"""Monte Carlo estimator of the reflected radiance ``L_r`` of the paper's Eq. 3, for a batch of
shading points, with environment sampling (the paper) or multiple importance sampling.

    L_r(x, wo) = integral over the sphere of E(wi) V(x, wi) f(x, wi, wo) max(n.wi, 0) dwi

Strategies (``strategy``)
    ``"env"``   all ``n_rays`` from :meth:`EnvironmentMap.sample` (the paper's estimator).
    ``"brdf"``  all from the BRDF lobe mixture (:func:`core.pbr.brdf.sample_brdf`).
    ``"mis"``   ``ceil(n_rays / 2)`` environment + ``floor(n_rays / 2)`` BRDF samples combined with
                Veach's power heuristic (beta = 2) in its multi-sample form::

                    L_r = sum_s sum_j w_s(x_sj) g(x_sj) / (n_s p_s(x_sj)),
                    w_s = (n_s p_s)^2 / sum_t (n_t p_t)^2

                written as ``g * n_s p_s / sum_t (n_t p_t)^2`` (one division, no 0/0).

Inputs (batch of P points, world frame, metres)
    points ``[P, 3]``, normals ``[P, 3]`` (need not be unit; a zero normal reflects nothing),
    wo ``[P, 3]`` toward the viewer, albedo ``[P, 3]``, roughness and metallic ``[P, 1]`` or
    ``[P]``. Units: radiance in the units of the map.

Visibility
    ``visibility(origins [M, 3], dirs [M, 3], t_max=None) -> [M]`` in [0, 1] (e.g. a
    :class:`core.pbr.visibility.GaussianTracer`); None = everything visible. Shadow rays are cast
    only for samples that can contribute (``n.wi > 0``, ``f > 0``, radiance > 0), from
    ``points + normal_offset * n``.

Differentiability
    The result is differentiable w.r.t. the environment map parameter (through the radiance of
    each sample), the materials and the normals (through f and the cosine). Sample directions,
    pdfs, MIS weights and visibility are constants of the estimator (unbiased gradients for a
    fixed sampling density).

Memory and speed: points are processed in chunks of ``chunk_points``.
"""

from __future__ import annotations

from typing import Callable

import torch

from core.errors import ConfigError, ShapeError
from core.numerics import require_finite, safe_normalize
from core.pbr.brdf import check_brdf_model, cook_torrance, dot, pdf_brdf, sample_brdf
from core.pbr.envmap import EnvironmentMap

Visibility = Callable[..., torch.Tensor]
STRATEGIES = ("env", "brdf", "mis")


def check_shading_inputs(points, normals, wo, albedo, roughness, metallic):
    """Validate and reshape shading inputs; returns them with roughness/metallic as ``[P, 1]``."""
    def t(x, name, width):
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise ShapeError(f"{name}: expected a floating torch tensor")
        if width == 1 and x.dim() == 1:
            x = x[:, None]
        if x.dim() != 2 or x.shape[1] != width:
            raise ShapeError(f"{name}: expected shape [P, {width}], got {list(x.shape)}")
        require_finite(x.detach(), name)
        return x

    points = t(points, "points", 3)
    p = points.shape[0]
    out = [points]
    for x, name, w in ((normals, "normals", 3), (wo, "wo", 3), (albedo, "albedo", 3),
                       (roughness, "roughness", 1), (metallic, "metallic", 1)):
        x = t(x, name, w)
        if x.shape[0] != p:
            raise ShapeError(f"{name}: has {x.shape[0]} rows, points has {p}")
        out.append(x)
    return out


def _visible(visibility, origins, dirs, active, dtype):
    """Visibility [M] with shadow rays cast only where ``active``."""
    v = torch.zeros(origins.shape[0], dtype=dtype)
    if visibility is None:
        v[active] = 1.0
        return v
    idx = torch.nonzero(active).reshape(-1)
    if idx.numel():
        vis = visibility(origins[idx].detach(), dirs[idx].detach())
        vis = torch.as_tensor(vis, dtype=dtype).detach().reshape(-1)
        if vis.shape[0] != idx.shape[0]:
            raise ShapeError(f"visibility: returned {vis.shape[0]} values for {idx.shape[0]} rays")
        require_finite(vis, "visibility")
        v[idx] = vis.clamp(0.0, 1.0)
    return v


def estimate_reflected(points, normals, wo, albedo, roughness, metallic, env: EnvironmentMap, *,
                       n_rays: int = 64, strategy: str = "env", visibility: Visibility | None = None,
                       generator: torch.Generator | None = None, specular=1.0, normal_offset: float = 0.0,
                       chunk_points: int = 4096, stats: dict | None = None, diffuse: str = "lambert",
                       masking: str = "schlick") -> torch.Tensor:
    """Estimate ``L_r`` ``[P, 3]`` (see the module docstring). ``specular``: number or ``[P, 1]``,
    ``diffuse``, ``masking``: the BRDF's diffuse lobe and masking term (see
    :func:`core.pbr.brdf.cook_torrance`). ``stats`` (optional dict) receives counts of
    samples and shadow rays.

    Raises:
        ConfigError: unknown ``strategy``, ``n_rays < 1``, bad ``normal_offset``/``chunk_points``.
        ShapeError / NumericalError: bad inputs (named).
    """
    if strategy not in STRATEGIES:
        raise ConfigError(f"strategy: must be one of {STRATEGIES}, got {strategy!r}")
    check_brdf_model(diffuse, masking)
    if isinstance(n_rays, bool) or not isinstance(n_rays, int) or n_rays < 1:
        raise ConfigError(f"n_rays: must be an int >= 1, got {n_rays!r}")
    if isinstance(chunk_points, bool) or not isinstance(chunk_points, int) or chunk_points < 1:
        raise ConfigError(f"chunk_points: must be an int >= 1, got {chunk_points!r}")
    if not isinstance(normal_offset, (int, float)) or not (0.0 <= float(normal_offset) < 1e3):
        raise ConfigError(f"normal_offset: must be a number in [0, 1e3) metres, got {normal_offset!r}")
    points, normals, wo, albedo, roughness, metallic = check_shading_inputs(
        points, normals, wo, albedo, roughness, metallic)
    if not isinstance(env, EnvironmentMap):
        raise ShapeError(f"env: expected an EnvironmentMap, got {type(env).__name__}")
    spec = specular if isinstance(specular, torch.Tensor) else torch.tensor(float(specular))
    if spec.dim() == 2 and spec.shape[0] != points.shape[0]:
        raise ShapeError(f"specular: expected a number or [P, 1], got {list(spec.shape)}")
    n_env = n_rays if strategy == "env" else (0 if strategy == "brdf" else (n_rays + 1) // 2)
    n_brdf = n_rays - n_env
    st = stats if stats is not None else {}
    st.setdefault("samples", 0)
    st.setdefault("shadow_rays", 0)
    outs = []
    for b in range(0, points.shape[0], chunk_points):
        e = min(points.shape[0], b + chunk_points)
        sp = spec[b:e] if spec.dim() == 2 else spec
        outs.append(_estimate_chunk(points[b:e], normals[b:e], wo[b:e], albedo[b:e], roughness[b:e],
                                    metallic[b:e], env, n_env, n_brdf, visibility, generator, sp,
                                    float(normal_offset), st, diffuse, masking))
    if not outs:
        return torch.zeros(0, 3, dtype=env.dtype)
    out = torch.cat(outs, 0)
    require_finite(out.detach(), "L_r")
    return out


def _estimate_chunk(x, n, wo, albedo, rough, metal, env, n_env, n_brdf, visibility, gen, spec, offset, st,
                    diffuse="lambert", masking="schlick"):
    p = x.shape[0]
    dt = env.dtype
    n_u = safe_normalize(n.to(dt))
    wo_u = safe_normalize(wo.to(dt))
    albedo, rough, metal = albedo.to(dt), rough.to(dt), metal.to(dt)
    spec = spec.to(dt)

    def expand(t, k):
        return t[:, None, :].expand(p, k, t.shape[-1]).reshape(p * k, t.shape[-1])

    total = torch.zeros(p, 3, dtype=dt)
    parts = []
    if n_env:
        dirs, pdf_e, rad = env.sample(p * n_env, gen)
        parts.append(("env", n_env, dirs, pdf_e[:, None], rad))
    if n_brdf:
        k = n_brdf
        u = torch.rand(p * k, 3, generator=gen, dtype=dt)
        sp_k = expand(spec, k) if spec.dim() == 2 else spec
        dirs, pdf_b = sample_brdf(expand(n_u, k), expand(wo_u, k), expand(albedo, k), expand(rough, k),
                                  expand(metal, k), u, sp_k)
        parts.append(("brdf", k, dirs, pdf_b, env.lookup(dirs)))
    for kind, k, dirs, pdf_own, rad in parts:
        nk, wok, ak, rk, mk = (expand(t, k) for t in (n_u, wo_u, albedo, rough, metal))
        sp_k = expand(spec, k) if spec.dim() == 2 else spec
        f = cook_torrance(nk, dirs, wok, ak, rk, mk, sp_k, diffuse, masking)
        cos = dot(nk, dirs).clamp_min(0.0)
        with torch.no_grad():
            if n_env and n_brdf:
                pe = pdf_own if kind == "env" else env.pdf(dirs)[:, None]
                pb = pdf_own if kind == "brdf" else pdf_brdf(nk, dirs, wok, ak, rk, mk, sp_k)
                own = n_env * pe if kind == "env" else n_brdf * pb
                denom = (n_env * pe) ** 2 + (n_brdf * pb) ** 2
                coef = torch.where(denom > 0, own / torch.where(denom > 0, denom, torch.ones_like(denom)),
                                   torch.zeros_like(denom))
            else:
                coef = torch.where(pdf_own > 0, 1.0 / (k * torch.where(pdf_own > 0, pdf_own, torch.ones_like(pdf_own))),
                                   torch.zeros_like(pdf_own))
            g_det = (f.detach() * rad.detach()).amax(-1, keepdim=True) * cos.detach() * coef
            active = (g_det[:, 0] > 0)
        origins = expand(x.to(dt) + offset * n_u, k)
        vis = _visible(visibility, origins, dirs, active, dt)
        st["samples"] += int(dirs.shape[0])
        st["shadow_rays"] += int(active.sum()) if visibility is not None else 0
        contrib = f * rad * (cos * coef * vis[:, None])
        total = total + contrib.reshape(p, k, 3).sum(1)
    return total
