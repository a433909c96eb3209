"""Generate a synthetic benchmark scene bundle: a procedural street rendered by Mitsuba 3.

Ground truth (path-traced frames, G-buffers, LiDAR, relit frames) comes from Mitsuba only, never
from this project's renderer. Deterministic for a given :class:`SynthConfig` (Mitsuba's sampler
is seeded per frame).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from core.bundle import BundleWriter, Camera
from core.io.hdri import HDRI_DIR, column_shift, load_hdri, resolve_hdri, rotate_equirect  # noqa: F401
from core.synth.config import SynthConfig
from core.synth.mitsuba_backend import RayCaster, render_beauty, render_gbuffers
from core.synth.random_street import ego_lane_y as _y
from core.synth.random_street import make_random_street
from core.synth.randomise import SUNSKY, lens_k1
from core.synth.sensor import apply_sensor, auto_exposure, source_coords, warp_bilinear
from core.synth.sky import sun_sky_map
from core.synth.street import EGO_LANE_Y, make_street
from core.tonemap import hdr_to_ldr, ldr_to_uint8

# The bundled HDRI library lives in core.io.hdri; these names are kept for the generator's callers.
resolve_envmap = resolve_hdri
rotate_envmap = rotate_equirect
load_envmap = load_hdri


def ego_positions(cfg: SynthConfig) -> np.ndarray:
    """Ego x position [T] of each time index, metres."""
    return np.arange(cfg.num_frames) * cfg.ego_speed * cfg.frame_dt


def camera_pose(cfg: SynthConfig, x: float, y: float) -> np.ndarray:
    """OpenCV cam_to_world [4, 4] of a forward-looking camera at (x, y, camera height), pitched down."""
    p = math.radians(cfg.camera_pitch_deg)
    fwd = np.array([math.cos(p), 0.0, -math.sin(p)])
    right = np.array([0.0, -1.0, 0.0])  # looking +x with z up, right is -y
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, fwd, [x, y, cfg.camera_height_m]
    return m


def intrinsics(cfg: SynthConfig) -> Camera:
    fx = cfg.width / 2.0 / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    k1 = _k1(cfg)
    return Camera("front", cfg.width, cfg.height, fx, fx, cfg.width / 2.0, cfg.height / 2.0,
                  (k1, 0.0, 0.0, 0.0, 0.0) if k1 else ())


def _k1(cfg: SynthConfig) -> float:
    spec = cfg.scene_spec
    return lens_k1(spec.edge_distortion, cfg.hfov_deg, cfg.width, cfg.height) if spec is not None else 0.0


def ego_lane_y(cfg: SynthConfig) -> float:
    """y of the train trajectory: the fixed generator's ego lane, or the randomised street's."""
    if cfg.scene_spec is None:
        return EGO_LANE_Y

    return _y(cfg.scene_spec)


# --------------------------------------------------------------------------------------------
# per-process render work (workers rebuild the street from the config: it is deterministic)
# --------------------------------------------------------------------------------------------
_CACHE: dict = {}


def _street(cfg: SynthConfig):
    key = ("street", cfg)
    if key not in _CACHE:
        if cfg.scene_spec is None:
            _CACHE[key] = make_street(cfg, ego_positions(cfg))
        else:
            _CACHE[key] = make_random_street(cfg.scene_spec, ego_positions(cfg), cfg.street_length_m,
                                             cfg.frame_dt, cfg.ego_speed)
    return _CACHE[key]


def _env(name: str, rot: float, spec=None) -> np.ndarray:
    """A bundled HDRI / file rotated, or (randomised scenes) the training light of ``spec``:
    the analytic sun-and-sky map (``name == "sunsky"``) or the HDRI, times the spec's intensity."""
    key = ("env", name, rot, spec)
    if key not in _CACHE:
        if spec is not None and name == SUNSKY:
            _CACHE[key] = sun_sky_map(spec.sun_elevation_deg, spec.sun_azimuth_deg, spec.turbidity,
                                      height=512, intensity=spec.intensity)
        elif spec is not None:
            _CACHE[key] = (load_envmap(name, rot) * np.float32(spec.intensity)).astype(np.float32)
        else:
            _CACHE[key] = load_envmap(name, rot)
    return _CACHE[key]


