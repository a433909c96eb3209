"""A rendering scenario: what a relight or night request asks of a reconstruction, as one value.

The relight and night jobs of the service, the ``brdf relight`` / ``brdf night`` commands and the
tests all build a :class:`Scenario` and call :func:`render_scenario`; none of them holds scenario
logic of its own.

* views: frames of the capture (:func:`views_from_frames`) or a new camera path
  (:func:`views_from_path`); OpenCV cameras, scene times in seconds;
* lighting: an HDR environment map (linear radiance, project equirect convention) with a rotation
  about +z (degrees) and a scale (the night sky is the scene's own map scaled down);
* local lights (:class:`LightSpec`: point / spot, candela, world or attached to an object), street
  lights (:mod:`core.render.streetlights`: spots pointing down, placed from a spec, by a spacing
  along the road, or detected as poles in the LiDAR / the Gaussians) and vehicle lights
  (:func:`core.render.objects.vehicle_lights`: two headlights and two tail lights on every vehicle
  node, following its pose, switchable per object);
* object edits (:class:`core.relight.ObjectEdit`: insert a copy or an asset, move, retime, remove);
* exposure: automatic (:mod:`core.render.exposure`, one value for the clip, the default of the
  night and relight requests) or an explicit EV on top of the capture's LDR exposure; rays per
  pixel, shadows, denoiser.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from core.bundle import open_bundle
from core.camera import Camera
from core.errors import ConfigError
from core.io.envmap_file import read_envmap
from core.io.hdri import hdri_names
from core.pbr.envmap import EnvironmentMap
from core.pbr.lights import PointLight, SpotLight
from core.pbr.render import (PRODUCT_DIFFUSE, PRODUCT_INDIRECT_SPECULAR_RAYS, PRODUCT_MASKING, PRODUCT_OPAQUE_ABOVE,
                             ClipHook, PBRSettings)
from core.pbr.visibility import TraceSettings
from core.relight import ObjectEdit, View
from core.render.exposure import AutoExposure
from core.rotations import quat_slerp, quat_to_rotmat, rotmat_to_quat

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
    range_m: float | None = None

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
    street_lights: tuple[LightSpec, ...] = ()
    """Street lamps (:func:`core.render.streetlights.lamp_lights`), reported apart from ``lights``."""
    headlights: bool = False
    """Vehicle lights on every vehicle node (:func:`core.render.objects.vehicle_lights`)."""
    headlight_intensity: float = 3000.0
    """Candela of each headlight."""
    tail_lights: bool = True
    """With ``headlights``: two red tail lights per vehicle too."""
    tail_light_intensity: float = 10.0
    """Candela of each tail light."""
    vehicle_lights_off: tuple[str, ...] = ()
    """Objects whose vehicle lights are off."""
    edits: tuple[ObjectEdit, ...] = ()
    """Object edits applied to the scene graph first."""
    exposure_ev: float | None = 0.0
    """Exposure on top of the capture's LDR exposure, EV (stops); None: automatic
    (``auto_exposure``, measured on the rendered clip)."""
    auto_exposure: AutoExposure = field(default_factory=AutoExposure)
    """Settings of the automatic exposure (used when ``exposure_ev`` is None)."""
    base_exposure: float = 1.0
    """The capture's LDR exposure (the bundle's ``ldr.exposure``)."""
    gamma: float = 2.2
    """LDR gamma."""
    rays_per_pixel: int = 64
    """PBR rays per pixel (with ``adaptive_rays``: the most a pixel takes)."""
    adaptive_rays: bool = False
    """Skip: rays per pixel set by the measured variance. Every pixel takes
    ``PBRSettings.adaptive_min_batches`` batches, then stops once its LDR standard error is below
    ``PBRSettings.adaptive_tol`` (:mod:`core.pbr.integrator`). Recorded in the metrics'
    ``skips_fired`` with the mean rays spent. Off by default: within noise but it saved no time
    (``benchmarks/bench_skips.py``, 6 tiny streets relit under sunset at 64 rays: 57-62 rays
    spent, relight PSNR -0.001 +- 0.003 dB, -0.10 +- 0.16 s)."""
    reuse_visibility_across_requests: bool = True
    """Skip: reuse the reconstruction's cached visibility across relight requests of one scene.
    The static shadow-ray BVH (and, under the same map, the visibility cache) of an earlier
    request in this process is reused when the shadow casters are the same to the bit
    (:class:`core.pbr.render.ClipHook`; one context is kept, ~150 MB with its cache). Recorded
    in the metrics' ``skips_fired``. On: within noise (``benchmarks/bench_skips.py``, 6 tiny
    streets, the second of two requests: relight PSNR -0.001 +- 0.002 dB, 0.27 +- 0.15 s of
    ~1.2 s saved, the setup 0.35 -> 0.02 s)."""
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
    18.65 / 0.596. Contact shadows shorter than this are lost (except objects an edit placed:
    ``object_shadow_t_min_m``)."""
    object_shadow_t_min_m: float = 0.05
    """Shadow rays ignore the Gaussians of objects an edit inserted or moved
    (:attr:`core.scene_graph.RigidNode.edited`) closer than this along the ray, metres: they are
    traced as a BVH of their own (``TraceSettings.t_min_objects``), so an inserted car keeps the
    contact shadow that ``shadow_t_min_m`` would cut off while the road keeps its own guard.
    Without edits it changes nothing. Chosen on ``benchmarks/bench_insertion.py`` (a copy of a
    parked car inserted into the default scene's 0.25x quick reconstruction; its cast-shadow IoU
    against Mitsuba under five sunny maps): 0.5 (= ``shadow_t_min_m``, as before) mean 0.652 / min 0.360; 0, 0.02, 0.05,
    0.1 and 0.2 all 0.775-0.776 / 0.688-0.689; 0.3 0.754 / 0.680. 0.05 sits inside that flat
    range, clear of its edge, and keeps a margin for the object's own points that the box test of
    :func:`core.pbr.render.on_objects` leaves out (its lowest 0.15 m). Points on the object itself
    trace its Gaussians from ``shadow_t_min_m``, so it does not shadow its own surface (without
    that exception, 0.2 darkened the car's median luminance by 10-27%)."""
    indirect_bounces: int = 2
    """Indirect light of the PBR pass: the approximate diffuse bounces
    (:attr:`core.pbr.render.PBRSettings.indirect_bounces`; 0 = direct light only, the paper)."""
    indirect_specular_rays: int = PRODUCT_INDIRECT_SPECULAR_RAYS
    """GGX shadow rays per pixel of the specular bounce
    (:attr:`core.pbr.render.PBRSettings.indirect_specular_rays`; 0 = the bounce lights the
    diffuse lobe only)."""
    diffuse: str = PRODUCT_DIFFUSE
    """The BRDF's diffuse lobe (:attr:`core.pbr.render.PBRSettings.diffuse`): Burley's, whose
    base colour the recovered albedo is. Chosen on the default scene's quick reconstruction (the
    development scene), relit against Mitsuba under three held-back maps: lambert 22.50 / 19.09 /
    16.65 dB (sunset / forest / courtyard), burley 22.76 / 19.35 / 16.64; under the capture's own
    map the non-sky radiance came out 0.90 of Mitsuba's with lambert, 0.97 with burley."""
    opaque_above: float = PRODUCT_OPAQUE_ABOVE
    """Pixels at least this opaque are surfaces, shaded without the map showing through
    (:attr:`core.pbr.render.PBRSettings.opaque_above`)."""
    object_solids: bool = True
    """Shadow rays meet each tracked object's filled inside, not only its shell of splats
    (:attr:`core.pbr.render.PBRSettings.object_solids`; an edited object carries its own filler
    either way). Measured on the development scenes' quick reconstructions, the same
    reconstruction evaluated both ways (``benchmarks/results/object_solids.json``): relit
    20.48 -> 20.64 dB and re-render 19.75 -> 19.96 dB (default scene), 21.34 -> 21.43 and
    21.23 -> 21.36 dB (dev1), 22.33 -> 22.42 and 21.06 -> 21.13 dB (dev2); NVS unchanged."""
    masking: str = PRODUCT_MASKING
    """The BRDF's masking-shadowing term (:attr:`core.pbr.render.PBRSettings.masking`): the exact
    Smith term, as the principled BSDF. Chosen on the default scene's quick reconstruction (with
    Burley's lobe), same reconstruction rendered both ways: relit 22.75 / 19.35 / 16.64 dB
    (sunset / forest / courtyard) with the paper's Schlick-Smith, 22.97 / 19.51 / 16.53 with
    smith; re-rendered under the capture's own map 20.28 -> 20.40 dB."""
    denoiser: str = "oidn"
    """``none``, ``oidn`` or ``diffusion``."""
    denoiser_fallback: str | None = "none"
    """Used when the denoiser cannot run (None: fail)."""
    fps: float = 10.0
    """Video frame rate."""
    outputs: tuple[str, ...] = ("exr", "mp4", "png")
    """What to write."""
    corrector: object = None
    """The reconstruction's scene corrector (:class:`core.gen.scene_corrector.SceneCorrector`,
    the ``corrector`` stage), applied to the denoised LDR frames when the render is under the
    light and exposure it was fitted at: the capture's recovered map (its
    ``fitted_light``), unrotated and unscaled, no added lights, ``exposure_ev`` 0. Otherwise it is
    not applied and the result's metrics say why. None: none (:func:`scene_corrector` loads a
    run's)."""

    def __post_init__(self) -> None:
        if not self.views:
            raise ConfigError("views: at least one view is needed")
        env = np.asarray(self.envmap)
        if env.ndim != 3 or env.shape[2] != 3 or env.shape[1] != 2 * env.shape[0]:
            raise ConfigError(f"envmap: expected an equirect [H, 2H, 3] map, got {env.shape}")
        if not np.isfinite(env).all() or (env < 0).any():
            raise ConfigError("envmap: values must be finite and >= 0")
        checks = [("rotation_deg", self.rotation_deg, -1e6, 1e6), ("sky_scale", self.sky_scale, 0, 1e6),
                  ("fps", self.fps, 1e-3, 240), ("headlight_intensity", self.headlight_intensity, 0, 1e7),
                  ("tail_light_intensity", self.tail_light_intensity, 0, 1e7)]
        if self.exposure_ev is not None:
            checks.append(("exposure_ev", self.exposure_ev, -20, 20))
        for name, v, lo, hi in checks:
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"{name}: must be a finite number in [{lo}, {hi}], got {v!r}")
        if self.denoiser not in DENOISERS:
            raise ConfigError(f"denoiser: must be one of {DENOISERS}, got {self.denoiser!r}")
        if self.denoiser_fallback is not None and self.denoiser_fallback not in DENOISERS:
            raise ConfigError(f"denoiser_fallback: must be one of {DENOISERS} or None, got {self.denoiser_fallback!r}")
        if not (isinstance(self.normal_offset_m, (int, float)) and 0 <= self.normal_offset_m <= 10):
            raise ConfigError(f"normal_offset_m: must be in [0, 10] metres, got {self.normal_offset_m!r}")
        for name in ("shadow_t_min_m", "object_shadow_t_min_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0 <= v <= 100):
                raise ConfigError(f"{name}: must be in [0, 100] metres, got {v!r}")
        for name in ("adaptive_rays", "reuse_visibility_across_requests", "object_solids"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}: expected true or false, got {getattr(self, name)!r}")
        if not (isinstance(self.rays_per_pixel, int) and 1 <= self.rays_per_pixel <= 4096):
            raise ConfigError(f"rays_per_pixel: must be an int in [1, 4096], got {self.rays_per_pixel!r}")
        if not isinstance(self.auto_exposure, AutoExposure):
            raise ConfigError(f"auto_exposure: expected an AutoExposure, got {type(self.auto_exposure).__name__}")
        if self.corrector is not None:
            from core.gen.scene_corrector import SceneCorrector

            if not isinstance(self.corrector, SceneCorrector):
                raise ConfigError(f"corrector: expected a SceneCorrector or None, got {type(self.corrector).__name__}")
        for name in ("lights", "street_lights"):
            for i, lt in enumerate(getattr(self, name)):
                if not isinstance(lt, LightSpec):
                    raise ConfigError(f"{name}[{i}]: expected a LightSpec, got {type(lt).__name__}")


def views_from_frames(bundle, split: str = "test", start: int = 0, stop: int | None = None,
                      step: int = 1) -> list[View]:
    """Views of the capture's frames (``split``: train, test or all), sliced ``start:stop:step``."""
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
        out.append(View(Camera.from_bundle(c, f), float(t), f.id))
    return out


def views_from_path(bundle, camera: str, poses: Sequence[tuple], what: str = "camera_path") -> list[View]:
    """Views along a new camera path: ``poses`` = ``[(cam_to_world 4x4, time_s), ...]`` with the
    intrinsics of the scene's camera ``camera``."""
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
        out.append(View(Camera.from_bundle(cam, m), float(t), f"{i:05d}"))
    return out


def views_from_capture(bundle, *, split: str = "train", camera: str | None = None, lateral_shift_m: float = 0.0,
                       height_shift_m: float = 0.0, start_s: float | None = None, stop_s: float | None = None,
                       fps: float | None = None, what: str = "captured_path") -> list[View]:
    """Views along the capture's own camera path, edited: the path of ``camera`` (default: the
    first camera of ``split``'s frames) in ``split`` (train, test, all), shifted sideways by
    ``lateral_shift_m`` (to the camera's left, level with the ground: a lane change) and up by
    ``height_shift_m``, resampled at ``fps`` frames per second between ``start_s`` and
    ``stop_s`` (scene seconds, inclusive; default the capture's first and last time). Poses
    between two captured frames are interpolated (linear position, slerp rotation). Without
    ``fps`` the captured frames themselves are used (in the time range). ConfigError names the
    field."""
    if split not in ("train", "test", "all"):
        raise ConfigError(f"{what}.split: must be train, test or all, got {split!r}")
    frames = bundle.frames(None if split == "all" else split)
    if not frames:
        raise ConfigError(f"{what}.split: the scene has no {split} frames")
    cams = sorted({f.camera for f in frames})
    cam_id = camera if camera is not None else frames[0].camera
    if cam_id not in cams:
        raise ConfigError(f"{what}.camera: no camera {cam_id!r} in the {split} frames (cameras: {cams})")
    times = bundle.manifest.times
    frames = sorted((f for f in frames if f.camera == cam_id), key=lambda f: f.time_index)
    ts = np.array([times[f.time_index] if f.time_index < len(times) else float(f.time_index) for f in frames])
    poses = np.stack([np.asarray(f.cam_to_world, np.float64) for f in frames])
    for name, v, lo, hi in (("lateral_shift_m", lateral_shift_m, -100, 100), ("height_shift_m", height_shift_m, -100, 100)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise ConfigError(f"{what}.{name}: must be a finite number in [{lo}, {hi}] metres, got {v!r}")
    t0 = float(ts[0]) if start_s is None else float(start_s)
    t1 = float(ts[-1]) if stop_s is None else float(stop_s)
    if not (math.isfinite(t0) and math.isfinite(t1)) or t0 > t1:
        raise ConfigError(f"{what}.start_s: the time range [{t0}, {t1}] is empty")
    if t1 < ts[0] - 1e-6 or t0 > ts[-1] + 1e-6:
        raise ConfigError(f"{what}.start_s: the time range [{t0}, {t1}] s lies outside the capture "
                          f"[{ts[0]:g}, {ts[-1]:g}] s")
    t0, t1 = max(t0, float(ts[0])), min(t1, float(ts[-1]))
    if fps is None:
        sel = [i for i in range(len(ts)) if t0 - 1e-6 <= ts[i] <= t1 + 1e-6]
        samples = [(float(ts[i]), poses[i]) for i in sel]
    else:
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 240):
            raise ConfigError(f"{what}.fps: must be in (0, 240], got {fps!r}")
        n = int(math.floor((t1 - t0) * fps + 1e-6)) + 1
        if n > 10_000:
            raise ConfigError(f"{what}.fps: {n} frames in the time range; at most 10000")
        samples = []
        for k in range(n):
            t = t0 + k / fps
            j = int(np.searchsorted(ts, t))
            if j <= 0 or len(ts) == 1:
                m = poses[0]
            elif j >= len(ts):
                m = poses[-1]
            else:
                w = (t - ts[j - 1]) / max(ts[j] - ts[j - 1], 1e-12)
                q = quat_slerp(rotmat_to_quat(torch.from_numpy(poses[j - 1][:3, :3])),
                               rotmat_to_quat(torch.from_numpy(poses[j][:3, :3])), float(w))
                m = np.eye(4)
                m[:3, :3] = quat_to_rotmat(q).numpy()
                m[:3, 3] = poses[j - 1][:3, 3] + w * (poses[j][:3, 3] - poses[j - 1][:3, 3])
            samples.append((t, m))
    c = bundle.manifest.cameras[cam_id]
    out = []
    for i, (t, m) in enumerate(samples):
        m = m.copy()
        left = -m[:3, 0].copy()
        left[2] = 0.0
        nrm = float(np.linalg.norm(left))
        if nrm > 1e-9:
            m[:3, 3] += lateral_shift_m * left / nrm
        m[2, 3] += height_shift_m
        out.append(View(Camera.from_bundle(c, m), float(t), f"{i:05d}"))
    return out


def load_path_json(bundle, path: str | Path) -> tuple[list[View], float]:
    """A camera path file: ``{"camera": id, "fps": 10, "poses": [{"cam_to_world": 4x4, "time_s": t}]}``
    (the REST ``camera_path`` object)."""
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
    names = {n.name for n in graph.nodes}
    out = []
    for i, lt in enumerate(specs):
        if lt.attach_to is not None and lt.attach_to not in names:
            raise ConfigError(f"{what}[{i}].attach_to: no object {lt.attach_to!r} in the reconstruction "
                              f"(objects: {sorted(names)})")
        kw = dict(position=tuple(lt.position), color=tuple(lt.color), intensity=lt.intensity, node=lt.attach_to,
                  name=f"{what}[{i}]", range=lt.range_m)
        if lt.kind == "spot":
            out.append(SpotLight(direction=tuple(lt.direction), inner_deg=lt.cone_inner_deg,
                                 outer_deg=lt.cone_outer_deg, **kw))
        else:
            out.append(PointLight(**kw))
    return out


def headlights(graph, intensity: float) -> list:
    """Two forward spot lights on every vehicle node of ``graph`` (node frame, they follow it);
    :func:`core.render.objects.vehicle_lights` without tail lights."""
    from core.render.objects import vehicle_lights

    return vehicle_lights(graph, headlight_cd=intensity, tail_lights=False)


#: The night sky of a reconstruction that has no recovered environment map (no pbr stage): a
#: uniform overcast grey (linear radiance), before the night's ``sky_scale``.
FALLBACK_SKY_RADIANCE = 0.5


def scene_sky(run) -> tuple[np.ndarray, str]:
    """The reconstruction's own sky: ``(envmap [512, 1024, 3], what it is)``. The map the run's
    latest pbr or joint stage recovered; without one, a uniform grey sky
    (:data:`FALLBACK_SKY_RADIANCE`), said so in the note. Never the bundle's ground truth."""
    path, stage = run.latest_envmap()
    if path is not None:
        return np.asarray(read_envmap(path), np.float32), f"recovered by the reconstruction's {stage} stage"
    return (np.full((512, 1024, 3), FALLBACK_SKY_RADIANCE, np.float32),
            "uniform grey: the reconstruction has no recovered sky (run its pbr stage)")


#: How street lights are placed: ``detect`` (poles in the LiDAR, else in the Gaussians; the
#: spacing rows when none is found, said so), ``spacing`` (rows along the road), ``none``.
STREET_LIGHT_PLACEMENTS = ("detect", "spacing", "none")


def street_lights_for(bundle, graph=None, *, placement: str = "detect", positions=None,
                      settings=None, intensity_cd: float | None = None) -> tuple[list, list, str]:
    """Street lamps of a scene: ``(LightSpec spots, Lamp values, note)``. ``positions`` (a list of
    ``[x, y]`` / ``[x, y, z]``) wins over ``placement``; ``detect`` looks for poles in the
    bundle's LiDAR, else in the reconstruction's opaque background Gaussians (``graph``), and
    falls back to ``spacing`` rows along the capture's camera path when it finds none."""
    from core.render.streetlights import (
        Ground,
        StreetLightSettings,
        detect_poles,
        lamp_lights,
        lamps_along_path,
        lamps_at,
    )

    s = settings or StreetLightSettings()
    if placement not in STREET_LIGHT_PLACEMENTS:
        raise ConfigError(f"street_light_placement: must be one of {STREET_LIGHT_PLACEMENTS}, got {placement!r}")
    frames = sorted(bundle.frames("train") or bundle.frames(None), key=lambda f: f.time_index)
    path = np.array([np.asarray(f.cam_to_world, np.float64)[:3, 3] for f in frames]) if frames else None
    points, what = None, ""
    if bundle.manifest.lidar:
        points, what = bundle.load_lidar()[:, 3:6], "the LiDAR"
    elif graph is not None:
        bg = graph.background
        keep = bg.opacities().detach().reshape(-1) > 0.5
        points, what = bg.means.detach()[keep].to(torch.float64).numpy(), "the reconstruction's Gaussians"
    fallback_z = float(np.median(path[:, 2])) - 1.6 if path is not None and len(path) else 0.0
    ground = Ground(points, s.ground_radius_m, fallback_z) if points is not None else None
    if positions is not None:
        lamps, note = lamps_at(positions, ground, s), f"{len(positions)} placed from the request's positions"
    elif placement == "none":
        lamps, note = [], "street lights off"
    else:
        lamps, note = [], ""
        if placement == "detect":
            if points is not None:
                lamps = detect_poles(points, s, what="points", path_xyz=path)
                note = f"{len(lamps)} detected as poles in {what}"
            else:
                note = "no LiDAR and no reconstruction to detect poles in"
        if not lamps:
            if path is None:
                raise ConfigError("street_lights: the scene has no camera path to place lamps along")
            lamps = lamps_along_path(path, ground, s)
            note = (note + "; " if note else "") + f"{len(lamps)} placed every {s.spacing_m:g} m along the road"
    return lamp_lights(lamps, s, intensity_cd), lamps, note


def scene_corrector(run):
    """``(SceneCorrector or None, note)``: the corrector the run's ``corrector`` stage fitted on
    its capture, or None with the reason."""
    from core.gen.scene_corrector import light_fingerprint, load_corrector
    from core.io.envmap_file import read_envmap

    path = run.stage_dir("corrector") / "corrector.pt"
    if not run.is_done("corrector") or not path.is_file():
        return None, "none: the reconstruction has no corrector stage"
    net = load_corrector(path)
    if net.fitted_light is None:  # written before the light was recorded: the map it was fitted under
        env_path, _stage = run.latest_envmap(before="corrector")
        if env_path is None:
            return None, f"none: {path} has no recorded light and the run no recovered map"
        net.fitted_light = light_fingerprint(read_envmap(env_path))
    return net, f"fitted on the capture ({path}); applied under the capture's recovered light only"


def night_scenario(run, *, sky_scale: float = 0.02, headlights: bool = True, headlight_intensity: float = 3000.0,
                   exposure_ev: float | None = None, street_lights: bool = True, street_light_placement: str = "detect",
                   street_light_positions=None, street_light_intensity: float | None = None,
                   street_light_spacing_m: float | None = None, graph=None, bundle=None,
                   **kw) -> tuple["Scenario", str]:
    """The night :class:`Scenario` of a reconstruction run: its own sky (:func:`scene_sky`)
    scaled by ``sky_scale``, vehicle lights on every vehicle node, street lamps
    (:func:`street_lights_for`; the lamps in ``Scenario.street_lights``), automatic exposure
    unless ``exposure_ev`` is given; ``kw`` are the other :class:`Scenario` fields (views,
    lights, edits, ...). ``graph`` / ``bundle``: the run's, when the caller has them loaded.
    Returns (scenario, note on the sky and the street lights)."""
    from core.render.streetlights import StreetLightSettings

    env, note = scene_sky(run)
    lamps = ()
    if street_lights:
        if bundle is None:
            bundle = open_bundle(run.scene_path(), validate=False)
        st = StreetLightSettings() if street_light_spacing_m is None else StreetLightSettings(
            spacing_m=street_light_spacing_m)
        specs, _lamps, lnote = street_lights_for(bundle, graph, placement=street_light_placement,
                                                 positions=street_light_positions, settings=st,
                                                 intensity_cd=street_light_intensity)
        lamps = tuple(specs)
        note = f"{note}; street lights: {lnote}"
    return Scenario(envmap=env, sky_scale=sky_scale, headlights=headlights, headlight_intensity=headlight_intensity,
                    exposure_ev=exposure_ev, street_lights=lamps, **kw), note


def request_problems(manifest, request: dict, object_ids: Sequence[str] | None = None) -> list[str]:
    """Every reference of a relight / night request (the REST body as a dict) that the scene
    cannot satisfy, each as ``"<field>: <problem> (<valid choices>)"``; empty when all is well.
    Checked: ``envmap_name`` (a bundled HDRI), ``frames`` (the range selects a frame),
    ``camera_path.camera`` / ``captured_path`` (camera, split, time range), ``object_edits``
    (ids in order: an edit may refer to an object an earlier edit inserted, not to one it
    removed; explicit pose time indices), ``lights[i].attach_to`` and ``vehicle_lights_off``
    (objects after the edits). ``object_ids``: the objects a reconstruction has (default: the
    bundle's tracked objects)."""
    out: list[str] = []
    ids = list(object_ids) if object_ids is not None else [o.id for o in manifest.objects]
    n_times = len(manifest.times)
    name = request.get("envmap_name")
    if name is not None and name not in hdri_names():
        out.append(f"envmap_name: no bundled HDRI {name!r} (choices: {hdri_names()})")
    fr = request.get("frames")
    if fr:
        split = fr.get("split", "all")
        n = len(manifest.frames) if split == "all" else len(manifest.split(split))
        sel = range(n)[fr.get("start", 0):fr.get("stop"):fr.get("step", 1)]
        if len(sel) == 0:
            out.append(f"frames: the range [{fr.get('start', 0)}:{fr.get('stop')}:{fr.get('step', 1)}] selects no "
                       f"frame of the {n} {split} frame(s) (start must be below {n})")
    cams = sorted(manifest.cameras)
    cp = request.get("camera_path")
    if cp and cp.get("camera") not in manifest.cameras:
        out.append(f"camera_path.camera: no camera {cp.get('camera')!r} in the scene (cameras: {cams})")
    cap = request.get("captured_path")
    if cap:
        split = cap.get("split", "train")
        frames = list(manifest.frames) if split == "all" else list(manifest.split(split))
        if not frames:
            out.append(f"captured_path.split: the scene has no {split} frames")
        else:
            fc = sorted({f.camera for f in frames})
            cam = cap.get("camera") or frames[0].camera
            if cam not in fc:
                out.append(f"captured_path.camera: no camera {cam!r} in the {split} frames (cameras: {fc})")
            ts = [manifest.times[f.time_index] for f in frames if f.time_index < n_times]
            if ts:
                lo, hi = min(ts), max(ts)
                t0 = cap.get("start_s")
                t1 = cap.get("stop_s")
                if (t0 is not None and t0 > hi + 1e-6) or (t1 is not None and t1 < lo - 1e-6):
                    out.append(f"captured_path.start_s: the time range [{t0}, {t1}] s lies outside the capture "
                               f"[{lo:g}, {hi:g}] s")
    cur = list(ids)
    for i, e in enumerate(request.get("object_edits") or []):
        w = f"object_edits[{i}]"
        op, oid = e.get("op"), e.get("object_id")
        if op in ("move", "remove") and oid not in cur:
            out.append(f"{w}.object_id: no object {oid!r} in the scene (objects: {cur})")
        if op == "insert":
            if oid in cur:
                out.append(f"{w}.object_id: {oid!r} already exists; pick a new id (objects: {cur})")
            if e.get("source_scene_id") is None and e.get("source_object_id") not in cur:  # (another scene: the caller)
                out.append(f"{w}.source_object_id: no object {e.get('source_object_id')!r} in the scene "
                           f"(objects: {cur})")
        for k, pz in enumerate(e.get("poses") or []):
            if not 0 <= pz.get("time_index", -1) < n_times:
                out.append(f"{w}.poses[{k}].time_index: must be in [0, {n_times - 1}] (the scene's time indices)")
        if op == "remove" and oid in cur:
            cur.remove(oid)
        elif op == "insert" and oid not in cur:
            cur.append(oid)
    for i, lt in enumerate(request.get("lights") or []):
        a = lt.get("attach_to")
        if a is not None and a not in cur:
            out.append(f"lights[{i}].attach_to: no object {a!r} in the scene (objects: {cur})")
    for i, a in enumerate(request.get("vehicle_lights_off") or []):
        if a not in cur:
            out.append(f"vehicle_lights_off[{i}]: no object {a!r} in the scene (objects: {cur})")
    return out


@dataclass
class ScenarioResult:
    """What :func:`render_scenario` wrote and measured."""

    result: object
    """:class:`core.relight.RelightResult`."""
    frames: int
    lights: int
    metrics: dict = field(default_factory=dict)


def _corrector_gate(scenario: Scenario, n_lights: int):
    """``(corrector or None, note)``: the scenario's corrector when this render is under the light
    and exposure it was fitted at (the capture's recovered map, unrotated, unscaled, no added
    lights, ``exposure_ev`` 0), else None and why. The corrector learns the capture's light with
    the reconstruction's mistakes: under a new map it made every relit FLIP worse on three
    development streets (``benchmarks/results/corrector.json``)."""
    from core.gen.scene_corrector import light_fingerprint

    corrector = scenario.corrector
    if corrector is None:
        return None, "none"
    why = []
    if scenario.exposure_ev != 0.0:
        why.append(f"fitted at the capture's exposure, this render's is "
                   f"{'automatic' if scenario.exposure_ev is None else f'{scenario.exposure_ev:+g} EV'}")
    fitted = getattr(corrector, "fitted_light", None)
    if fitted is not None:
        if light_fingerprint(scenario.envmap) != fitted:
            why.append("fitted under the capture's recovered map, this render is under another map")
        if scenario.rotation_deg % 360.0 != 0.0:
            why.append(f"fitted under the unrotated map, this render's is rotated {scenario.rotation_deg:g} deg")
        if scenario.sky_scale != 1.0:
            why.append(f"fitted under the map as recovered, this render scales it by {scenario.sky_scale:g}")
        if n_lights:
            why.append(f"fitted without added lights, this render has {n_lights}")
    if why:
        return None, "not applied: " + "; ".join(why)
    return corrector, "applied (fitted on the capture)"


def render_scenario(graph, scenario: Scenario, out_dir: str | Path, *,
                    on_frame: Callable[[int, int], None] | None = None,
                    features_out: list | None = None) -> ScenarioResult:
    """Apply the edits, place the lights, render the views with the PBR pass, denoise, correct
    (``scenario.corrector``), write EXR / MP4 / PNG into ``out_dir``
    (:func:`core.relight.render_clip`; ``features_out`` receives the corrector's features)."""
    from core.relight import apply_edits, render_clip

    if not isinstance(scenario, Scenario):
        raise ConfigError(f"scenario: expected a Scenario, got {type(scenario).__name__}")
    from core.render.objects import vehicle_lights

    g = apply_edits(graph, list(scenario.edits), what="object_edits") if scenario.edits else graph
    lights = to_lights(scenario.lights, g) + to_lights(scenario.street_lights, g, what="street_lights")
    if scenario.headlights:
        lights += vehicle_lights(g, headlight_cd=scenario.headlight_intensity,
                                 tail_light_cd=scenario.tail_light_intensity, tail_lights=scenario.tail_lights,
                                 off=scenario.vehicle_lights_off)
    elif scenario.vehicle_lights_off:
        vehicle_lights(g, off=scenario.vehicle_lights_off)  # still names an unknown id
    env = EnvironmentMap(np.asarray(scenario.envmap, np.float32) * scenario.sky_scale,
                         rotation_deg=scenario.rotation_deg, resample_to=(512, 1024))
    settings = PBRSettings(rays_per_pixel=scenario.rays_per_pixel,
                           exposure=scenario.base_exposure * 2.0 ** (scenario.exposure_ev or 0.0),
                           gamma=scenario.gamma,
                           shadows=scenario.shadows, normal_offset=scenario.normal_offset_m,
                           trace=TraceSettings(leaf_size=16, t_min=scenario.shadow_t_min_m,
                                               t_min_objects=scenario.object_shadow_t_min_m),
                           reuse_visibility=len(scenario.views) > 1, adaptive=scenario.adaptive_rays,
                           indirect_bounces=scenario.indirect_bounces, diffuse=scenario.diffuse,
                           indirect_specular_rays=scenario.indirect_specular_rays,
                           masking=scenario.masking, opaque_above=scenario.opaque_above,
                           object_solids=scenario.object_solids)
    corrector, corrector_note = _corrector_gate(scenario, len(lights))
    with ClipHook(reuse_across_clips=scenario.reuse_visibility_across_requests) as hook:
        res = render_clip(g, env, list(scenario.views), out_dir, settings=settings, lights=lights,
                          outputs=list(scenario.outputs), denoiser=scenario.denoiser,
                          denoiser_fallback=scenario.denoiser_fallback, fps=scenario.fps, on_frame=on_frame,
                          auto_exposure=scenario.auto_exposure if scenario.exposure_ev is None else None,
                          corrector=corrector, features_out=features_out)
    fired = []
    mean_rays = hook.mean_samples
    if scenario.adaptive_rays and mean_rays is not None and mean_rays < scenario.rays_per_pixel:
        fired.append({"skip": "adaptive_rays", "why": f"pixels stopped once their LDR standard error fell below "
                      f"{settings.adaptive_tol:g}: {mean_rays:.1f} of {scenario.rays_per_pixel} rays per shaded "
                      f"pixel on average", "mean_rays_per_pixel": round(mean_rays, 2)})
    if hook.reused is not None:
        fired.append({"skip": "reuse_visibility_across_requests",
                      "why": "an earlier request of this reconstruction in this process had built the static "
                             + ("shadow-ray BVH and, under the same map, the visibility cache" if
                                hook.reused == "bvh+visibility" else "shadow-ray BVH"),
                      "reused": hook.reused})
    ev = math.log2(res.exposure / scenario.base_exposure) if res.exposure > 0 and scenario.base_exposure > 0 else None
    return ScenarioResult(res, len(scenario.views), len(lights),
                          {"frames": len(scenario.views), "seconds_per_frame": round(res.seconds_per_frame, 3),
                           "rays_per_pixel": scenario.rays_per_pixel, "denoiser": res.denoiser,
                           "denoiser_fallback_reason": res.denoiser_note, "lights": len(lights),
                           "exposure": "auto" if scenario.exposure_ev is None else "fixed",
                           "exposure_ev": None if ev is None else round(ev, 3),
                           "exposure_limited_by": res.exposure_note,
                           "street_lights": [[round(float(x), 3) for x in lt.position] for lt in scenario.street_lights],
                           "mean_rays_per_pixel": None if mean_rays is None else round(mean_rays, 2),
                           "setup_seconds": round(hook.setup_seconds, 3), "skips_fired": fired,
                           "corrector": corrector_note})


__all__ = ["LightSpec", "Scenario", "ScenarioResult", "views_from_frames", "views_from_path", "views_from_capture", "load_path_json",
           "to_lights", "headlights", "render_scenario", "scene_sky", "street_lights_for", "STREET_LIGHT_PLACEMENTS", "request_problems",
           "night_scenario", "FALLBACK_SKY_RADIANCE", "scene_corrector"]
