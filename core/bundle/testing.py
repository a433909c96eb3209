"""Fake bundles for tests and benchmarks: valid bundles with random content, written without a
renderer (the one builder the core tests, the service tests and the load benchmark use)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.bundle.schema import Camera
from core.bundle.writer import BundleWriter
from core.conventions import look_at


def write_fake_bundle(root: Path, *, frames: int = 3, width: int = 32, height: int = 24, test_frames: int = 1,
                      with_gt: bool = True, seed: int = 0, name: str | None = None, focal: float | None = None,
                      source: dict | None = None, extras: bool = False) -> Path:
    """A valid bundle of ``frames`` random frames from one forward camera driving along +x.

    The last ``test_frames`` frames are the test split. ``with_gt`` adds per-frame ground truth
    (rgb, albedo, roughness, metallic, normal +z, depth) and a constant 16x32 environment map.
    ``extras`` adds a sky mask (top third) and a LiDAR sweep per frame, a tracked car, and (with
    ground truth) a relit set for the last frame. ``name`` defaults to ``bundle-{seed}``,
    ``focal`` (pixels) to the width. Returns the bundle root."""
    rng = np.random.default_rng(seed)
    focal = float(width) if focal is None else focal
    w = BundleWriter(root, f"bundle-{seed}" if name is None else name, overwrite=True, source=source)
    w.set_times([0.1 * t for t in range(frames)])
    w.add_camera(Camera("front", width, height, focal, focal, width / 2, height / 2))
    for t in range(frames):
        img = rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)
        sky = None
        if extras:
            sky = np.zeros((height, width), bool)
            sky[: height // 3] = True
        gt = None
        if with_gt:
            n = np.zeros((height, width, 3), np.float32)
            n[..., 2] = 1.0
            gt = {"rgb": rng.uniform(0, 2, (height, width, 3)).astype(np.float32),
                  "albedo": rng.uniform(0, 1, (height, width, 3)).astype(np.float32),
                  "roughness": rng.uniform(0, 1, (height, width, 1)).astype(np.float32),
                  "metallic": rng.uniform(0, 1, (height, width, 1)).astype(np.float32),
                  "normal": n, "depth": rng.uniform(1, 50, (height, width, 1)).astype(np.float32)}
        w.add_frame(f"f{t:03d}", "front", t, look_at([t * 1.0, 0.0, 1.5], [t * 1.0 + 10.0, 0.0, 1.0]), image=img,
                    split="test" if t >= frames - test_frames else "train", sky_mask=sky, ground_truth=gt)
        if extras:
            pts = np.concatenate([np.tile([t, 0, 1.9], (50, 1)), rng.uniform(-5, 5, (50, 3))], 1)
            w.add_lidar(t, pts)
    if extras:
        pose = {t: np.array([[1, 0, 0, 5.0 + t], [0, 1, 0, 2.0], [0, 0, 1, 0.75], [0, 0, 0, 1]])
                for t in range(frames)}
        w.add_object("car0", "car", (4.4, 1.8, 1.5), pose)
    if with_gt:
        env = np.ones((16, 32, 3), np.float32)
        w.set_ground_truth_envmap(env, "const")
        if extras:
            w.add_relit("const2", env * 2,
                        {f"f{frames - 1:03d}": rng.uniform(0, 1, (height, width, 3)).astype(np.float32)})
    return w.finish()
