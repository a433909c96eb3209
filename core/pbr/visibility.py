"""Shadow-ray visibility through 3D Gaussians (3DGRT response), with a BVH, and its brute-force twin.

For a ray ``x(t) = o + t d`` (world, metres, ``d`` unit; ``t`` in metres) the visibility is

    V = prod_k (1 - alpha_k),   alpha_k = min(max_alpha, o_k * g_k),
    g_k = max_{t in [t_min, t_max]} exp(-|M_k (x(t) - mu_k)|^2 / 2),   M_k = S_k^-1 R_k^T

i.e. each Gaussian's *maximum response along the ray* (3DGRT, Moenne-Loccoz et al. 2024), with
the maximising ``t`` clamped to the ray segment. ``t_min`` (metres) offsets the start of every
ray so a surface does not shadow itself: a flat Gaussian on which the ray starts is left behind
once ``t_min cos(theta) >> its thickness``. ``t_max`` is +inf for the environment and the
distance to the light for a local light. A tracer built with ``objects=True`` (the Gaussians of
objects a relight inserted or moved, traced as a BVH of their own) starts its rays at
``TraceSettings.t_min_objects`` instead, so an inserted car keeps its contact shadow while the
reconstructed road keeps the larger ``t_min`` that stops it shadowing itself.

Truncation (the same rule in the kernel and in the reference, so they agree exactly): a Gaussian
counts only where ``o_k g_k >= alpha_min``, and never beyond ``cutoff_sigma`` standard
deviations, i.e. when the squared Mahalanobis distance at the maximiser is
``<= r2max_k = min(cutoff_sigma^2, 2 ln(o_k / alpha_min))``. Gaussians with
``o_k < alpha_min`` are dropped. The truncation ellipsoid's axis-aligned box is what the BVH is
built over, so culling by the BVH never changes the result. Scales are floored at
``min_scale`` (metres).

Order: the product commutes, so traversal is unordered (nearer child first, only to stop
early). Early stop: a ray returns as soon as ``V < early_stop``; the returned value is that V,
so the error is below ``early_stop``.

Differentiability: none. Visibility is returned detached (geometry is frozen in the PBR stage,
which differentiates with respect to the environment map and materials; the kernel has no
backward pass).

Kernel: C++ (``native/trace4.hpp``, built and cached by :mod:`core.pbr._native`, the same build
approach as the rasterizer's): a binned-SAH binary BVH collapsed to a 4-wide BVH with SSE box
tests; one call spreads the rays over ``std::thread`` workers (one per core). Build: ~0.1-0.2 s
for 50k Gaussians. Throughput on these 2-core machines (synthetic street, 50k flat Gaussians,
cosine-distributed shadow rays from surface points): ~0.6 Mrays/s on one core, ~0.9-1.2 Mrays/s
on two (measured while the machine was shared); see the per-ray counters in
:attr:`GaussianTracer.last_stats`. A tracer also holds the fused integrator's copy
(:meth:`GaussianTracer.native_handle`): the same SAH build collapsed to an 8-wide BVH with the
records as SoA float32 arrays for a 16-wide AVX-512 leaf test (:mod:`core.pbr.integrator`).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass

import numpy as np
import torch

from core.errors import ConfigError, ShapeError
from core.native_build import default_threads  # noqa: E402,F401 - one definition, re-exported
from core.numerics import require_finite, safe_normalize
from core.pbr import _native
from core.raster.splat import quat_to_rotmat, safe_normalize_quat


@dataclass(frozen=True)
class TraceSettings:
    """How shadow rays are traced. Lengths in metres."""

    t_min: float = 1e-2
    """Ray start offset (self-shadowing guard), metres."""
    t_min_objects: float | None = None
    """Ray start offset through the Gaussians of a tracer built with ``objects=True`` (the
    objects a relight inserted or moved: :attr:`core.render.scenario.Scenario.object_shadow_t_min_m`),
    metres; None = ``t_min``. Each BVH of the integrator has its own offset, so a small one here
    keeps an object's contact shadow without letting the rest of the scene shadow itself."""
    early_stop: float = 1e-3
    """Stop a ray once V drops below this (0 disables early stopping)."""
    max_alpha: float = 0.99
    """Upper clamp of a single Gaussian's alpha (as in 3DGS / 3DGRT)."""
    alpha_min: float = 1.0 / 255.0
    """Contributions below this alpha are ignored (sets the truncation radius)."""
    cutoff_sigma: float = 3.0
    """Never count a Gaussian beyond this many standard deviations."""
    min_scale: float = 1e-6
    """Floor of every Gaussian scale (a thinner Gaussian is treated as this thick)."""
    leaf_size: int = 4
    """Gaussians per BVH leaf (SAH may make leaves up to 4x larger when splitting does not pay)."""
    threads: int = 0
    """Worker threads of the kernel; 0 = every core this process may use."""

    def __post_init__(self) -> None:
        def num(name, lo, hi, lo_open=False):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < lo or v > hi or (lo_open and v == lo):
                raise ConfigError(f"{name}: must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {v!r}")

        num("t_min", 0.0, 1e3)
        if self.t_min_objects is not None:
            num("t_min_objects", 0.0, 1e3)
        num("early_stop", 0.0, 1.0)
        num("max_alpha", 0.0, 1.0, lo_open=True)
        num("alpha_min", 0.0, 1.0, lo_open=True)
        num("cutoff_sigma", 0.0, 1e3, lo_open=True)
        num("min_scale", 0.0, 1e6, lo_open=True)
        for name, lo in (("leaf_size", 1), ("threads", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo or v > 4096:
                raise ConfigError(f"{name}: must be an int in [{lo}, 4096], got {v!r}")


def _t_min(settings: TraceSettings, objects: bool) -> float:
    """The minimum ray distance of a tracer (``objects``: of edited objects)."""
    if objects and settings.t_min_objects is not None:
        return float(settings.t_min_objects)
    return float(settings.t_min)


def _check(x, name: str, width: int | None) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise ShapeError(f"{name}: expected a floating torch tensor")
    if width is not None and (x.dim() != 2 or x.shape[1] != width):
        if not (width == 1 and x.dim() == 1):
            raise ShapeError(f"{name}: expected shape [N, {width}], got {list(x.shape)}")
    require_finite(x.detach(), name)
    return x.detach()


def prepare_gaussians(means, quats, scales, opacities, settings: TraceSettings, dtype=torch.float64):
    """The per-Gaussian quantities of the response, with truncation applied.

    Args: means ``[N, 3]`` world metres; quats ``[N, 4]`` wxyz (need not be unit); scales ``[N, 3]``
    metres (activated); opacities ``[N]`` or ``[N, 1]`` in [0, 1] (activated).

    Returns a dict of tensors of the kept Gaussians (``o >= alpha_min``): ``mu [K, 3]``,
    ``M [K, 3, 3]`` (``S^-1 R^T``), ``opacity [K]``, ``r2max [K]``, ``lo``/``hi [K, 3]``
    (truncation boxes) and ``index [K]`` (rows of the input).
    """
    means = _check(means, "means", 3)
    quats = _check(quats, "quats", 4)
    scales = _check(scales, "scales", 3)
    opacities = _check(opacities, "opacities", 1).reshape(-1)
    n = means.shape[0]
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities)):
        if t.shape[0] != n:
            raise ShapeError(f"{name}: has {t.shape[0]} rows, means has {n}")
    if bool((scales < 0).any()):
        raise ConfigError("scales: must be >= 0 (activated scales, metres)")
    op = opacities.to(dtype).clamp(0.0, 1.0)
    keep = op >= settings.alpha_min
    idx = torch.nonzero(keep).reshape(-1)
    op = op[idx]
    rot = quat_to_rotmat(safe_normalize_quat(quats[idx].to(dtype)))  # [K, 3, 3], columns = axes
    s = scales[idx].to(dtype).clamp_min(settings.min_scale)
    m = rot.transpose(1, 2) / s[:, :, None]  # row i = axis_i / s_i
    r2max = torch.minimum(
        torch.full_like(op, settings.cutoff_sigma ** 2),
        2.0 * torch.log(op / settings.alpha_min),
    ).clamp_min(0.0)
    half = torch.sqrt(((rot * s[:, None, :]) ** 2).sum(-1)) * torch.sqrt(r2max)[:, None]
    mu = means[idx].to(dtype)
    return {"mu": mu, "M": m, "opacity": op, "r2max": r2max, "lo": mu - half, "hi": mu + half, "index": idx}


