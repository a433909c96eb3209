"""Builders of small drivestudio and nerfstudio capture layouts, with the ground truth they encode.

Fixtures return factories so a test can build a layout and then break one file of it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core.conventions import OPENCV_TO_OPENGL, look_at

IMG_W, IMG_H = 64, 48


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = c, s, -s, c
    return m


def translate(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = [x, y, z]
    return m


def apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ m[:3, :3].T + m[:3, 3]


def box_corners(size) -> np.ndarray:
    """8 corners [8, 3] of a box centred at the origin with extents ``size`` (l, w, h)."""
    l, w, h = size
    return np.array([[sx * l / 2, sy * w / 2, sz * h / 2]
                     for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])


def write_matrix(path: Path, m: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.asarray(m, dtype=np.float64))


def write_jpeg(path: Path, w: int, h: int, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(path, quality=90)


def write_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


# ---------------------------------------------------------------------------------------------
# drivestudio
# ---------------------------------------------------------------------------------------------
@dataclass
class DriveScene:
    root: Path
    times: list[int]
    cams: list[int]
    ego: dict[int, np.ndarray]                 # t -> vehicle_to_world
    extrinsic: dict[int, np.ndarray]           # cam -> camera_to_vehicle (Waymo camera axes)
    intrinsics: dict[int, list[float]]         # cam -> fx fy cx cy k1 k2 p1 p2 k3
    lidar_rows: dict[int, np.ndarray]          # t -> float32 [N, 14] vehicle frame
    box_pose: dict[int, np.ndarray]            # t -> obj_to_world of instance "0"
    box_sizes: list[list[float]]               # per-frame sizes of instance "0"
    box_size_median: tuple[float, float, float]
    box_surface_idx: dict[int, np.ndarray]     # t -> row indices in lidar_rows of box-surface points
    extra: dict = field(default_factory=dict)


def build_drivestudio(root: Path, *, n_times: int = 3, with_instances: bool = True,
                      with_lidar: bool = True, with_sky: bool = True) -> DriveScene:
    root.mkdir(parents=True, exist_ok=True)
    times = list(range(n_times))
    cams = [0, 3]  # FRONT and SIDE_LEFT
    # Ego drives along +x (world), drifting left a little and turning left by 0.04 rad per step.
    ego = {t: translate(100.0 + 8.0 * t, -40.0 + 0.3 * t, 3.0) @ rot_z(0.04 * t) for t in times}
    extrinsic = {
        0: translate(1.5, 0.0, 2.0),                                          # looks along vehicle +x
        3: translate(1.0, 0.9, 1.8) @ rot_z(np.pi / 2) @ rot_y(0.05),         # looks left, pitched down
    }
    intrinsics = {
        0: [60.0, 58.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        3: [50.0, 51.0, 31.5, 23.5, 0.01, -0.002, 0.0, 0.0, 0.0],
    }
    for t in times:
        write_matrix(root / "ego_pose" / f"{t:03d}.txt", ego[t])
        for c in cams:
            write_jpeg(root / "images" / f"{t:03d}_{c}.jpg", IMG_W, IMG_H, seed=10 * t + c)
    for c in cams:
        write_matrix(root / "extrinsics" / f"{c}.txt", extrinsic[c])
        (root / "intrinsics").mkdir(exist_ok=True)
        (root / "intrinsics" / f"{c}.txt").write_text("\n".join(repr(v) for v in intrinsics[c]) + "\n")
    if with_sky:
        mask = np.zeros((IMG_H, IMG_W), np.uint8)
        mask[: IMG_H // 3] = 255
        write_png(root / "sky_masks" / f"{0:03d}_0.png", mask)

    # A vehicle 18 m ahead of the ego, slightly to the left, yawed by 0.1 rad.
    box_pose = {t: ego[t] @ translate(18.0, 0.5, 0.8) @ rot_z(0.1) for t in times}
    box_sizes = [[4.5, 2.0, 1.6], [4.4, 2.1, 1.55], [4.6, 1.9, 1.7], [4.5, 2.0, 1.6]][:n_times]
    median = tuple(float(v) for v in np.median(np.asarray(box_sizes), axis=0))
    l, w, h = median
    surface_local = np.array([[-l / 2, 0.0, 0.0], [-l / 2, 0.5, 0.3], [-l / 2, -0.6, -0.4],
                              [0.5, 0.2, h / 2], [1.0, w / 2, 0.1]])

    rng = np.random.default_rng(7)
    lidar_rows, surface_idx = {}, {}
    for t in times:
        ground = np.stack([rng.uniform(5, 30, 40), rng.uniform(-5, 5, 40), np.full(40, -0.1)], axis=1)
        on_box = apply(np.linalg.inv(ego[t]) @ box_pose[t], surface_local)  # vehicle frame
        pts = np.concatenate([ground, on_box])
        rows = np.zeros((len(pts), 14), np.float32)
        rows[:, 0:3] = [0.0, 0.0, 2.1]
        rows[:, 3:6] = pts
        rows[:, 6:9] = rng.normal(size=(len(pts), 3))
        rows[:, 11] = rng.uniform(0, 1, len(pts))
        rows[:, 13] = 1
        lidar_rows[t] = rows
        surface_idx[t] = np.arange(len(ground), len(pts))
        if with_lidar:
            (root / "lidar").mkdir(exist_ok=True)
            rows.tofile(root / "lidar" / f"{t:03d}.bin")

    if with_instances:
        ped_times = times[1:]
        ped_pose = {t: ego[t] @ translate(10.0, -3.0, 0.9) for t in ped_times}
        info = {
            "0": {"id": "vehicle_abc", "class_name": "Vehicle", "frame_annotations": {
                "frame_idx": times, "obj_to_world": [box_pose[t].tolist() for t in times],
                "box_size": box_sizes}},
            "1": {"id": "ped_xyz", "class_name": "Pedestrian", "frame_annotations": {
                "frame_idx": ped_times, "obj_to_world": [ped_pose[t].tolist() for t in ped_times],
                "box_size": [[0.8, 0.8, 1.8]] * len(ped_times)}},
        }
        (root / "instances").mkdir(exist_ok=True)
        (root / "instances" / "instances_info.json").write_text(json.dumps(info))
        frame_instances = {str(t): [0] + ([1] if t in ped_times else []) for t in times}
        (root / "instances" / "frame_instances.json").write_text(json.dumps(frame_instances))

    return DriveScene(root, times, cams, ego, extrinsic, intrinsics, lidar_rows, box_pose, box_sizes,
                      median, surface_idx)


@pytest.fixture
def drivestudio_scene(tmp_path):
    """Factory: ``drivestudio_scene(**opts)`` builds a layout under tmp_path/"src"."""
    def make(**opts) -> DriveScene:
        return build_drivestudio(tmp_path / "src", **opts)
    return make


# ---------------------------------------------------------------------------------------------
# nerfstudio
# ---------------------------------------------------------------------------------------------
NS_W, NS_H = 80, 60
NS_TARGET = np.array([1.0, 2.0, 0.5])


@dataclass
class NerfScene:
    root: Path
    target: np.ndarray
    c2w_opencv: dict[str, np.ndarray]   # file_path -> cam_to_world (OpenCV axes)
    meta: dict


def build_nerfstudio(root: Path, *, world: np.ndarray | None = None) -> NerfScene:
    """Three frames looking at NS_TARGET, listed out of file-name order; the last in file order
    overrides the focal length. ``world``: optional 4x4 applied to the whole scene."""
    root.mkdir(parents=True, exist_ok=True)
    world = np.eye(4) if world is None else world
    eyes = {"images/frame_00003.png": [5.0, 2.0, 1.5],
            "images/frame_00001.png": [1.0, -3.0, 2.0],
            "images/frame_00002.png": [-3.0, 4.5, 1.0]}
    target = apply(world, NS_TARGET[None])[0]
    up = world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    c2w, frames = {}, []
    for i, (fp, eye) in enumerate(eyes.items()):
        m = look_at(apply(world, np.array([eye]))[0], target, up)
        c2w[fp] = m
        arr = np.random.default_rng(i).integers(0, 256, (NS_H, NS_W, 3), dtype=np.uint8)
        write_png(root / fp, arr)
        fr = {"file_path": fp, "transform_matrix": (m @ OPENCV_TO_OPENGL).tolist(),
              "mask_path": fp.replace("images", "masks")}
        if fp.endswith("00003.png"):
            fr.update({"fl_x": 90.0, "fl_y": 90.0})
        frames.append(fr)
    meta = {"camera_model": "OPENCV", "fl_x": 70.0, "fl_y": 72.0, "cx": NS_W / 2, "cy": NS_H / 2,
            "w": NS_W, "h": NS_H, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": frames, "ply_file_path": "sparse_pc.ply"}
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return NerfScene(root, target, c2w, meta)


@pytest.fixture
def nerfstudio_scene(tmp_path):
    """Factory: ``nerfstudio_scene(**opts)`` builds a capture under tmp_path/"ns"."""
    def make(**opts) -> NerfScene:
        return build_nerfstudio(tmp_path / "ns", **opts)
    return make


@pytest.fixture
def geom():
    """Small geometry helpers for the tests (conftest modules are not importable by name)."""
    from types import SimpleNamespace

    return SimpleNamespace(apply=apply, box_corners=box_corners, rot_z=rot_z, rot_y=rot_y,
                           translate=translate, write_matrix=write_matrix)
