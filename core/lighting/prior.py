"""The lighting prior E_g (paper Eq. 6), physically fitted: an HDR environment map 512x1024 in the
project convention, from posed LDR frames, sky masks and the reconstruction's depth and normals.

Steps (world frame, z up; directions unit; radiance linear = ldr^gamma / exposure)

1. **Sky pixels on the sphere.** Every sky-mask pixel of every frame gets its world ray direction
   (:func:`core.conventions.camera_ray_directions`) and its linear radiance. Pixels at the LDR
   clip (>= ``saturation`` in a channel) are *censored*: the true value is only known to be
   above the clip level.
2. **Sun direction**, two cues, both measurable:
   * *shading*: on unclipped surface pixels of the reconstruction, shading = radiance / albedo
     (= irradiance / pi for Lambertian surfaces). For a candidate direction s the model
     ``S = a + c (1 + n_z) / 2 + e max(0, n . s)`` (ambient, sky dome, sun) is fitted by linear
     least squares; the candidate with the smallest mean |residual| (and e > 0) is the sun.
     Search: a coarse grid over the upper hemisphere, then two finer grids around the best.
     Cast shadows enter only as residual noise (a height-map shadow test from the reconstructed
     depth was tried and made it worse on the default scene: the casters of most shadows on a
     street - buildings behind or above the camera - are never in view).
     With an occluder model the default search (``sun_model="auto"``) uses the sky-patch
     transport of :mod:`core.lighting.sky_transport` instead: the sky as 48 non-negative patches
     seen through the occluders (the observed sky as a prior), the light the frames saw on the
     occluders as interreflection, plus the candidate sun's shadowed term.
   * *sky*: saturated sky pixels forming a compact cluster (angular radius <= ``sun_cluster_deg``,
     most of the saturated pixels): the sun disc in view; accepted when the shading residual at
     its direction is among the best (``sky_cue_tolerance``; else haze / a bright object).
3. **Parametric sky.** log L_c(d) = a_c + b_c z + g_c exp(-gamma(d, s) / 15 deg) for d above the
   horizon (z = elevation sine, gamma the angle to the sun), fitted per channel by robust least
   squares to the observed sky directions (censored residuals for clipped pixels: only a model
   *below* the clip level is penalised), with a weak ridge prior (b -> -0.5: skies darken
   towards the zenith; g -> 0) because the camera sees only a band above the horizon. Below the
   horizon: the median radiance of the non-sky pixels whose rays point down (the ground as seen).
4. **Sun strength.** With the direction fixed, the shading model is refitted per channel; its
   sun coefficient e is E_sun / pi. The sun is composed as a disc of radius
   :data:`SUN_RADIUS_DEG` whose radiance makes its irradiance exactly E_sun on the discrete map.

Evaluation helpers: :func:`sun_direction_error_deg`, :func:`envmap_log_error`,
:func:`brightest_direction` (the sun of a ground-truth map: its brightest pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.camera import Camera
from core.conventions import envmap_directions, envmap_solid_angles, pixel_to_direction, project_points
from core.errors import ConfigError, ShapeError
from core.gen.encoding import area_downsample
from core.lighting.sky_transport import ALBEDO_FLOOR, SkyTransport, TransportSettings, paper_brdf_weights
from core.numerics import require_finite_np

#: Angular radius of the composed sun disc. The real sun is 0.27 deg; 1.5 deg spans a few pixels
#: of a 512x1024 map (0.35 deg per pixel) so importance sampling finds it; its irradiance is exact.
SUN_RADIUS_DEG = 1.5
#: Width of the sky's aureole (glow) term around the sun, degrees.
GLOW_WIDTH_DEG = 15.0
#: Largest log-amplitude of the glow term: the sky next to the sun at most e^5 ~ 150 x brighter
#: than the model without it (sunsets and haze reach tens of times; the sun disc is separate).
MAX_GLOW_LOG = 5.0
#: Largest |log-slope| of the sky radiance in the elevation sine (e^5 ~ 150 x from horizon to
#: zenith).
MAX_SKY_SLOPE_LOG = 5.0
#: Smallest linear radiance of a channel used by the colour cue (about 1/500 of a mid-grey
#: surface under the sun: below it the 8-bit capture has no colour left, only quantisation).
CHROMA_MIN_RADIANCE = 2e-3


@dataclass(frozen=True)
class LightingSettings:
    """Settings of :func:`estimate_lighting`."""

    height: int = 512
    """Rows of the output map (columns = 2 x rows)."""
    saturation: float = 0.98
    """LDR value at or above which a channel counts as clipped."""
    sun_cluster_deg: float = 6.0
    """Largest angular radius of a saturated cluster accepted as the sun in view."""
    sky_cue_tolerance: float = 0.25
    """The sky cue is accepted when the shading residual at its direction is at most
    ``best + tolerance (median - best)`` of the shading search (a direction the shading also
    supports); otherwise the cluster was haze or a bright object."""
    min_shading_contrast: float = 0.02
    """Smallest relative improvement of the best direction's shading residual over the median
    direction's for the shading cue to count (below it: overcast, no sun)."""
    max_points: int = 4000
    """Surface pixels (random subset) used by the shading fit."""
    coarse_step_deg: float = 8.0
    """Step of the coarse sun search grid (azimuth and elevation)."""
    search_starts: int = 4
    """The sun search refines around this many of the best coarse candidates (at least 2.5 grid
    steps apart) and keeps the best refined one: the valley of the true sun is a few degrees wide
    (sharp shadows) and the 8-degree grid can miss it (v14: the true sun's residual 0.259, below
    the 0.263 the single refinement ended at 84 deg away)."""
    min_elevation_deg: float = 2.0
    """Lowest sun elevation searched."""
    max_sky_samples: int = 20000
    """Sky pixels used by the sky fit (random subset)."""
    ridge: float = 0.05
    """Weight of the sky fit's prior residuals (relative to one observation)."""
    seed: int = 0
    """Seed of the random subsets."""
    shadow_offset_m: float = 0.05
    """Shadow rays of the cast-shadow cue start this far above the surface (metres)."""
    max_metallic: float = 0.1
    """With ``metallic`` given: surface samples above it are left out of the shading fit (a
    metal's radiance is a reflection of its surroundings, not albedo x irradiance). Measured with
    ``min_roughness`` on 10 sunny development streets (s100-s111 without the two overcast ones,
    true meshes as occluders): mean sun error 28.6 -> 22.1 deg, median 29.7 -> 23.2."""
    min_roughness: float = 0.5
    """With ``roughness`` given: samples below it are left out (glossy highlights)."""
    min_albedo: float = 0.05
    """Samples whose albedo (mean of RGB) is at or below it are left out of the shading fit
    (radiance / albedo amplifies everything that is not diffuse reflection)."""
    sun_model: str = "auto"
    """Model of the sun search: ``"transport"`` (:mod:`core.lighting.sky_transport`: the sky as
    non-negative patches seen through the occluders, the observed sky as a prior, the light the
    frames saw on the occluders as interreflection), ``"lambert"`` (ambient + uniform dome +
    sun), ``"lambert+transport"`` (the lambert search finds the sun's region, the transport model
    places the sun within ``transport_cone_deg`` of it; needs ``visibility``, else lambert alone)
    or ``"auto"``: transport when an occluder model (``visibility``) is given, else lambert
    (without occluders the patches next to the sun can stand in for it: default scene 94 deg
    off with transport, 14 with lambert). Measured on 8 sunny development streets (city,
    sunrise, sunset: s100, s101, s104-s106, s109-s111) with the true meshes as occluders: mean
    sun error 15.5 -> 12.3 deg, median 13.9 -> 4.6 (lambert -> transport); the five city and
    sunrise streets all within 6.1 deg (lambert: one at 27.6); the three sunsets (sun 3.3 deg
    above the horizon) stay 19-50 deg off with either. The validation city street v14 (city at
    105 deg) stayed 88 deg off with either until the occluders' blurred edges were sharpened
    (``benchmarks/lighting_harness.py``'s ``ORACLE_EDGE_REFINE``, sliver faces in :mod:`core.synth.oracle`), the surfaces got the
    paper's BRDF (``surface_brdf``) and the search several starts (``search_starts``): 3.2 deg."""
    surface_brdf: str = "paper"
    """Reflectance model of the surface samples in the transport fit: ``"lambert"`` (radiance /
    albedo = irradiance / pi) or ``"paper"``: the paper's BRDF with the samples' roughness and
    metallic and the direction they were seen from (:func:`core.lighting.sky_transport.paper_brdf_weights`;
    needs ``albedo`` and ``roughness``, else Lambert, see ``diagnostics["surface_brdf"]``).
    Asphalt (albedo 0.09, roughness 0.85) seen 5-10 deg above the road reflects a sun ahead of
    the camera 2-7x more than Lambert says. Measured with the sharpened oracle occluders and
    ``search_starts=4`` (``benchmarks/eval_lighting.py``, 11 streets): the six city and sunrise
    streets lambert -> paper: largest error 43.1 -> 8.4 deg (s105), others equal within 0.5;
    the five sunsets: v13 54.8 -> 1.8, s111 14.5 -> 86.7 (no sun found: its shading contrast fell
    below ``min_shading_contrast``)."""
    min_view_cos: float = 0.0
    """Surface samples seen at a cosine (normal . direction to the camera) at or below it are left
    out (0: those facing away from the camera, where a view-dependent BRDF is undefined)."""
    transport: TransportSettings = field(default_factory=TransportSettings)
    """Patches and priors of the ``"transport"`` sun model."""
    basin_quantile: float = 0.0
    """The sun search refines only around the low region of its coarse grid: the centroid of the
    candidates with the lowest ``basin_quantile`` of residuals, and the best candidates within
    ``basin_radius_deg`` of it (0 = off: the best candidates anywhere). On a reconstruction the
    landscape is noisy: its lowest point jumps between narrow valleys with the random surface
    subset, while the low region stays put. (Tried beside it and not kept: the sky's aureole as a
    second cue, a parametric sky fitted around each candidate: within 0.4 deg on the three
    development scenes. Again on two low-sun development streets, as a weighted cue over the
    frames' sky luminance with a 15 and a 45 deg glow term: the sky band showed no glow, the sun
    moved 8.2 -> 9.5 and 5.5 -> 14.9 deg, ``benchmarks/results/low_sun_dev_quick.json``.)"""
    chroma_weight: float = 0.0
    """Weight of the colour cue in the ``"lambert"`` sun search (0 = off: luminance only). Sunlight
    is warmer than skylight, so the red/blue ratio of a sample's shading (radiance / albedo, per
    channel) tells sunlit from shaded pixels even where the albedo is off by a grey factor (a
    reconstruction's albedo often bakes some of the sun in, which the luminance cue then reads as
    light). With it the score of a candidate is ``lum / lum_0 + chroma_weight * chroma / chroma_0``:
    the mean |residual| of the luminance fit (:func:`_shading_fit`) and of the chroma fit
    ``log(S_r / S_b) = a + c (1 + n_z) / 2 + e h`` with ``h = t / (t + chroma_knee)``,
    ``t = V max(0, n . s)``, each over the same fit without the sun and at most 1 (a cue whose fit
    has no sun term, ``e <= 0``, counts as 1: no brighter or no warmer sunlit side).

    Measured as the pbr stage's prior search (``benchmarks/bench_sun.py``, ``chroma_weight`` 1.0
    against 0; the volume2 stage of one reconstruction each): default scene (quick) 4.7 -> 10.9
    deg, dev1 (benchmark) 30.1 -> 28.9, dev2 (benchmark, a 7.9 deg sunrise sun) 27.6 -> 27.5: no
    better on the whole, so off; 3.0 on the default scene: 11.5. (Also tried beside it and not
    kept: ranking the search's best coarse candidates 20 deg apart by the PBR pass itself, each
    candidate's sun and the prior's sky with L1-optimal gains on 1024 pixels of each training
    frame: on the default scene it preferred a candidate 30.5 deg off, L1 0.0836, to the
    prior's 4.6 deg one, 0.0865.)"""
    chroma_knee: float = 0.25
    """Sun shading ``V max(0, n . s)`` at which the chroma of a sample is half way from the sky's
    to the sun's (about the ratio of sky to sun irradiance)."""
    basin_radius_deg: float = 15.0
    """Radius around the basin centroid in which refinement starts are taken and refinement
    stays. Measured with ``basin_quantile`` 0.05 on four development reconstructions (two of the
    default scene, dev1, dev2; ``benchmarks/bench_sun.py``): starts within 20 deg whose
    refinement could leave the radius put the sun 11.2 / 32.9 / 6.8 / 38.9 deg off; refinement
    held within 20 deg 11.2 / 6.1 / 6.8 / 38.9, within 15 or 10 deg 11.2 / 6.1 / 6.8 / 22.3."""

    transport_points: int = 4000
    """``sun_model="lambert+transport"``: surface samples (a random subset of the ``max_points``)
    of the transport step (the transport fit's cost grows with samples x patches x rays: on a
    quick development reconstruction 4000 took about 30 s, 16000 over ten minutes)."""
    transport_cone_deg: float = 30.0
    """``sun_model="lambert+transport"``: the transport search stays within this angle of the
    lambert search's sun (the lambert model finds the sun's region, the sky patches of the
    transport model then tell a low sun from its glow: see ``sun_model``)."""

    def __post_init__(self) -> None:
        if self.height < 8 or not (0.5 < self.saturation <= 1.0) or self.max_points < 50 or self.search_starts < 1:
            raise ConfigError(f"LightingSettings out of range: {self}")
        if self.surface_brdf not in ("lambert", "paper"):
            raise ConfigError(f"surface_brdf: must be 'lambert' or 'paper', got {self.surface_brdf!r}")
        if not (-1.0 <= self.min_view_cos < 1.0):
            raise ConfigError(f"min_view_cos: must be in [-1, 1), got {self.min_view_cos}")
        if not (0.0 <= self.basin_quantile < 1.0) or not (0.0 < self.basin_radius_deg <= 180.0):
            raise ConfigError(f"basin_quantile / basin_radius_deg: must be in [0, 1) / (0, 180], got "
                              f"{self.basin_quantile} / {self.basin_radius_deg}")
        if not (self.chroma_weight >= 0.0 and math.isfinite(self.chroma_weight)) or not self.chroma_knee > 0.0:
            raise ConfigError(f"chroma_weight / chroma_knee: expected >= 0 / > 0, got {self.chroma_weight} / "
                              f"{self.chroma_knee}")
        if self.sun_model not in ("auto", "transport", "lambert", "lambert+transport"):
            raise ConfigError(f"sun_model: must be 'auto', 'transport', 'lambert' or 'lambert+transport', got "
                              f"{self.sun_model!r}")
        if self.transport_points < 50:
            raise ConfigError(f"transport_points: must be >= 50, got {self.transport_points}")
        if not (0.0 < self.transport_cone_deg <= 180.0):
            raise ConfigError(f"transport_cone_deg: must be in (0, 180], got {self.transport_cone_deg}")


