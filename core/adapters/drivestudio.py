"""Import a drivestudio / OmniRe processed Waymo scene into a scene bundle.

Source layout (one scene directory, ``t`` = time index, ``cam`` = integer camera id)::

    images/{t:03d}_{cam}.jpg            camera images (.png is accepted too)
    ego_pose/{t:03d}.txt                4x4 vehicle -> world, whitespace separated
    extrinsics/{cam}.txt                4x4 camera -> vehicle, Waymo camera axes (x fwd, y left, z up)
    intrinsics/{cam}.txt                9 numbers: fx fy cx cy k1 k2 p1 p2 k3
    lidar/{t:03d}.bin                   optional, float32 rows of 14 values in the VEHICLE frame:
                                        origin xyz, point xyz, flow xyz, flow class, ground label,
                                        intensity, elongation, laser id
    sky_masks/{t:03d}_{cam}.png         optional, non-zero = sky
    instances/instances_info.json       optional, tracked boxes (see below)
    instances/frame_instances.json      optional, {frame_idx: [instance ids]} (cross-check only)

``instances_info.json`` maps an instance id to ``{"id", "class_name", "frame_annotations":
{"frame_idx": [t...], "obj_to_world": [4x4...], "box_size": [[l, w, h]...]}}`` (parallel lists).

Conversion (see :mod:`core.conventions`):

* ``cam_to_world[t, cam] = ego_pose[t] @ extrinsic[cam] @ WAYMO_TO_OPENCV`` (OpenCV camera axes).
  The Waymo world frame is already right-handed z-up in metres, so it is kept as it is; with
  ``recenter=True`` it is shifted (translation only) so the first imported ego position is the
  origin, which keeps float32 LiDAR coordinates precise. The shift is stored in the manifest's
  ``source.world_offset`` (bundle world = Waymo world - offset).
* Camera ids stay drivestudio's integer ids as strings ("0".."4"); their Waymo names (0 FRONT,
  1 FRONT_LEFT, 2 FRONT_RIGHT, 3 SIDE_LEFT, 4 SIDE_RIGHT) are stored in
  ``source.camera_names``. Frame ids are ``"{t:03d}_{cam}"`` with the source time index ``t``.
* The layout has no timestamps: time index ``t`` gets ``t * time_step`` seconds (Waymo runs at
  10 Hz, so ``time_step = 0.1``). Bundle time indices are renumbered 0..T-1 over the imported
  time steps; ``source.source_time_indices`` lists the original ones.
* Image width/height come from the image files; images are copied unchanged (JPEG stays JPEG).
  Distortion ``k1 k2 p1 p2 k3`` is kept in the camera record when any coefficient is non-zero.
* LiDAR: origin and hit point are moved to the world with ``ego_pose[t]`` and stored as
  float32 [N, 6]; the other 8 columns are dropped, as are rows holding NaN/Inf.
* Boxes: ``obj_to_world`` per annotated frame; the box size is the per-dimension median over all
  of the instance's annotations (drivestudio's sizes jitter from frame to frame).
* With ``test_every=N`` every N-th imported time step (positions N-1, 2N-1, ...) goes to the
  "test" split with all its cameras; otherwise every frame is "train".
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from core.adapters._common import check_test_every, read_numbers, rigid_or_error, split_for
from core.adapters._common import progress as _progress
from core.bundle.schema import Camera
from core.bundle.writer import BundleWriter
from core.conventions import WAYMO_TO_OPENCV
from core.errors import BundleError, ConfigError
from core.io.images import image_size, read_mask

#: drivestudio's Waymo camera ids and names.
WAYMO_CAMERA_NAMES = {0: "FRONT", 1: "FRONT_LEFT", 2: "FRONT_RIGHT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT"}
#: Seconds between time indices (Waymo sensors run at 10 Hz).
WAYMO_TIME_STEP = 0.1
#: float32 values per LiDAR row in drivestudio's ``lidar/*.bin``.
LIDAR_ROW_FLOATS = 14

_REQUIRED_DIRS = ("images", "ego_pose", "extrinsics", "intrinsics")
_IMAGE_RE = re.compile(r"^(\d+)_(\d+)\.(jpe?g|png)$", re.IGNORECASE)


def import_drivestudio(src_dir: str | Path, out_dir: str | Path, *,
                       cameras: Iterable[int | str] | None = None,
                       frames: Iterable[int] | None = None,
                       name: str | None = None, overwrite: bool = False, progress: bool = True,
                       test_every: int | None = None, time_step: float = WAYMO_TIME_STEP,
                       lidar: bool = True, objects: bool = True, recenter: bool = False) -> Path:
    """Convert a drivestudio processed Waymo scene ``src_dir`` into a bundle at ``out_dir``.

    cameras: camera ids to import (ints, digit strings or Waymo names like "FRONT"); None = all
        found in ``images/``.
    frames: source time indices to import (a range or list); None = all found in ``images/``.
    name: bundle name (default: the source directory's name).
    overwrite: replace a non-empty ``out_dir`` (the old bundle is kept until the new one is valid).
    progress: show a tqdm progress bar.
    test_every: None (all "train") or N >= 2: every N-th imported time step is "test".
    time_step: seconds between consecutive source time indices.
    lidar / objects: import the LiDAR sweeps / tracked boxes when present.
    recenter: shift the world so the first imported ego position is the origin (module doc).

    Returns the bundle directory. Raises :class:`BundleError` naming the source file that is
    missing or malformed, :class:`ConfigError` for bad arguments.
    """
    check_test_every(test_every)
    if not (isinstance(time_step, (int, float)) and time_step > 0):
        raise ConfigError(f"time_step: expected a positive number of seconds, got {time_step!r}")
    src = Path(src_dir)
    if not src.is_dir():
        raise BundleError("drivestudio scene directory not found", str(src))
    for sub in _REQUIRED_DIRS:
        if not (src / sub).is_dir():
            raise BundleError(f"missing folder '{sub}/' (expected the drivestudio processed Waymo layout: "
                              f"{', '.join(d + '/' for d in _REQUIRED_DIRS)})", str(src / sub))

    images = _scan_images(src / "images")
    cams = _select_cameras(cameras, sorted({c for _, c in images}), src / "images")
    found_ts = sorted({t for t, c in images if c in cams})
    ts = _select_frames(frames, found_ts, src / "images")
    tindex = {t: i for i, t in enumerate(ts)}

    # -- poses and intrinsics: all parsed before anything is written ---------------------------
    ego: dict[int, np.ndarray] = {}
    for t in ts:
        p = src / "ego_pose" / f"{t:03d}.txt"
        if not p.is_file():
            have = sorted(images[(t, c)].name for c in cams if (t, c) in images)
            raise BundleError(f"missing ego pose for time index {t}, which has images ({', '.join(have)})",
                              str(p))
        ego[t] = _read_matrix(p, "ego pose (vehicle-to-world 4x4)")
    offset = ego[ts[0]][:3, 3].copy() if recenter else np.zeros(3)
    for t in ts:
        ego[t][:3, 3] -= offset

    cam_records: dict[int, Camera] = {}
    cam_to_vehicle: dict[int, np.ndarray] = {}
    unused = [c for c in cams if not any((t, c) in images for t in ts)]
    if unused and cameras is not None:
        raise BundleError(f"camera(s) {unused} have no images at the selected time indices {ts}",
                          str(src / "images"))
    cams = [c for c in cams if c not in unused]
    for c in cams:
        ext_path = src / "extrinsics" / f"{c}.txt"
        cam_to_vehicle[c] = _read_matrix(ext_path, "extrinsic (camera-to-vehicle 4x4)") @ WAYMO_TO_OPENCV
        cam_records[c] = _read_camera(src / "intrinsics" / f"{c}.txt", c, images, ts, image_size)

    sky_dir = src / "sky_masks"
    lidar_dir = src / "lidar"
    do_lidar = lidar and lidar_dir.is_dir()
    tracks = _read_instances(src / "instances", tindex, offset) if objects else []

    source = {
        "kind": "drivestudio",
        "path": str(src.resolve()),
        "camera_names": {str(c): WAYMO_CAMERA_NAMES.get(c, f"CAMERA_{c}") for c in cams},
        "source_time_indices": list(ts),
        "time_step_s": float(time_step),
        "world_offset": [float(x) for x in offset],
        "test_every": test_every,
    }
    missing_lidar: list[int] = []
    dropped_rows = 0
    with BundleWriter(out_dir, name or src.resolve().name, overwrite=overwrite, source=source,
                      description=f"imported from drivestudio scene {src.resolve().name}") as w:
        w.set_times([t * float(time_step) for t in ts])
        for c in cams:
            w.add_camera(cam_records[c])
        for pos, t in enumerate(_progress(ts, enabled=progress, total=len(ts), desc="drivestudio")):
            split = split_for(pos, test_every)
            for c in cams:
                img = images.get((t, c))
                if img is None:
                    continue
                cam = cam_records[c]
                mask = None
                mpath = sky_dir / f"{t:03d}_{c}.png"
                if mpath.is_file():
                    mask = read_mask(mpath)
                    if mask.shape != (cam.height, cam.width):
                        raise BundleError(f"sky mask is {mask.shape[1]}x{mask.shape[0]} but the image is "
                                          f"{cam.width}x{cam.height}", str(mpath))
                w.add_frame(f"{t:03d}_{c}", str(c), pos, ego[t] @ cam_to_vehicle[c], image_file=img,
                            split=split, sky_mask=mask)
            if do_lidar:
                lpath = lidar_dir / f"{t:03d}.bin"
                if not lpath.is_file():
                    missing_lidar.append(t)
                    continue
                pts, dropped = _read_lidar(lpath, ego[t])
                dropped_rows += dropped
                w.add_lidar(pos, pts)
        for oid, cls, size, poses in tracks:
            w.add_object(oid, cls, size, poses)
        if missing_lidar:
            warnings.warn(f"{lidar_dir}: no sweep for time indices {missing_lidar}; imported without LiDAR",
                          stacklevel=2)
            w.source["lidar_missing_time_indices"] = missing_lidar
        if dropped_rows:
            w.source["lidar_dropped_nonfinite_rows"] = dropped_rows
        return w.finish()


# ---------------------------------------------------------------------------------------------
def _scan_images(d: Path) -> dict[tuple[int, int], Path]:
    out: dict[tuple[int, int], Path] = {}
    for p in sorted(d.iterdir()):
        m = _IMAGE_RE.match(p.name)
        if not m or not p.is_file():
            continue
        key = (int(m.group(1)), int(m.group(2)))
        if key in out:
            raise BundleError(f"two images for time index {key[0]} camera {key[1]}: {out[key].name} and "
                              f"{p.name}", str(p))
        out[key] = p
    if not out:
        raise BundleError("no images named {t:03d}_{cam}.jpg (e.g. 000_0.jpg)", str(d))
    return out


def _select_cameras(cameras, found: list[int], images_dir: Path) -> list[int]:
    if cameras is None:
        return found
    if isinstance(cameras, (str, int)):
        cameras = [cameras]
    by_name = {v: k for k, v in WAYMO_CAMERA_NAMES.items()}
    out: list[int] = []
    for c in cameras:
        if isinstance(c, bool):
            raise ConfigError(f"cameras: not a camera id: {c!r}")
        if isinstance(c, str):
            cid = int(c) if c.strip().isdigit() else by_name.get(c.strip().upper())
        elif isinstance(c, (int, np.integer)):
            cid = int(c)
        else:
            cid = None
        if cid is None:
            raise ConfigError(f"cameras: unknown camera {c!r} (use ids 0..4 or names {sorted(by_name)})")
        if cid not in found:
            raise BundleError(f"camera {c!r} (id {cid}) has no images; cameras found: {found}", str(images_dir))
        if cid not in out:
            out.append(cid)
    if not out:
        raise ConfigError("cameras: empty selection")
    return sorted(out)


def _select_frames(frames, found: list[int], images_dir: Path) -> list[int]:
    if frames is None:
        return found
    try:
        req = sorted({int(t) for t in frames})
    except (TypeError, ValueError):
        raise ConfigError(f"frames: expected a range or list of time indices, got {frames!r}") from None
    if not req:
        raise ConfigError("frames: empty selection")
    have = set(found)
    missing = [t for t in req if t not in have]
    if missing:
        raise BundleError(f"no images of the selected cameras for time indices {missing[:20]}"
                          f"{' ...' if len(missing) > 20 else ''} (found {found[0]}..{found[-1]})",
                          str(images_dir))
    return req


def _read_matrix(path: Path, what: str) -> np.ndarray:
    return rigid_or_error(read_numbers(path, 16, what).reshape(4, 4), path)


def _read_camera(path: Path, cam: int, images: dict, ts: list[int], image_size) -> Camera:
    fx, fy, cx, cy, *dist = read_numbers(path, 9, "intrinsics (fx fy cx cy k1 k2 p1 p2 k3)").tolist()
    size = None
    first = None
    for t in ts:
        img = images.get((t, cam))
        if img is None:
            continue
        try:
            wh = tuple(int(v) for v in image_size(img))
        except Exception as e:  # noqa: BLE001 - any decoder error becomes a BundleError on the file
            raise BundleError(f"unreadable image: {e}", str(img)) from None
        if size is None:
            size, first = wh, img
        elif wh != size:
            raise BundleError(f"image is {wh[0]}x{wh[1]} but {first.name} of the same camera is "
                              f"{size[0]}x{size[1]}", str(img))
    assert size is not None  # every selected camera has images at some selected time
    width, height = size
    if fx <= 0 or fy <= 0:
        raise BundleError(f"focal lengths must be > 0, got fx={fx} fy={fy}", str(path))
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise BundleError(f"principal point ({cx}, {cy}) lies outside the {width}x{height} image "
                          f"{first.name} (were the images resized?)", str(path))
    return Camera(str(cam), width, height, fx, fy, cx, cy, tuple(dist) if any(dist) else ())


def _read_lidar(path: Path, ego: np.ndarray) -> tuple[np.ndarray, int]:
    nbytes = path.stat().st_size
    row = LIDAR_ROW_FLOATS * 4
    if nbytes % row:
        raise BundleError(f"size {nbytes} bytes is not a multiple of {row} ({LIDAR_ROW_FLOATS} float32 "
                          f"values per point)", str(path))
    raw = np.fromfile(path, dtype="<f4").reshape(-1, LIDAR_ROW_FLOATS)[:, :6].astype(np.float64)
    ok = np.all(np.isfinite(raw), axis=1)
    raw = raw[ok]
    r, tr = ego[:3, :3], ego[:3, 3]
    pts = np.concatenate([raw[:, :3] @ r.T + tr, raw[:, 3:6] @ r.T + tr], axis=1)
    return pts.astype(np.float32), int((~ok).sum())


def _read_instances(d: Path, tindex: dict[int, int], offset: np.ndarray) -> list[tuple]:
    """Tracks as (id, class, size, {bundle time index: obj_to_world}) for the imported times."""
    info_path = d / "instances_info.json"
    if not info_path.is_file():
        return []
    info = _read_json(info_path)
    if not isinstance(info, dict):
        raise BundleError("expected an object keyed by instance id", str(info_path))
    tracks = []
    present: dict[int, set[str]] = {}
    for key, inst in info.items():
        where = str(key)
        if not isinstance(inst, dict) or not isinstance(inst.get("frame_annotations"), dict):
            raise BundleError("expected {'class_name', 'frame_annotations': {...}}", str(info_path), where)
        fa = inst["frame_annotations"]
        lists = {}
        for k in ("frame_idx", "obj_to_world", "box_size"):
            v = fa.get(k)
            if not isinstance(v, list):
                raise BundleError(f"missing list '{k}'", str(info_path), f"{where}.frame_annotations.{k}")
            lists[k] = v
        n = len(lists["frame_idx"])
        if n == 0:
            continue
        if len(lists["obj_to_world"]) != n or len(lists["box_size"]) != n:
            raise BundleError(f"frame_idx, obj_to_world and box_size must have the same length, got {n}, "
                              f"{len(lists['obj_to_world'])}, {len(lists['box_size'])}", str(info_path),
                              f"{where}.frame_annotations")
        try:
            sizes = np.asarray(lists["box_size"], dtype=np.float64)
        except (TypeError, ValueError):
            sizes = None
        if sizes is None or sizes.shape != (n, 3) or not np.all(np.isfinite(sizes)):
            raise BundleError("box_size must be a list of [l, w, h] numbers", str(info_path),
                              f"{where}.frame_annotations.box_size")
        size = np.median(sizes, axis=0)
        poses = {}
        for k, (t, m) in enumerate(zip(lists["frame_idx"], lists["obj_to_world"])):
            if isinstance(t, bool) or not isinstance(t, (int, float)) or float(t) != int(t):
                raise BundleError(f"frame index must be an integer, got {t!r}", str(info_path),
                                  f"{where}.frame_annotations.frame_idx[{k}]")
            if int(t) not in tindex:
                continue
            pose = rigid_or_error(m, info_path, f"{where}.frame_annotations.obj_to_world[{k}]")
            pose[:3, 3] -= offset
            poses[tindex[int(t)]] = pose
            present.setdefault(int(t), set()).add(where)
        if not poses:
            continue
        if np.any(size <= 0):
            raise BundleError(f"median box size {size.tolist()} has a non-positive dimension", str(info_path),
                              f"{where}.frame_annotations.box_size")
        cls = inst.get("class_name") or "unknown"
        tracks.append((where, str(cls), tuple(float(s) for s in size), poses))

    fi_path = d / "frame_instances.json"
    if fi_path.is_file():
        fi = _read_json(fi_path)
        if not isinstance(fi, dict):
            raise BundleError("expected an object frame index -> list of instance ids", str(fi_path))
        diffs = []
        for t in tindex:
            listed = fi.get(str(t), fi.get(t))
            if listed is None:
                continue
            listed_s = {str(i) for i in listed}
            got = present.get(t, set())
            if listed_s != got:
                diffs.append(f"frame {t}: listed {sorted(listed_s)} vs annotated {sorted(got)}")
        if diffs:
            warnings.warn(f"{fi_path} disagrees with {info_path.name} for {len(diffs)} frame(s), e.g. "
                          f"{diffs[0]}; boxes are taken from {info_path.name}", stacklevel=3)
    return tracks


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise BundleError(f"not UTF-8 text: {e}", str(path)) from None
    except json.JSONDecodeError as e:
        raise BundleError(f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}", str(path)) from None
    except OSError as e:
        raise BundleError(f"cannot read: {e}", str(path)) from None