def _rays(origins, dirs, t_max):
    origins = _check(origins, "origins", 3)
    dirs = _check(dirs, "dirs", 3)
    if dirs.shape != origins.shape:
        raise ShapeError(f"dirs: shape {list(dirs.shape)} differs from origins {list(origins.shape)}")
    if t_max is not None:
        t_max = _check(torch.as_tensor(t_max, dtype=origins.dtype), "t_max", None).reshape(-1)
        if t_max.numel() == 1:
            t_max = t_max.expand(origins.shape[0])
        if t_max.shape[0] != origins.shape[0]:
            raise ShapeError(f"t_max: expected [{origins.shape[0]}] values, got {t_max.shape[0]}")
    return origins, dirs, t_max


class GaussianTracer:
    """BVH over Gaussians for shadow rays; call it as ``visibility(origins, dirs, t_max=None)``.

    Args: as :func:`prepare_gaussians`, plus ``settings`` and ``objects`` (these Gaussians are
    edited objects: rays start at ``settings.t_min_objects``, see :attr:`t_min`). The BVH is built
    once here (C++, ~20 ms for 50k Gaussians); build a new tracer when the Gaussians move.
    """

    def __init__(self, means, quats, scales, opacities, settings: TraceSettings | None = None, *,
                 objects: bool = False):
        self.settings = settings or TraceSettings()
        self.objects = bool(objects)
        #: Minimum ray distance through these Gaussians, metres: ``settings.t_min``, or
        #: ``settings.t_min_objects`` (when set) for a tracer of edited objects.
        self.t_min = _t_min(self.settings, self.objects)
        #: Minimum ray distance through these Gaussians for rays that start on an edited object's
        #: own surface (the integrator's ``on_object`` points): ``settings.t_min`` (an object's
        #: Gaussians must not shadow its own surface).
        self.t_min_on_objects = float(self.settings.t_min)
        prep = prepare_gaussians(means, quats, scales, opacities, self.settings, torch.float64)
        k = int(prep["mu"].shape[0])
        self.num_gaussians = int(means.shape[0])
        self.num_kept = k
        lib = _native.lib()
        lo = np.ascontiguousarray(prep["lo"].numpy(), dtype=np.float32)
        hi = np.ascontiguousarray(prep["hi"].numpy(), dtype=np.float32)
        perm = np.zeros(max(k, 1), np.int32)
        nodes = np.zeros((k + 1) * _native.NODE_BYTES, np.uint8)
        depth = ctypes.c_int32(0)
        nn = lib.bv_build(lo.ctypes.data, hi.ctypes.data, k, self.settings.leaf_size, perm.ctypes.data,
                          nodes.ctypes.data, ctypes.byref(depth))
        if depth.value > 120:
            raise ConfigError(f"means: BVH depth {depth.value} exceeds the kernel's stack (120); "
                              "the Gaussians are degenerate (e.g. thousands at one point)")
        self.num_nodes = int(nn)
        self.depth = int(depth.value)
        self._nodes = nodes[: max(self.num_nodes, 1) * _native.NODE_BYTES].copy()
        rec = np.zeros((max(k, 1), _native.GAUSS_FLOATS), np.float32)
        if k:
            p = torch.from_numpy(perm[:k].astype(np.int64))
            rec[:k, 0:3] = prep["mu"][p].numpy()
            rec[:k, 3:12] = prep["M"][p].reshape(k, 9).numpy()
            rec[:k, 12] = prep["opacity"][p].numpy()
            rec[:k, 13] = prep["r2max"][p].numpy()
        self._records = rec
        # the fused integrator's copy: the same SAH build collapsed to an 8-wide BVH, and the
        # records in its leaf order as SoA arrays (16-wide AVX-512 leaf test)
        perm8 = np.zeros(max(k, 1), np.int32)
        nodes8 = np.zeros((k + 1) * _native.NODE8_BYTES, np.uint8)
        depth8 = ctypes.c_int32(0)
        nn8 = lib.pi_build8(lo.ctypes.data, hi.ctypes.data, k, self.settings.leaf_size, perm8.ctypes.data,
                            nodes8.ctypes.data, ctypes.byref(depth8))
        self._nodes8 = nodes8[: max(int(nn8), 1) * _native.NODE8_BYTES].copy()
        self.num_nodes8 = int(nn8)
        soa = np.zeros((_native.SOA_ARRAYS, max(k, 1) + _native.SOA_PAD), np.float32)
        if k:
            p8 = torch.from_numpy(perm8[:k].astype(np.int64))
            soa[0:3, :k] = prep["mu"][p8].numpy().T
            soa[3:12, :k] = prep["M"][p8].reshape(k, 9).numpy().T
            soa[12, :k] = prep["opacity"][p8].numpy()
            soa[13, :k] = prep["r2max"][p8].numpy()
        self._soa = soa
        self.last_stats: dict[str, int] = {}

    @classmethod
    def from_gaussians(cls, gaussians, settings: TraceSettings | None = None, *,
                       objects: bool = False) -> "GaussianTracer":
        """Build from a :class:`core.gaussians.Gaussians` container (activated attributes)."""
        with torch.no_grad():
            return cls(gaussians.means, gaussians.rotations(), gaussians.scales(), gaussians.opacities(),
                       settings, objects=objects)

    def native_handle(self) -> tuple[int, int, int, int]:
        """``(nodes pointer, node count, SoA pointer, SoA row length)`` for the fused integrator
        (valid while this tracer is alive)."""
        return (self._nodes8.ctypes.data, self.num_nodes8 if self.num_kept else 0, self._soa.ctypes.data,
                int(self._soa.shape[1]))

    def __call__(self, origins: torch.Tensor, dirs: torch.Tensor, t_max=None) -> torch.Tensor:
        """Visibility ``[M]`` in [0, 1] (detached, dtype of ``origins``) of rays ``origins`` and
        ``dirs`` ``[M, 3]`` (world; dirs normalised here, zero dirs give V = 1) over
        ``t in [self.t_min, t_max]`` (``t_max``: None = inf, a number, or ``[M]``)."""
        origins, dirs, t_max = _rays(origins, dirs, t_max)
        m = origins.shape[0]
        d = safe_normalize(dirs if dirs.dtype == torch.float32 else dirs.to(torch.float64))
        zero = (d * d).sum(-1) < 0.5
        o32 = np.ascontiguousarray(origins.to(torch.float32).numpy())
        d32 = np.ascontiguousarray(d.to(torch.float32).numpy())
        tm = None
        if t_max is not None or bool(zero.any()):
            tmx = torch.full((m,), math.inf, dtype=torch.float64) if t_max is None else t_max.to(torch.float64).clone()
            tmx[zero] = -1.0
            tm = np.ascontiguousarray(tmx.to(torch.float32).numpy())
        out = np.empty(m, np.float32)
        stats = np.zeros(3, np.int64)
        s = self.settings
        _native.lib().bv_trace(self._nodes.ctypes.data, self.num_nodes, self._records.ctypes.data,
                               o32.ctypes.data, d32.ctypes.data, None if tm is None else tm.ctypes.data, m,
                               float(self.t_min), float(s.early_stop), float(s.max_alpha),
                               int(s.threads or default_threads()), out.ctypes.data, stats.ctypes.data)
        self.last_stats = {"rays": m, "node_visits": int(stats[0]), "gaussian_tests": int(stats[1]),
                           "gaussians_counted": int(stats[2])}
        return torch.from_numpy(out).to(origins.dtype)


