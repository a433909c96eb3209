"""Point and spot lights (supplement, "Local Light Rendering"): scene-graph attachment, falloff,
smooth cone, and their direct contribution with a deterministic shadow ray.

For a shading point ``x`` (world, metres) and a light at ``p``::

    d = |p - x|,  wl = (p - x) / d                      (wl points away from the surface)
    E_l = intensity * color / max(d^2, LIGHT_DIST_SQ_MIN) * window(d) * cone(wl)
    L_r += E_l * V(x, wl) * f(x, wl, wo) * max(n.wl, 0)

Units: ``intensity`` is radiant intensity (W/sr, or any radiometric unit consistent with the
environment map's radiance): it gives irradiance ``intensity / d^2`` at normal incidence.
``color`` is a linear RGB multiplier. Lengths in metres. Angles are DEGREES in the API
(``inner_deg``, ``outer_deg``: half-angles of the cone, measured from its axis) and radians
inside.

Falloff
    ``1/d^2`` with ``d^2`` floored at :data:`core.numerics.LIGHT_DIST_SQ_MIN` (1 cm^2: a light at
    the shading point is finite; there ``wl`` is undefined and the contribution is 0).
    ``range`` (optional, metres): a smooth window ``clamp(1 - (d / range)^4, 0, 1)^2`` that
    reaches 0 at ``d = range`` (as in Unreal / Filament), so culling by range is exact.
Cone (spot lights)
    ``smoothstep(cos(outer), cos(inner), dot(-wl, axis))``: 1 inside the inner cone, 0 outside
    the outer cone, a Hermite blend between (``inner == outer`` is a hard edge).
Attachment
    ``node=None``: position and direction are in the world frame. ``node="car3"``: they are in
    that scene-graph node's frame and :func:`lights_to_world` places them with the node's
    ``obj_to_world`` 4x4 pose (headlights move with their car).
Culling
    :func:`direct_lighting` with ``cull=True`` evaluates the BRDF and casts a shadow ray only
    for (point, light) pairs inside the range, inside the outer cone and above both horizons
    (``n.wl > 0``, ``n.wo > 0``); every skipped pair contributes exactly 0 unculled, so the
    result is the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import torch

from core.conventions import is_rigid
from core.errors import ConfigError, ShapeError
from core.numerics import LIGHT_DIST_SQ_MIN, LIGHT_INTENSITY_MAX, require_finite, safe_normalize, safe_sqrt, smoothstep
from core.pbr.brdf import cook_torrance, dot
from core.pbr.mis import Visibility, check_shading_inputs


def _vec3(v, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ShapeError(f"{name}: expected 3 numbers, got shape {np.asarray(v).shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: must be finite, got {tuple(a)}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _number(v, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
        raise ConfigError(f"{name}: must be a finite number, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light. ``position`` in the frame of ``node`` (world if None), metres."""

    position: tuple[float, float, float]
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    range: float | None = None
    node: str | None = None
    name: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        col = _vec3(self.color, "color")
        if min(col) < 0:
            raise ConfigError(f"color: must be >= 0, got {col}")
        object.__setattr__(self, "color", col)
        inten = _number(self.intensity, "intensity")
        if inten < 0:
            raise ConfigError(f"intensity: must be >= 0, got {inten}")
        if inten * max(col) > LIGHT_INTENSITY_MAX:
            raise ConfigError(f"intensity: intensity * max(color) = {inten * max(col):.3g} exceeds "
                              f"{LIGHT_INTENSITY_MAX:g} (float32 safety limit)")
        object.__setattr__(self, "intensity", inten)
        if self.range is not None:
            r = _number(self.range, "range")
            if r <= 0:
                raise ConfigError(f"range: must be > 0 metres or None, got {r}")
            object.__setattr__(self, "range", r)
        if self.node is not None and (not isinstance(self.node, str) or not self.node):
            raise ConfigError(f"node: must be a non-empty string or None, got {self.node!r}")


