"""Write scene bundles. Writes go to a staging directory that replaces the target only when the
bundle is complete and valid, so a failure never destroys a bundle already stored there."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from core.bundle.reader import validate_bundle
from core.bundle.schema import (GT_FRAME_LAYERS, MANIFEST_NAME, Camera, Frame, GroundTruth, LidarSweep, Manifest,
                                ObjectTrack, RelitSet, parse_manifest, parse_rigid)
from core.errors import BundleError, ConfigError, ShapeError
from core.io.envmap_file import read_envmap, write_envmap
from core.io.exr import write_exr
from core.io.images import write_png
from core.numerics import require_finite_np


class BundleWriter:
    """Incrementally build a bundle in a staging directory; :meth:`finish` publishes it.

    Example::

        w = BundleWriter("out/scene", name="scene")
        w.set_times([0.0, 0.1])
        w.add_camera(Camera("front", 320, 213, 300, 300, 160, 106.5))
        w.add_frame("000_front", "front", 0, cam_to_world, image=rgb_uint8)
        w.finish()
    """

    def __init__(self, root: str | Path, name: str, *, overwrite: bool = False, description: str = "",
                 source: dict | None = None, ldr_exposure: float = 1.0, ldr_gamma: float = 2.2):
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ConfigError(f"root: {self.root} exists and is not a directory")
        if self.root.exists() and any(self.root.iterdir()) and not overwrite:
            raise ConfigError(f"root: {self.root} exists and is not empty (pass overwrite=True to replace it)")
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self._stage_dir: Path | None = None  # created on the first write
        self.name = name
        self.description = description
        self.source = dict(source or {})
        self.ldr_exposure = float(ldr_exposure)
        self.ldr_gamma = float(ldr_gamma)
        self.times: list[float] = []
        self.cameras: dict[str, Camera] = {}
        self.frames: list[Frame] = []
        self.lidar: list[LidarSweep] = []
        self.objects: list[ObjectTrack] = []
        self.ground_truth: GroundTruth | None = None
        self._relit: list[RelitSet] = []
        self._done = False

    # -------------------------------------------------------------------------------------------
    @property
    def _stage(self) -> Path:
        if self._stage_dir is None:
            self._stage_dir = Path(tempfile.mkdtemp(prefix=f".{self.root.name}.staging-", dir=self.root.parent))
        return self._stage_dir

    @staticmethod
    def _rigid(m, arg: str) -> np.ndarray:
        try:
            return parse_rigid(m, arg)
        except BundleError as e:
            raise ConfigError(f"{arg}: {str(e).split(': ', 1)[-1]}") from None

    def _out(self, rel: str) -> Path:
        p = self._stage / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def set_times(self, times) -> None:
        """Timestamps (seconds) of time indices 0..T-1, strictly increasing."""
        self.times = [float(t) for t in times]

    def add_camera(self, cam: Camera) -> None:
        self.cameras[cam.id] = cam

    def add_frame(self, frame_id: str, camera: str, time_index: int, cam_to_world: np.ndarray, *,
                  image: np.ndarray | None = None, image_file: str | Path | None = None,
                  split: str = "train", sky_mask: np.ndarray | None = None,
                  ground_truth: dict[str, np.ndarray] | None = None) -> Frame:
        """Add a frame. Give the LDR ``image`` (uint8 [H, W, 3], or float in [0, 1]) or an
        ``image_file`` (PNG/JPEG, copied as is). ``sky_mask``: bool [H, W], True = sky.
        ``ground_truth``: layers as in ``GT_FRAME_LAYERS`` (rgb HDR, albedo, roughness, metallic,
        normal world, depth metres)."""
        if camera not in self.cameras:
            raise ConfigError(f"camera: unknown camera {camera!r}; add it first")
        if any(f.id == frame_id for f in self.frames):
            raise ConfigError(f"frame_id: duplicate frame id {frame_id!r}")
        self._rigid(cam_to_world, f"cam_to_world (frame {frame_id})")
        if (image is None) == (image_file is None):
            raise ConfigError("image/image_file: give exactly one")
        if image_file is not None:
            if not Path(image_file).is_file():
                raise ConfigError(f"image_file: not found: {image_file}")
            if Path(image_file).suffix.lower() not in (".png", ".jpg", ".jpeg"):
                raise ConfigError(f"image_file: must be .png, .jpg or .jpeg, got {image_file}")
        if image is not None:
            rel = f"images/{frame_id}.png"
            write_png(self._out(rel), image)
        else:
            ext = Path(image_file).suffix.lower()
            rel = f"images/{frame_id}{ext}"
            shutil.copyfile(image_file, self._out(rel))
        mask_rel = None
        if sky_mask is not None:
            mask_rel = f"sky_masks/{frame_id}.png"
            write_png(self._out(mask_rel), (np.asarray(sky_mask).astype(bool) * 255).astype(np.uint8))
        gt_rel = None
        if ground_truth is not None:
            missing = set(GT_FRAME_LAYERS) - set(ground_truth)
            if missing:
                raise ConfigError(f"ground_truth: missing layers {sorted(missing)}")
            gt_rel = f"ground_truth/frames/{frame_id}.exr"
            # All layers in half float, ZIP (lossless) compression: keeps bundles small. Half holds
            # radiance up to 65504 (larger values are clamped to it, see write_exr) and depth with
            # a relative precision of 5e-4 (2.5 cm at 50 m).
            write_exr(self._out(gt_rel), ground_truth, precision="half", compression="zip",
                      channel_names={"normal": ("X", "Y", "Z")})
        fr = Frame(frame_id, rel, camera, int(time_index), np.asarray(cam_to_world, np.float64), split,
                   mask_rel, gt_rel)
        self.frames.append(fr)
        return fr

    def add_lidar(self, time_index: int, points: np.ndarray) -> None:
        """points: [N, 6] world, metres (sensor origin xyz, hit point xyz)."""
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 6:
            raise ShapeError(f"points: expected [N, 6], got {list(pts.shape)}")
        require_finite_np(pts, "points")
        if any(s.time_index == int(time_index) for s in self.lidar):
            raise ConfigError(f"time_index: a sweep for time index {time_index} was already added")
        rel = f"lidar/{int(time_index):04d}.npy"
        np.save(self._out(rel), pts)
        self.lidar.append(LidarSweep(int(time_index), rel))

    def add_object(self, obj_id: str, cls: str, size, poses: dict[int, np.ndarray]) -> None:
        """A tracked rigid object: box ``size`` (l, w, h metres), poses time_index -> obj_to_world."""
        for t, m in poses.items():
            self._rigid(m, f"poses[{t}] (object {obj_id})")
        self.objects.append(ObjectTrack(obj_id, cls, tuple(float(s) for s in size),
                                        {int(t): np.asarray(m, np.float64) for t, m in poses.items()}))

    def _write_envmap(self, name: str, envmap: np.ndarray | None, envmap_file: str | Path | None) -> str:
        if (envmap is None) == (envmap_file is None):
            raise ConfigError("envmap/envmap_file: give exactly one")
        if envmap_file is not None:
            src = Path(envmap_file)
            read_envmap(src)  # refuse a bad file before copying it
            rel = f"ground_truth/envmaps/{name}{src.suffix.lower()}"
            shutil.copyfile(src, self._out(rel))
        else:
            rel = f"ground_truth/envmaps/{name}.exr"
            write_envmap(self._out(rel), envmap)
        return rel

    def set_ground_truth_envmap(self, envmap: np.ndarray | None, name: str, rotation_deg: float = 0.0, *,
                                envmap_file: str | Path | None = None) -> None:
        """The environment map [H, W, 3] the frames were rendered under (project convention), or
        ``envmap_file``: an .exr/.hdr file already in that convention, copied as is (keeps the
        source's compression: a bundled HDRI stays ~200 KB)."""
        rel = self._write_envmap(name, envmap, envmap_file)
        self.ground_truth = GroundTruth(rel, name, float(rotation_deg), ())

    def add_relit(self, name: str, envmap: np.ndarray | None, frames_hdr: dict[str, np.ndarray],
                  rotation_deg: float = 0.0, *, envmap_file: str | Path | None = None) -> None:
        """Ground-truth HDR frames [H, W, 3] of existing frame ids under another envmap (array or
        ``envmap_file``, as in :meth:`set_ground_truth_envmap`)."""
        if self.ground_truth is None:
            raise ConfigError("set_ground_truth_envmap must be called before add_relit")
        known = {f.id for f in self.frames}
        unknown = sorted(set(frames_hdr) - known)
        if unknown:
            raise ConfigError(f"frames_hdr: unknown frame ids {unknown[:5]}")
        env_rel = self._write_envmap(name, envmap, envmap_file)
        frames = {}
        for fid, rgb in frames_hdr.items():
            rel = f"ground_truth/relit/{name}/{fid}.exr"
            write_exr(self._out(rel), {"rgb": rgb}, precision="half", compression="zip")
            frames[fid] = rel
        self._relit.append(RelitSet(name, env_rel, float(rotation_deg), frames))

    # -------------------------------------------------------------------------------------------
    def manifest(self) -> Manifest:
        gt = None
        if self.ground_truth is not None:
            gt = GroundTruth(self.ground_truth.envmap, self.ground_truth.envmap_name,
                             self.ground_truth.envmap_rotation_deg, tuple(self._relit))
        m = Manifest(
            name=self.name, times=tuple(self.times), cameras=dict(self.cameras), frames=tuple(self.frames),
            lidar=tuple(sorted(self.lidar, key=lambda s: s.time_index)), objects=tuple(self.objects),
            ldr_exposure=self.ldr_exposure, ldr_gamma=self.ldr_gamma, ground_truth=gt,
            description=self.description, source=self.source,
        )
        return parse_manifest(json.loads(json.dumps(m.to_dict())))  # round trip = schema check

    def finish(self, validate: bool = True) -> Path:
        """Write the manifest, validate the staged bundle, and move it into place. Returns root."""
        if self._done:
            raise ConfigError("finish: bundle already finished")
        try:
            m = self.manifest()
            (self._stage / MANIFEST_NAME).write_text(json.dumps(m.to_dict(), indent=1), encoding="utf-8")
            if validate:
                issues = validate_bundle(self._stage)
                if issues:
                    raise BundleError("written bundle is invalid: " + "; ".join(map(str, issues[:5])))
            old = None
            if self.root.exists():
                old = self.root.with_name(f".{self.root.name}.old-{os.getpid()}")
                os.replace(self.root, old)
            try:
                os.replace(self._stage, self.root)
            except BaseException:
                if old is not None:  # put the previous bundle back
                    os.replace(old, self.root)
                raise
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            shutil.rmtree(self._stage, ignore_errors=True)
            self._done = True
            raise
        self._done = True
        return self.root

    def abort(self) -> None:
        """Drop the staging directory; the target is untouched."""
        if self._stage_dir is not None:
            shutil.rmtree(self._stage_dir, ignore_errors=True)
        self._done = True

    def __enter__(self) -> "BundleWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not self._done:
            self.abort()
