"""The scene bundle manifest (``bundle.json``): typed records, parsing and serialisation.

A scene bundle is a directory (or the same tree packed as .zip / .tar.gz) holding a posed capture
of a street and, for synthetic scenes, its ground truth. Layout (paths are relative to the root,
use ``/`` and never leave it)::

    bundle.json                         manifest, this module (format + version below)
    images/<frame_id>.png|.jpg          LDR frames, 8-bit sRGB-like: ldr = (exposure*hdr)^(1/gamma)
    sky_masks/<frame_id>.png            optional, 8-bit, non-zero = sky
    lidar/<time_index:04d>.npy          optional, float32 [N, 6] world frame, metres:
                                        sensor origin xyz, hit point xyz
    ground_truth/frames/<frame_id>.exr  synthetic only (half float, ZIP; HDR clamped at 65504):
                                        layers rgb (HDR beauty), albedo (R,G,B),
                                        roughness (Y), metallic (Y), normal (X,Y,Z world, unit),
                                        depth (Y, camera z-depth in metres, 0 on sky)
    ground_truth/envmaps/<name>.exr     synthetic only: equirect HDR maps in the project's convention
                                        (core/conventions.py), float32
    ground_truth/relit/<name>/<frame_id>.exr  synthetic only: HDR beauty (layer rgb) of a frame
                                        under another environment map

The manifest (JSON) has these keys (``?`` = optional)::

    format        "brdfusion-scene-bundle"
    version       1  (SCHEMA_VERSION; readers refuse unknown versions)
    name          short scene name
    description?  free text
    times         [T] seconds: timestamp of each time index 0..T-1 (strictly increasing)
    cameras       {camera_id: {width, height, fx, fy, cx, cy, distortion?: [k1, k2, p1, p2, k3]}}
    frames        [{id, image, camera, time_index, cam_to_world (4x4, OpenCV axes, world z-up),
                    split ("train" | "test"), sky_mask?, ground_truth?}]
    lidar?        [{time_index, file}]
    objects?      [{id, class, size [l, w, h] metres (box x, y, z extents in the object frame,
                    box centred at the object origin), poses [{time_index, obj_to_world 4x4}]}]
    ldr           {exposure, gamma}: how the LDR images relate to scene radiance
    ground_truth? {envmap, envmap_name, envmap_rotation_deg,
                   relit?: [{name, envmap, envmap_rotation_deg, frames: {frame_id: path}}]}
    source?       {kind: "synthetic" | "drivestudio" | "nerfstudio" | ..., plus free fields}
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.conventions import is_rigid
from core.errors import BundleError

FORMAT_NAME = "brdfusion-scene-bundle"
SCHEMA_VERSION = 1
MANIFEST_NAME = "bundle.json"
SPLITS = ("train", "test")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: Layers every ground-truth frame EXR must hold, with their channel counts.
GT_FRAME_LAYERS = {"rgb": 3, "albedo": 3, "roughness": 1, "metallic": 1, "normal": 3, "depth": 1}


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of one camera, pixels. Image is ``width`` x ``height``."""

    id: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


@dataclass(frozen=True)
class Frame:
    """One image of the capture."""

    id: str
    image: str
    camera: str
    time_index: int
    cam_to_world: np.ndarray  # [4, 4] OpenCV camera axes -> world
    split: str = "train"
    sky_mask: str | None = None
    ground_truth: str | None = None


@dataclass(frozen=True)
class LidarSweep:
    """One LiDAR sweep: ``file`` holds float32 [N, 6] world (origin xyz, point xyz)."""

    time_index: int
    file: str


@dataclass(frozen=True)
class ObjectTrack:
    """A tracked rigid object: box ``size`` (l, w, h metres) and a pose per observed time index."""

    id: str
    cls: str
    size: tuple[float, float, float]
    poses: dict[int, np.ndarray]  # time_index -> obj_to_world [4, 4]


@dataclass(frozen=True)
class RelitSet:
    """Ground-truth frames of the same scene under another environment map."""

    name: str
    envmap: str
    envmap_rotation_deg: float
    frames: dict[str, str]


@dataclass(frozen=True)
class GroundTruth:
    envmap: str
    envmap_name: str
    envmap_rotation_deg: float = 0.0
    relit: tuple[RelitSet, ...] = ()