@dataclass(frozen=True)
class SpotLight(PointLight):
    """A spot light: a point light restricted to a cone about ``direction`` (in the node frame).
    ``inner_deg <= outer_deg`` are half-angles in degrees, in [0, 180]."""

    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    inner_deg: float = 20.0
    outer_deg: float = 30.0

    def __post_init__(self) -> None:
        super().__post_init__()
        d = np.asarray(_vec3(self.direction, "direction"))
        nrm = float(np.linalg.norm(d))
        if nrm < 1e-9:
            raise ConfigError("direction: must be a non-zero vector")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / nrm))
        inner = _number(self.inner_deg, "inner_deg")
        outer = _number(self.outer_deg, "outer_deg")
        if not 0.0 <= inner <= 180.0:
            raise ConfigError(f"inner_deg: must be in [0, 180], got {inner}")
        if not 0.0 <= outer <= 180.0:
            raise ConfigError(f"outer_deg: must be in [0, 180], got {outer}")
        if inner > outer:
            raise ConfigError(f"inner_deg: {inner} exceeds outer_deg {outer}")


@dataclass
class LightSet:
    """World-space lights packed as tensors (L lights). ``position``, ``axis`` ``[L, 3]``;
    ``radiant`` ``[L, 3]`` = intensity * color; ``cos_inner``, ``cos_outer`` ``[L]`` (point lights:
    -2, -2, i.e. no cone); ``range`` ``[L]`` (inf = none); ``is_spot`` ``[L]`` bool."""

    position: torch.Tensor
    axis: torch.Tensor
    radiant: torch.Tensor
    cos_inner: torch.Tensor
    cos_outer: torch.Tensor
    range: torch.Tensor
    is_spot: torch.Tensor
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.position.shape[0])


def lights_to_world(lights: Sequence[PointLight], node_poses: Mapping[str, object] | None = None,
                    dtype: torch.dtype = torch.float32) -> LightSet:
    """Place lights in the world: those attached to a node are transformed by
    ``node_poses[node]`` (4x4 ``obj_to_world``, rigid). Raises ConfigError naming a missing node
    or a non-rigid pose."""
    node_poses = node_poses or {}
    pos, axis, rad, ci, co, rng, spot, names = [], [], [], [], [], [], [], []
    for i, light in enumerate(lights):
        if not isinstance(light, PointLight):
            raise ConfigError(f"lights[{i}]: expected a PointLight or SpotLight, got {type(light).__name__}")
        p = np.asarray(light.position, dtype=np.float64)
        a = np.asarray(getattr(light, "direction", (0.0, 0.0, -1.0)), dtype=np.float64)
        if light.node is not None:
            if light.node not in node_poses:
                raise ConfigError(f"node_poses: no pose for node {light.node!r} (light {i} {light.name!r})")
            m = np.asarray(node_poses[light.node], dtype=np.float64)
            if not is_rigid(m):
                raise ConfigError(f"node_poses[{light.node!r}]: not a rigid 4x4 transform")
            p = m[:3, :3] @ p + m[:3, 3]
            a = m[:3, :3] @ a
        pos.append(p)
        axis.append(a / max(np.linalg.norm(a), 1e-12))
        rad.append(np.asarray(light.color) * light.intensity)
        if isinstance(light, SpotLight):
            ci.append(math.cos(math.radians(light.inner_deg)))
            co.append(math.cos(math.radians(light.outer_deg)))
            spot.append(True)
        else:
            ci.append(-2.0)
            co.append(-2.0)
            spot.append(False)
        rng.append(math.inf if light.range is None else light.range)
        names.append(light.name)

    def t(x, shape):
        return torch.tensor(np.asarray(x, dtype=np.float64).reshape(shape), dtype=dtype)

    n = len(pos)
    return LightSet(t(pos, (n, 3)), t(axis, (n, 3)), t(rad, (n, 3)), t(ci, (n,)), t(co, (n,)),
                    t(rng, (n,)), torch.tensor(spot, dtype=torch.bool).reshape(n), names)


