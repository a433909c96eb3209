"""Randomised synthetic streets for training the learned priors (opt-in; the profiles are untouched).

:class:`RandomisationSettings` holds the range of every axis a real capture varies along (street
geometry, materials, camera, lens, light, sensor). :func:`sample_spec` draws one concrete
:class:`SceneSpec` from them, deterministically from a seed; :func:`spec_config` turns a spec
into a :class:`~core.synth.config.SynthConfig` (``scene_spec`` set) that
:func:`~core.synth.generate.generate_scene` renders with Mitsuba. Which regions of the ranges are
held out for out-of-distribution testing is declared once in :mod:`core.synth.splits`; pass
``exclude``/``only`` there, never here by hand.

Ranges are ``(low, high)`` tuples, inclusive; categorical axes are tuples of names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from core.errors import ConfigError
from core.synth.config import SynthConfig

#: Layout styles of the randomised street generator (:mod:`core.synth.random_street`).
LAYOUT_STYLES = ("terraced", "detached", "boulevard", "narrow")
#: Facade palettes (:data:`core.synth.textures.PALETTES`).
FACADE_PALETTES = ("plaster", "brick", "concrete", "sandstone", "pastel", "dark")
#: The name of the analytic sun-and-sky map as a scene's envmap (:mod:`core.synth.sky`).
SUNSKY = "sunsky"


@dataclass(frozen=True)
class RandomisationSettings:
    """The ranges a randomised scene is drawn from (one draw per scene, from its seed)."""

    # --- street geometry -------------------------------------------------------------------------
    layout_styles: tuple[str, ...] = LAYOUT_STYLES
    """Layout styles: terraced (continuous facades), detached (gaps, per-building setbacks),
    boulevard (wide road, dense trees), narrow (narrow road, tall buildings, few cars)."""
    road_half_width_m: tuple[float, float] = (3.0, 9.0)
    """Half the width of the carriageway (curb to centre line), metres. Narrow streets draw from
    the lowest third, boulevards from the highest third."""
    sidewalk_width_m: tuple[float, float] = (1.5, 6.0)
    """Sidewalk width between curb and the building line, metres."""
    building_height_m: tuple[float, float] = (4.0, 30.0)
    """Height of each building, metres (drawn per building)."""
    building_width_m: tuple[float, float] = (5.0, 20.0)
    """Frontage of each building along the street, metres (drawn per building)."""
    setback_m: tuple[float, float] = (0.0, 5.0)
    """Extra distance of a facade behind the building line, metres (per building in detached and
    boulevard layouts, 0 in terraced and narrow ones)."""
    building_gap_m: tuple[float, float] = (0.0, 8.0)
    """Gap between neighbouring buildings, metres (0 in terraced and narrow layouts)."""
    # --- materials -------------------------------------------------------------------------------
    facade_palettes: tuple[str, ...] = FACADE_PALETTES
    """Facade palettes; one is drawn per scene and every facade of the scene uses it."""
    albedo_noise: tuple[float, float] = (0.05, 0.35)
    """Relative amplitude of the spatial albedo noise of textured parts (facades, road, sidewalk,
    curbs, planters)."""
    texture_repeat_m: tuple[float, float] = (1.5, 6.0)
    """Metres covered by one repeat of a facade texture (brick/panel scale)."""
    facade_roughness: tuple[float, float] = (0.4, 1.0)
    """Roughness of a dielectric facade (per building)."""
    metal_facade_prob: float = 0.1
    """Probability that a building is metal-clad (metallic 0.6-1, roughness 0.2-0.6)."""
    road_albedo: tuple[float, float] = (0.05, 0.25)
    """Mean albedo (grey level) of the road surface."""
    road_roughness: tuple[float, float] = (0.5, 1.0)
    """Roughness of road, sidewalk and curb (per part)."""
    glass_albedo: tuple[float, float] = (0.02, 0.25)
    """Albedo of window glass (per building; tinted slightly)."""
    glass_roughness: tuple[float, float] = (0.0, 0.2)
    """Roughness of window glass (per building)."""
    glass_metallic: tuple[float, float] = (0.0, 0.6)
    """Metallic of window glass (0 = clear, higher = mirror-coated), per building."""
    window_fill: tuple[float, float] = (0.3, 1.0)
    """Fraction of window slots that hold a window (per building)."""
    tree_spacing_m: tuple[float, float] = (8.0, 30.0)
    """Distance between trees along a sidewalk, metres (per scene; boulevards use the low end)."""
    crown_radius_m: tuple[float, float] = (0.8, 2.5)
    """Radius of a tree crown, metres (per tree)."""
    hedge_prob: float = 0.3
    """Probability that a building gap or setback holds a hedge."""
    # --- vehicles --------------------------------------------------------------------------------
    parked_cars: tuple[int, int] = (0, 8)
    """Number of parked cars (per scene)."""
    moving_cars: tuple[int, int] = (0, 4)
    """Number of moving (tracked) cars (per scene)."""
    vehicle_length_m: tuple[float, float] = (3.6, 5.6)
    """Vehicle length, metres (width and height scale with it)."""
    paint_roughness: tuple[float, float] = (0.05, 0.6)
    """Roughness of a vehicle's paint (per vehicle)."""
    paint_metallic: tuple[float, float] = (0.0, 1.0)
    """Metallic of a vehicle's paint (per vehicle; solid to metallic paints)."""
    # --- camera and lens -------------------------------------------------------------------------
    camera_height_m: tuple[float, float] = (1.2, 2.5)
    """Camera height above the road, metres."""
    camera_pitch_deg: tuple[float, float] = (-10.0, 10.0)
    """Camera pitch, degrees, positive = down (``SynthConfig.camera_pitch_deg``)."""
    hfov_deg: tuple[float, float] = (50.0, 110.0)
    """Horizontal field of view, degrees."""
    resolutions: tuple[tuple[int, int], ...] = ((256, 192), (288, 162), (240, 160), (320, 180), (256, 256))
    """Image sizes (width, height) drawn from: 4:3, 16:9, 3:2 and square."""
    distortion_prob: float = 0.5
    """Probability that the lens has radial distortion (else a pinhole)."""
    edge_distortion: tuple[float, float] = (-0.10, 0.04)
    """Relative radial displacement at the image corner, (r_distorted / r_pinhole - 1) of the
    direction the corner pixel shows: negative = barrel, positive = pincushion. Stored in the
    bundle as OpenCV k1 (:func:`lens_k1`)."""
    # --- light -----------------------------------------------------------------------------------
    hdris: tuple[str, ...] = ("city", "courtyard", "forest", "night", "sunrise", "sunset")
    """Bundled real HDRIs (data/hdri) a scene may be lit by."""
    hdri_rotation_deg: tuple[float, float] = (0.0, 360.0)
    """Rotation of an HDRI about +z, degrees."""
    intensity: tuple[float, float] = (0.25, 4.0)
    """Multiplier of the light's radiance (drawn log-uniformly)."""
    sky_prob: float = 0.5
    """Probability that the light is the analytic sun-and-sky map instead of an HDRI."""
    sun_elevation_deg: tuple[float, float] = (2.0, 85.0)
    """Sun elevation above the horizon of the analytic sky, degrees."""
    sun_azimuth_deg: tuple[float, float] = (0.0, 360.0)
    """Sun azimuth of the analytic sky, degrees from +x toward +y (the street runs along x)."""
    turbidity: tuple[float, float] = (1.8, 10.0)
    """Atmospheric turbidity of the analytic sky (2 = very clear, 10 = hazy)."""
    relight_count: int = 2
    """Relit ground-truth sets per scene (HDRIs of the same pool, other than the training one)."""
    # --- sensor (applied to the LDR input frames only, never to ground truth) ------------------
    exposure_ev: tuple[float, float] = (-1.5, 1.0)
    """Exposure offset, stops, from the auto exposure (median luminance of the first train frame
    to 0.18)."""
    gamma: tuple[float, float] = (1.8, 2.6)
    """Display gamma of the tone curve (recorded in the bundle's ``ldr.gamma``)."""
    contrast: tuple[float, float] = (0.0, 0.5)
    """S-curve strength applied after the gamma: y - s sin(2 pi y) / (2 pi) (0 = none). Not in
    the bundle's tone map, like an unknown camera response."""
    shot_noise: tuple[float, float] = (0.0, 0.02)
    """Poisson-like noise: variance = shot_noise * exposed linear value."""
    read_noise: tuple[float, float] = (0.0, 0.01)
    """Gaussian read noise, standard deviation in exposed linear units."""
    jpeg_prob: float = 0.7
    """Probability that the frames are stored as JPEG (else PNG)."""
    jpeg_quality: tuple[int, int] = (40, 95)
    """JPEG quality of the LDR frames."""

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.endswith("_prob"):
                if not 0.0 <= v <= 1.0:
                    raise ConfigError(f"{f.name}: a probability in [0, 1], got {v!r}")
            elif isinstance(v, tuple) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
                if not v[0] <= v[1]:
                    raise ConfigError(f"{f.name}: range (low, high) needs low <= high, got {v!r}")
            elif isinstance(v, tuple) and not v:
                raise ConfigError(f"{f.name}: must not be empty")
        bad = set(self.layout_styles) - set(LAYOUT_STYLES)
        if bad:
            raise ConfigError(f"layout_styles: unknown {sorted(bad)} (known: {LAYOUT_STYLES})")
        bad = set(self.facade_palettes) - set(FACADE_PALETTES)
        if bad:
            raise ConfigError(f"facade_palettes: unknown {sorted(bad)} (known: {FACADE_PALETTES})")
        if not (self.camera_height_m[0] > 0 and 10 <= self.hfov_deg[0] and self.hfov_deg[1] <= 150):
            raise ConfigError(f"camera_height_m/hfov_deg: out of range ({self.camera_height_m}, {self.hfov_deg})")
        if not -0.3 < self.edge_distortion[0]:
            raise ConfigError(f"edge_distortion: below -0.3 the lens is not invertible ({self.edge_distortion})")
        if self.intensity[0] <= 0:
            raise ConfigError(f"intensity: must be > 0 ({self.intensity})")
        if any(w < 8 or h < 8 for w, h in self.resolutions):
            raise ConfigError(f"resolutions: each side >= 8 ({self.resolutions})")