@dataclass
class LightingEstimate:
    """Result of :func:`estimate_lighting`."""

    envmap: np.ndarray
    """[H, 2H, 3] float32 linear HDR, project equirect convention."""
    sun_dir: np.ndarray
    """[3] unit world direction towards the sun."""
    sun_irradiance: np.ndarray
    """[3] irradiance of the sun on a surface facing it (0 when no sun was found)."""
    sun_source: str
    """``"sky"`` (saturated cluster in view), ``"shadow"`` (shadow score) or ``"none"``."""
    sky_coeffs: np.ndarray
    """[3, 3] per channel (a, b, g) of the sky model."""
    ground_radiance: np.ndarray
    """[3] radiance of the lower hemisphere."""
    diagnostics: dict = field(default_factory=dict)
    """Scores, pixel counts, visibility, ratios: what the estimate rests on."""


# ---------------------------------------------------------------------------------------------
# geometry helpers
# ---------------------------------------------------------------------------------------------

def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _sph(az, el):
    az, el = np.asarray(az, np.float64), np.asarray(el, np.float64)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def sun_direction_error_deg(a, b) -> float:
    """Angle in degrees between two directions."""
    return float(np.degrees(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


def brightest_direction(env) -> np.ndarray:
    """World direction [3] of the brightest pixel (mean of RGB) of an equirect map."""
    lum = np.asarray(env, np.float64).mean(-1)
    r, c = np.unravel_index(int(np.argmax(lum)), lum.shape)
    return pixel_to_direction(r, c, *lum.shape)


def sky_statistics(env, sun_radius_deg: float = 3.0) -> dict:
    """How sunny a map is (a ground-truth map's conditions, beside a sun error): the sun is its
    brightest pixel, its disc everything within ``sun_radius_deg``.

    Returns ``sun_elevation_deg``; ``direct_fraction``: the disc's share of the irradiance on a
    horizontal surface (clear sky with a high sun: 0.7-0.9; overcast: 0); ``sun_share``: the
    disc's share of the map's total power (radiance x solid angle)."""
    e = require_finite_np(np.asarray(env, np.float64), "env")
    if e.ndim != 3 or e.shape[2] != 3 or e.shape[1] != 2 * e.shape[0]:
        raise ShapeError(f"env: expected [H, 2H, 3], got {list(e.shape)}")
    h, w = e.shape[:2]
    lum = e.mean(-1).reshape(-1)
    dirs = envmap_directions(h, w).reshape(-1, 3)
    d_omega = np.repeat(envmap_solid_angles(h, w), w)
    sun = brightest_direction(e)
    disc = dirs @ sun >= math.cos(math.radians(sun_radius_deg))
    horiz = lum * d_omega * np.maximum(dirs[:, 2], 0.0)
    total_h, total = float(horiz.sum()), float((lum * d_omega).sum())
    return {"sun_elevation_deg": float(np.degrees(np.arcsin(np.clip(sun[2], -1.0, 1.0)))),
            "direct_fraction": float(horiz[disc].sum() / total_h) if total_h > 0 else 0.0,
            "sun_share": float((lum * d_omega)[disc].sum() / total) if total > 0 else 0.0}


def envmap_log_error(est, gt, low_res: tuple[int, int] = (64, 128)) -> dict:
    """Log-space errors of an estimated map against ground truth (same convention): mean
    |log(1 + E_est) - log(1 + E_gt)| per pixel weighted by solid angle, at full resolution
    (``log_l1``) and after area-averaging both to ``low_res`` (``log_l1_lowres``: insensitive to
    sub-degree misplacement of the sun), plus the same for the upper hemisphere only
    (``log_l1_sky``)."""
    est, gt = np.asarray(est, np.float32), np.asarray(gt, np.float32)
    if gt.shape != est.shape:
        raise ShapeError(f"est {est.shape} and gt {gt.shape} differ")
    out = {}
    for key, (a, b) in {"": (est, gt), "_lowres": (area_downsample(est, *low_res), area_downsample(gt, *low_res))}.items():
        h, w = a.shape[:2]
        sa = envmap_solid_angles(h, w)[:, None]
        d = np.abs(np.log1p(a) - np.log1p(b)).mean(-1)
        out["log_l1" + key] = float((d * sa).sum() / (sa.sum() * w))
        if key == "":
            top = slice(0, h // 2)
            out["log_l1_sky"] = float((d[top] * sa[top]).sum() / (sa[top].sum() * w))
    return out


# ---------------------------------------------------------------------------------------------
# the estimate
# ---------------------------------------------------------------------------------------------

def _camera_batch(cameras, t: int, h: int, w: int, name: str = "cameras") -> Camera:
    """``cameras`` (a batched :class:`Camera` or a sequence of single ones) as one batch of ``t``
    cameras of image size ``w`` x ``h``; errors name ``name``."""
    if not isinstance(cameras, Camera):
        if isinstance(cameras, (str, bytes)) or not hasattr(cameras, "__iter__"):
            raise ConfigError(f"{name}: expected a batched Camera or a sequence of Camera, "
                              f"got {type(cameras).__name__}")
        cams = list(cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise ConfigError(f"{name}: expected a batched Camera or a non-empty sequence of Camera")
        if len({(c.width, c.height) for c in cams}) != 1:
            raise ShapeError(f"{name}: the frames' cameras have different image sizes")
        cameras = Camera.stack(cams)
    if not cameras.is_batched:
        raise ShapeError(f"{name}: expected a batch of {t} cameras (one per frame), got one camera "
                         f"(Camera.stack a camera per frame)")
    if len(cameras) != t:
        raise ShapeError(f"{name}: expected {t} cameras (one per frame), got {len(cameras)}")
    if (cameras.height, cameras.width) != (h, w):
        raise ShapeError(f"{name}: image size {cameras.width}x{cameras.height} does not match the "
                         f"frames' {w}x{h} (width x height)")
    return cameras


def _check_inputs(frames, cameras, sky, depth, normals):
    f = require_finite_np(np.asarray(frames, np.float32), "frames")
    if f.ndim != 4 or f.shape[-1] != 3:
        raise ShapeError(f"frames: expected [T, H, W, 3] LDR, got {f.shape}")
    t, h, w, _ = f.shape
    p = _camera_batch(cameras, t, h, w)
    s = np.asarray(sky).astype(bool)
    if s.shape != (t, h, w):
        raise ShapeError(f"sky_masks: expected [{t}, {h}, {w}], got {s.shape}")
    d = require_finite_np(np.asarray(depth, np.float32).reshape(t, h, w), "depth")
    n = require_finite_np(np.asarray(normals, np.float32), "normals")
    if n.shape != (t, h, w, 3):
        raise ShapeError(f"normals: expected [{t}, {h}, {w}, 3] (world), got {n.shape}")
    return f, p, s, d, n


def _shading_residuals(nrm, shading, s_dir, vis=None):
    """Least squares of the Lambertian shading model S = a + c (1 + n_z) / 2 + e V max(0, n . s)
    on surface samples (``vis``: the samples' visibility V of direction ``s_dir``, None = 1);
    returns (per-sample residuals [N], (a, c, e))."""
    nd = np.maximum(nrm @ s_dir, 0.0)
    if vis is not None:
        nd = nd * vis
    x = np.stack([np.ones_like(nd), (1.0 + nrm[:, 2]) / 2.0, nd], 1)
    coef, *_ = np.linalg.lstsq(x, shading, rcond=None)
    return shading - x @ coef, coef


def _shading_fit(nrm, shading, s_dir, vis=None):
    """:func:`_shading_residuals` as (mean |residual|, (a, c, e)); inf when e <= 0 (no sun term)."""
    r, coef = _shading_residuals(nrm, shading, s_dir, vis)
    return (float(np.mean(np.abs(r))) if coef[2] > 0 else math.inf), coef


def _null_residual(nrm, y) -> float:
    """Mean |residual| of ``y ~ a + c (1 + n_z) / 2`` (the fit without a sun), floored above 0."""
    x = np.stack([np.ones(len(y)), (1.0 + nrm[:, 2]) / 2.0], 1)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    return max(float(np.mean(np.abs(y - x @ coef))), 1e-12)


def _chroma_fit(nrm, chroma, s_dir, vis, knee: float) -> float:
    """Mean |residual| of ``chroma ~ a + c (1 + n_z) / 2 + e t / (t + knee)``, ``t = V max(0, n . s)``;
    inf when ``e <= 0`` (the sunlit side is not the warmer one)."""
    t = np.maximum(nrm @ s_dir, 0.0)
    if vis is not None:
        t = t * vis
    x = np.stack([np.ones_like(t), (1.0 + nrm[:, 2]) / 2.0, t / (t + knee)], 1)
    coef, *_ = np.linalg.lstsq(x, chroma, rcond=None)
    return float(np.mean(np.abs(chroma - x @ coef))) if coef[2] > 0 else math.inf


def _lambert_score(nrm, shading, vis_of=None, chroma=None, chroma_weight: float = 0.0, chroma_knee: float = 0.25):
    """``score(dirs [K, 3]) -> [K]``: mean |residual| of :func:`_shading_fit` per candidate sun.
    ``vis_of(dirs [K, 3]) -> [K, N]``: the samples' visibility of each candidate (cast shadows).
    ``chroma`` ([N] log(S_r / S_b) of the samples, NaN where unusable) with ``chroma_weight`` > 0:
    the colour cue is added (:attr:`LightingSettings.chroma_weight`)."""
    use_c = chroma is not None and chroma_weight > 0
    if use_c:
        ok = np.isfinite(chroma)
        if ok.sum() < 50:
            use_c = False
        else:
            n_c, c_c = nrm[ok], chroma[ok]
            lum0, chroma0 = _null_residual(nrm, shading), _null_residual(n_c, c_c)

    def score(cands):
        vis = vis_of(cands) if vis_of is not None else [None] * len(cands)
        out = []
        for c, v in zip(cands, vis):
            r = _shading_fit(nrm, shading, c, v)[0]
            if use_c:  # each cue over its no-sun fit; a cue without a sun term counts as that fit
                rc = _chroma_fit(n_c, c_c, c, None if v is None else v[ok], chroma_knee)
                r = min(r / lum0, 1.0) + chroma_weight * min(rc / chroma0, 1.0)
            out.append(r)
        return np.array(out)
    return score


def _transport_in_cone(t_score, centre, s: LightingSettings, diag: dict) -> np.ndarray:
    """The transport search (``t_score``, :func:`_transport_score`) restricted to directions within
    ``s.transport_cone_deg`` of ``centre`` [3] (the lambert search's sun); its best direction, or
    ``centre`` when no candidate in the cone has a sun term. Records ``diag["transport_search"]``."""
    c = _unit(centre)
    cos_c = math.cos(math.radians(s.transport_cone_deg))

    def cone_score(dirs):
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        out = np.full(len(d), np.inf)
        inside = d @ c >= cos_c
        if inside.any():
            out[inside] = t_score(d[inside])
        return out
    t_sun, t_res, d_t = _search_sun(cone_score, s)
    ok = math.isfinite(t_res)
    diag["transport_search"] = {"residual": t_res if ok else None, "contrast": d_t["shading_contrast"],
                                "cone_deg": s.transport_cone_deg, "sun_dir": [round(float(x), 6) for x in t_sun],
                                "moved_deg": round(sun_direction_error_deg(t_sun, c), 2) if ok else 0.0,
                                "used": bool(ok)}
    return _unit(t_sun) if ok else c


def _transport_score(tr):
    """``score(dirs [K, 3]) -> [K]``: mean |residual| of the sky-patch transport fit
    (:class:`core.lighting.sky_transport.SkyTransport`) per candidate sun."""
    def score(cands):
        cols = tr.sun_columns(cands)
        return np.array([tr.fit(cols[:, j])[0] for j in range(cols.shape[1])])
    return score


def _search_sun(score, s: LightingSettings):
    """Coarse grid over the upper hemisphere, then two finer grids around the best residuals
    (with ``s.basin_quantile``: only within ``s.basin_radius_deg`` of the centroid of the grid's
    low region, which is a start too); ``score(dirs [K, 3]) -> [K]`` is the residual of each
    candidate (inf: no sun term)."""
    step = math.radians(s.coarse_step_deg)
    el_min = math.radians(s.min_elevation_deg)
    az = np.arange(-math.pi, math.pi, step)
    el = np.arange(el_min, math.radians(88.0), step)
    a_, e_ = np.meshgrid(az, el, indexing="ij")
    grid = _sph(a_.ravel(), e_.ravel())
    res = score(grid)
    # refine from the best few well-separated coarse candidates: the valley of the true sun is
    # only a few degrees wide (sharp shadows) and can sit between grid points
    allowed = np.isfinite(res)
    basin, cos_basin = None, math.cos(math.radians(s.basin_radius_deg))
    if s.basin_quantile > 0 and allowed.sum() >= 10:
        # the low region of the coarse grid as a whole: its centroid is stable where the single
        # best candidate jumps between narrow valleys of a noisy landscape
        fin = np.flatnonzero(allowed)
        low = fin[res[fin] <= np.quantile(res[fin], s.basin_quantile)]
        c = grid[low].mean(0)
        if np.linalg.norm(c) > 1e-6:
            basin = _unit(c)
            allowed &= grid @ basin >= cos_basin
    starts: list[int] = []
    for i in np.argsort(res):
        if len(starts) == s.search_starts or not np.isfinite(res[i]):
            break
        if allowed[i] and all(grid[i] @ grid[j] < math.cos(2.5 * step) for j in starts):
            starts.append(int(i))
    cand = [(a_.ravel()[i], e_.ravel()[i], float(res[i])) for i in starts]
    if basin is not None:  # the centroid itself is a start too
        cb = float(score(basin[None])[0])
        cand.append((math.atan2(basin[1], basin[0]), math.asin(float(np.clip(basin[2], -1, 1))), cb))
    b0 = int(np.argmin(res))
    best_res, ba, be = math.inf, a_.ravel()[b0], e_.ravel()[b0]
    refined = []
    for ca, ce, cr in cand:
        for fine in (step / 4, step / 16):
            da = np.arange(-4, 5) * fine
            aa, ee = np.meshgrid(ca + da / max(math.cos(ce), 0.2),
                                 np.clip(ce + da, el_min, math.radians(89.0)), indexing="ij")
            cand_dirs = _sph(aa.ravel(), ee.ravel())
            r2 = score(cand_dirs)
            if basin is not None:  # the refinement stays in the basin too
                r2 = np.where(cand_dirs @ basin >= cos_basin, r2, np.inf)
            b2 = int(np.argmin(r2))
            if r2[b2] <= cr:
                ca, ce, cr = aa.ravel()[b2], ee.ravel()[b2], float(r2[b2])
        refined.append(([round(float(x), 6) for x in _sph(ca, ce)], float(cr)))
        if cr < best_res:
            ba, be, best_res = ca, ce, cr
    finite = res[np.isfinite(res)]
    # contrast: how much better the best direction explains the shading than a typical one
    contrast = float(1.0 - best_res / np.median(finite)) if len(finite) else 0.0
    med = float(np.median(finite)) if len(finite) else math.inf
    d = {"shading_residual": best_res, "shading_residual_median": med, "shading_contrast": contrast,
         "candidates": refined}
    if basin is not None:
        d["basin_centroid"] = [round(float(x), 4) for x in basin]
    return _sph(ba, be), best_res, d


def _sky_cluster(dirs_sat: np.ndarray, s: LightingSettings):
    """Centroid of the largest compact cluster of saturated sky directions, or None."""
    if len(dirs_sat) < 3:
        return None
    # greedy clustering on a coarse angular grid: the densest 3-degree cap
    rng = np.random.default_rng(s.seed)
    sub = dirs_sat if len(dirs_sat) <= 4000 else dirs_sat[rng.choice(len(dirs_sat), 4000, replace=False)]
    cos_r = math.cos(math.radians(s.sun_cluster_deg))
    counts = (sub @ sub.T > cos_r).sum(1)
    c = _unit(sub[counts == counts.max()].mean(0))
    member = dirs_sat @ c > cos_r
    frac = member.mean()
    # compact: the cluster must hold most of the saturated pixels (a hazy, broadly clipped sky
    # spreads them over far more than one cap)
    if frac < 0.6:
        return None
    return _unit(dirs_sat[member].mean(0))


def _fit_sky(dirs, rad, censored, sun, s: LightingSettings):
    """Per channel (a, b, g) of log L = a + b z + g glow; censored residuals for clipped pixels."""
    from scipy.optimize import least_squares

    glow = np.exp(-np.degrees(np.arccos(np.clip(dirs @ sun, -1, 1))) / GLOW_WIDTH_DEG) if sun is not None else np.zeros(len(dirs))
    z = dirs[:, 2]
    coeffs = np.zeros((3, 3))
    n = len(dirs)
    lam = math.sqrt(s.ridge * n)
    for c in range(3):
        y = np.log(np.maximum(rad[:, c], 1e-6))
        cen = censored[:, c]

        def res(p):
            m = p[0] + p[1] * z + p[2] * glow
            r = m - y
            r = np.where(cen, np.minimum(r, 0.0), r)  # clipped: only a model below the clip counts
            return np.concatenate([r, [lam * (p[1] + 0.5), lam * p[2]]])

        a0 = np.median(y[~cen]) if (~cen).any() else y.max()
        # bounded: an unobserved sun region once let the glow reach exp(43) (h7 with the
        # transport sun: log error 0.83); the aureole is at most e^MAX_GLOW_LOG x the sky
        sol = least_squares(res, [a0, -0.5, 0.1], loss="soft_l1", f_scale=0.3,
                            bounds=([-np.inf, -MAX_SKY_SLOPE_LOG, 0.0], [np.inf, MAX_SKY_SLOPE_LOG, MAX_GLOW_LOG]))
        coeffs[c] = sol.x
    return coeffs


def sky_radiance(dirs, coeffs, sun, ground) -> np.ndarray:
    """Radiance [..., 3] of the parametric sky (upper hemisphere) and ground (lower) at dirs."""
    d = np.asarray(dirs, np.float64)
    z = d[..., 2]
    glow = np.exp(-np.degrees(np.arccos(np.clip(d @ sun, -1, 1))) / GLOW_WIDTH_DEG) if sun is not None else 0 * z
    L = np.exp(coeffs[None, :, 0] + coeffs[None, :, 1] * z.reshape(-1, 1) + coeffs[None, :, 2] * np.asarray(glow).reshape(-1, 1))
    L = L.reshape(*z.shape, 3)
    return np.where((z >= 0)[..., None], L, np.asarray(ground)[None] * np.ones_like(L))


def compose_envmap(coeffs, sun_dir, sun_irradiance, ground, height: int = 512) -> np.ndarray:
    """The [height, 2 height, 3] map of the sky model plus a sun disc of radius
    :data:`SUN_RADIUS_DEG` whose discrete irradiance equals ``sun_irradiance``."""
    w = 2 * height
    dirs = envmap_directions(height, w)
    env = sky_radiance(dirs.reshape(-1, 3), coeffs, sun_dir, ground).reshape(height, w, 3)
    if sun_dir is not None and np.any(np.asarray(sun_irradiance) > 0):
        disc = dirs @ _unit(sun_dir) >= math.cos(math.radians(SUN_RADIUS_DEG))
        if not disc.any():
            r, c = np.unravel_index(int(np.argmax(dirs @ _unit(sun_dir))), disc.shape)
            disc[r, c] = True
        sa = np.broadcast_to(envmap_solid_angles(height, w)[:, None], disc.shape)
        omega = float(sa[disc].sum())
        env[disc] += np.asarray(sun_irradiance)[None] / omega
    return env.astype(np.float32)


def observed_radiance_lookup(cameras, depth, radiance, invalid, rel_tol: float = 0.05, abs_tol_m: float = 0.15):
    """``radiance_at(points [M, 3]) -> (L [M], known [M] bool)``: the radiance the frames saw at
    world points (metres), from the first frame whose depth map holds the point (|z - depth| <=
    rel_tol z + abs_tol_m) at a valid pixel (``invalid`` [T, H, W]: sky or clipped).

    cameras: the ``T`` frames' cameras, a batched :class:`core.camera.Camera` (or a sequence of
    single ones) of image size W x H (OpenCV camera axes, world metres); depth: [T, H, W] camera
    z-depth, metres; radiance: [T, H, W] linear; invalid: [T, H, W] bool.

    Raises :class:`ShapeError` when the cameras, ``radiance`` or ``invalid`` do not match
    ``depth`` [T, H, W] (each named)."""
    depth = np.asarray(depth)
    if depth.ndim != 3:
        raise ShapeError(f"depth: expected [T, H, W] camera z-depth, got {depth.shape}")
    t_n, h, w = depth.shape
    radiance, invalid = np.asarray(radiance), np.asarray(invalid)
    for name, a in (("radiance", radiance), ("invalid", invalid)):
        if a.shape != depth.shape:
            raise ShapeError(f"{name}: expected [{t_n}, {h}, {w}] like depth, got {a.shape}")
    cams = _camera_batch(cameras, t_n, h, w)
    poses = cams.pose_numpy()
    # per frame (fx, fy, cx, cy) in pixels, as Python floats
    intr = [tuple(float(cams.K[t, i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))) for t in range(t_n)]

    def radiance_at(points):
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.zeros(len(pts))
        known = np.zeros(len(pts), bool)
        for t in range(t_n):
            todo = np.flatnonzero(~known)
            if not len(todo):
                break
            uv, z = project_points(pts[todo], poses[t], *intr[t])
            front = (z > 1e-3) & np.isfinite(uv).all(-1)
            uv = np.floor(np.where(front[:, None], uv, -1.0)).astype(np.int64)
            u, v = uv[:, 0], uv[:, 1]
            ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            uu, vv = np.where(ok, u, 0), np.where(ok, v, 0)
            d = depth[t, vv, uu]
            ok &= (d > 0) & ~invalid[t, vv, uu] & (np.abs(d - z) <= rel_tol * z + abs_tol_m)
            out[todo[ok]] = radiance[t, vv[ok], uu[ok]]
            known[todo[ok]] = True
        return out, known
    return radiance_at


def estimate_lighting(frames_ldr, cameras, sky_masks, depth, normals, *,
                      albedo=None, exposure: float = 1.0, gamma: float = 2.2,
                      settings: LightingSettings | None = None, visibility=None, roughness=None,
                      metallic=None) -> LightingEstimate:
    """Fit the lighting prior (module docstring).

    Args:
        frames_ldr: [T, H, W, 3] LDR in [0, 1] (the captured frames).
        cameras: the frames' cameras, a batch of ``T`` :class:`core.camera.Camera` of image size
            W x H (``Camera.stack`` of one per frame, or that sequence itself): OpenCV camera
            axes, world metres, intrinsics in pixels.
        sky_masks: [T, H, W] bool, True = sky.
        depth: [T, H, W] camera z-depth in metres of the reconstruction (0 / sky ignored).
        normals: [T, H, W, 3] world normals of the reconstruction.
        albedo: [T, H, W, 3] albedo of the reconstruction (strongly recommended: without it the
            shading cue sees albedo differences between surface orientations as lighting).
        exposure, gamma: the frames' tone map (bundle ``ldr``).
        visibility: optional occluder model of the reconstruction, ``(origins [M, 3], dirs
            [M, 3]) -> V [M]`` in [0, 1] (world, metres; e.g. a
            :class:`core.pbr.visibility.GaussianTracer` of its Gaussians): the shading fit then
            models cast shadows, ``e V max(0, n . s)``, for every candidate sun direction.
        roughness, metallic: [T, H, W] (or [T, H, W, 1]) of the reconstruction, optional: glossy
            and metallic pixels (``settings.min_roughness`` / ``max_metallic``) are left out of
            the shading fit.

    Returns:
        :class:`LightingEstimate` (envmap 512x1024 by default).
    """
    s = settings or LightingSettings()
    f, cams, sky, dep, nrm = _check_inputs(frames_ldr, cameras, sky_masks, depth, normals)
    t, h, w, _ = f.shape
    poses = cams.pose_numpy()
    rng = np.random.default_rng(s.seed)
    rad = np.power(f.astype(np.float64), gamma) / exposure
    sat = f >= s.saturation
    rays = np.stack([c.ray_directions() for c in cams])
    diag: dict = {}

    # --- sky observations
    sky_dirs, sky_rad, sky_sat = rays[sky], rad[sky], sat[sky]
    diag["sky_pixels"] = int(len(sky_dirs))
    diag["sky_saturated_fraction"] = float(sky_sat.all(-1).mean()) if len(sky_dirs) else 0.0

    # --- surface samples for the shading fit: shading = radiance / albedo (Lambert: E / pi)
    surf = (~sky) & (dep > 0) & ~sat.any(-1) & (np.linalg.norm(nrm, axis=-1) > 0.5)
    view_cos = -np.einsum("thwc,thwc->thw", _unit(nrm), rays)  # normal . (direction to the camera)
    surf &= view_cos > s.min_view_cos
    mats = {}
    for name, arr, keep in (("roughness", roughness, lambda a: a >= s.min_roughness),
                            ("metallic", metallic, lambda a: a <= s.max_metallic)):
        if arr is not None:
            a = require_finite_np(np.asarray(arr, np.float32), name)
            if a.size != t * h * w:
                raise ShapeError(f"{name}: expected [{t}, {h}, {w}], got {a.shape}")
            mats[name] = a.reshape(t, h, w)
            surf &= keep(mats[name])
    if albedo is not None:
        alb = np.asarray(albedo, np.float64).reshape(t, h, w, 3)
        surf &= alb.mean(-1) > s.min_albedo
        shade_all = (rad[surf] / np.maximum(alb[surf], ALBEDO_FLOOR)).mean(-1)
    else:  # no albedo: luminance only (albedo variation then biases the fit, see module doc)
        shade_all = rad[surf] @ np.array([0.2126, 0.7152, 0.0722])
    diag["surface_pixels"] = int(surf.sum())
    n_all = _unit(nrm[surf])
    idx = np.flatnonzero(np.ones(len(n_all), bool))
    pick = idx if len(idx) <= s.max_points else rng.choice(idx, s.max_points, replace=False)
    nn, shade = n_all[pick], shade_all[pick]
    diag["surface_samples"] = int(len(pick))
    diag["albedo_used"] = albedo is not None
    vis_of = None
    if visibility is not None:  # surface points (camera z-depth along each ray), lifted off the surface
        fwd = poses[:, :3, 2]
        centre = np.broadcast_to(poses[:, None, None, :3, 3], rays.shape)
        zd = dep[..., None] / np.maximum(np.einsum("thwk,tk->thw", rays, fwd)[..., None], 1e-6)
        pts = (centre + rays * zd)[surf][pick] + nn * s.shadow_offset_m

        def vis_of(dirs):
            dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
            o = np.broadcast_to(pts[None], (len(dirs),) + pts.shape).reshape(-1, 3)
            d = np.broadcast_to(dirs[:, None], (len(dirs), len(pts), 3)).reshape(-1, 3)
            v = np.asarray(visibility(o, d), np.float64).reshape(len(dirs), len(pts))
            if not np.isfinite(v).all():
                raise ConfigError("visibility: returned non-finite values")
            return np.clip(v, 0.0, 1.0)
    diag["cast_shadows"] = vis_of is not None

    # --- sun direction
    source, sun, coef = "none", np.array([0.0, 0.0, 1.0]), np.zeros(3)
    if len(pick) >= 50:
        model = s.sun_model if s.sun_model != "auto" else ("transport" if vis_of is not None else "lambert")
        if model == "lambert+transport" and vis_of is None:  # the transport step needs the occluders
            model = "lambert"
        diag["sun_model"] = model
        t_score = None
        if model in ("transport", "lambert+transport"):
            # clipped channels only bound the radiance from below: at the clip level
            sky_low = np.where(sky_sat, (s.saturation ** gamma) / exposure, sky_rad).mean(-1)
            seen = None
            if vis_of is not None and s.transport.interreflection:
                seen = observed_radiance_lookup(cams, dep, rad.mean(-1), sky | sat.any(-1))
            # the transport's samples: all of them, or (the second step of lambert+transport) a
            # random subset of transport_points (its cost grows with samples x patches x rays)
            tp = np.arange(len(pick))
            if model == "lambert+transport" and len(tp) > s.transport_points:
                tp = np.sort(rng.choice(tp, s.transport_points, replace=False))
            diag["transport_samples"] = int(len(tp))
            tpick = pick[tp]
            weights, brdf = None, "lambert"
            if s.surface_brdf == "paper" and albedo is not None and "roughness" in mats:
                met = mats["metallic"][surf][tpick] if "metallic" in mats else np.zeros(len(tpick))
                weights = paper_brdf_weights(nn[tp], -rays[surf][tpick], alb[surf][tpick], mats["roughness"][surf][tpick],
                                             met)
                brdf = "paper"
            diag["surface_brdf"] = brdf
            tr = SkyTransport(pts[tp] if vis_of is not None else np.zeros_like(nn[tp]), nn[tp], shade[tp], visibility,
                              sky_dirs, sky_low, s.transport, radiance_at=seen, sky_clipped=sky_sat.any(-1),
                              weights=weights)
            diag["interreflection_known_fraction"] = tr.known_fraction
            score = t_score = _transport_score(tr)
        if model != "transport":
            chroma = None
            if albedo is not None and s.chroma_weight > 0:  # log(S_r / S_b): the colour cue
                a_rb, r_rb = alb[surf][pick][:, [0, 2]], rad[surf][pick][:, [0, 2]]
                good = (a_rb > s.min_albedo).all(1) & (r_rb > CHROMA_MIN_RADIANCE).all(1)
                sh = np.log(np.maximum(r_rb, CHROMA_MIN_RADIANCE)) - np.log(np.maximum(a_rb, ALBEDO_FLOOR))
                chroma = np.where(good, sh[:, 0] - sh[:, 1], np.nan)
                diag["chroma_samples"] = int(good.sum())
            score = _lambert_score(nn, shade, vis_of, chroma, s.chroma_weight, s.chroma_knee)
        sun_fit, res_best, d_sh = _search_sun(score, s)
        diag.update(d_sh)
        if math.isfinite(res_best) and d_sh["shading_contrast"] >= s.min_shading_contrast:
            sun, source = sun_fit, "shading"
            if model == "lambert+transport":
                sun = _transport_in_cone(t_score, sun_fit, s, diag)
    sat_all = sky_sat.all(-1)
    cluster = _sky_cluster(sky_dirs[sat_all], s) if sat_all.any() else None
    if cluster is not None and cluster[2] > 0:
        diag["sky_cluster_dir"] = cluster.tolist()
        res_c = float(score(cluster[None])[0]) if len(pick) >= 50 else math.inf
        diag["sky_cluster_residual"] = res_c
        best, med = diag.get("shading_residual", math.inf), diag.get("shading_residual_median", math.inf)
        if source == "none" or res_c <= best + s.sky_cue_tolerance * (med - best):
            sun, source = cluster, "sky"
    diag["sun_source"] = source

    # --- sky fit
    sub = np.arange(len(sky_dirs))
    if len(sub) > s.max_sky_samples:
        sub = rng.choice(sub, s.max_sky_samples, replace=False)
    sub = sub[sky_dirs[sub, 2] > -0.02]
    if len(sub) < 20:
        coeffs = np.array([[math.log(0.5), -0.5, 0.0]] * 3)
        diag["sky_fit"] = "prior only (fewer than 20 sky pixels)"
    else:
        coeffs = _fit_sky(sky_dirs[sub], sky_rad[sub], sky_sat[sub], sun if source != "none" else None, s)
    down = (~sky) & (rays[..., 2] < -0.05)
    ground = np.median(rad[down], axis=0) if down.any() else np.exp(coeffs[:, 0]) * 0.3
    ground = np.maximum(ground, 1e-4)

    # --- sun strength: the fitted shading term e max(0, n . s) is E_sun / pi (Lambert, per
    # channel by refitting with the direction fixed)
    e_sun = np.zeros(3)
    if source != "none" and albedo is not None:
        chans = rad[surf][pick] / np.maximum(alb[surf][pick], ALBEDO_FLOOR)
        v_sun = vis_of(sun)[0] if vis_of else None
        for ch in range(3):
            _, cf = _shading_fit(nn, chans[:, ch], sun, v_sun)
            e_sun[ch] = max(float(cf[2]), 0.0) * math.pi
        diag["sun_irradiance_fit"] = e_sun.tolist()
    env = compose_envmap(coeffs, sun if source != "none" else None, e_sun, ground, s.height)
    return LightingEstimate(env, _unit(sun), e_sun.astype(np.float32), source, coeffs, ground.astype(np.float32), diag)


def numpy_visibility(tracer):
    """``(origins [M, 3], dirs [M, 3]) -> V [M]`` on numpy arrays through a
    :class:`core.pbr.visibility.GaussianTracer` (the ``visibility`` of :func:`estimate_lighting`)."""
    import torch

    def visibility(origins, dirs, t_max=None):
        tm = None if t_max is None else torch.from_numpy(np.ascontiguousarray(t_max, np.float32))
        return tracer(torch.from_numpy(np.ascontiguousarray(origins, np.float32)),
                      torch.from_numpy(np.ascontiguousarray(dirs, np.float32)), tm).numpy()
    return visibility
