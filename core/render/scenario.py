"""A rendering scenario: what a relight or night request asks of a reconstruction, as one value.

The relight and night jobs of the service, the ``brdf relight`` / ``brdf night`` commands and the
tests all build a :class:`Scenario` and call :func:`render_scenario`; none of them holds scenario
logic of its own.

* views: frames of the capture (:func:`views_from_frames`) or a new camera path
  (:func:`views_from_path`); OpenCV cameras, scene times in seconds;
* lighting: an HDR environment map (linear radiance, project equirect convention) with a rotation
  about +z (degrees) and a scale (the night sky is the scene's own map scaled down);
* local lights (:class:`LightSpec`: point / spot, candela, world or attached to an object) and the
  night's vehicle headlights (two spots forward per tracked object);
* object edits (:class:`core.relight.ObjectEdit`: insert a copy, move, remove);
* exposure (EV, on top of the capture's LDR exposure), rays per pixel, shadows, denoiser.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.errors import ConfigError
from core.relight import ObjectEdit, View

#: Headlights of the night scenario, in the object frame (x forward, y left, z up; metres; the
#: tracked boxes of the bundles are centred on the car).
HEADLIGHT_OFFSETS = ((2.2, 0.6, -0.1), (2.2, -0.6, -0.1))
DENOISERS = ("none", "oidn", "diffusion")


@dataclass(frozen=True)
class LightSpec:
    """A point or spot light: ``position`` world metres (object frame when ``attach_to``),
    ``direction`` the spot axis (any length > 0), ``intensity`` candela, cone angles degrees."""

    kind: str
    position: tuple[float, float, float]
    intensity: float
    direction: tuple[float, float, float] | None = None
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cone_inner_deg: float = 20.0
    cone_outer_deg: float = 30.0
    attach_to: str | None = None

    @classmethod
    def from_dict(cls, d: dict, what: str = "light") -> "LightSpec":
        """From a JSON object (the REST ``LocalLight`` fields); ConfigError naming the field."""
        if not isinstance(d, dict):
            raise ConfigError(f"{what}: expected an object, got {type(d).__name__}")
        known = {"kind", "position", "intensity", "direction", "color", "cone_inner_deg", "cone_outer_deg",
                 "attach_to"}
        bad = sorted(set(d) - known)
        if bad:
            raise ConfigError(f"{what}: unknown field(s) {bad} (fields: {sorted(known)})")
        for k in ("kind", "position", "intensity"):
            if k not in d:
                raise ConfigError(f"{what}.{k}: required")
        if d["kind"] not in ("point", "spot"):
            raise ConfigError(f"{what}.kind: must be 'point' or 'spot', got {d['kind']!r}")

        def vec(k):
            v = d.get(k)
            if v is None:
                return None
            if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) and
                                                                        math.isfinite(x) for x in v)):
                raise ConfigError(f"{what}.{k}: expected 3 finite numbers, got {v!r}")
            return tuple(float(x) for x in v)

        inten = d["intensity"]
        if not (isinstance(inten, (int, float)) and math.isfinite(inten) and inten > 0):
            raise ConfigError(f"{what}.intensity: must be a finite number > 0 (candela), got {inten!r}")
        spec = cls(d["kind"], vec("position"), float(inten), vec("direction"), vec("color") or (1.0, 1.0, 1.0),
                   float(d.get("cone_inner_deg", 20.0)), float(d.get("cone_outer_deg", 30.0)), d.get("attach_to"))
        if spec.kind == "spot" and (spec.direction is None or max(abs(x) for x in spec.direction) < 1e-9):
            raise ConfigError(f"{what}.direction: a spot light needs a non-zero direction")
        if spec.cone_inner_deg > spec.cone_outer_deg:
            raise ConfigError(f"{what}.cone_inner_deg: must not exceed cone_outer_deg")
        return spec


@dataclass(frozen=True)
class Scenario:
    """Everything a render of a reconstruction depends on besides the reconstruction itself."""

    views: tuple[View, ...]
    """Cameras and times to render."""
    envmap: np.ndarray
    """HDR environment map [H, W, 3] (linear radiance), before rotation and scale."""
    rotation_deg: float = 0.0
    """Rotation of the map about +z, degrees (azimuth)."""
    sky_scale: float = 1.0
    """Multiplier on the map (the night sky: the scene's own map scaled down)."""
    lights: tuple[LightSpec, ...] = ()
    """Local lights."""
    headlights: bool = False
    """Two forward spots on every tracked object (night)."""
    headlight_intensity: float = 3000.0
    """Candela of each headlight."""
    edits: tuple[ObjectEdit, ...] = ()
    """Object edits applied to the scene graph first."""
    exposure_ev: float = 0.0
    """Exposure on top of the capture's LDR exposure, EV (stops)."""
    base_exposure: float = 1.0
    """The capture's LDR exposure (the bundle's ``ldr.exposure``)."""
    gamma: float = 2.2
    """LDR gamma."""
    rays_per_pixel: int = 64
    """PBR rays per pixel."""
    shadows: bool = True
    """Ray-traced visibility (off: every light sample is visible)."""
    normal_offset_m: float = 0.1
    """Shadow rays start this far along the normal, metres. A reconstruction's surfaces are
    Gaussians a few centimetres thick, not the oracle's thin ones (the PBR pass's default 0.02):
    measured on the default scene's quick reconstruction, 0.1 raises the relit SSIM from 0.54 to
    0.59 (sunset) and 0.46 to 0.51 (forest) at the same PSNR (+-0.15 dB)."""
    shadow_t_min_m: float = 0.5
    """Shadow rays ignore Gaussians closer than this along the ray, metres. A reconstructed road
    is a few centimetres thick and not quite flat: a ray toward a low sun grazes it and the road
    shadows itself in dark blotches. Chosen on the two development scenes (default, dev1; quick
    reconstructions, relit under their three held-back maps, PSNR / SSIM): 0.01 m 17.84 / 0.500
    and 18.18 / 0.514; 0.5 m 17.73 / 0.507 and 18.77 / 0.570; 1.0 m 17.60 / 0.505 and
    18.65 / 0.596. Contact shadows shorter than this are lost."""
    denoiser: str = "oidn"
    """``none``, ``oidn`` or ``diffusion``."""
    denoiser_fallback: str | None = "none"
    """Used when the denoiser cannot run (None: fail)."""
    fps: float = 10.0
    """Video frame rate."""
    outputs: tuple[str, ...] = ("exr", "mp4", "png")
    """What to write."""

    def __post_init__(self) -> None:
        if not self.views:
            raise ConfigError("views: at least one view is needed")
        env = np.asarray(self.envmap)
        if env.ndim != 3 or env.shape[2] != 3 or env.shape[1] != 2 * env.shape[0]:
            raise ConfigError(f"envmap: expected an equirect [H, 2H, 3] map, got {env.shape}")
        if not np.isfinite(env).all() or (env < 0).any():
            raise ConfigError("envmap: values must be finite and >= 0")
        for name, v, lo, hi in (("rotation_deg", self.rotation_deg, -1e6, 1e6), ("sky_scale", self.sky_scale, 0, 1e6),
                                ("exposure_ev", self.exposure_ev, -20, 20), ("fps", self.fps, 1e-3, 240)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"{name}: must be a finite number in [{lo}, {hi}], got {v!r}")
        if self.denoiser not in DENOISERS:
            raise ConfigError(f"denoiser: must be one of {DENOISERS}, got {self.denoiser!r}")
        if self.denoiser_fallback is not None and self.denoiser_fallback not in DENOISERS:
            raise ConfigError(f"denoiser_fallback: must be one of {DENOISERS} or None, got {self.denoiser_fallback!r}")
        if not (isinstance(self.normal_offset_m, (int, float)) and 0 <= self.normal_offset_m <= 10):
            raise ConfigError(f"normal_offset_m: must be in [0, 10] metres, got {self.normal_offset_m!r}")
        if not (isinstance(self.shadow_t_min_m, (int, float)) and 0 <= self.shadow_t_min_m <= 100):
            raise ConfigError(f"shadow_t_min_m: must be in [0, 100] metres, got {self.shadow_t_min_m!r}")
        if not (isinstance(self.rays_per_pixel, int) and 1 <= self.rays_per_pixel <= 4096):
            raise ConfigError(f"rays_per_pixel: must be an int in [1, 4096], got {self.rays_per_pixel!r}")


def views_from_frames(bundle, split: str = "test", start: int = 0, stop: int | None = None,
                      step: int = 1) -> list[View]:
    """Views of the capture's frames (``split``: train, test or all), sliced ``start:stop:step``."""
    from core.pbr.render import Camera

    if split not in ("train", "test", "all"):
        raise ConfigError(f"split: must be train, test or all, got {split!r}")
    if step < 1:
        raise ConfigError(f"step: must be >= 1, got {step}")
    frames = bundle.frames(None if split == "all" else split)[start:stop:step]
    if not frames:
        raise ConfigError(f"frames: the range selects no frame of the scene ({split} [{start}:{stop}:{step}])")
    times = bundle.manifest.times
    out = []
    for f in frames:
        c = bundle.camera(f)
        t = times[f.time_index] if f.time_index < len(times) else float(f.time_index)
        out.append(View(Camera(np.asarray(f.cam_to_world, np.float64), c.fx, c.fy, c.cx, c.cy, c.width, c.height),
                        float(t), f.id))
    return out


def views_from_path(bundle, camera: str, poses: Sequence[tuple], what: str = "camera_path") -> list[View]:
    """Views along a new camera path: ``poses`` = ``[(cam_to_world 4x4, time_s), ...]`` with the
    intrinsics of the scene's camera ``camera``."""
    from core.pbr.render import Camera

    cam = bundle.manifest.cameras.get(camera)
    if cam is None:
        raise ConfigError(f"{what}.camera: no camera {camera!r} in the scene (cameras: {sorted(bundle.manifest.cameras)})")
    if not poses:
        raise ConfigError(f"{what}.poses: at least one pose is needed")
    out = []
    for i, (c2w, t) in enumerate(poses):
        m = np.asarray(c2w, np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ConfigError(f"{what}.poses[{i}].cam_to_world: expected a finite 4x4 matrix")
        r = m[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or abs(np.linalg.det(r) - 1) > 1e-4:
            raise ConfigError(f"{what}.poses[{i}].cam_to_world: the rotation is not orthonormal")
        out.append(View(Camera(m, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height), float(t), f"{i:05d}"))
    return out


def load_path_json(bundle, path: str | Path) -> tuple[list[View], float]:
    """A camera path file: ``{"camera": id, "fps": 10, "poses": [{"cam_to_world": 4x4, "time_s": t}]}``
    (the REST ``camera_path`` object)."""
    import json

    p = Path(path)
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--path {p}: not a readable JSON file ({exc})") from exc
    if not isinstance(d, dict) or "poses" not in d or "camera" not in d:
        raise ConfigError(f"--path {p}: expected an object with 'camera' and 'poses'")
    try:
        poses = [(x["cam_to_world"], float(x.get("time_s", 0.0))) for x in d["poses"]]
    except (TypeError, KeyError) as exc:
        raise ConfigError(f"--path {p}: each pose needs cam_to_world (and time_s)") from exc
    return views_from_path(bundle, str(d["camera"]), poses, what=f"--path {p}"), float(d.get("fps", 10.0))


def to_lights(specs: Sequence[LightSpec], graph, what: str = "lights") -> list:
    """:class:`core.pbr.lights.PointLight` / ``SpotLight`` of the specs; ConfigError naming an
    ``attach_to`` that is not an object of ``graph``."""
    from core.pbr.lights import PointLight, SpotLight

    names = {n.name for n in graph.nodes}
    out = []
    for i, lt in enumerate(specs):
        if lt.attach_to is not None and lt.attach_to not in names:
            raise ConfigError(f"{what}[{i}].attach_to: no object {lt.attach_to!r} in the reconstruction "
                              f"(objects: {sorted(names)})")
        kw = dict(position=tuple(lt.position), color=tuple(lt.color), intensity=lt.intensity, node=lt.attach_to,
                  name=f"{what}[{i}]")
        if lt.kind == "spot":
            out.append(SpotLight(direction=tuple(lt.direction), inner_deg=lt.cone_inner_deg,
                                 outer_deg=lt.cone_outer_deg, **kw))
        else:
            out.append(PointLight(**kw))
    return out


def headlights(graph, intensity: float) -> list:
    """Two forward spot lights on every object node of ``graph`` (object frame, they follow it)."""
    from core.pbr.lights import SpotLight

    out = []
    for n in graph.nodes:
        for k, off in enumerate(HEADLIGHT_OFFSETS):
            out.append(SpotLight(off, direction=(1.0, 0.0, -0.08), inner_deg=12.0, outer_deg=30.0,
                                 intensity=intensity, color=(1.0, 0.95, 0.85), range=60.0, node=n.name,
                                 name=f"{n.name}/headlight{k}"))
    return out


#: The night sky of a reconstruction that has no recovered environment map (no pbr stage): a
#: uniform overcast grey (linear radiance), before the night's ``sky_scale``.
FALLBACK_SKY_RADIANCE = 0.5


def scene_sky(run) -> tuple[np.ndarray, str]:
    """The reconstruction's own sky: ``(envmap [512, 1024, 3], what it is)``. The map the run's
    latest pbr or joint stage recovered; without one, a uniform grey sky
    (:data:`FALLBACK_SKY_RADIANCE`), said so in the note. Never the bundle's ground truth."""
    from core.io.envmap_file import read_envmap

    path, stage = run.latest_envmap()
    if path is not None:
        return np.asarray(read_envmap(path), np.float32), f"recovered by the reconstruction's {stage} stage"
    return (np.full((512, 1024, 3), FALLBACK_SKY_RADIANCE, np.float32),
            "uniform grey: the reconstruction has no recovered sky (run its pbr stage)")


def night_scenario(run, *, sky_scale: float = 0.02, headlights: bool = True, headlight_intensity: float = 3000.0,
                   exposure_ev: float = 2.0, **kw) -> tuple["Scenario", str]:
    """The night :class:`Scenario` of a reconstruction run: its own sky (:func:`scene_sky`)
    scaled by ``sky_scale``, headlights on every tracked object, exposure raised; ``kw`` are
    the other :class:`Scenario` fields (views, lights, edits, ...). Returns (scenario, sky note)."""
    env, note = scene_sky(run)
    return Scenario(envmap=env, sky_scale=sky_scale, headlights=headlights, headlight_intensity=headlight_intensity,
                    exposure_ev=exposure_ev, **kw), note


@dataclass
class ScenarioResult:
    """What :func:`render_scenario` wrote and measured."""

    result: object
    """:class:`core.relight.RelightResult`."""
    frames: int
    lights: int
    metrics: dict = field(default_factory=dict)


def render_scenario(graph, scenario: Scenario, out_dir: str | Path, *,
                    on_frame: Callable[[int, int], None] | None = None) -> ScenarioResult:
    """Apply the edits, place the lights, render the views with the PBR pass, denoise, write EXR /
    MP4 / PNG into ``out_dir`` (:func:`core.relight.render_clip`)."""
    from core.pbr.envmap import EnvironmentMap
    from core.pbr.render import PBRSettings
    from core.pbr.visibility import TraceSettings
    from core.relight import apply_edits, render_clip

    if not isinstance(scenario, Scenario):
        raise ConfigError(f"scenario: expected a Scenario, got {type(scenario).__name__}")
    g = apply_edits(graph, list(scenario.edits), what="object_edits") if scenario.edits else graph
    lights = to_lights(scenario.lights, g)
    if scenario.headlights:
        lights += headlights(g, scenario.headlight_intensity)
    env = EnvironmentMap(np.asarray(scenario.envmap, np.float32) * scenario.sky_scale,
                         rotation_deg=scenario.rotation_deg, resample_to=(512, 1024))
    settings = PBRSettings(rays_per_pixel=scenario.rays_per_pixel,
                           exposure=scenario.base_exposure * 2.0 ** scenario.exposure_ev, gamma=scenario.gamma,
                           shadows=scenario.shadows, normal_offset=scenario.normal_offset_m,
                           trace=TraceSettings(leaf_size=16, t_min=scenario.shadow_t_min_m),
                           reuse_visibility=len(scenario.views) > 1)
    res = render_clip(g, env, list(scenario.views), out_dir, settings=settings, lights=lights,
                      outputs=list(scenario.outputs), denoiser=scenario.denoiser,
                      denoiser_fallback=scenario.denoiser_fallback, fps=scenario.fps, on_frame=on_frame)
    return ScenarioResult(res, len(scenario.views), len(lights),
                          {"frames": len(scenario.views), "seconds_per_frame": round(res.seconds_per_frame, 3),
                           "rays_per_pixel": scenario.rays_per_pixel, "denoiser": res.denoiser,
                           "denoiser_fallback_reason": res.denoiser_note, "lights": len(lights)})


__all__ = ["LightSpec", "Scenario", "ScenarioResult", "views_from_frames", "views_from_path", "load_path_json",
           "to_lights", "headlights", "render_scenario", "HEADLIGHT_OFFSETS", "scene_sky",
           "night_scenario", "FALLBACK_SKY_RADIANCE"]
