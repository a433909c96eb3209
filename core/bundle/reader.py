"""Open, validate and read scene bundles (see :mod:`core.bundle.schema` for the layout)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.bundle.schema import GT_FRAME_LAYERS, MANIFEST_NAME, Frame, Manifest, parse_manifest
from core.errors import BundleError, CoreError
from core.io.envmap_file import read_envmap
from core.io.exr import exr_header, read_exr
from core.io.images import image_size, read_image, read_mask

#: Largest manifest accepted (bytes): a manifest of 10k frames is ~10 MB.
MAX_MANIFEST_BYTES = 64 * 1024 * 1024


@dataclass(frozen=True)
class BundleIssue:
    """One problem found by :func:`validate_bundle`: the file, the field, and what is wrong."""

    path: str
    field: str | None
    message: str

    def __str__(self) -> str:
        return f"{self.path}{f' [{self.field}]' if self.field else ''}: {self.message}"


def read_manifest(root: str | Path) -> Manifest:
    """Read and parse ``root/bundle.json``. Raises :class:`BundleError` naming file and field."""
    root = Path(root)
    if not root.is_dir():
        raise BundleError(f"not a directory: {root}", str(root))
    mpath = root / MANIFEST_NAME
    if not mpath.is_file():
        raise BundleError(f"missing manifest (expected {MANIFEST_NAME} at the bundle root)", MANIFEST_NAME)
    if mpath.stat().st_size > MAX_MANIFEST_BYTES:
        raise BundleError(f"manifest larger than {MAX_MANIFEST_BYTES} bytes", MANIFEST_NAME)
    try:
        data = json.loads(mpath.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise BundleError(f"not UTF-8 text: {e}", MANIFEST_NAME) from None
    except json.JSONDecodeError as e:
        raise BundleError(f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}", MANIFEST_NAME) from None
    return parse_manifest(data)


def _check_files(root: Path, m: Manifest) -> list[BundleIssue]:
    """File-level checks: every referenced file exists, is readable and has consistent size."""
    issues: list[BundleIssue] = []

    def exists(rel: str, field: str) -> Path | None:
        p = root / rel
        try:
            p.resolve().relative_to(root.resolve())
        except ValueError:
            issues.append(BundleIssue(rel, field, "path leaves the bundle (symlink?)"))
            return None
        if not p.is_file():
            issues.append(BundleIssue(rel, field, "file is missing"))
            return None
        return p

    for i, f in enumerate(m.frames):
        cam = m.cameras[f.camera]
        fld = f"frames[{i}] (id {f.id})"
        p = exists(f.image, f"{fld}.image")
        if p is not None:
            try:
                w, h = image_size(p)
                if (w, h) != (cam.width, cam.height):
                    issues.append(BundleIssue(f.image, f"{fld}.image",
                                              f"image is {w}x{h} but camera {f.camera!r} intrinsics say "
                                              f"{cam.width}x{cam.height}"))
            except CoreError as e:
                issues.append(BundleIssue(f.image, f"{fld}.image", f"unreadable image: {e}"))
        if f.sky_mask:
            p = exists(f.sky_mask, f"{fld}.sky_mask")
            if p is not None:
                try:
                    w, h = image_size(p)
                    if (w, h) != (cam.width, cam.height):
                        issues.append(BundleIssue(f.sky_mask, f"{fld}.sky_mask",
                                                  f"mask is {w}x{h}, image is {cam.width}x{cam.height}"))
                except CoreError as e:
                    issues.append(BundleIssue(f.sky_mask, f"{fld}.sky_mask", f"unreadable mask: {e}"))
        if f.ground_truth:
            p = exists(f.ground_truth, f"{fld}.ground_truth")
            if p is not None:
                issues += _check_gt_exr(p, f.ground_truth, f"{fld}.ground_truth", cam.width, cam.height,
                                        GT_FRAME_LAYERS, exr_header)

    for i, s in enumerate(m.lidar):
        fld = f"lidar[{i}].file"
        p = exists(s.file, fld)
        if p is None:
            continue
        try:
            pts = np.load(p, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError) as e:
            issues.append(BundleIssue(s.file, fld, f"not a .npy array: {e}"))
            continue
        if pts.ndim != 2 or pts.shape[1] != 6:
            issues.append(BundleIssue(s.file, fld, f"expected shape [N, 6] (origin xyz, point xyz), "
                                                   f"got {list(pts.shape)}"))
        elif pts.dtype != np.float32:
            issues.append(BundleIssue(s.file, fld, f"expected float32, got {pts.dtype}"))
        elif not np.all(np.isfinite(pts)):
            issues.append(BundleIssue(s.file, fld, "contains NaN or Inf"))

    if m.ground_truth is not None:
        maps = [(m.ground_truth.envmap, "ground_truth.envmap")]
        maps += [(r.envmap, f"ground_truth.relit[{i}].envmap") for i, r in enumerate(m.ground_truth.relit)]
        for rel, fld in maps:
            p = exists(rel, fld)
            if p is not None:
                try:
                    read_envmap(p)
                except CoreError as e:
                    issues.append(BundleIssue(rel, fld, str(e)))
        for i, r in enumerate(m.ground_truth.relit):
            for fid, rel in r.frames.items():
                cam = m.cameras[m.frame(fid).camera]
                fld = f"ground_truth.relit[{i}].frames.{fid}"
                p = exists(rel, fld)
                if p is not None:
                    issues += _check_gt_exr(p, rel, fld, cam.width, cam.height, {"rgb": 3}, exr_header)
    return issues


def _check_gt_exr(p: Path, rel: str, fld: str, width: int, height: int, layers: dict[str, int],
                  exr_header) -> list[BundleIssue]:
    try:
        hdr = exr_header(p)
    except CoreError as e:
        return [BundleIssue(rel, fld, f"unreadable EXR: {e}")]
    out = []
    if (hdr.width, hdr.height) != (width, height):
        out.append(BundleIssue(rel, fld, f"EXR is {hdr.width}x{hdr.height}, image is {width}x{height}"))
    chans = set(hdr.channels)
    for layer, n in layers.items():
        have = [c for c in chans if (c.rsplit(".", 1)[0] if "." in c else "rgb") == layer]
        if len(have) != n:
            out.append(BundleIssue(rel, fld, f"layer {layer!r} must have {n} channel(s), found {sorted(have)}"))
    return out


def validate_bundle(root: str | Path) -> list[BundleIssue]:
    """Check a bundle directory; return every problem found (empty list = valid).

    Manifest errors stop the check at the first one (later fields may depend on it); file-level
    problems are all collected.
    """
    root = Path(root)
    try:
        m = read_manifest(root)
    except BundleError as e:
        return [BundleIssue(e.path or MANIFEST_NAME, e.field, str(e).split(": ", 1)[-1])]
    return _check_files(root, m)


class SceneBundle:
    """A validated scene bundle on disk, with typed accessors.

    Use :func:`open_bundle` to create one. Images come back as float32 [H, W, 3] in [0, 1].
    """

    def __init__(self, root: Path, manifest: Manifest):
        self.root = root
        self.manifest = manifest

    # convenience ------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.manifest.name

    def frames(self, split: str | None = None) -> list[Frame]:
        return [f for f in self.manifest.frames if split is None or f.split == split]

    def camera(self, frame: Frame):
        return self.manifest.cameras[frame.camera]

    def path(self, rel: str) -> Path:
        return self.root / rel

    # loaders ----------------------------------------------------------------------------------
    def load_image(self, frame: Frame) -> np.ndarray:
        """LDR image [H, W, 3] float32 in [0, 1]."""
        return read_image(self.path(frame.image)).astype(np.float32) / 255.0

    def load_sky_mask(self, frame: Frame) -> np.ndarray | None:
        """Sky mask [H, W] bool (True = sky) or None when the bundle has none for this frame."""
        return read_mask(self.path(frame.sky_mask)) if frame.sky_mask else None

    def load_lidar(self, time_index: int | None = None) -> np.ndarray:
        """LiDAR points float32 [N, 6] world (origin xyz, point xyz) of one time index, or all."""
        sweeps = [s for s in self.manifest.lidar if time_index is None or s.time_index == time_index]
        if not sweeps:
            return np.zeros((0, 6), np.float32)
        return np.concatenate([np.load(self.path(s.file), allow_pickle=False).astype(np.float32)
                               for s in sweeps])

    def load_ground_truth(self, frame: Frame) -> dict[str, np.ndarray]:
        """Ground-truth layers of a synthetic frame: rgb, albedo, roughness, metallic, normal, depth."""
        if not frame.ground_truth:
            raise BundleError("frame has no ground truth", MANIFEST_NAME, f"frames (id {frame.id})")
        return read_exr(self.path(frame.ground_truth))

    def load_envmap(self, relit_name: str | None = None) -> np.ndarray:
        """Ground-truth environment map [H, W, 3] float32 (training one, or a relit set's)."""
        gt = self.manifest.ground_truth
        if gt is None:
            raise BundleError("bundle has no ground truth", MANIFEST_NAME, "ground_truth")
        if relit_name is None:
            return read_envmap(self.path(gt.envmap))
        for r in gt.relit:
            if r.name == relit_name:
                return read_envmap(self.path(r.envmap))
        raise BundleError(f"no relit set named {relit_name!r}", MANIFEST_NAME, "ground_truth.relit")

    def load_relit_frame(self, relit_name: str, frame_id: str) -> np.ndarray:
        """Ground-truth HDR beauty [H, W, 3] float32 of frame ``frame_id`` under the held-back map
        ``relit_name`` (BundleError naming the set or the frame when the bundle has none)."""
        gt = self.manifest.ground_truth
        if gt is None:
            raise BundleError("bundle has no ground truth", MANIFEST_NAME, "ground_truth")
        rl = next((r for r in gt.relit if r.name == relit_name), None)
        if rl is None:
            raise BundleError(f"no relit set named {relit_name!r}", MANIFEST_NAME, "ground_truth.relit")
        if frame_id not in rl.frames:
            raise BundleError(f"relit set {relit_name!r} has no frame {frame_id!r}", MANIFEST_NAME,
                              f"ground_truth.relit.{relit_name}.frames")
        hdr = read_exr(self.path(rl.frames[frame_id]))
        hdr = hdr["rgb"] if isinstance(hdr, dict) else hdr
        return np.asarray(hdr, np.float32)[..., :3]


def open_bundle(root: str | Path, validate: bool = True) -> SceneBundle:
    """Open a bundle directory. With ``validate`` every referenced file is checked first and the
    first problems are raised as one :class:`BundleError` listing them all (up to 20)."""
    root = Path(root)
    if validate:
        issues = validate_bundle(root)
        if issues:
            lines = "\n  ".join(str(i) for i in issues[:20])
            more = f"\n  ... and {len(issues) - 20} more" if len(issues) > 20 else ""
            first = issues[0]
            raise BundleError(f"invalid bundle {root} ({len(issues)} problem(s)):\n  {lines}{more}",
                              None, None) if len(issues) > 1 else BundleError(first.message, first.path, first.field)
    return SceneBundle(root, read_manifest(root))