def light_geometry(x: torch.Tensor, lights: LightSet, l: int):
    """For light ``l`` and points ``x`` ``[P, 3]``: ``(wl [P, 3], dist [P, 1], attenuation
    [P, 1])`` where attenuation = window * cone / max(d^2, LIGHT_DIST_SQ_MIN) (no color)."""
    to_l = lights.position[l].to(x.dtype) - x
    d2 = (to_l * to_l).sum(-1, keepdim=True)
    wl = safe_normalize(to_l)
    dist = safe_sqrt(d2)  # finite gradient at d = 0
    att = 1.0 / d2.clamp_min(LIGHT_DIST_SQ_MIN)
    r = lights.range[l].to(x.dtype)
    if bool(torch.isfinite(r)):
        q = d2 / (r * r)
        att = att * (1.0 - q * q).clamp(0.0, 1.0) ** 2
    if bool(lights.is_spot[l]):
        cos_axis = -(wl * lights.axis[l].to(x.dtype)).sum(-1, keepdim=True)
        att = att * smoothstep(lights.cos_outer[l].to(x.dtype), lights.cos_inner[l].to(x.dtype), cos_axis)
    return wl, dist, att


def direct_lighting(points, normals, wo, albedo, roughness, metallic, lights: LightSet, *,
                    visibility: Visibility | None = None, cull: bool = True, specular=1.0,
                    normal_offset: float = 0.0, stats: dict | None = None, diffuse: str = "lambert",
                    masking: str = "schlick") -> torch.Tensor:
    """Sum over lights of ``E_l V f max(n.wl, 0)``: ``[P, 3]`` (see the module docstring).

    Shapes as :func:`core.pbr.mis.estimate_reflected`. ``visibility(origins, dirs, t_max)``
    casts one deterministic shadow ray per (point, light) from ``points + normal_offset * n``
    toward the light, ending at the light (``t_max = d``). ``diffuse``, ``masking``: the BRDF's
    diffuse lobe and masking term (:func:`core.pbr.brdf.cook_torrance`). ``stats`` receives ``pairs`` and
    ``evaluated`` counts (evaluated < pairs when culling skips work).
    """
    points, normals, wo, albedo, roughness, metallic = check_shading_inputs(
        points, normals, wo, albedo, roughness, metallic)
    if not isinstance(lights, LightSet):
        raise ShapeError(f"lights: expected a LightSet (see lights_to_world), got {type(lights).__name__}")
    dt = points.dtype
    n_u = safe_normalize(normals)
    wo_u = safe_normalize(wo)
    spec = specular if isinstance(specular, torch.Tensor) else torch.tensor(float(specular), dtype=dt)
    out = torch.zeros(points.shape[0], 3, dtype=dt)
    st = stats if stats is not None else {}
    st.setdefault("pairs", 0)
    st.setdefault("evaluated", 0)
    for l in range(len(lights)):
        wl, dist, att = light_geometry(points, lights, l)
        st["pairs"] += points.shape[0]
        if cull:
            with torch.no_grad():
                keep = (att[:, 0] > 0) & (dot(n_u, wl)[:, 0] > 0) & (dot(n_u, wo_u)[:, 0] > 0)
                keep &= (lights.radiant[l] > 0).any()
            idx = torch.nonzero(keep).reshape(-1)
            if idx.numel() == 0:
                continue
        else:
            idx = torch.arange(points.shape[0])
        st["evaluated"] += int(idx.numel())
        sp = spec[idx] if spec.dim() == 2 else spec
        f = cook_torrance(n_u[idx], wl[idx], wo_u[idx], albedo[idx], roughness[idx], metallic[idx], sp, diffuse,
                          masking)
        cos = dot(n_u[idx], wl[idx]).clamp_min(0.0)
        if visibility is None:
            vis = torch.ones(idx.shape[0], dtype=dt)
        else:
            origins = (points[idx] + normal_offset * n_u[idx]).detach()
            vis = torch.as_tensor(visibility(origins, wl[idx].detach(), dist[idx, 0].detach()), dtype=dt).reshape(-1)
            require_finite(vis, "visibility")
            vis = vis.clamp(0.0, 1.0)
        contrib = lights.radiant[l].to(dt) * att[idx] * f * cos * vis[:, None]
        out = out.index_add(0, idx, contrib)
    require_finite(out.detach(), "direct_lighting")
    return out
