"""Encoders between the project's images / G-buffers / environment maps and the data spaces of
the model contracts (:mod:`core.gen.contract`). numpy, float32, channels-first outputs.

Inputs are channels-last as the bundles store them: images [H, W, 3], single layers [H, W] or
[H, W, 1], normals in the **world** frame (bundles, PBR G-buffers), depth = camera z in metres
(0 on sky), environment maps [He, We, 3] linear HDR (project equirect convention).
"""

from __future__ import annotations

import numpy as np

from core.conventions import envmap_directions
from core.errors import ShapeError
from core.gen import contract as C
from core.numerics import require_finite_np


def _img(a, name: str, channels: int | None = None) -> np.ndarray:
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or (channels is not None and a.shape[-1] != channels):
        want = f"[H, W, {channels}]" if channels else "[H, W, C]"
        raise ShapeError(f"{name}: expected {want}, got {a.shape}")
    return require_finite_np(a, name)


def ldr_to_data(ldr) -> np.ndarray:
    """LDR [..] in [0, 1] -> data space 2 ldr - 1 (same shape)."""
    return np.asarray(ldr, np.float32) * 2.0 - 1.0


def data_to_ldr(x) -> np.ndarray:
    """Data space -> LDR, clipped to [0, 1]."""
    return np.clip((np.asarray(x, np.float32) + 1.0) * 0.5, 0.0, 1.0)


def encode_depth(depth) -> np.ndarray:
    """Camera z-depth (metres, 0 = sky / no surface) -> exp(-z / DEPTH_SCALE_M), sky -> 0."""
    d = np.asarray(depth, np.float32)
    return np.where(d > 0, np.exp(-np.maximum(d, 0) / C.DEPTH_SCALE_M), 0.0).astype(np.float32)


def decode_depth(enc) -> np.ndarray:
    """Inverse of :func:`encode_depth` (values <= 1e-6 -> 0 = sky)."""
    e = np.asarray(enc, np.float32)
    safe = np.clip(e, 1e-6, 1.0)
    return np.where(e > 1e-6, -C.DEPTH_SCALE_M * np.log(safe), 0.0).astype(np.float32)


def world_to_camera_dirs(dirs_world, cam_to_world) -> np.ndarray:
    """Directions/normals [..., 3] world -> camera frame (OpenCV): ``R^T d``."""
    r = np.asarray(cam_to_world, np.float64)[:3, :3]
    return (np.asarray(dirs_world, np.float64) @ r).astype(np.float32)


def camera_to_world_dirs(dirs_cam, cam_to_world) -> np.ndarray:
    """Directions [..., 3] camera frame -> world: ``R d``."""
    r = np.asarray(cam_to_world, np.float64)[:3, :3]
    return (np.asarray(dirs_cam, np.float64) @ r.T).astype(np.float32)


def encode_gbuffer(albedo, roughness, metallic, normal_cam, depth) -> np.ndarray:
    """G-buffer layers (channels-last, normals in the camera frame) -> [9, H, W] G-buffer data
    space of the ``inverse_gbuffer`` contract."""
    a = _img(albedo, "albedo", 3)
    r = _img(roughness, "roughness", 1)
    m = _img(metallic, "metallic", 1)
    n = _img(normal_cam, "normal", 3)
    d = _img(depth, "depth", 1)
    if not (a.shape[:2] == r.shape[:2] == m.shape[:2] == n.shape[:2] == d.shape[:2]):
        raise ShapeError(f"G-buffer layers differ in size: albedo {a.shape}, roughness {r.shape}, "
                         f"metallic {m.shape}, normal {n.shape}, depth {d.shape}")
    x = np.concatenate([a * 2 - 1, r * 2 - 1, m * 2 - 1, n, encode_depth(d) * 2 - 1], axis=-1)
    return np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32)


def decode_gbuffer(x) -> dict[str, np.ndarray]:
    """[9, H, W] G-buffer data space -> channels-last layers: albedo, roughness, metallic in
    [0, 1] (clipped), normal (camera frame, renormalised; zero stays zero), depth (metres)."""
    x = np.asarray(x, np.float32)
    if x.ndim != 3 or x.shape[0] != C.GBUFFER_CHANNELS:
        raise ShapeError(f"x: expected [9, H, W], got {x.shape}")
    t = x.transpose(1, 2, 0)
    sl = C.GBUFFER_SLICES
    n = t[..., sl["normal"]]
    ln = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(ln > 0.2, n / np.maximum(ln, 1e-6), 0.0)
    return {"albedo": np.clip((t[..., sl["albedo"]] + 1) / 2, 0, 1),
            "roughness": np.clip((t[..., sl["roughness"]] + 1) / 2, 0, 1),
            "metallic": np.clip((t[..., sl["metallic"]] + 1) / 2, 0, 1),
            "normal": n.astype(np.float32),
            "depth": decode_depth(np.clip((t[..., sl["depth"]] + 1) / 2, 0, 1))}


