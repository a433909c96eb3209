"""Python side of the fused C++ integrator (``_integrator.cpp``): environment tables, the SIMD
shadow-ray tracer over one to three BVHs (each with its own t_min), the cross-frame visibility
cache, and :func:`integrate`.

The integrator computes, for a batch of shading points, exactly the estimator of
:func:`core.pbr.mis.estimate_reflected` (environment / BRDF / MIS sampling, power heuristic)
plus :func:`core.pbr.lights.direct_lighting` (point and spot lights, one deterministic shadow ray
each), in one pass per point, in float32 with double accumulation. It is not differentiable: the
PyTorch estimator stays the training path and the twin in the tests (same expectation; the
deterministic pieces, BRDF values, pdfs, environment lookups and visibility, agree to float32
precision).

Sampling inside the kernel: environment samples pick a texel with a Vose alias table over
:meth:`core.pbr.envmap.EnvironmentMap.pixel_probabilities` (the same distribution as the torch
sampler, which inverts CDFs), then a direction uniform in solid angle inside the texel; the pdf is
the texel's density over solid angle. BRDF samples draw the lobe mixture of
:func:`core.pbr.brdf.sample_brdf`.

Visibility reuse (:class:`VisibilityCache`, clips): environment samples are taken from a fixed
pool of ``pool_size`` directions drawn once from the map (a "many lights" representation of the
map, seeded, identical for every frame). Each surface point belongs to a world-space cell whose
size is ``cache_cell_px`` pixel footprints at its depth rounded up to a power of two times 1 mm
(so a point keeps its cell while the camera moves, until its footprint doubles), keyed also by
the octant of its normal. A cell always uses the same run of pool directions, and the
visibility of (cell, pool direction) is traced once and then read from the lock-free hash table
by every later pixel and frame in that cell (a cell stores the ``block`` values of its run, as
uint16; the table holds ``2^log2_capacity`` cells and stops inserting at 70% full). The cached
value was traced from the first pixel's
point of the cell, so shadow edges are resolved to one cell (about ``cache_cell_px`` pixels);
BRDF samples and local lights are always traced. The benchmark measures what this costs in PSNR.

Adaptive sampling: samples are drawn in batches of ``batch`` (env and BRDF in the overall ratio);
after ``min_batches`` batches a point stops once the standard error of its luminance, mapped
through the slope of the tone curve ``(exposure y)^(1/gamma)`` at the pixel's value, falls below
``tol`` (LDR units; pixels that tone-map to white stop at once).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass

import numpy as np
import torch

from core.camera import Camera, require_one_camera
from core.errors import ConfigError
from core.pbr import _native
from core.pbr.brdf import check_brdf_model
from core.pbr.envmap import EnvironmentMap

_f32 = np.float32


def _c(a: np.ndarray, dtype=np.float32) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def _np(x, width=None) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().to(torch.float32).cpu().numpy()
    a = np.asarray(x, dtype=np.float32)
    if width == 1:
        a = a.reshape(-1)
    return np.ascontiguousarray(a)


class NativeEnv:
    """The tables the kernel samples an :class:`EnvironmentMap` with (built once per map)."""

    def __init__(self, env: EnvironmentMap):
        if not isinstance(env, EnvironmentMap):
            raise ConfigError(f"env: expected an EnvironmentMap, got {type(env).__name__}")
        h, w = env.height, env.width
        self.height, self.width = h, w
        # texel records (r, g, b, pdf) and alias records (probability, index): one cache line
        # serves a texel's radiance and density, one its alias decision
        self.tex = np.empty((h, w, 4), np.float32)
        with torch.no_grad():
            self.tex[..., :3] = env.radiance_map().detach().to(torch.float32).numpy()
        self.tex[..., 3] = env._pdf_pixel.numpy()
        prob = _c(env._prob.numpy().reshape(-1), np.float64)
        aprob = np.empty(h * w, np.float32)
        aidx = np.empty(h * w, np.int32)
        _native.lib().pi_build_alias(prob.ctypes.data, h * w, aprob.ctypes.data, aidx.ctypes.data)
        self.alias = np.empty((h * w, 2), np.float32)
        self.alias[:, 0] = aprob
        self.alias[:, 1] = aidx.view(np.float32)
        self.cos_edge = _c(np.cos(np.arange(h + 1) / h * math.pi))
        self.rot = float(env._rotation_rad)
        self.black = bool(env.fallback_uniform)

    def args(self):
        """Positional arguments (H, W, tex, alias, cos_edge, rot, black) of the kernel."""
        return (self.height, self.width, self.tex.ctypes.data, self.alias.ctypes.data, self.cos_edge.ctypes.data,
                self.rot, int(self.black))

    def eval(self, dirs) -> tuple[np.ndarray, np.ndarray]:
        """Kernel lookup ``[m, 3]`` and pdf ``[m]`` of world directions (for the twin tests)."""
        d = _np(dirs).reshape(-1, 3)
        rad = np.empty_like(d)
        pdf = np.empty(len(d), np.float32)
        _native.lib().pi_env_eval(*self.args(), d.ctypes.data, len(d), rad.ctypes.data, pdf.ctypes.data)
        return rad, pdf

    def sample(self, m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``m`` kernel samples: dirs ``[m, 3]``, pdf ``[m]``, radiance ``[m, 3]``."""
        dirs = np.empty((m, 3), np.float32)
        pdf = np.empty(m, np.float32)
        rad = np.empty((m, 3), np.float32)
        _native.lib().pi_env_sample(*self.args(), int(seed) & (2 ** 64 - 1), m, dirs.ctypes.data, pdf.ctypes.data,
                                    rad.ctypes.data)
        return dirs, pdf, rad