@dataclass(frozen=True)
class Manifest:
    name: str
    times: tuple[float, ...]
    cameras: dict[str, Camera]
    frames: tuple[Frame, ...]
    lidar: tuple[LidarSweep, ...] = ()
    objects: tuple[ObjectTrack, ...] = ()
    ldr_exposure: float = 1.0
    ldr_gamma: float = 2.2
    ground_truth: GroundTruth | None = None
    description: str = ""
    source: dict[str, Any] = field(default_factory=dict)
    version: int = SCHEMA_VERSION

    def frame(self, frame_id: str) -> Frame:
        for f in self.frames:
            if f.id == frame_id:
                return f
        raise KeyError(frame_id)

    def split(self, split: str) -> list[Frame]:
        return [f for f in self.frames if f.split == split]

    # -----------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": self.version,
            "name": self.name,
            "description": self.description,
            "times": [float(t) for t in self.times],
            "cameras": {
                c.id: {
                    "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy,
                    "cx": c.cx, "cy": c.cy,
                    **({"distortion": list(c.distortion)} if c.distortion else {}),
                }
                for c in self.cameras.values()
            },
            "frames": [
                {
                    "id": f.id, "image": f.image, "camera": f.camera, "time_index": f.time_index,
                    "cam_to_world": _mat_to_list(f.cam_to_world), "split": f.split,
                    **({"sky_mask": f.sky_mask} if f.sky_mask else {}),
                    **({"ground_truth": f.ground_truth} if f.ground_truth else {}),
                }
                for f in self.frames
            ],
            "ldr": {"exposure": self.ldr_exposure, "gamma": self.ldr_gamma},
        }
        if self.lidar:
            d["lidar"] = [{"time_index": s.time_index, "file": s.file} for s in self.lidar]
        if self.objects:
            d["objects"] = [
                {
                    "id": o.id, "class": o.cls, "size": list(o.size),
                    "poses": [{"time_index": t, "obj_to_world": _mat_to_list(m)}
                              for t, m in sorted(o.poses.items())],
                }
                for o in self.objects
            ]
        if self.ground_truth is not None:
            g = self.ground_truth
            d["ground_truth"] = {
                "envmap": g.envmap, "envmap_name": g.envmap_name,
                "envmap_rotation_deg": g.envmap_rotation_deg,
                "relit": [
                    {"name": r.name, "envmap": r.envmap, "envmap_rotation_deg": r.envmap_rotation_deg,
                     "frames": dict(r.frames)}
                    for r in g.relit
                ],
            }
        if self.source:
            d["source"] = self.source
        return d


def _mat_to_list(m: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(m, dtype=np.float64)]


# ---------------------------------------------------------------------------------------------
# parsing: every failure is a BundleError naming the manifest field
# ---------------------------------------------------------------------------------------------

_WHERE = MANIFEST_NAME


