"""The physically based rendering pass (paper Eq. 3) on rasterized G-buffers.

Per pixel (world frame, metres; OpenCV camera, :mod:`core.conventions`):

    O          composited opacity;  z = D / O  (D: composited camera z-depth)
    x          = c + d z / (d . f)     surface point (c camera centre, d unit ray, f forward axis)
    n          = N / |N|, flipped toward the viewer when n . wo < 0   (wo = -d)
    A, R, M    = composited albedo, roughness, metallic divided by O (expected values given a hit)
    L_r        = Monte Carlo estimate of  integral E(wi) V(x, wi) f(wi, wo) (n . wi)+ dwi
                 + sum over local lights of E_l V(x, wl) f(wl, wo) (n . wl)+   (supplement)
    C_pbr      = (1 - O) E(d) + O L_r       (L_r alone where O >= opaque_above: a surface)
    C_ldr      = clip(exposure C_pbr, 0, 1)^(1 / gamma)        (gamma = 2.2)

With :attr:`PBRSettings.indirect_bounces` > 0 (the product's scenarios and the pbr and joint
stages: 2), ``L_r`` also gets an approximate diffuse bounce, :func:`indirect_light`: the paper
renders direct light only, but in a street 18-22% of the light a camera sees has bounced
(measured with Mitsuba, ``benchmarks/bench_visibility.py``).

``E(d)`` is the map's radiance along the camera ray (the paper's ``E(w_o)``). ``L_r`` is weighted
by ``O`` because the G-buffers are accumulated sums: a pixel half covered by a surface blends half
surface, half sky; for opaque surfaces (``O = 1``) this is the paper's formula exactly. With
:attr:`PBRSettings.opaque_above` < 1 a pixel at least that opaque counts as a surface (weight 1,
no map behind it): reconstructed surfaces are rarely exactly opaque. A zero normal (nothing
composited) reflects nothing.

Backends (:attr:`PBRSettings.backend`)
    ``"native"``: the fused C++ integrator (:mod:`core.pbr.integrator`): fast, not
    differentiable, with the skips (sky, light culling, visibility reuse, adaptive sampling).
    ``"torch"``: :func:`core.pbr.mis.estimate_reflected` + :func:`core.pbr.lights.direct_lighting`
    with the BVH shadow rays: differentiable with respect to the environment map (and the
    G-buffers); the training path, e.g. with ``pixels=`` a random subset of 2048 non-sky pixels
    (:func:`sample_pixels`). Both estimate the same expectation.

Outputs: :class:`PBRResult` (HDR beauty, LDR, L_r, G-buffers, samples per pixel, timings,
counters); :func:`write_frame_exr` writes HDR beauty and every G-buffer layer into one
multi-layer EXR: the beauty (``R, G, B``) and ``Lr`` are written as **float32** (a 1e6 sun stays
finite: float32 holds up to 3.4e38), the G-buffers as half (their values are small; the EXR
writer clamps half values at 65504, so nothing is ever Inf). :func:`write_clip_mp4` writes LDR
frames as H.264.

Clips: :class:`ClipRenderer` renders frames of a :class:`core.scene_graph.SceneGraph` (or a
fixed set of Gaussians) along a camera path: the shadow-ray BVH of the background and static
nodes is built once (only moving nodes get a per-frame BVH; visibility is the product of both),
the environment tables once, and with ``reuse_visibility`` a :class:`VisibilityCache` carries
environment visibility across frames. When ``TraceSettings.t_min_objects`` differs from
``t_min``, the nodes an object edit placed (:attr:`core.scene_graph.RigidNode.edited`) leave
those BVHs for a per-frame third one traced from ``t_min_objects``; a scene without edits
renders as before, to the bit.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
import time
from collections import OrderedDict
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np
import torch

from core.camera import Camera
from core.errors import ConfigError, ShapeError
from core.gaussians import Gaussians
from core.io.exr import write_exr
from core.io.video import write_mp4
from core.numerics import EPS_PDF, require_finite, safe_normalize
from core.pbr.brdf import DIFFUSE_MODELS, MASKING_MODELS, pdf_ggx_vndf, sample_cosine, sample_ggx_vndf, specular_lobe
from core.pbr.envmap import EnvironmentMap, luminance
from core.pbr.integrator import NativeEnv, VisibilityCache, integrate
from core.pbr.lights import direct_lighting, lights_to_world
from core.pbr.mis import estimate_reflected
from core.pbr.visibility import GaussianTracer, TraceSettings
from core.raster import RasterSettings, rasterize_gaussians
from core.scene_graph import SceneGraph
from core.tonemap import ldr_to_uint8

SAMPLINGS = ("env", "brdf", "mis")
BACKENDS = ("native", "torch")


#: The shading model the product renders with (relight, night, the evaluation and the pbr and joint
#: stages: :class:`core.render.scenario.Scenario`, :class:`core.synth.evaluate.EvalSettings`,
#: :class:`core.stages.pbr_settings.StageShading`), where the bare :class:`PBRSettings` keep the paper's:
#: Burley's diffuse lobe, the exact Smith masking term, pixels at least half opaque shaded as surfaces.
PRODUCT_DIFFUSE = "burley"
PRODUCT_MASKING = "smith"
PRODUCT_OPAQUE_ABOVE = 0.5
#: GGX shadow rays per pixel of the specular bounce in the product's renders and stages
#: (:attr:`PBRSettings.indirect_specular_rays`). Measured on the development scenes at quick, pbr
#: and joint re-run from one volume2 each (``benchmarks/results/specular_bounce.json``): 0 -> 4
#: relit 20.83 -> 21.09 / 22.18 -> 22.08 dB, SSIM 0.613 -> 0.620 / 0.757 -> 0.764, re-render
#: 23.05 -> 23.23 / 19.48 -> 19.91 dB, metallic RMSE 0.109 -> 0.106 / 0.128 -> 0.120 (default
#: scene / dev5).
PRODUCT_INDIRECT_SPECULAR_RAYS = 4


@dataclass(frozen=True)
class PBRSettings:
    """How the PBR pass samples, skips work and tone-maps. Lengths in metres."""

    rays_per_pixel: int = 64
    """Environment + BRDF samples (each with its shadow ray) per shaded pixel (the paper's N_r)."""
    sampling: str = "mis"
    """``"env"`` (the paper: environment importance sampling only), ``"brdf"`` or ``"mis"`` (half
    environment, half BRDF samples, power heuristic)."""
    backend: str = "native"
    """``"native"`` (fused C++ kernel, not differentiable) or ``"torch"`` (differentiable)."""
    exposure: float = 1.0
    """LDR exposure: ``C_ldr = clip(exposure * C_pbr, 0, 1)^(1/gamma)``."""
    gamma: float = 2.2
    """LDR gamma (the paper's 2.2)."""
    specular: float = 1.0
    """Scale of the BRDF's microfacet term: 1 = the paper; 0 = pure Lambert (validation against
    Lambertian ground truth)."""
    diffuse: str = "lambert"
    """The BRDF's diffuse lobe (:data:`core.pbr.brdf.DIFFUSE_MODELS`): ``"lambert"`` (the paper) or
    ``"burley"`` (Burley's 2015 diffuse of the principled BSDF, whose base colour the recovered
    albedo is: :mod:`core.pbr.brdf`)."""
    masking: str = "schlick"
    """The BRDF's microfacet masking-shadowing term (:data:`core.pbr.brdf.MASKING_MODELS`):
    ``"schlick"`` (the paper's Schlick-Smith) or ``"smith"`` (exact Smith, as the principled BSDF:
    :mod:`core.pbr.brdf`)."""
    shadows: bool = True
    """Trace shadow rays through the Gaussians; False treats every light sample as visible (no
    BVH is built and no visibility cache is used)."""
    normal_offset: float = 0.02
    """Shadow rays start this far along the normal (metres) so a surface does not shadow itself."""
    skip_sky: bool = True
    """Shade only pixels with opacity >= ``sky_opacity`` (the rest show the environment)."""
    sky_opacity: float = 1.0 / 255.0
    """Opacity below which a pixel counts as sky (its L_r weight O is below this)."""
    cull_lights: bool = True
    """Evaluate a light at a pixel only inside its range and cone and above the horizon (exact)."""
    adaptive: bool = False
    """Adaptive sampling (native): stop a pixel once its LDR standard error is below ``adaptive_tol``."""
    adaptive_tol: float = 0.005
    """LDR standard error (0..1 units) at which a pixel stops sampling (0.01 stopped pixels that
    had not yet drawn the sun: -0.36 dB on the benchmark street; 0.005 with 6 batches: within
    the seed-to-seed spread)."""
    adaptive_batch: int = 8
    """Samples per batch of the adaptive criterion."""
    adaptive_min_batches: int = 6
    """Batches every pixel takes before it may stop (few batches make the variance estimate
    unreliable: a pixel that has not yet drawn the sun stops dark)."""
    roulette: float = 0.5
    """Native: shadow-ray Russian roulette (unbiased). After a pixel's first 4 samples, a sample
    whose unoccluded contribution is below ``roulette`` x the pixel's running mean is traced with
    probability ``max(contribution / (roulette x mean), 0.05)`` and weighted by its inverse; 0
    traces every sample. Measured on the benchmark street (64 rays, MIS, idle 2-core machine):
    0.5 traces 23% fewer shadow rays, 16% less time, -0.07 dB."""
    reuse_visibility: bool = False
    """Native: take environment samples from a fixed pool and cache their visibility per
    world-space surface cell across frames (see :mod:`core.pbr.integrator`)."""
    cache_cell_px: float = 1.0
    """Cell size of the visibility cache in pixel footprints (rounded up to a power of 2 x 1 mm):
    shadows through cached directions are resolved to a cell (1-2 pixels at 1). Measured on the
    benchmark street, 24-frame clip from a static camera, seeds 0-2: 1.0 hits 90% of lookups with
    the last frame's PSNR within 0.02 dB of no cache; 2.0 hits 93% but loses 0.08 dB on the
    first frame (pixels of one frame share a cell's value); 0.5 hits 88%."""
    cache_pool: int = 4096
    """Environment directions in the pool of the visibility cache."""
    cache_check: float = 0.25
    """Probability that a cache hit is traced anyway (a spot check); an entry whose traced value
    differs from the cached one by more than 0.25 (a shadow edge crosses the cell in that
    direction) is retired and always traced from then on. 0 uses cached values as they are
    (shadows blurred to the cell size)."""
    indirect_bounces: int = 0
    """Indirect light, approximated (0 = off: direct light only, the paper's Eq. 3). A direction
    the Gaussians block does not see the map but a surface of the scene: its diffuse light is
    ``rho (1 - V) L_b`` with ``rho = (1 - M) A`` the diffuse albedo, ``V`` the pixel's
    cosine-weighted visibility (``indirect_rays`` cosine-sampled shadow rays) and ``L_b`` the
    mean direct radiance leaving the frame's shaded surfaces, scaled by ``sum_{k<B} r^k`` for
    ``B`` bounces (``r`` the frame's mean ``rho (1 - V)``: light bouncing again). See
    :func:`indirect_light`. ``V`` is traced through the scene's Gaussians, not through objects an
    edit inserted or moved (tracers built with ``objects=True``): the side of an inserted car
    facing its own shadow reflects little, and as a blocker it added the frame's mean radiance
    to its contact shadow (the default scene's quick reconstruction, ``bench_insertion.py``,
    city 36 / 216 / 306: cast-shadow IoU 0.577 / 0.638 / 0.558 with the car in ``V``)."""
    opaque_above: float = 1.0
    """Pixels whose composited opacity ``O`` is at least this are surfaces: ``C_pbr = L_r``, the
    coverage renormalised as the G-buffers are (expected values given a hit), instead of
    ``(1 - O) E(d) + O L_r``. 1.0 = the paper's blend everywhere. A reconstructed road or wall is
    0.93-0.98 opaque in a quarter of its pixels (splat layers, not glass), and the blend shows
    the map's own lower hemisphere through it: under the courtyard map, whose floor is sunlit,
    the default scene's road came out in orange blotches 3-10x brighter than Mitsuba's. The
    scenarios and the stages use 0.5 (below it a pixel is sky or a silhouette's edge and keeps
    the blend)."""
    indirect_specular_rays: int = 0
    """GGX-sampled shadow rays per pixel of the specular bounce (:func:`indirect_light`; 0 = the
    bounce reaches the diffuse lobe only): blocked directions of the specular lobe reflect the
    same ``L_b``, so glass and metal reflect the street's facades instead of black. Only with
    ``indirect_bounces`` > 0."""
    indirect_rays: int = 4
    """Cosine-sampled shadow rays per pixel estimating ``V`` of the indirect term (4 and 8 gave
    the same relit PSNR on the default scene, 19.02 dB, after the denoiser; each ray costs about
    what 4-5 rays of the fused integrator do)."""
    seed: int = 0
    """Random seed (frames of a clip add their index)."""
    threads: int = 0
    """Kernel threads; 0 = every core this process may use."""
    trace: TraceSettings = field(default_factory=lambda: TraceSettings(leaf_size=16))
    """Shadow-ray settings (offset along the ray, early stop, BVH leaf size)."""
    object_solids: bool = False
    """Shadow rays of a :class:`core.scene_graph.SceneGraph` also meet each tracked object's
    inside, filled with opaque Gaussians (:meth:`core.scene_graph.SceneGraph.node_solid`): a
    reconstructed car is a thin shell of splats that lets a fifth of the light through. Off here
    and in the pbr and joint stages; on in the relight scenarios and the evaluation
    (:attr:`core.render.scenario.Scenario.object_solids`)."""

    def __post_init__(self) -> None:
        def is_int(v, lo, hi):
            return not isinstance(v, bool) and isinstance(v, int) and lo <= v <= hi

        def is_num(v, lo, hi, lo_open=False):
            return (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi
                    and not (lo_open and v == lo))

        checks = {
            "rays_per_pixel": is_int(self.rays_per_pixel, 1, 1 << 20),
            "sampling": self.sampling in SAMPLINGS,
            "backend": self.backend in BACKENDS,
            "exposure": is_num(self.exposure, 0.0, 1e12, True),
            "gamma": is_num(self.gamma, 0.0, 100.0, True),
            "specular": is_num(self.specular, 0.0, 1.0),
            "diffuse": self.diffuse in DIFFUSE_MODELS,
            "masking": self.masking in MASKING_MODELS,
            "normal_offset": is_num(self.normal_offset, 0.0, 10.0),
            "sky_opacity": is_num(self.sky_opacity, 0.0, 1.0),
            "opaque_above": is_num(self.opaque_above, 0.0, 1.0, True),
            "adaptive_tol": is_num(self.adaptive_tol, 0.0, 1.0, True),
            "adaptive_batch": is_int(self.adaptive_batch, 1, 1 << 20),
            "adaptive_min_batches": is_int(self.adaptive_min_batches, 2, 1 << 20),
            "roulette": is_num(self.roulette, 0.0, 100.0),
            "cache_cell_px": is_num(self.cache_cell_px, 0.0, 64.0, True),
            "cache_pool": is_int(self.cache_pool, 16, 1 << 22),
            "cache_check": is_num(self.cache_check, 0.0, 1.0),
            "seed": is_int(self.seed, 0, 2 ** 52),
            "indirect_bounces": is_int(self.indirect_bounces, 0, 16),
            "indirect_rays": is_int(self.indirect_rays, 1, 1024),
            "indirect_specular_rays": is_int(self.indirect_specular_rays, 0, 1024),
            "threads": is_int(self.threads, 0, 4096),
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"{name}: invalid value {getattr(self, name)!r}")
        for name in ("skip_sky", "cull_lights", "adaptive", "reuse_visibility", "shadows", "object_solids"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}: expected a bool, got {getattr(self, name)!r}")
        if not isinstance(self.trace, TraceSettings):
            raise ConfigError(f"trace: expected TraceSettings, got {type(self.trace).__name__}")

    @property
    def split(self) -> tuple[int, int]:
        """(environment samples, BRDF samples) per pixel."""
        n = self.rays_per_pixel
        if self.sampling == "env":
            return n, 0
        if self.sampling == "brdf":
            return 0, n
        return (n + 1) // 2, n // 2


#: Margin (metres) of an edited object's box within which a shading point lies on the object.
OBJECT_MARGIN_M = 0.1
#: The lowest part of an edited object's box (metres) whose points are not on the object: the
#: road under and beside it, which must keep the object's contact shadow.
OBJECT_FLOOR_M = 0.15


def on_objects(points: torch.Tensor, boxes) -> torch.Tensor:
    """Bool ``[P]``: the points (world, metres) inside one of ``boxes`` (``(obj_to_world [4, 4],
    (l, w, h))``, the box centred on the object frame's origin) grown by ``OBJECT_MARGIN_M``,
    and above its lowest ``OBJECT_FLOOR_M`` (or its lower half, when thinner)."""
    out = torch.zeros(points.shape[0], dtype=torch.bool)
    p = points.detach().to(torch.float64)
    for pose, size in boxes:
        m = torch.as_tensor(np.asarray(pose, np.float64))
        q = (p - m[:3, 3]) @ m[:3, :3]  # object frame
        half = torch.as_tensor(np.asarray(size, np.float64)) / 2.0
        floor = min(OBJECT_FLOOR_M, float(half[2]))  # an object thinner than that: its upper half
        inside = (q.abs() <= half + OBJECT_MARGIN_M).all(-1) & (q[:, 2] > -half[2] + floor)
        out |= inside
    return out


@dataclass
class ShadingInputs:
    """Per-pixel shading inputs ``[H*W, C]`` (torch, flattened row-major) from the G-buffers."""

    points: torch.Tensor
    normals: torch.Tensor
    wo: torch.Tensor
    view_dirs: torch.Tensor
    albedo: torch.Tensor
    roughness: torch.Tensor
    metallic: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor


@dataclass
class PBRResult:
    """One rendered frame. ``hdr``, ``ldr``, ``lr``: ``[H, W, 3]`` torch (``hdr`` = C_pbr,
    ``lr`` = O L_r, or L_r where O >= ``opaque_above``); ``samples`` ``[H, W]`` int (samples
    spent per pixel); ``gbuffers``: the
    rasterizer's layers as expected values (``depth`` in metres, 0 on sky; ``normal`` unit, facing
    the camera; ``opacity``); ``timings`` (seconds) and ``counters``. With ``pixels`` given, the
    image tensors are ``[K, 3]`` for those flat pixel indices."""

    hdr: torch.Tensor
    ldr: torch.Tensor
    lr: torch.Tensor
    samples: torch.Tensor
    gbuffers: dict
    timings: dict
    counters: dict


def shading_inputs(gbuf, camera: Camera, sky_opacity: float = 1.0 / 255.0) -> ShadingInputs:
    """Unproject the G-buffers (a :class:`core.raster.RasterOutput` or a dict with ``opacity``,
    ``depth``, ``normal``, ``albedo``, ``roughness``, ``metallic`` ``[H, W, C]`` accumulated
    sums) into per-pixel shading inputs (see the module docstring)."""
    g = gbuf.as_dict() if hasattr(gbuf, "as_dict") else dict(gbuf)
    cam = Camera.of(camera)
    h, w = cam.height, cam.width
    for k, c in (("opacity", 1), ("depth", 1), ("normal", 3), ("albedo", 3), ("roughness", 1), ("metallic", 1)):
        t = g.get(k)
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (h, w, c):
            raise ShapeError(f"gbuffers[{k!r}]: expected a tensor [{h}, {w}, {c}], got "
                             f"{getattr(t, 'shape', type(t).__name__)}")
    dt = g["opacity"].dtype
    o = g["opacity"].reshape(-1, 1).clamp(0.0, 1.0)
    inv = torch.where(o > 0, 1.0 / torch.where(o > 0, o, torch.ones_like(o)), torch.zeros_like(o))
    d = torch.from_numpy(cam.ray_directions()).to(dt).reshape(-1, 3)
    c2w = torch.as_tensor(cam.pose_numpy(), dtype=dt)
    fwd = c2w[:3, 2]
    z = (g["depth"].reshape(-1, 1) * inv).clamp_min(0.0)
    pts = c2w[:3, 3] + d * (z / (d @ fwd)[:, None])
    n = g["normal"].reshape(-1, 3)
    n2 = (n * n).sum(-1, keepdim=True)
    n = torch.where(n2 > 1e-12, n / torch.sqrt(torch.where(n2 > 1e-12, n2, torch.ones_like(n2))), torch.zeros_like(n))
    wo = -d
    n = torch.where((n * wo).sum(-1, keepdim=True) < 0, -n, n)
    return ShadingInputs(pts, n, wo, d, (g["albedo"].reshape(-1, 3) * inv).clamp(0, 1),
                         (g["roughness"].reshape(-1, 1) * inv).clamp(0, 1),
                         (g["metallic"].reshape(-1, 1) * inv).clamp(0, 1), o, z)


def sample_pixels(opacity: torch.Tensor, n: int = 2048, *, generator: torch.Generator | None = None,
                  sky_opacity: float = 1.0 / 255.0) -> torch.Tensor:
    """``n`` random flat indices of non-sky pixels (without replacement; all of them if fewer)
    of an opacity ``[H, W, 1]`` or ``[H, W]`` buffer: the training subset."""
    o = opacity.detach().reshape(-1)
    cand = torch.nonzero(o >= sky_opacity).reshape(-1)
    if cand.numel() <= n:
        return cand
    perm = torch.randperm(cand.numel(), generator=generator)[:n]
    return cand[perm].sort().values


def indirect_light(points: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor, metallic: torch.Tensor,
                   direct: torch.Tensor, tracers, *, bounces: int = 2, rays: int = 4, normal_offset: float = 0.02,
                   generator: torch.Generator | None = None, wo: torch.Tensor | None = None,
                   roughness: torch.Tensor | None = None, specular_rays: int = 0, masking: str = "smith",
                   specular: float = 1.0) -> torch.Tensor:
    """Approximate diffuse indirect light ``[P, 3]`` (same units as ``direct``) at shading points.

    A direction that the Gaussians block sees another surface of the scene instead of the map.
    Its radiance is approximated by ``L_b``, the mean of ``direct`` (the direct radiance leaving
    the shaded points, ``[P, 3]``) over the points, so

        L_ind = rho (1 - V) L_b sum_{k < bounces} r^k,    rho = (1 - metallic) albedo,

    with ``V`` the cosine-weighted visibility of each point (``rays`` cosine-sampled shadow rays
    through ``tracers``, their product, from ``normal_offset`` metres off the surface) and
    ``r`` the mean of ``rho (1 - V)`` (each further bounce returns that share). For a Lambertian
    receiver the blocked part of the hemisphere then reflects ``rho (1 - V) L_b``, exactly when
    every blocking surface leaves radiance ``L_b``. Not in the paper, which renders direct light
    only: measured with Mitsuba (``benchmarks/bench_visibility.py``) the light that bounces is
    18-22% of a street's radiance.

    With ``specular_rays`` > 0 the blocked part of the *specular* lobe sees the same ``L_b``:

        L_ind += L_b sum_{k < bounces} r^k  E_j[(1 - V(wi_j)) f_s(wi_j, wo) (n . wi_j) / p(wi_j)]

    over ``specular_rays`` GGX visible-normal samples ``wi_j`` (density ``p``), ``f_s`` the
    microfacet term of the BRDF (:func:`core.pbr.brdf.specular_lobe`). Without it a window or a
    metal car reflects black wherever its mirror direction meets the street's own buildings
    (the diffuse bounce gives a metal nothing: ``rho = 0``), where Mitsuba reflects the facades.

    Args:
        points, normals: ``[P, 3]`` world, metres; unit normals (a zero normal gets no light).
        albedo: ``[P, 3]``; metallic ``[P, 1]``; direct ``[P, 3]`` (gradients flow through
            ``albedo``, ``metallic``, ``roughness`` and ``direct``; visibility and the sampled
            directions have none).
        tracers: :class:`GaussianTracer` objects (visibility = their product).
        wo: ``[P, 3]`` unit directions toward the viewer and ``roughness`` ``[P, 1]``: needed
            when ``specular_rays`` > 0.
        specular_rays: GGX samples per point of the specular bounce (0 = diffuse bounce only).
        masking, specular: the BRDF's masking term and microfacet scale
            (:attr:`PBRSettings.masking`, :attr:`PBRSettings.specular`).
    """
    if points.shape[0] == 0:
        return torch.zeros_like(direct)
    if not (isinstance(bounces, int) and bounces >= 1 and isinstance(rays, int) and rays >= 1):
        raise ConfigError(f"bounces, rays: expected ints >= 1, got {bounces!r}, {rays!r}")
    if not (isinstance(specular_rays, int) and specular_rays >= 0):
        raise ConfigError(f"specular_rays: expected an int >= 0, got {specular_rays!r}")
    if specular_rays and (wo is None or roughness is None or wo.shape != points.shape
                          or roughness.shape != (points.shape[0], 1)):
        raise ShapeError(f"wo, roughness: expected [P, 3] and [P, 1] with P = {points.shape[0]} when "
                         f"specular_rays > 0, got {None if wo is None else tuple(wo.shape)}, "
                         f"{None if roughness is None else tuple(roughness.shape)}")

    p = points.shape[0]
    with torch.no_grad():
        n = normals.detach().to(torch.float64)
        u = torch.rand(p, rays, 2, generator=generator, dtype=torch.float64)
        wi = sample_cosine(n[:, None, :].expand(p, rays, 3), u).reshape(-1, 3)
        org = (points.detach().to(torch.float64) + normal_offset * n)[:, None, :].expand(p, rays, 3).reshape(-1, 3)
        v = torch.ones(p * rays, dtype=torch.float64)
        for t in tracers:
            v = v * t(org, wi).to(torch.float64)
        lit = (n * n).sum(-1) > 0.5  # a zero normal (nothing composited) reflects nothing
        blocked = torch.where(lit, 1.0 - v.reshape(p, rays).mean(1), torch.zeros(p, dtype=torch.float64))
    rho = (1.0 - metallic) * albedo
    occ = blocked.to(rho.dtype)[:, None]
    r = (rho * occ).mean(0)
    gain = sum(r ** k for k in range(bounces))
    bounce = direct.mean(0) * gain
    out = rho * occ * bounce
    if specular_rays:
        out = out + _specular_bounce(points, n, wo, albedo, roughness, metallic, tracers, specular_rays,
                                     normal_offset, generator, masking, specular, lit) * bounce
    require_finite(out, "indirect light")
    return out


def _specular_bounce(points, n, wo, albedo, roughness, metallic, tracers, rays: int, normal_offset: float,
                     generator, masking: str, specular: float, lit: torch.Tensor) -> torch.Tensor:
    """``E_j[(1 - V(wi_j)) f_s (n . wi_j) / p(wi_j)]`` ``[P, 3]`` of :func:`indirect_light` (dtype of
    ``albedo``): the share of a unit radiance from every blocked direction that the specular lobe
    reflects toward ``wo``."""
    p = points.shape[0]
    dt = albedo.dtype
    with torch.no_grad():
        ne = n[:, None, :].expand(p, rays, 3)
        woe = safe_normalize(wo.detach().to(torch.float64))[:, None, :].expand(p, rays, 3)
        re = roughness.detach().to(torch.float64)[:, None, :].expand(p, rays, 1)
        u = torch.rand(p, rays, 2, generator=generator, dtype=torch.float64)
        wi = sample_ggx_vndf(ne, woe, re, u)
        pdf = pdf_ggx_vndf(ne, wi, woe, re)
        cos = (ne * wi).sum(-1, keepdim=True)
        ok = (cos > 0) & (pdf > EPS_PDF) & lit[:, None, None]
        org = (points.detach().to(torch.float64) + normal_offset * n)[:, None, :].expand(p, rays, 3).reshape(-1, 3)
        v = torch.ones(p * rays, dtype=torch.float64)
        for t in tracers:
            v = v * t(org, wi.reshape(-1, 3)).to(torch.float64)
        scale = torch.where(ok, (1.0 - v.reshape(p, rays, 1)) * cos / torch.where(ok, pdf, torch.ones_like(pdf)),
                            torch.zeros_like(pdf)).to(dt)
    f = specular_lobe(ne.to(dt), wi.to(dt), woe.to(dt), albedo[:, None, :].expand(p, rays, 3),
                      roughness[:, None, :].expand(p, rays, 1), metallic[:, None, :].expand(p, rays, 1), masking)
    return specular * (f * scale).mean(1)


def tonemap(hdr: torch.Tensor, exposure: float, gamma: float) -> torch.Tensor:
    """``clip(exposure * hdr, 0, 1)^(1/gamma)`` (torch; the gradient is finite at 0)."""
    x = (hdr * exposure).clamp(0.0, 1.0)
    return torch.where(x > 1e-8, torch.pow(x.clamp_min(1e-8), 1.0 / gamma), torch.zeros_like(x))


class FrameContext:
    """What several frames share: the environment map, its kernel tables, the static BVH and an
    optional visibility cache. Build once per (environment, static scene)."""

    def __init__(self, env: EnvironmentMap, settings: PBRSettings, static_gaussians=None,
                 static_tracer: GaussianTracer | None = None):
        self.env = env
        self.settings = settings
        self.native_env = NativeEnv(env) if settings.backend == "native" else None
        if static_tracer is None and static_gaussians is not None and static_gaussians.num > 0 and settings.shadows:
            static_tracer = GaussianTracer.from_gaussians(static_gaussians, settings.trace)
        self.static_tracer = static_tracer if settings.shadows else None
        self.cache = None
        if settings.reuse_visibility and settings.shadows and self.native_env is not None:
            self.cache = VisibilityCache(self.native_env, pool_size=settings.cache_pool,
                                         cell_px=settings.cache_cell_px, block=max(1, settings.split[0]),
                                         seed=settings.seed + 12345)


def render_pbr(gbuf, camera, env: EnvironmentMap, *, settings: PBRSettings | None = None, tracers=(),
               lights=None, pixels: torch.Tensor | None = None, context: FrameContext | None = None,
               frame_index: int = 0, generator: torch.Generator | None = None, object_boxes=()) -> PBRResult:
    """The PBR pass on G-buffers (see the module docstring).

    Args:
        gbuf: :class:`core.raster.RasterOutput` (or a dict of accumulated ``[H, W, C]`` layers).
        camera: :class:`Camera` (or any object with its attributes).
        env: the environment map (its radiance and sampling tables).
        tracers: up to three :class:`GaussianTracer` in all with the ``context``'s static one
            (visibility = their product, each BVH traced from its own ``t_min``); with a
            ``context``, its static tracer is used in addition. Empty = everything visible.
        lights: a :class:`core.pbr.lights.LightSet` (world frame) or None.
        pixels: flat pixel indices to shade (training subset); the result tensors are then
            ``[K, 3]``. Sky pixels in the subset get ``(1 - O) E(d)`` as everywhere.
        context: a :class:`FrameContext` to reuse tables / static BVH / cache across frames.
        frame_index: added to the seed (clips).
        object_boxes: ``(obj_to_world [4, 4], (l, w, h))`` of each edited object (native
            backend): a shading point inside one, above its lowest ``OBJECT_FLOOR_M`` (the road
            under it stays out), lies on the object, and its shadow rays cross an objects' tracer
            from the scene's ``t_min``, so the object's own Gaussians do not shadow its surface.
        generator: torch generator of the torch backend.
    """
    s = settings or PBRSettings()
    if not isinstance(s, PBRSettings):
        raise ConfigError(f"settings: expected PBRSettings, got {type(s).__name__}")
    if not isinstance(env, EnvironmentMap):
        raise ConfigError(f"env: expected an EnvironmentMap, got {type(env).__name__}")
    cam = Camera.of(camera)
    timings: dict = {}
    t0 = time.perf_counter()
    si = shading_inputs(gbuf, cam, s.sky_opacity)
    hw = cam.height * cam.width
    all_idx = torch.arange(hw) if pixels is None else torch.as_tensor(pixels, dtype=torch.long).reshape(-1)
    if all_idx.numel() and (int(all_idx.min()) < 0 or int(all_idx.max()) >= hw):
        raise ShapeError(f"pixels: indices must be in [0, {hw})")
    o = si.opacity[all_idx]
    shade = (o[:, 0] >= s.sky_opacity) if s.skip_sky else torch.ones(o.shape[0], dtype=torch.bool)
    sel = all_idx[shade]
    tr = [t for t in ((context.static_tracer if context else None), *tracers) if t is not None] if s.shadows else []
    if len(tr) > 3:
        raise ConfigError("tracers: at most three BVHs in total (static, dynamic, edited objects)")
    timings["setup"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    n_env, n_brdf = s.split
    counters: dict = {"shaded_pixels": int(sel.numel())}
    dt = si.points.dtype
    lr_sel = torch.zeros(sel.numel(), 3, dtype=dt)
    samples = torch.zeros(all_idx.numel(), dtype=torch.int32)
    if s.backend == "native":
        nenv = context.native_env if context is not None and context.native_env is not None else NativeEnv(env)
        # the luminance of (1 - O) E(wo) only feeds the adaptive criterion: skip the lookup otherwise
        bg = luminance(env.lookup(si.view_dirs[sel]).detach()) * (1.0 - si.opacity[sel, 0]) if s.adaptive else None
        res = integrate(si.points[sel], si.normals[sel], si.wo[sel], si.albedo[sel], si.roughness[sel],
                        si.metallic[sel], nenv, tr, lights, n_env=n_env, n_brdf=n_brdf, specular=s.specular,
                        diffuse=s.diffuse, masking=s.masking, normal_offset=s.normal_offset,
                        seed=s.seed * 1000003 + frame_index,
                        batch=s.adaptive_batch if s.adaptive else (1 << 30), adapt_tol=s.adaptive_tol if s.adaptive else 0.0,
                        adapt_min_batches=s.adaptive_min_batches, exposure=s.exposure, gamma=s.gamma,
                        weight=si.opacity[sel, 0], background_lum=bg, depth=si.depth[sel, 0],
                        cull_lights=s.cull_lights, cache=context.cache if context else None, camera=cam,
                        threads=s.threads, ids=sel, roulette=s.roulette, cache_check=s.cache_check,
                        cache_bvhs=1 if (tr and context is not None and context.static_tracer is not None) else 0,
                        on_object=on_objects(si.points[sel], object_boxes) if object_boxes and tr else None)
        lr_sel = torch.from_numpy(res.radiance).to(dt)
        samples[shade] = torch.from_numpy(res.samples)
        counters.update(res.counters)
    else:
        def vis(origins, dirs, t_max=None):
            v = torch.ones(origins.shape[0], dtype=torch.float64)
            for t in tr:
                v = v * t(origins, dirs, t_max).to(torch.float64)
            return v

        st: dict = {}
        if sel.numel():
            lr_sel = estimate_reflected(si.points[sel], si.normals[sel], si.wo[sel], si.albedo[sel],
                                        si.roughness[sel], si.metallic[sel], env, n_rays=s.rays_per_pixel,
                                        strategy=s.sampling, visibility=vis if tr else None, generator=generator,
                                        specular=s.specular, diffuse=s.diffuse, masking=s.masking,
                                        normal_offset=s.normal_offset, stats=st).to(dt)
            if lights is not None and len(lights):
                lr_sel = lr_sel + direct_lighting(si.points[sel], si.normals[sel], si.wo[sel], si.albedo[sel],
                                                  si.roughness[sel], si.metallic[sel], lights,
                                                  visibility=vis if tr else None, cull=s.cull_lights,
                                                  specular=s.specular, diffuse=s.diffuse, masking=s.masking,
                                                  normal_offset=s.normal_offset, stats=st).to(dt)
        samples[shade] = s.rays_per_pixel
        counters.update(st)
    timings["shade"] = time.perf_counter() - t1
    # the bounce's blocked directions see the scene, not an edited object: an inserted car's
    # shadowed side reflects little, and counting it as the frame's mean radiance lit its contact
    # shadow (benchmarks/bench_insertion.py: mean IoU 0.685 with it, see PBRSettings.indirect_bounces)
    tr_ind = [t for t in tr if not getattr(t, "objects", False)]
    if s.indirect_bounces > 0 and tr_ind and sel.numel():
        t3 = time.perf_counter()
        gen = generator if generator is not None else torch.Generator().manual_seed(s.seed * 1000003 + frame_index)
        lr_sel = lr_sel + indirect_light(si.points[sel], si.normals[sel], si.albedo[sel], si.metallic[sel], lr_sel,
                                         tr_ind, bounces=s.indirect_bounces, rays=s.indirect_rays,
                                         normal_offset=s.normal_offset, generator=gen, wo=si.wo[sel],
                                         roughness=si.roughness[sel], specular_rays=s.indirect_specular_rays,
                                         masking=s.masking, specular=s.specular).to(dt)
        timings["indirect"] = time.perf_counter() - t3
    t2 = time.perf_counter()
    lr = torch.zeros(all_idx.numel(), 3, dtype=dt)
    lr = lr.index_put((torch.nonzero(shade).reshape(-1),), lr_sel)
    # the surface's share of the pixel: O, or all of it where O says surface (opaque_above)
    w = torch.where(o >= s.opaque_above, torch.ones_like(o), o)
    lr = lr * w
    # E(wo) only where the environment shows through (w < 1): most pixels are opaque surfaces
    see_sky = torch.nonzero(w[:, 0] < 1.0).reshape(-1)
    sky = torch.zeros(all_idx.numel(), 3, dtype=dt)
    if see_sky.numel():
        sky = sky.index_put((see_sky,), env.lookup(si.view_dirs[all_idx[see_sky]]).to(dt))
    hdr = (1.0 - w) * sky + lr
    ldr = tonemap(hdr, s.exposure, s.gamma)
    g = gbuf.as_dict() if hasattr(gbuf, "as_dict") else dict(gbuf)
    gb = {
        "opacity": si.opacity.detach().reshape(cam.height, cam.width, 1),
        "depth": torch.where(si.opacity > s.sky_opacity, si.depth, torch.zeros_like(si.depth)).detach()
        .reshape(cam.height, cam.width, 1),
        "normal": si.normals.detach().reshape(cam.height, cam.width, 3),
        "albedo": si.albedo.detach().reshape(cam.height, cam.width, 3),
        "roughness": si.roughness.detach().reshape(cam.height, cam.width, 1),
        "metallic": si.metallic.detach().reshape(cam.height, cam.width, 1),
    }
    if "color" in g and isinstance(g["color"], torch.Tensor):
        gb["color"] = g["color"].detach()
    if pixels is None:
        hdr = hdr.reshape(cam.height, cam.width, 3)
        ldr = ldr.reshape(cam.height, cam.width, 3)
        lr = lr.reshape(cam.height, cam.width, 3)
        samples = samples.reshape(cam.height, cam.width)
    timings["compose"] = time.perf_counter() - t2
    return PBRResult(hdr, ldr, lr, samples, gb, timings, counters)


#: Frame contexts kept for reuse across clips (:class:`ClipHook` with ``reuse_across_clips``),
#: least recently used dropped first. One: a visibility cache holds ~150 MB (2^21 cells x the
#: environment samples per pixel x 2 bytes), and a request under another map still finds the
#: BVH in it before it is replaced.
SHARED_CONTEXTS = 1
_shared: "OrderedDict[tuple, FrameContext]" = OrderedDict()
_shared_lock = threading.Lock()
_clip_hook: ContextVar["ClipHook | None"] = ContextVar("clip_hook", default=None)


def gaussians_fingerprint(g) -> str:
    """A content hash of Gaussians' shadow-casting fields (means, rotations, scales, opacities):
    clips share shadow rays only when their shadow casters are the same to the bit."""
    if g is None or g.num == 0:
        return "empty"
    h = hashlib.blake2b(digest_size=16)
    for k in ("means", "quats", "log_scales", "opacity_logits"):
        h.update(getattr(g, k).detach().to(torch.float64).contiguous().numpy().tobytes())
    return h.hexdigest()


def _env_fingerprint(env: EnvironmentMap) -> str:
    return hashlib.blake2b(env.radiance_map().detach().to(torch.float32).contiguous().numpy().tobytes(),
                           digest_size=16).hexdigest()


def clear_shared_contexts() -> None:
    """Forget every frame context kept for reuse across clips."""
    with _shared_lock:
        _shared.clear()


class ClipHook:
    """What a caller wants of the :class:`ClipRenderer` built inside a function it does not
    control (:func:`core.relight.render_clip`); install it with ``with hook:``.

    ``reuse_across_clips``: the frame context (the static shadow-ray BVH; with the same
    environment map and sampling, the visibility cache and the map's kernel tables too) comes from
    a clip rendered before in this process when its static shadow casters are the same
    (:func:`gaussians_fingerprint`), and is kept for the next (:data:`SHARED_CONTEXTS`). A relight
    request after another of the same reconstruction then builds no BVH; one under the same map
    starts with a warm visibility cache.

    Records over the frames rendered while installed: ``frames``, ``samples`` and
    ``shaded_pixels`` (what the adaptive sampler spent), ``reused`` (what came from an earlier
    clip: None, ``"bvh"`` or ``"bvh+visibility"``) and ``setup_seconds``."""

    def __init__(self, reuse_across_clips: bool = False):
        self.reuse_across_clips = bool(reuse_across_clips)
        self.frames = 0
        self.samples = 0
        self.shaded_pixels = 0
        self.reused: str | None = None
        self.setup_seconds = 0.0
        self._token = None

    def __enter__(self) -> "ClipHook":
        self._token = _clip_hook.set(self)
        return self

    def __exit__(self, *exc) -> None:
        _clip_hook.reset(self._token)

    def context(self, env: EnvironmentMap, settings: "PBRSettings", shadow_static) -> FrameContext:
        """The frame context of a new clip (shared or new, see the class docstring)."""
        t0 = time.perf_counter()
        try:
            if not (self.reuse_across_clips and settings.shadows and shadow_static is not None):
                return FrameContext(env, settings, static_gaussians=shadow_static)
            g_key = (gaussians_fingerprint(shadow_static), settings.trace)
            full_key = g_key + (_env_fingerprint(env), settings.backend, settings.reuse_visibility,
                                settings.cache_pool, settings.cache_cell_px, settings.split[0], settings.seed,
                                settings.normal_offset)
            with _shared_lock:
                ctx = _shared.get(full_key)
                if ctx is not None:
                    _shared.move_to_end(full_key)
                    self.reused = "bvh+visibility" if ctx.cache is not None else "bvh"
                    return ctx
                tracer = next((c.static_tracer for k, c in reversed(_shared.items())
                               if k[:2] == g_key and c.static_tracer is not None), None)
            if tracer is not None:
                self.reused = "bvh"
            ctx = FrameContext(env, settings, static_gaussians=shadow_static, static_tracer=tracer)
            with _shared_lock:
                _shared[full_key] = ctx
                while len(_shared) > SHARED_CONTEXTS:
                    _shared.popitem(last=False)
            return ctx
        finally:
            self.setup_seconds += time.perf_counter() - t0

    def record(self, res: PBRResult) -> None:
        self.frames += 1
        self.samples += int(res.samples.sum())
        self.shaded_pixels += int(res.counters.get("shaded_pixels", 0))

    @property
    def mean_samples(self) -> float | None:
        """Mean samples per shaded pixel (None before any shaded pixel)."""
        return self.samples / self.shaded_pixels if self.shaded_pixels else None


class ClipRenderer:
    """Render frames of a scene along a camera path with reuse across frames.

    Args:
        scene: a :class:`core.scene_graph.SceneGraph` or a :class:`core.gaussians.Gaussians`
            (static).
        env: environment map.
        settings: :class:`PBRSettings`.
        lights: list of :class:`core.pbr.lights.PointLight` / ``SpotLight`` (placed per frame by
            the node poses).
        static_reuse: build the shadow-ray BVH of the background and static nodes once (True) or
            rebuild the whole BVH every frame (False: the "without" of that skip).
        raster_settings: :class:`core.raster.RasterSettings` for the G-buffers.
    """

    def __init__(self, scene, env: EnvironmentMap, settings: PBRSettings | None = None, *, lights=(),
                 static_reuse: bool = True, raster_settings=None):
        self.settings = settings or PBRSettings()
        self.env = env
        self.lights = list(lights)
        self.static_reuse = bool(static_reuse)
        self.raster_settings = raster_settings or RasterSettings(threads=self.settings.threads or None)
        if isinstance(scene, SceneGraph):
            self.graph = scene
            self.static = scene._static_part().detach() if self.static_reuse else None
        elif isinstance(scene, Gaussians):
            self.graph = None
            self.static = scene.detach()
        else:
            raise ConfigError(f"scene: expected a SceneGraph or Gaussians, got {type(scene).__name__}")
        t0 = time.perf_counter()
        # edited objects (inserted or moved) get a BVH of their own, traced from t_min_objects, when
        # that differs from t_min (otherwise nothing changes: same BVHs as without the option)
        ts = self.settings.trace
        self.objects = (self.graph.edited_nodes() if self.graph is not None and self.settings.shadows
                        and ts.t_min_objects is not None and ts.t_min_objects != ts.t_min else frozenset())
        # static shadow casters: the static part plus the graph's shadow-only occluders
        sol = self.settings.object_solids
        shadow_static = (self.graph.shadow_static_except(self.objects, sol) if self.graph is not None
                         else self.static) if self.static_reuse else None
        self.hook = _clip_hook.get()
        self.context = (self.hook.context(env, self.settings, shadow_static) if self.hook is not None
                        else FrameContext(env, self.settings, static_gaussians=shadow_static))
        self.setup_seconds = time.perf_counter() - t0

    def _with_shadow_only(self, g: Gaussians, time_s: float, names) -> Gaussians:
        """``g`` (composed at ``time_s``) plus the graph's occluders and, with
        :attr:`PBRSettings.object_solids`, the interior fills of the nodes in ``names``."""
        parts = [g]
        occ = self.graph.occluders
        if occ is not None and occ.num:
            parts.append(occ.detach().to(g.dtype))
        if self.settings.object_solids:
            sol_g = self.graph.solids_at(time_s, names)
            if sol_g is not None:
                parts.append(sol_g.detach().to(g.dtype))
        return Gaussians.cat(parts) if len(parts) > 1 else g

    def render(self, camera, time_s: float = 0.0, frame_index: int = 0) -> PBRResult:
        cam = Camera.of(camera)
        t0 = time.perf_counter()
        with torch.no_grad():
            if self.graph is not None:
                g = self.graph.compose(float(time_s)).detach()
                poses = self.graph.node_poses(float(time_s))
            else:
                g = self.static
                poses = {}
            dyn = obj = None
            if not self.settings.shadows:
                pass  # every light sample is visible: no BVH
            elif self.objects:
                sol = self.settings.object_solids
                obj_g = self.graph.shadow_nodes_at(float(time_s), self.objects, sol)
                if obj_g is not None:
                    obj = GaussianTracer.from_gaussians(obj_g, self.settings.trace, objects=True)
                if self.static_reuse:
                    movers = [n.name for n in self.graph.nodes if not n.is_static and n.name not in self.objects]
                    mov_g = self.graph.shadow_nodes_at(float(time_s), movers, sol)
                else:
                    rest = self.graph.compose(float(time_s), hidden=self.objects).detach()
                    others = [n.name for n in self.graph.nodes if n.name not in self.objects]
                    mov_g = self._with_shadow_only(rest, float(time_s), others)
                if mov_g is not None and mov_g.num:
                    dyn = GaussianTracer.from_gaussians(mov_g, self.settings.trace)
            elif self.static_reuse:
                n_static = self.static.num if self.static is not None else 0
                movers = g.index(slice(n_static, None)) if g.num > n_static else None
                if movers is not None and self.graph is not None and self.settings.object_solids:
                    sol_g = self.graph.solids_at(float(time_s), [n.name for n in self.graph.nodes if not n.is_static])
                    if sol_g is not None:
                        movers = Gaussians.cat([movers, sol_g.detach().to(movers.dtype)])
                if movers is not None:
                    dyn = GaussianTracer.from_gaussians(movers, self.settings.trace)
            else:
                gs = (self._with_shadow_only(g, float(time_s), [n.name for n in self.graph.nodes])
                      if self.graph is not None else g)
                dyn = GaussianTracer.from_gaussians(gs, self.settings.trace) if gs.num else None
            t_bvh = time.perf_counter() - t0
            out = rasterize_gaussians(g, cam, settings=self.raster_settings)
            t_raster = time.perf_counter() - t0 - t_bvh
            ls = lights_to_world(self.lights, poses) if self.lights else None
            boxes = [(poses[n.name].numpy(), n.size) for n in self.graph.nodes
                     if n.name in self.objects and n.name in poses and n.size is not None] if obj else []
            res = render_pbr(out, cam, self.env, settings=self.settings, tracers=[t for t in (dyn, obj) if t],
                             lights=ls,
                             context=self.context, frame_index=frame_index, object_boxes=boxes)
        res.timings["bvh"] = t_bvh
        res.timings["raster"] = t_raster
        res.timings["total"] = time.perf_counter() - t0
        if self.hook is not None:
            self.hook.record(res)
        return res


def write_frame_exr(path: str | os.PathLike, result: PBRResult) -> None:
    """One multi-layer EXR: beauty ``R, G, B`` and ``Lr`` in float32 (never overflows), the
    G-buffers (opacity, depth in metres, normal, albedo, roughness, metallic, color if present)
    and ``samples`` (per pixel) in half (clamped at 65504 by the writer, never Inf)."""
    if result.hdr.dim() != 3:
        raise ShapeError("result: a full frame is needed (rendered without pixels=)")
    layers = {"rgb": result.hdr.detach().to(torch.float32).numpy(),
              "Lr": result.lr.detach().to(torch.float32).numpy()}
    for k, v in result.gbuffers.items():
        layers[k] = v.detach().to(torch.float32).numpy()
    layers["samples"] = result.samples.to(torch.float32).numpy()
    write_exr(path, layers, precision={"rgb": "float", "Lr": "float"})


def write_clip_mp4(path: str | os.PathLike, frames, fps: float = 10) -> None:
    """LDR frames (``[H, W, 3]`` tensors or arrays in [0, 1], or :class:`PBRResult`) as H.264 MP4."""
    def u8(f):
        x = f.ldr if isinstance(f, PBRResult) else f
        x = x.detach().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        return ldr_to_uint8(np.clip(x, 0.0, 1.0))

    write_mp4(path, (u8(f) for f in frames), fps=fps)