@dataclass(frozen=True)
class SceneSpec:
    """One concrete draw from :class:`RandomisationSettings`: everything scene-wide. Per-building,
    per-tree and per-car values are drawn by the street generator from ``seed`` within
    ``settings``."""

    seed: int
    """Seed of the street generator and of the sensor noise."""
    split: str
    """The split this spec was drawn for (see :mod:`core.synth.splits`)."""
    layout: str
    """Layout style (:data:`LAYOUT_STYLES`)."""
    palette: str
    """Facade palette (:data:`FACADE_PALETTES`)."""
    road_half_width_m: float
    """Half width of the carriageway, metres."""
    sidewalk_width_m: float
    """Sidewalk width, metres."""
    tree_spacing_m: float
    """Distance between trees, metres."""
    num_parked_cars: int
    """Parked cars."""
    num_moving_cars: int
    """Moving cars."""
    camera_height_m: float
    """Camera height, metres."""
    camera_pitch_deg: float
    """Camera pitch, degrees, positive = down."""
    hfov_deg: float
    """Horizontal field of view, degrees."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    edge_distortion: float
    """Relative radial displacement at the image corner (0 = pinhole)."""
    light: str
    """The training light: an HDRI name, or :data:`SUNSKY`."""
    light_rotation_deg: float
    """Rotation of the HDRI about +z, degrees (0 for the sky: its sun azimuth places it)."""
    intensity: float
    """Radiance multiplier of the training light."""
    sun_elevation_deg: float
    """Sun elevation of the analytic sky, degrees (unused for an HDRI)."""
    sun_azimuth_deg: float
    """Sun azimuth of the analytic sky, degrees (unused for an HDRI)."""
    turbidity: float
    """Turbidity of the analytic sky (unused for an HDRI)."""
    relight_envmaps: tuple[str, ...]
    """HDRIs of the relit ground truth (from the split's allowed pool)."""
    exposure_ev: float
    """Exposure offset from the auto exposure, stops."""
    gamma: float
    """Tone-curve gamma."""
    contrast: float
    """S-curve strength."""
    shot_noise: float
    """Shot-noise factor."""
    read_noise: float
    """Read-noise standard deviation."""
    jpeg_quality: int
    """JPEG quality of the frames; 0 = PNG."""
    settings: RandomisationSettings = field(default_factory=RandomisationSettings)
    """The ranges the street generator draws per-object values from."""



def lens_k1(edge_distortion: float, hfov_deg: float, width: int, height: int) -> float:
    """OpenCV k1 (r_d = r_u (1 + k1 r_u^2), normalised coordinates) of a lens whose image corner
    (radius r_c) shows the direction at pinhole radius r_u = r_c / (1 + edge_distortion):
    k1 = e (1 + e)^2 / r_c^2. Monotonic over the image while e > -1/3."""
    if edge_distortion == 0.0:
        return 0.0
    rc2 = (math.tan(math.radians(hfov_deg) / 2.0) ** 2) * (1.0 + (height / width) ** 2)
    e = edge_distortion
    return e * (1.0 + e) ** 2 / rc2


def _uniform(rng: np.random.Generator, r) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def _log_uniform(rng: np.random.Generator, r) -> float:
    return float(math.exp(rng.uniform(math.log(r[0]), math.log(r[1])))) if r[1] > r[0] else float(r[0])


def _pick(rng: np.random.Generator, options, name: str):
    if not options:
        raise ConfigError(f"{name}: no value left to draw from (every option held out)")
    return options[int(rng.integers(len(options)))]


def sample_spec(settings: RandomisationSettings, seed: int, *, split: str = "train",
                overrides: dict | None = None, rng: np.random.Generator | None = None) -> SceneSpec:
    """Draw one :class:`SceneSpec` from ``settings`` (deterministic in ``seed``; pass ``rng`` to
    continue another stream). ``overrides`` narrows axes: a key of :class:`RandomisationSettings`
    with a smaller range or a shorter tuple of names (this is how :mod:`core.synth.splits` keeps
    held-out regions out of training)."""
    if overrides:
        unknown = set(overrides) - {f.name for f in fields(RandomisationSettings)}
        if unknown:
            raise ConfigError(f"overrides: unknown settings {sorted(unknown)}")
        s = replace(settings, **overrides)
    else:
        s = settings
    rng = rng if rng is not None else np.random.default_rng(seed)
    layout = _pick(rng, s.layout_styles, "layout_styles")
    lo, hi = s.road_half_width_m
    third = (hi - lo) / 3.0
    road_r = {"narrow": (lo, lo + third), "boulevard": (hi - third, hi)}.get(layout, (lo, hi))
    sw_r = (s.sidewalk_width_m[0], (s.sidewalk_width_m[0] + s.sidewalk_width_m[1]) / 2) if layout == "narrow" else s.sidewalk_width_m
    tree_r = (s.tree_spacing_m[0], (s.tree_spacing_m[0] + s.tree_spacing_m[1]) / 2) if layout == "boulevard" else s.tree_spacing_m
    palette = _pick(rng, s.facade_palettes, "facade_palettes")
    w, h = s.resolutions[int(rng.integers(len(s.resolutions)))]
    cars_p = int(rng.integers(s.parked_cars[0], s.parked_cars[1] + 1))
    cars_m = int(rng.integers(s.moving_cars[0], s.moving_cars[1] + 1))
    if layout == "narrow":
        cars_p, cars_m = cars_p // 2, min(cars_m, 1)
    cam_h = _uniform(rng, s.camera_height_m)
    pitch = _uniform(rng, s.camera_pitch_deg)
    hfov = _uniform(rng, s.hfov_deg)
    lens_on, lens_e = rng.uniform() < s.distortion_prob, _uniform(rng, s.edge_distortion)
    distort = lens_e if lens_on else 0.0  # both drawn: distortion_prob changes the lens only
    use_sky = rng.uniform() < s.sky_prob
    hdri = _pick(rng, s.hdris, "hdris")
    light = SUNSKY if use_sky else hdri
    rot = 0.0 if use_sky else round(_uniform(rng, s.hdri_rotation_deg), 3)
    intensity = _log_uniform(rng, s.intensity)
    elev, az, turb = _uniform(rng, s.sun_elevation_deg), _uniform(rng, s.sun_azimuth_deg), _uniform(rng, s.turbidity)
    pool = [n for n in s.hdris if n != light]
    order = rng.permutation(len(pool)) if pool else []
    relight = tuple(pool[int(i)] for i in order[: s.relight_count])
    jpeg = int(rng.integers(s.jpeg_quality[0], s.jpeg_quality[1] + 1)) if rng.uniform() < s.jpeg_prob else 0
    return SceneSpec(
        seed=int(seed), split=split, layout=layout, palette=palette,
        road_half_width_m=round(_uniform(rng, road_r), 3), sidewalk_width_m=round(_uniform(rng, sw_r), 3),
        tree_spacing_m=round(_uniform(rng, tree_r), 3), num_parked_cars=cars_p, num_moving_cars=cars_m,
        camera_height_m=round(cam_h, 4), camera_pitch_deg=round(pitch, 3), hfov_deg=round(hfov, 3),
        width=int(w), height=int(h), edge_distortion=round(distort, 4), light=light,
        light_rotation_deg=rot, intensity=round(intensity, 4), sun_elevation_deg=round(elev, 3),
        sun_azimuth_deg=round(az, 3), turbidity=round(turb, 3), relight_envmaps=relight,
        exposure_ev=round(_uniform(rng, s.exposure_ev), 3), gamma=round(_uniform(rng, s.gamma), 3),
        contrast=round(_uniform(rng, s.contrast), 3), shot_noise=round(_uniform(rng, s.shot_noise), 5),
        read_noise=round(_uniform(rng, s.read_noise), 5), jpeg_quality=jpeg, settings=settings,
    )


def spec_config(spec: SceneSpec, base: SynthConfig, **overrides) -> SynthConfig:
    """The :class:`SynthConfig` that renders ``spec``: the base profile's frame count, samples,
    LiDAR and timing, the spec's camera, light and street (``scene_spec`` set). ``overrides``
    replace further fields (e.g. a tiny ``width``/``height`` in tests)."""
    cfg = replace(base, seed=spec.seed, width=spec.width, height=spec.height, hfov_deg=spec.hfov_deg,
                  camera_height_m=spec.camera_height_m, camera_pitch_deg=spec.camera_pitch_deg,
                  envmap=spec.light, envmap_rotation_deg=spec.light_rotation_deg,
                  relight_envmaps=spec.relight_envmaps, num_parked_cars=spec.num_parked_cars,
                  num_moving_cars=spec.num_moving_cars, gamma=spec.gamma, scene_spec=spec,
                  test_offset_m=min(base.test_offset_m, spec.road_half_width_m / 2.0))
    if overrides:
        cfg = replace(cfg, **overrides)
    return cfg