def _bvh_arrays(tracers):
    tracers = [t for t in tracers if t is not None]
    k = _native.MAX_BVHS
    if len(tracers) > k:
        raise ConfigError(f"tracers: at most {k} BVHs (static, dynamic, edited objects)")
    handles = [t.native_handle() for t in tracers]
    pad = [0] * (k - len(handles))
    nodes = (ctypes.c_void_p * k)(*[h[0] for h in handles] + pad)
    nums = (ctypes.c_int64 * k)(*[h[1] for h in handles] + pad)
    soas = (ctypes.c_void_p * k)(*[h[2] for h in handles] + pad)
    npads = (ctypes.c_int64 * k)(*[h[3] for h in handles] + pad)
    tmins = (ctypes.c_float * k)(*[float(t.t_min) for t in tracers] + pad)  # each tracer's own
    return nodes, nums, soas, npads, tmins, len(handles)


def _bvh_tmin_own(tracers):
    """Each tracer's minimum distance for rays from a point on an edited object."""
    tracers = [t for t in tracers if t is not None]
    return (ctypes.c_float * _native.MAX_BVHS)(*[float(t.t_min_on_objects) for t in tracers]
                                               + [0] * (_native.MAX_BVHS - len(tracers)))


def trace_simd(tracers, origins, dirs, t_max=None, *, threads: int = 0) -> tuple[np.ndarray, dict]:
    """Visibility ``[m]`` (float32) of rays through the product of one to three
    :class:`core.pbr.visibility.GaussianTracer` BVHs with the kernel's SIMD leaf test (the
    integrator's shadow rays). Each BVH from its tracer's ``t_min``; early stop and max alpha
    from the first tracer's settings."""
    from core.pbr.visibility import default_threads

    o = _np(origins).reshape(-1, 3)
    d = _np(dirs).reshape(-1, 3)
    tm = None if t_max is None else _c(np.broadcast_to(np.asarray(t_max, np.float32), (len(o),)))
    out = np.empty(len(o), np.float32)
    stats = np.zeros(3, np.int64)
    s = [t for t in tracers if t is not None][0].settings
    nodes, nums, soas, npads, tmins, nb = _bvh_arrays(tracers)
    _native.lib().pi_trace(nodes, nums, soas, npads, tmins, nb, o.ctypes.data, d.ctypes.data,
                           None if tm is None else tm.ctypes.data, len(o), s.early_stop, s.max_alpha,
                           int(threads or default_threads()), out.ctypes.data, stats.ctypes.data)
    return out, {"rays": int(stats[0]), "node_visits": int(stats[1]), "leaf_visits": int(stats[2])}


