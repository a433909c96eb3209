"""Import a nerfstudio capture (``transforms.json`` + images) into a scene bundle.

``transforms.json`` holds camera intrinsics at the top level and/or per frame (a per-frame value
overrides the top-level one): ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, optional
``k1 k2 p1 p2 k3`` and ``camera_model``; and ``frames: [{file_path, transform_matrix, ...}]``
where ``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, z back).

Conversion (see :mod:`core.conventions`):

* ``cam_to_world = transform_matrix @ OPENCV_TO_OPENGL`` gives OpenCV camera axes (the matrix is
  its own inverse). A 3x4 ``transform_matrix`` gets the row 0 0 0 1.
* World axes: nerfstudio worlds are arbitrary (COLMAP's, often y or -z up, arbitrary scale). The
  bundle assumes z up in metres but the world is kept **as given** unless asked otherwise:
  ``world_up=(x, y, z)`` rotates the world (about its origin, smallest rotation) so that vector
  becomes +z; ``orient=True`` does the same with the mean camera up vector (-y of the OpenCV
  camera), which is right for captures taken with a level camera. The rotation applied is stored
  in ``source.world_rotation``. Scale is never changed.
* Missing ``fl_y`` = ``fl_x``; missing ``fl_x`` is derived from ``camera_angle_x`` (Blender
  layout); missing ``cx``/``cy`` = image centre; missing ``w``/``h`` are read from the image.
  ``camera_model`` must be ``PINHOLE``, ``OPENCV`` or ``SIMPLE_PINHOLE``-like (fisheye and
  equirectangular captures are refused). Frames with different intrinsics get different cameras,
  ids "0", "1", ... in order of first use.
* Frames are sorted by ``file_path``; frame ``i`` gets time index ``i`` and ``i * time_step``
  seconds (default 0.1 s). A frame's own ``time`` field is not used. Frame ids are
  ``"{i:04d}_{file stem}"``.
* Images (PNG/JPEG) are copied unchanged. A ``file_path`` without suffix tries ``.png`` then
  ``.jpg`` (Blender layout).
* Not imported (recorded in ``source.skipped``): ``mask_path`` (nerfstudio masks mark pixels to
  ignore, not sky), ``depth_file_path``, and the ``ply_file_path`` point cloud (the bundle's LiDAR
  needs a sensor origin per point, which a SfM point cloud does not have).
* With ``test_every=N`` frames at positions N-1, 2N-1, ... are "test", the others "train".
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from core.adapters._common import COPYABLE_IMAGE_SUFFIXES, check_test_every, rigid_or_error, safe_id, split_for
from core.adapters._common import progress as _progress
from core.bundle.schema import Camera
from core.bundle.writer import BundleWriter
from core.conventions import OPENCV_TO_OPENGL
from core.errors import BundleError, ConfigError
from core.io.images import image_size

#: Default seconds between consecutive frames (nerfstudio captures carry no timestamps).
DEFAULT_TIME_STEP = 0.1
_PINHOLE_MODELS = {"PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL"}


def import_nerfstudio(src_dir: str | Path, out_dir: str | Path, *, name: str | None = None,
                      overwrite: bool = False, test_every: int | None = None, progress: bool = True,
                      transforms: str = "transforms.json", orient: bool = False,
                      world_up=None, time_step: float = DEFAULT_TIME_STEP) -> Path:
    """Convert the nerfstudio capture in ``src_dir`` into a bundle at ``out_dir``.

    name: bundle name (default: the source directory's name).
    overwrite: replace a non-empty ``out_dir`` (the old bundle is kept until the new one is valid).
    test_every: None (all "train") or N >= 2: frames N-1, 2N-1, ... (sorted order) are "test".
    progress: show a tqdm progress bar.
    transforms: name of the transforms file inside ``src_dir``.
    orient / world_up: optional re-orientation of the world to z-up (module doc); default off.
    time_step: seconds between consecutive frames.

    Returns the bundle directory. Raises :class:`BundleError` naming the file (and field) that is
    missing or malformed, :class:`ConfigError` for bad arguments.
    """
    check_test_every(test_every)
    if orient and world_up is not None:
        raise ConfigError("orient/world_up: give at most one")
    if not (isinstance(time_step, (int, float)) and time_step > 0):
        raise ConfigError(f"time_step: expected a positive number of seconds, got {time_step!r}")
    src = Path(src_dir)
    if not src.is_dir():
        raise BundleError("nerfstudio capture directory not found", str(src))
    tpath = src / transforms
    if not tpath.is_file():
        raise BundleError(f"missing {transforms} (expected a nerfstudio capture directory)", str(tpath))
    try:
        meta = json.loads(tpath.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise BundleError(f"not UTF-8 text: {e}", str(tpath)) from None
    except json.JSONDecodeError as e:
        raise BundleError(f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}", str(tpath)) from None
    if not isinstance(meta, dict):
        raise BundleError("expected a JSON object", str(tpath))
    frames_raw = meta.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise BundleError("expected a non-empty list of frames", str(tpath), "frames")

    entries = []
    for i, f in enumerate(frames_raw):
        fld = f"frames[{i}]"
        if not isinstance(f, dict):
            raise BundleError("expected an object", str(tpath), fld)
        fp = f.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise BundleError("missing 'file_path'", str(tpath), f"{fld}.file_path")
        if "transform_matrix" not in f:
            raise BundleError("missing 'transform_matrix'", str(tpath), f"{fld}.transform_matrix")
        entries.append((fp, i, f))
    entries.sort(key=lambda e: (e[0], e[1]))

    # -- resolve images, intrinsics and poses before writing anything ---------------------------
    cams: dict[tuple, Camera] = {}
    plan = []
    for pos, (fp, i, f) in enumerate(entries):
        fld = f"frames[{i}]"
        img = _resolve_image(src, fp, tpath, f"{fld}.file_path")
        c2w_gl = rigid_or_error(f["transform_matrix"], tpath, f"{fld}.transform_matrix")
        key = _intrinsics(meta, f, img, tpath, fld, image_size)
        if key not in cams:
            cams[key] = Camera(str(len(cams)), *key)
        plan.append((pos, f"{pos:04d}_{safe_id(Path(fp).stem)}", img, cams[key].id, c2w_gl @ OPENCV_TO_OPENGL))

    rot = np.eye(3)
    if orient:
        up = np.mean([-p[4][:3, 1] for p in plan], axis=0)
        rot = _rotation_to_z(up, "orient: the cameras' mean up vector")
    elif world_up is not None:
        rot = _rotation_to_z(np.asarray(world_up, dtype=np.float64), "world_up")
    if not np.allclose(rot, np.eye(3)):
        r4 = np.eye(4)
        r4[:3, :3] = rot
        plan = [(pos, fid, img, cid, r4 @ c2w) for pos, fid, img, cid, c2w in plan]

    skipped = sorted({k for _, _, f in entries for k in ("mask_path", "depth_file_path") if f.get(k)}
                     | ({"ply_file_path"} if meta.get("ply_file_path") else set()))
    source = {
        "kind": "nerfstudio",
        "path": str(src.resolve()),
        "transforms": transforms,
        "time_step_s": float(time_step),
        "world_rotation": [[float(x) for x in row] for row in rot],
        "skipped": skipped,
        "test_every": test_every,
    }
    with BundleWriter(out_dir, name or src.resolve().name, overwrite=overwrite, source=source,
                      description=f"imported from nerfstudio capture {src.resolve().name}") as w:
        w.set_times([k * float(time_step) for k in range(len(plan))])
        for cam in cams.values():
            w.add_camera(cam)
        for pos, fid, img, cid, c2w in _progress(plan, enabled=progress, total=len(plan), desc="nerfstudio"):
            w.add_frame(fid, cid, pos, c2w, image_file=img, split=split_for(pos, test_every))
        return w.finish()


# ---------------------------------------------------------------------------------------------
def _resolve_image(src: Path, fp: str, tpath: Path, fld: str) -> Path:
    p = Path(fp)
    if not p.is_absolute():
        p = src / fp
    candidates = [p]
    if not p.suffix:
        candidates += [p.with_name(p.name + ext) for ext in (".png", ".jpg", ".jpeg")]
    for c in candidates:
        if c.is_file():
            if c.suffix.lower() not in COPYABLE_IMAGE_SUFFIXES:
                raise BundleError(f"unsupported image format {c.suffix!r} (bundles hold PNG or JPEG): {c}",
                                  str(tpath), fld)
            return c
    raise BundleError(f"frame image not found: {p}", str(tpath), fld)


def _intrinsics(meta: dict, f: dict, img: Path, tpath: Path, fld: str, image_size) -> tuple:
    """(width, height, fx, fy, cx, cy, distortion) of one frame (per-frame values override)."""
    def get(k):
        if k in f:
            return f[k], f"{fld}.{k}"
        return meta.get(k), k

    def num(k, *, required=False, positive=False):
        v, where = get(k)
        if v is None:
            if required:
                raise BundleError(f"missing intrinsic '{k}' (neither in the frame nor at the top level)",
                                  str(tpath), where)
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise BundleError(f"expected a finite number, got {v!r}", str(tpath), where)
        if positive and v <= 0:
            raise BundleError(f"must be > 0, got {v!r}", str(tpath), where)
        return float(v)

    model, where = get("camera_model")
    if model is not None and str(model).upper() not in _PINHOLE_MODELS:
        raise BundleError(f"unsupported camera_model {model!r} (only pinhole models with OpenCV "
                          f"distortion: {sorted(_PINHOLE_MODELS)})", str(tpath), where)
    wv, hv = num("w", positive=True), num("h", positive=True)
    try:
        iw, ih = (int(v) for v in image_size(img))
    except Exception as e:  # noqa: BLE001 - any decoder error becomes a BundleError on the file
        raise BundleError(f"unreadable image: {e}", str(img)) from None
    if (wv is not None and int(wv) != iw) or (hv is not None and int(hv) != ih):
        raise BundleError(f"image {img.name} is {iw}x{ih} but the intrinsics say w={wv} h={hv}",
                          str(tpath), fld)
    fx = num("fl_x", positive=True)
    if fx is None:
        ang = num("camera_angle_x", positive=True)
        if ang is None:
            raise BundleError("missing intrinsic 'fl_x' (and no 'camera_angle_x')", str(tpath), get("fl_x")[1])
        fx = 0.5 * iw / math.tan(0.5 * ang)
    fy = num("fl_y", positive=True)
    fy = fx if fy is None else fy
    cx = num("cx")
    cy = num("cy")
    cx = iw / 2.0 if cx is None else cx
    cy = ih / 2.0 if cy is None else cy
    if not (0 <= cx <= iw and 0 <= cy <= ih):
        raise BundleError(f"principal point ({cx}, {cy}) outside the {iw}x{ih} image", str(tpath), fld)
    dist = [num(k) or 0.0 for k in ("k1", "k2", "p1", "p2", "k3")]
    return (iw, ih, fx, fy, cx, cy, tuple(dist) if any(dist) else ())


def _rotation_to_z(up: np.ndarray, what: str) -> np.ndarray:
    """Smallest rotation taking direction ``up`` to +z."""
    n = float(np.linalg.norm(up)) if up.shape == (3,) and np.all(np.isfinite(up)) else 0.0
    if n < 1e-9:
        raise ConfigError(f"{what}: expected a non-zero 3-vector, got {up!r}")
    a = up / n
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(a, z)
    c = float(a @ z)
    if c < -1.0 + 1e-12:  # up = -z: half turn about x
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)