def _req(d: dict, key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise BundleError(f"expected an object, got {type(d).__name__}", _WHERE, where)
    if key not in d:
        raise BundleError(f"missing required field '{key}'", _WHERE, where)
    return d[key]


def _num(x: Any, where: str, *, positive: bool = False, integer: bool = False) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise BundleError(f"expected a number, got {x!r}", _WHERE, where)
    if not math.isfinite(float(x)):
        raise BundleError(f"not finite: {x!r}", _WHERE, where)
    if integer and (not isinstance(x, int) and not float(x).is_integer()):
        raise BundleError(f"expected an integer, got {x!r}", _WHERE, where)
    if positive and x <= 0:
        raise BundleError(f"must be > 0, got {x!r}", _WHERE, where)
    return int(x) if integer else float(x)


def _str(x: Any, where: str) -> str:
    if not isinstance(x, str) or not x:
        raise BundleError(f"expected a non-empty string, got {x!r}", _WHERE, where)
    return x


def _relpath(x: Any, where: str) -> str:
    p = _str(x, where)
    parts = p.replace("\\", "/").split("/")
    if p.startswith("/") or ".." in parts or ":" in parts[0]:
        raise BundleError(f"path must be relative and stay inside the bundle, got {p!r}", _WHERE, where)
    return "/".join(parts)


def parse_rigid(x: Any, where: str) -> np.ndarray:
    """Parse a 4x4 rigid transform; errors name ``where``."""
    try:
        m = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise BundleError("expected a 4x4 matrix of numbers", _WHERE, where) from None
    if m.shape != (4, 4):
        raise BundleError(f"expected a 4x4 matrix, got shape {m.shape}", _WHERE, where)
    if not np.all(np.isfinite(m)):
        raise BundleError("matrix contains NaN or Inf", _WHERE, where)
    if not is_rigid(m, tol=1e-3):
        raise BundleError("not a rigid transform (rotation must be orthonormal with det +1, "
                          "last row 0 0 0 1)", _WHERE, where)
    return m


def parse_manifest(d: Any) -> Manifest:
    """Parse a manifest dict (already JSON-decoded) into a :class:`Manifest`.

    Raises :class:`BundleError` naming the first offending field.
    """
    if not isinstance(d, dict):
        raise BundleError("manifest must be a JSON object", _WHERE)
    fmt = _req(d, "format", "format")
    if fmt != FORMAT_NAME:
        raise BundleError(f"unknown format {fmt!r}, expected {FORMAT_NAME!r}", _WHERE, "format")
    version = _req(d, "version", "version")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise BundleError(f"unknown version {version!r}; this reader supports version "
                          f"{SCHEMA_VERSION}", _WHERE, "version")
    name = _str(_req(d, "name", "name"), "name")

    times_raw = _req(d, "times", "times")
    if not isinstance(times_raw, list) or not times_raw:
        raise BundleError("expected a non-empty list of timestamps", _WHERE, "times")
    times = tuple(_num(t, f"times[{i}]") for i, t in enumerate(times_raw))
    if any(b <= a for a, b in zip(times, times[1:])):
        raise BundleError("timestamps must be strictly increasing", _WHERE, "times")

    cams_raw = _req(d, "cameras", "cameras")
    if not isinstance(cams_raw, dict) or not cams_raw:
        raise BundleError("expected a non-empty object of cameras", _WHERE, "cameras")
    cameras: dict[str, Camera] = {}
    for cid, c in cams_raw.items():
        w = f"cameras.{cid}"
        width = _num(_req(c, "width", w), f"{w}.width", positive=True, integer=True)
        height = _num(_req(c, "height", w), f"{w}.height", positive=True, integer=True)
        fx = _num(_req(c, "fx", w), f"{w}.fx", positive=True)
        fy = _num(_req(c, "fy", w), f"{w}.fy", positive=True)
        cx = _num(_req(c, "cx", w), f"{w}.cx")
        cy = _num(_req(c, "cy", w), f"{w}.cy")
        if not (0 <= cx <= width):
            raise BundleError(f"principal point cx={cx} outside the image width {width}", _WHERE, f"{w}.cx")
        if not (0 <= cy <= height):
            raise BundleError(f"principal point cy={cy} outside the image height {height}", _WHERE, f"{w}.cy")
        dist = c.get("distortion", [])
        if not isinstance(dist, list) or len(dist) not in (0, 4, 5):
            raise BundleError("distortion must be a list of 4 or 5 numbers (k1 k2 p1 p2 [k3])",
                              _WHERE, f"{w}.distortion")
        dist_t = tuple(_num(k, f"{w}.distortion[{i}]") for i, k in enumerate(dist))
        cameras[cid] = Camera(cid, width, height, fx, fy, cx, cy, dist_t)

    frames_raw = _req(d, "frames", "frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise BundleError("expected a non-empty list of frames", _WHERE, "frames")
    frames: list[Frame] = []
    seen: set[str] = set()
    for i, f in enumerate(frames_raw):
        w = f"frames[{i}]"
        fid = _str(_req(f, "id", w), f"{w}.id")
        w = f"frames[{i}] (id {fid})"
        if fid in seen:
            raise BundleError(f"duplicate frame id {fid!r}", _WHERE, f"{w}.id")
        seen.add(fid)
        cam = _str(_req(f, "camera", w), f"{w}.camera")
        if cam not in cameras:
            raise BundleError(f"unknown camera {cam!r} (known: {sorted(cameras)})", _WHERE, f"{w}.camera")
        ti = _num(_req(f, "time_index", w), f"{w}.time_index", integer=True)
        if not (0 <= ti < len(times)):
            raise BundleError(f"time_index {ti} outside 0..{len(times) - 1}", _WHERE, f"{w}.time_index")
        split = f.get("split", "train")
        if split not in SPLITS:
            raise BundleError(f"split must be one of {SPLITS}, got {split!r}", _WHERE, f"{w}.split")
        image = _relpath(_req(f, "image", w), f"{w}.image")
        if not image.lower().endswith(IMAGE_SUFFIXES):
            raise BundleError(f"image must be one of {IMAGE_SUFFIXES}, got {image!r}", _WHERE, f"{w}.image")
        frames.append(Frame(
            id=fid,
            image=image,
            camera=cam,
            time_index=ti,
            cam_to_world=parse_rigid(_req(f, "cam_to_world", w), f"{w}.cam_to_world"),
            split=split,
            sky_mask=_relpath(f["sky_mask"], f"{w}.sky_mask") if f.get("sky_mask") else None,
            ground_truth=_relpath(f["ground_truth"], f"{w}.ground_truth") if f.get("ground_truth") else None,
        ))

    lidar: list[LidarSweep] = []
    lidar_raw = d.get("lidar", []) or []
    if not isinstance(lidar_raw, list):
        raise BundleError("expected a list of sweeps", _WHERE, "lidar")
    seen_t: set[int] = set()
    for i, s in enumerate(lidar_raw):
        w = f"lidar[{i}]"
        ti = _num(_req(s, "time_index", w), f"{w}.time_index", integer=True)
        if not (0 <= ti < len(times)):
            raise BundleError(f"time_index {ti} outside 0..{len(times) - 1}", _WHERE, f"{w}.time_index")
        if ti in seen_t:
            raise BundleError(f"two sweeps for time_index {ti}", _WHERE, f"{w}.time_index")
        seen_t.add(ti)
        lidar.append(LidarSweep(ti, _relpath(_req(s, "file", w), f"{w}.file")))

    objects: list[ObjectTrack] = []
    seen_obj: set[str] = set()
    objects_raw = d.get("objects", []) or []
    if not isinstance(objects_raw, list):
        raise BundleError("expected a list of objects", _WHERE, "objects")
    for i, o in enumerate(objects_raw):
        w = f"objects[{i}]"
        oid = _str(_req(o, "id", w), f"{w}.id")
        if oid in seen_obj:
            raise BundleError(f"duplicate object id {oid!r}", _WHERE, f"{w}.id")
        seen_obj.add(oid)
        size = _req(o, "size", w)
        if not isinstance(size, list) or len(size) != 3:
            raise BundleError("size must be [length, width, height]", _WHERE, f"{w}.size")
        size_t = tuple(_num(s, f"{w}.size[{k}]", positive=True) for k, s in enumerate(size))
        poses_raw = _req(o, "poses", w)
        if not isinstance(poses_raw, list) or not poses_raw:
            raise BundleError("expected a non-empty list of poses", _WHERE, f"{w}.poses")
        poses: dict[int, np.ndarray] = {}
        for k, p in enumerate(poses_raw):
            wp = f"{w}.poses[{k}]"
            ti = _num(_req(p, "time_index", wp), f"{wp}.time_index", integer=True)
            if not (0 <= ti < len(times)):
                raise BundleError(f"time_index {ti} outside 0..{len(times) - 1}", _WHERE, f"{wp}.time_index")
            poses[ti] = parse_rigid(_req(p, "obj_to_world", wp), f"{wp}.obj_to_world")
        objects.append(ObjectTrack(oid, _str(o.get("class", "unknown"), f"{w}.class"), size_t, poses))

    ldr = d.get("ldr", {}) or {}
    if not isinstance(ldr, dict):
        raise BundleError("expected an object {exposure, gamma}", _WHERE, "ldr")
    exposure = _num(ldr.get("exposure", 1.0), "ldr.exposure", positive=True)
    gamma = _num(ldr.get("gamma", 2.2), "ldr.gamma", positive=True)

    gt = None
    if d.get("ground_truth"):
        g = d["ground_truth"]
        if not isinstance(g, dict):
            raise BundleError("expected an object", _WHERE, "ground_truth")
        relit_raw = g.get("relit", []) or []
        if not isinstance(relit_raw, list):
            raise BundleError("expected a list", _WHERE, "ground_truth.relit")
        relit = []
        for i, r in enumerate(relit_raw):
            w = f"ground_truth.relit[{i}]"
            fr = _req(r, "frames", w)
            if not isinstance(fr, dict):
                raise BundleError("expected an object frame_id -> path", _WHERE, f"{w}.frames")
            for fid in fr:
                if fid not in seen:
                    raise BundleError(f"unknown frame id {fid!r}", _WHERE, f"{w}.frames")
            relit.append(RelitSet(
                name=_str(_req(r, "name", w), f"{w}.name"),
                envmap=_relpath(_req(r, "envmap", w), f"{w}.envmap"),
                envmap_rotation_deg=_num(r.get("envmap_rotation_deg", 0.0), f"{w}.envmap_rotation_deg"),
                frames={k: _relpath(v, f"{w}.frames.{k}") for k, v in fr.items()},
            ))
        gt = GroundTruth(
            envmap=_relpath(_req(g, "envmap", "ground_truth"), "ground_truth.envmap"),
            envmap_name=str(g.get("envmap_name", "")),
            envmap_rotation_deg=_num(g.get("envmap_rotation_deg", 0.0), "ground_truth.envmap_rotation_deg"),
            relit=tuple(relit),
        )

    source = d.get("source", {}) or {}
    if not isinstance(source, dict):
        raise BundleError("expected an object", _WHERE, "source")
    return Manifest(
        name=name, times=times, cameras=cameras, frames=tuple(frames), lidar=tuple(lidar),
        objects=tuple(objects), ldr_exposure=exposure, ldr_gamma=gamma, ground_truth=gt,
        description=str(d.get("description", "")), source=dict(source),
        version=version,
    )