def _render_job(job: tuple) -> tuple:
    from core.camera import Camera

    kind, key, cfg, t, c2w, env_name, env_rot, seed = job
    cam_i = intrinsics(cfg)
    k1 = _k1(cfg)
    if k1:  # render a pinhole canvas covering the lens's field, then warp (core.synth.sensor)
        us, vs, px, py = source_coords(cfg.width, cfg.height, cam_i.fx, k1)
        W, H = cfg.width + 2 * px, cfg.height + 2 * py
        cam = Camera.from_intrinsics(c2w, cam_i.fx, cam_i.fy, W / 2.0, H / 2.0, W, H)
    else:
        cam = Camera.from_intrinsics(c2w, cam_i.fx, cam_i.fy, cam_i.cx, cam_i.cy, cfg.width, cfg.height)
    parts = _street(cfg).parts_at(t)
    if kind == "gbuffer":  # distorted: one ray per output pixel, exactly along its lens ray
        film_uv = np.stack([us / cam.width, vs / cam.height], -1) if k1 else None
        return kind, key, render_gbuffers(parts, cam, film_uv)
    spp = (cfg.relight_spp or 4 * cfg.spp) if kind.startswith("relit:") else cfg.spp
    spec = cfg.scene_spec if kind == "beauty" else None  # relit maps: the plain HDRIs
    img = render_beauty(parts, _env(env_name, env_rot, spec), cam, spp=spp, max_depth=cfg.max_depth, seed=seed)
    if k1:
        img = np.maximum(warp_bilinear(img, us, vs), 0.0)
    return kind, key, img


