"""Shared fixtures: a small valid bundle written without Mitsuba, and a tiny Mitsuba scene."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from core.bundle import BundleWriter, Camera
from core.conventions import look_at

REPO = Path(__file__).resolve().parents[1]


def write_small_bundle(root: Path, *, frames: int = 3, width: int = 32, height: int = 24,
                       with_gt: bool = True) -> Path:
    """A valid bundle of a few frames with simple content (no renderer involved)."""
    rng = np.random.default_rng(0)
    w = BundleWriter(root, "small", overwrite=True, source={"kind": "test"})
    w.set_times([0.1 * t for t in range(frames)])
    w.add_camera(Camera("front", width, height, 30.0, 30.0, width / 2, height / 2))
    for t in range(frames):
        c2w = look_at([t * 1.0, 0.0, 1.5], [t * 1.0 + 10.0, 0.0, 1.0])
        img = rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)
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
        w.add_frame(f"f{t:03d}", "front", t, c2w, image=img, split="test" if t == frames - 1 else "train",
                    sky_mask=sky, ground_truth=gt)
        pts = np.concatenate([np.tile([t, 0, 1.9], (50, 1)), rng.uniform(-5, 5, (50, 3))], 1)
        w.add_lidar(t, pts)
    pose = {t: np.array([[1, 0, 0, 5.0 + t], [0, 1, 0, 2.0], [0, 0, 1, 0.75], [0, 0, 0, 1]]) for t in range(frames)}
    w.add_object("car0", "car", (4.4, 1.8, 1.5), pose)
    if with_gt:
        env = np.ones((16, 32, 3), np.float32)
        w.set_ground_truth_envmap(env, "const")
        w.add_relit("const2", env * 2, {f"f{frames - 1:03d}": rng.uniform(0, 1, (height, width, 3)).astype(np.float32)})
    return w.finish()


@pytest.fixture
def small_bundle(tmp_path) -> Path:
    return write_small_bundle(tmp_path / "small")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A tiny synthetic street rendered by Mitsuba (profile ``tiny``, ~3 s)."""
    from core.synth import generate_scene, profile

    root = tmp_path_factory.mktemp("synth") / "tiny"
    return generate_scene(profile("tiny"), root, progress=False, workers=1)