def area_downsample(env, height: int, width: int) -> np.ndarray:
    """Average an equirect map [He, We, 3] to [height, width, 3] over whole blocks (He, We must
    be multiples; radiance-preserving per block)."""
    e = np.asarray(env, np.float32)
    if e.ndim != 3 or e.shape[0] % height or e.shape[1] % width:
        raise ShapeError(f"env: {e.shape} is not a multiple of {height}x{width}")
    fh, fw = e.shape[0] // height, e.shape[1] // width
    return e.reshape(height, fh, width, fw, e.shape[2]).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def encode_env(env_hdr, cam_to_world) -> dict[str, np.ndarray]:
    """DiffusionRenderer-style environment encoding for one frame: ``env_ldr``, ``env_log``,
    ``env_dir`` each [3, ENV_H, ENV_W] (see :mod:`core.gen.contract`). ``env_hdr``: [He, We, 3]
    linear radiance >= 0, He x We a multiple of 64 x 128 (e.g. 512 x 1024)."""
    e = _img(env_hdr, "env", 3)
    if (e < 0).any():
        raise ShapeError(f"env: {int((e < 0).sum())} negative radiance value(s)")
    small = area_downsample(e, C.ENV_H, C.ENV_W)
    dirs_cam = world_to_camera_dirs(envmap_directions(C.ENV_H, C.ENV_W), cam_to_world)
    t = lambda a: np.ascontiguousarray(a.transpose(2, 0, 1), dtype=np.float32)  # noqa: E731
    return {"env_ldr": t(small / (1.0 + small)),
            "env_log": t(np.log1p(small) / np.log1p(C.ENV_LOG_MAX)),
            "env_dir": t(dirs_cam)}


def forward_conditioning(albedo, roughness, metallic, normal_world, depth, cam_to_world,
                         env_hdr=None, env_encoded: dict | None = None) -> dict[str, np.ndarray]:
    """Conditioning inputs of the ``forward_denoiser`` contract for one frame (each [C, H, W]):
    normal (camera frame), depth (encoded), albedo, roughness, metallic, env_ldr/env_log/env_dir.
    Pass ``env_encoded`` (from :func:`encode_env`) to reuse an encoding."""
    n_cam = world_to_camera_dirs(_img(normal_world, "normal", 3), cam_to_world)
    ln = np.linalg.norm(n_cam, axis=-1, keepdims=True)
    n_cam = np.where(ln > 1e-6, n_cam / np.maximum(ln, 1e-6), 0.0)
    t = lambda a: np.ascontiguousarray(np.asarray(a, np.float32).transpose(2, 0, 1))  # noqa: E731
    out = {"normal": t(n_cam), "depth": t(encode_depth(_img(depth, "depth", 1))),
           "albedo": t(np.clip(_img(albedo, "albedo", 3), 0, 1)),
           "roughness": t(np.clip(_img(roughness, "roughness", 1), 0, 1)),
           "metallic": t(np.clip(_img(metallic, "metallic", 1), 0, 1))}
    if env_encoded is None:
        if env_hdr is None:
            raise ShapeError("forward_conditioning: give env_hdr or env_encoded")
        env_encoded = encode_env(env_hdr, cam_to_world)
    out.update(env_encoded)
    return out


def view_conditioning(cam_to_world, fx: float, fy: float, cx: float, cy: float, width: int,
                      height: int) -> np.ndarray:
    """The ``inverse_gbuffer`` contract's optional camera input for one frame: [6, H, W] float32,
    channels 0-2 the unit ray direction through each pixel centre, channels 3-5 the world up
    direction (+z), both in the camera frame (OpenCV axes). ``cam_to_world``: [4, 4] (or [3, 4]),
    world metres; ``fx, fy, cx, cy``: pinhole intrinsics in pixels of the ``width`` x ``height``
    image (a camera's lens distortion is not applied: the rays are the pinhole model's)."""
    c2w = require_finite_np(np.asarray(cam_to_world, np.float64), "cam_to_world")
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ShapeError(f"cam_to_world: expected [4, 4] or [3, 4], got {c2w.shape}")
    if not (fx > 0 and fy > 0) or width < 1 or height < 1:
        raise ShapeError(f"intrinsics: need fx, fy > 0 and a non-empty image, got fx {fx}, fy {fy}, "
                         f"{width}x{height}")
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    uu, vv = np.meshgrid(u, v)
    ray = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], 0)
    ray = ray / np.linalg.norm(ray, axis=0, keepdims=True)
    up = world_to_camera_dirs(np.array([0.0, 0.0, 1.0]), c2w)
    up = up / max(float(np.linalg.norm(up)), 1e-12)  # R is a rotation: |up| = 1 up to rounding
    up_img = np.broadcast_to(up.reshape(3, 1, 1), (3, height, width))
    return np.ascontiguousarray(np.concatenate([ray, up_img], 0), dtype=np.float32)