def simulate_lidar(cfg: SynthConfig, t: int, x: float) -> np.ndarray:
    """A spinning LiDAR at the ego position: float32 [N, 6] world (origin xyz, hit xyz)."""
    if cfg.lidar_beams == 0:
        return np.zeros((0, 6), np.float32)
    elev = np.radians(np.linspace(-25.0, 5.0, cfg.lidar_beams))
    az = np.linspace(0.0, 2 * math.pi, cfg.lidar_azimuth_steps, endpoint=False)
    E, A = np.meshgrid(elev, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    o = np.tile([x, ego_lane_y(cfg), cfg.lidar_height_m], (len(d), 1))
    dist = RayCaster(_street(cfg).parts_at(t)).cast(o, d, cfg.lidar_range_m)
    ok = np.isfinite(dist)
    pts = o[ok] + d[ok] * dist[ok, None]
    return np.concatenate([o[ok], pts], 1).astype(np.float32)


def generate_scene(cfg: SynthConfig, out_dir: str | Path, *, name: str | None = None,
                   overwrite: bool = False, progress: bool = True, workers: int | None = None) -> Path:
    """Render the street of ``cfg`` with Mitsuba and write a scene bundle to ``out_dir``.

    Train frames follow the ego lane; test (novel-view) frames a parallel path offset by
    ``cfg.test_offset_m``; relit ground truth is rendered for test frames. Returns the bundle root.
    """
    name = name or f"street_seed{cfg.seed}"
    spec = cfg.scene_spec
    env_train = _env(cfg.envmap, cfg.envmap_rotation_deg, spec)  # fail early on a bad envmap name
    for n in cfg.relight_envmaps:
        _env(n, 0.0)  # fail early on a bad envmap name
    ego_x = ego_positions(cfg)
    frames = []  # (frame_id, split, t, c2w)
    for t, x in enumerate(ego_x):
        frames.append((f"train_{t:03d}", "train", t, camera_pose(cfg, x, ego_lane_y(cfg))))
    for t, x in enumerate(ego_x):
        frames.append((f"test_{t:03d}", "test", t, camera_pose(cfg, x, ego_lane_y(cfg) + cfg.test_offset_m)))

    jobs = []
    for i, (fid, split, t, c2w) in enumerate(frames):
        jobs.append(("gbuffer", fid, cfg, t, c2w, None, 0.0, 0))
        jobs.append(("beauty", fid, cfg, t, c2w, cfg.envmap, cfg.envmap_rotation_deg, cfg.seed * 1000 + i))
    test_frames = [f for f in frames if f[1] == "test"][:: cfg.relight_every]
    for k, env_name in enumerate(cfg.relight_envmaps):
        for i, (fid, split, t, c2w) in enumerate(test_frames):
            jobs.append(("relit:" + env_name, fid, cfg, t, c2w, env_name, 0.0, cfg.seed * 1000 + 500 + 50 * k + i))

    results: dict = {}
    n_workers = workers if workers is not None else min(2, os.cpu_count() or 1)
    bar = tqdm(total=len(jobs) + cfg.num_frames, desc=f"generate {name}", unit="render", disable=not progress)
    if n_workers > 1:
        with ProcessPoolExecutor(n_workers, mp_context=mp.get_context("spawn")) as pool:
            for kind, key, out in pool.map(_render_job, jobs):
                results[(kind, key)] = out
                bar.update()
    else:
        for job in jobs:
            kind, key, out = _render_job(job)
            results[(kind, key)] = out
            bar.update()

    lidar = []
    for t, x in enumerate(ego_x):
        lidar.append(simulate_lidar(cfg, t, x))
        bar.update()
    bar.close()

    # exposure: the configured one, so the LDR frames of all scenes share one tone map;
    # randomised scenes: auto exposure on the first train frame, offset by the spec's stops
    exposure, gamma = cfg.exposure, cfg.gamma
    if spec is not None:
        exposure = round(auto_exposure(results[("beauty", frames[0][0])], spec.exposure_ev), 6)
    cam = intrinsics(cfg)
    street = _street(cfg)
    config = asdict(cfg)
    if spec is None:
        config.pop("scene_spec")  # the profiles' manifests stay as they were
    w = BundleWriter(out_dir, name, overwrite=overwrite,
                     description=f"Synthetic street (seed {cfg.seed}) rendered by Mitsuba 3 under {cfg.envmap}",
                     source={"kind": "synthetic", "generator": "core.synth", "config": _jsonable(config)},
                     ldr_exposure=exposure, ldr_gamma=gamma)
    tmp = None
    if spec is not None:
        tmp = tempfile.TemporaryDirectory(prefix="brdf-synth-")
        noise_rng = np.random.default_rng([spec.seed, 11])
    with w:
        w.set_times([t * cfg.frame_dt for t in range(cfg.num_frames)])
        w.add_camera(cam)
        for fid, split, t, c2w in frames:
            g = results[("gbuffer", fid)]
            hdr = results[("beauty", fid)]
            gt = {"rgb": hdr, "albedo": g["albedo"], "roughness": g["roughness"], "metallic": g["metallic"],
                  "normal": g["normal"], "depth": g["depth"]}
            if spec is None:
                ldr = ldr_to_uint8(hdr_to_ldr(hdr, exposure, gamma))
                w.add_frame(fid, cam.id, t, c2w, image=ldr, split=split, sky_mask=g["sky"], ground_truth=gt)
                continue

            ldr = apply_sensor(hdr, exposure, gamma, spec.contrast, spec.shot_noise, spec.read_noise, noise_rng)
            if spec.jpeg_quality:
                from PIL import Image

                jpg = Path(tmp.name) / f"{fid}.jpg"
                Image.fromarray(ldr).save(jpg, quality=int(spec.jpeg_quality))
                w.add_frame(fid, cam.id, t, c2w, image_file=jpg, split=split, sky_mask=g["sky"], ground_truth=gt)
            else:
                w.add_frame(fid, cam.id, t, c2w, image=ldr, split=split, sky_mask=g["sky"], ground_truth=gt)
        for t, pts in enumerate(lidar):
            w.add_lidar(t, pts)
        for car in street.cars:
            w.add_object(car.id, "car", car.size, car.poses)
        if spec is not None:  # the analytic sky or an HDRI times the intensity: write the array
            env_name_train = SUNSKY if cfg.envmap == SUNSKY else resolve_envmap(cfg.envmap).stem
            w.set_ground_truth_envmap(env_train, env_name_train, cfg.envmap_rotation_deg)
        elif column_shift(env_train, cfg.envmap_rotation_deg) == 0:  # unrotated: copy the file
            env_name_train = resolve_envmap(cfg.envmap).stem
            w.set_ground_truth_envmap(None, env_name_train, 0.0, envmap_file=resolve_envmap(cfg.envmap))
        else:
            env_name_train = resolve_envmap(cfg.envmap).stem
            w.set_ground_truth_envmap(env_train, env_name_train, cfg.envmap_rotation_deg)
        for env_name in cfg.relight_envmaps:
            w.add_relit(resolve_envmap(env_name).stem, None,
                        {fid: results[("relit:" + env_name, fid)] for fid, *_ in test_frames},
                        envmap_file=resolve_envmap(env_name))
        root = w.finish()
    if tmp is not None:
        tmp.cleanup()
    return root


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    return d