def eval_brdf(n, wi, wo, albedo, roughness, metallic, specular: float = 1.0,
              diffuse: str = "lambert", masking: str = "schlick") -> tuple[np.ndarray, np.ndarray]:
    """Kernel BRDF values ``[m, 3]`` and lobe-mixture pdfs ``[m]`` (for the twin tests);
    ``diffuse``, ``masking``: :data:`core.pbr.brdf.DIFFUSE_MODELS`, :data:`core.pbr.brdf.MASKING_MODELS`."""
    model = _model_bits(diffuse, masking)
    n, wi, wo, a = (_np(x).reshape(-1, 3) for x in (n, wi, wo, albedo))
    r, m = _np(roughness, 1), _np(metallic, 1)
    f = np.empty_like(n)
    pdf = np.empty(len(n), np.float32)
    _native.lib().pi_eval(n.ctypes.data, wi.ctypes.data, wo.ctypes.data, a.ctypes.data, r.ctypes.data,
                          m.ctypes.data, float(specular), model, len(n), f.ctypes.data, pdf.ctypes.data)
    return f, pdf


def _model_bits(diffuse: str, masking: str) -> int:
    """The kernel's BRDF model bits (``native/brdf.hpp``): 1 Burley's diffuse, 2 exact Smith G."""
    check_brdf_model(diffuse, masking)
    return int(diffuse == "burley") | (2 if masking == "smith" else 0)


class VisibilityCache:
    """Cross-frame visibility cache (see the module docstring): the kernel's hash table plus the
    pool of environment directions. ``block``: environment samples per pixel that are cached
    (set it to the pass's environment sample count). Valid for one environment map and one static set of
    occluders; call :meth:`clear` (or make a new one) when either changes."""

    def __init__(self, env: NativeEnv, *, pool_size: int = 4096, cell_px: float = 1.0, log2_capacity: int = 21,
                 block: int = 32, seed: int = 12345):
        if isinstance(pool_size, bool) or not isinstance(pool_size, int) or not 16 <= pool_size <= 1 << 22:
            raise ConfigError(f"pool_size: must be an int in [16, 4194304], got {pool_size!r}")
        if not (isinstance(cell_px, (int, float)) and math.isfinite(cell_px) and 0.0 < cell_px <= 64.0):
            raise ConfigError(f"cell_px: must be a number in (0, 64], got {cell_px!r}")
        self.env = env
        self.pool_size = pool_size
        self.cell_px = float(cell_px)
        self.log2_capacity = int(log2_capacity)
        if isinstance(block, bool) or not isinstance(block, int) or not 1 <= block <= 4096:
            raise ConfigError(f"block: must be an int in [1, 4096], got {block!r}")
        self.block = block
        self.pool_dir, self.pool_pdf, self.pool_rad = env.sample(pool_size, seed)
        self._lib = _native.lib()
        self._ptr = self._lib.pi_cache_create(self.log2_capacity, self.block)

    def clear(self) -> None:
        self._lib.pi_cache_free(self._ptr)
        self._ptr = self._lib.pi_cache_create(self.log2_capacity, self.block)

    @property
    def entries(self) -> int:
        """Surface cells in the table."""
        return int(self._lib.pi_cache_size(self._ptr))

    def __del__(self):
        ptr = getattr(self, "_ptr", None)
        if ptr:
            self._lib.pi_cache_free(ptr)
            self._ptr = None


@dataclass
class IntegratorOutput:
    """``radiance [P, 3]`` (L_r per point, float32 numpy, not weighted by opacity), ``samples
    [P]`` (environment/BRDF samples spent, int32) and kernel counters."""

    radiance: np.ndarray
    samples: np.ndarray
    counters: dict