def visibility_reference(means, quats, scales, opacities, origins, dirs, t_max=None,
                         settings: TraceSettings | None = None, early_stop: bool = False,
                         kernel_precision: bool = True, objects: bool = False) -> torch.Tensor:
    """Brute-force twin of :class:`GaussianTracer` in float64 (every ray against every Gaussian,
    ``O(rays x Gaussians)`` memory: tests only). ``objects``: as the tracer's (rays start at
    ``settings.t_min_objects`` when set). With ``early_stop=False`` (default) the product
    runs over all Gaussians. ``kernel_precision`` rounds the stored inputs (rays, mu, M, opacity,
    r2max, t_max) through float32 as the kernel stores them, so both agree to ~1e-12 (the
    arithmetic is float64 in both). Returns ``[M]`` float64."""
    s = settings or TraceSettings()
    t_min = _t_min(s, objects)
    prep = prepare_gaussians(means, quats, scales, opacities, s, torch.float64)
    origins, dirs, t_max = _rays(origins, dirs, t_max)
    o = origins.to(torch.float64)
    d = safe_normalize(dirs.to(torch.float64))
    if kernel_precision:
        def r32(x):
            return x.to(torch.float32).to(torch.float64)

        o, d = r32(o), r32(d)
        t_max = None if t_max is None else r32(t_max.to(torch.float64))
        prep = {k: (r32(v) if v.is_floating_point() else v) for k, v in prep.items()}
    m = o.shape[0]
    zero = (d * d).sum(-1) < 0.5
    tmx = torch.full((m,), math.inf, dtype=torch.float64) if t_max is None else t_max.to(torch.float64)
    if prep["mu"].shape[0] == 0:
        return torch.ones(m, dtype=torch.float64)
    rel = o[:, None, :] - prep["mu"][None]  # [M, K, 3]
    op = torch.einsum("kij,mkj->mki", prep["M"], rel)
    dp = torch.einsum("kij,mj->mki", prep["M"], d)
    a = (dp * dp).sum(-1)
    b = (op * dp).sum(-1)
    t = torch.where(a > 0, -b / torch.where(a > 0, a, torch.ones_like(a)), torch.full_like(a, t_min))
    t = torch.minimum(torch.maximum(t, torch.full_like(t, t_min)), tmx[:, None].expand_as(t))
    p = op + t[..., None] * dp
    rr = (p * p).sum(-1)
    alpha = torch.clamp(prep["opacity"][None] * torch.exp(-0.5 * rr), max=s.max_alpha)
    alpha = torch.where(rr <= prep["r2max"][None], alpha, torch.zeros_like(alpha))
    if early_stop:
        v = torch.ones(m, dtype=torch.float64)
        for k in range(alpha.shape[1]):
            v = torch.where(v < s.early_stop, v, v * (1.0 - alpha[:, k]))
    else:
        v = torch.prod(1.0 - alpha, dim=1)
    valid = (tmx >= t_min) & ~zero
    return torch.where(valid, v, torch.ones_like(v))