def integrate(points, normals, wo, albedo, roughness, metallic, env: NativeEnv, tracers=(), lights=None, *,
              n_env: int, n_brdf: int, specular: float = 1.0, normal_offset: float = 0.02, seed: int = 0,
              batch: int = 1 << 30, adapt_tol: float = 0.0, adapt_min_batches: int = 2, exposure: float = 1.0,
              gamma: float = 2.2, weight=None, background_lum=None, depth=None, cull_lights: bool = True,
              cache: VisibilityCache | None = None, camera: Camera | None = None, threads: int = 0,
              ids=None, cache_bvhs: int | None = None, mis_min_brdf: float = 0.0,
              roulette: float = 0.0, cache_check: float = 0.0, on_object=None,
              diffuse: str = "lambert", masking: str = "schlick") -> IntegratorOutput:
    """Run the fused kernel on ``P`` shading points (world frame, metres; see the module
    docstring). ``normals`` are used as given (face them toward the viewer first); ``lights`` is
    a :class:`core.pbr.lights.LightSet` or None; ``tracers`` up to three
    :class:`core.pbr.visibility.GaussianTracer` (visibility is their product, each traced from
    its own ``t_min``; none = all visible); ``on_object`` (bool ``[P]``): points on the surface of
    an edited object, whose rays cross every tracer from its ``t_min_on_objects``, so an object
    tracer's small ``t_min`` darkens what the object shadows, not the object itself. ``weight``
    (opacity) and ``background_lum`` (luminance of ``(1-O) E(wo)``) only feed the adaptive
    criterion; ``depth`` (``[P]``, metres, z along the optical axis of ``camera``) and ``camera``
    (one :class:`core.camera.Camera`, the view the points were shaded for: its focal length ``fx``
    in pixels turns ``cache_cell_px`` into a world size, depth / fx metres per pixel) only size the
    cache cells (``camera`` is required with ``cache``, unused without); ``ids`` (int, ``[P]``)
    selects each point's random stream (pass pixel indices so a pixel draws the same samples
    whichever subset is shaded; default: the point's index); ``cache_bvhs``: how
    many leading ``tracers`` are static (their visibility may be cached; the others, moving
    nodes, are traced every time; default all of them); ``mis_min_brdf`` > 0 (with both sample
    kinds): each point splits its ``n_env + n_brdf`` samples itself, a BRDF share of
    ``clamp(p_spec, mis_min_brdf, 1/2)`` (``p_spec``: the lobe mixture's specular probability), so
    rough dielectrics spend most samples on the environment and glossy metal half on the BRDF;
    ``roulette`` > 0: shadow-ray Russian roulette (unbiased): after a point's first 4 samples, a
    sample whose unoccluded contribution ``g`` is below ``roulette`` x the running mean is traced
    with probability ``q = max(g / (roulette x mean), 0.05)`` and weighted ``1/q``;
    ``cache_check`` > 0 (with ``cache``): a cache hit is re-traced with this probability; an entry
    whose traced value differs from the cached one (taken at another point of the cell) by more
    than 0.25 is retired and traced at every later lookup, so cells crossed by a shadow edge stop
    using the cache (0: cached values are used as they are, shadows blurred to the cell size);
    ``diffuse``, ``masking``: the diffuse lobe and the microfacet masking term
    (:data:`core.pbr.brdf.DIFFUSE_MODELS`, :data:`core.pbr.brdf.MASKING_MODELS`)."""
    from core.pbr.visibility import TraceSettings, default_threads

    model = _model_bits(diffuse, masking)
    if camera is not None:
        require_one_camera(camera)
    elif cache is not None:
        raise ConfigError("camera: required with cache (its focal length sizes the cache cells)")
    fx = camera.fx if camera is not None else 1.0
    pos = _np(points).reshape(-1, 3)
    p = len(pos)
    nrm, wo_, alb = (_np(x).reshape(-1, 3) for x in (normals, wo, albedo))
    rough, metal = _np(roughness, 1), _np(metallic, 1)
    for name, a in (("normals", nrm), ("wo", wo_), ("albedo", alb), ("roughness", rough), ("metallic", metal)):
        if a.shape[0] != p:
            raise ConfigError(f"{name}: has {a.shape[0]} rows, points has {p}")
    wgt = _np(np.ones(p, np.float32) if weight is None else weight, 1)
    bg = _np(np.zeros(p, np.float32) if background_lum is None else background_lum, 1)
    dep = _np(np.ones(p, np.float32) if depth is None else depth, 1)
    if ids is not None:
        ids = np.ascontiguousarray(ids.numpy() if isinstance(ids, torch.Tensor) else ids, dtype=np.int64).reshape(-1)
        if ids.shape[0] != p:
            raise ConfigError(f"ids: has {ids.shape[0]} rows, points has {p}")
    tr = [t for t in tracers if t is not None]
    ts = tr[0].settings if tr else TraceSettings()
    nodes, nums, soas, npads, tmins, nb = _bvh_arrays(tr)
    own = None
    if on_object is not None:
        own = np.ascontiguousarray(on_object.numpy() if isinstance(on_object, torch.Tensor) else on_object,
                                   dtype=np.uint8).reshape(-1)
        if own.shape[0] != p:
            raise ConfigError(f"on_object: has {own.shape[0]} rows, points has {p}")
    nthreads = int(threads or default_threads())
    lrec = np.zeros((0, _native.LIGHT_FLOATS), np.float32)
    if lights is not None and len(lights):
        n_l = len(lights)
        lrec = np.zeros((n_l, _native.LIGHT_FLOATS), np.float32)
        lrec[:, 0:3] = lights.position.detach().numpy()
        lrec[:, 3:6] = lights.axis.detach().numpy()
        lrec[:, 6:9] = lights.radiant.detach().numpy()
        lrec[:, 9] = lights.cos_inner.detach().numpy()
        lrec[:, 10] = lights.cos_outer.detach().numpy()
        lrec[:, 11] = lights.range.detach().numpy()
        lrec[:, 12] = lights.is_spot.numpy().astype(np.float32)
    lrec = _c(lrec)
    if cache_bvhs is None:
        cache_bvhs = nb
    iparams = np.array([n_env, n_brdf, max(1, min(batch, 1 << 30)), adapt_min_batches, int(bool(cull_lights)),
                        cache.pool_size if cache else 1, nthreads, nb, int(cache_bvhs)], np.int64)
    # fparams' t_min is unused (each BVH has its own, tmins)
    fparams = np.array([adapt_tol, exposure, 1.0 / gamma, normal_offset, specular,
                        cache.cell_px if cache else 0.0, 1.0 / fx, ts.t_min, ts.early_stop, ts.max_alpha,
                        float(int(seed) % (2 ** 52)), float(mis_min_brdf), float(roulette),
                        float(cache_check), float(model)], np.float64)
    out = np.zeros((p, 3), np.float32)
    used = np.zeros(p, np.int32)
    counters = np.zeros(_native.NUM_COUNTERS, np.int64)
    if p:
        _native.lib().pi_render(
            pos.ctypes.data, nrm.ctypes.data, wo_.ctypes.data, alb.ctypes.data, rough.ctypes.data, metal.ctypes.data,
            wgt.ctypes.data, bg.ctypes.data, dep.ctypes.data, None if ids is None else ids.ctypes.data, p,
            iparams.ctypes.data, fparams.ctypes.data,
            nodes, nums, soas, npads, tmins, _bvh_tmin_own(tr), None if own is None else own.ctypes.data,
            lrec.ctypes.data, len(lrec), *env.args(),
            cache.pool_dir.ctypes.data if cache else None, cache.pool_pdf.ctypes.data if cache else None,
            cache.pool_rad.ctypes.data if cache else None, cache._ptr if cache else None,
            out.ctypes.data, used.ctypes.data, counters.ctypes.data)
    names = ("samples", "shadow_rays", "cache_hits", "cache_lookups", "light_pairs", "light_evals", "node_visits",
             "leaf_visits", "traced_rays", "roulette_skipped", "cache_checks")
    return IntegratorOutput(out, used, {k: int(v) for k, v in zip(names, counters)})
