"""The one camera type of the project: :class:`Camera`, an OpenCV pinhole camera.

Frames (:mod:`core.conventions`)
    World: right-handed, z up, metres. Camera: OpenCV axes, x right, y down, z forward.
    ``cam_to_world`` is a rigid 4x4 matrix whose columns 0..2 are the camera axes in world
    coordinates and column 3 is the camera centre (metres). Pixel (u, v) = (column, row); the
    centre of the top-left pixel is (0.5, 0.5).
Intrinsics
    ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels (no skew, no distortion): a camera
    point ``(x, y, z)`` lands at ``u = fx x / z + cx``, ``v = fy y / z + cy``.
Batches
    A camera may hold ``B`` poses and intrinsics (``K`` [B, 3, 3], ``cam_to_world`` [B, 4, 4])
    of one image size: ``len(cam)``, ``cam[i]`` (one camera), ``cam[i:j]``, iteration and
    :meth:`Camera.stack`. The renderers take one camera at a time.

Every user of a camera (rasterizer, PBR pass, Mitsuba ground truth, relighting, stages) takes
this type. The scene bundle stores intrinsics per camera id (:class:`core.bundle.schema.Camera`,
the on-disk record, unchanged) and a pose per frame; :meth:`Camera.from_bundle` joins the two
and :meth:`Camera.to_bundle` gives the record back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterator, Sequence

import numpy as np
import torch

from core.bundle.schema import Camera as CameraRecord
from core.conventions import camera_ray_directions, project_points
from core.errors import ConfigError, NumericalError, ShapeError

#: Tolerances of the rigidity check of ``cam_to_world`` (rotation orthonormal and det +1 within
#: ``RIGID_ATOL``, last row 0 0 0 1 within ``LAST_ROW_ATOL``); the values the rasterizer always used.
RIGID_ATOL = 1e-3
LAST_ROW_ATOL = 1e-6


def _scalar(v: Any, name: str, positive: bool = False) -> float:
    """A finite number (int, float or one-element tensor, no gradient kept) named ``name``."""
    if isinstance(v, torch.Tensor):
        if v.numel() != 1:
            raise ShapeError(f"{name}: expected a scalar, got shape {list(v.shape)}")
        val = float(v.detach())
    else:
        try:
            val = float(v)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{name}: expected a number, got {v!r}") from exc
    if not math.isfinite(val):
        raise NumericalError(f"{name}: non-finite value {val}")
    if positive and val <= 0:
        raise ConfigError(f"{name}: must be > 0, got {val}")
    return val


def _size(v: Any, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ConfigError(f"{name}: expected an int >= 1, got {v!r}")
    return int(v)


def _matrix(x: Any, name: str, n: int) -> torch.Tensor:
    """``x`` as a float tensor [n, n] or [B, n, n]: tensors keep their dtype and autograd graph,
    arrays keep a float dtype (others become float64)."""
    if not isinstance(x, torch.Tensor):
        try:
            a = np.asarray(x)
        except Exception as exc:  # ragged lists and the like
            raise ShapeError(f"{name}: expected a [{n}, {n}] matrix, got {type(x).__name__}") from exc
        if a.dtype.kind not in "fiu":
            raise ShapeError(f"{name}: expected a numeric matrix, got dtype {a.dtype}")
        x = torch.as_tensor(a if a.dtype.kind == "f" else a.astype(np.float64))
    if not x.is_floating_point():
        raise ShapeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.dim() not in (2, 3) or tuple(x.shape[-2:]) != (n, n):
        raise ShapeError(f"{name}: expected shape [{n}, {n}] or [B, {n}, {n}], got {list(x.shape)}")
    if not bool(torch.isfinite(x.detach()).all()):
        bad = int((~torch.isfinite(x.detach())).sum())
        raise NumericalError(f"{name}: {bad} non-finite value(s) (NaN or Inf)")
    return x


@dataclass(frozen=True, eq=False)
class Camera:
    """OpenCV pinhole camera (one, or a batch of ``B`` with one image size).

    K: [3, 3] or [B, 3, 3] float64 tensor, pixels: ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``,
        fx, fy > 0. Intrinsics carry no gradient.
    cam_to_world: [4, 4] or [B, 4, 4] camera-to-world, metres, OpenCV camera axes (x right,
        y down, z forward), rigid. A tensor keeps its dtype and autograd graph (a pose may
        require grad); a numpy array or list becomes a tensor (float64 unless already float).
    width, height: image size, pixels (ints >= 1).

    A [3, 3] ``K`` with [B, 4, 4] poses (or the reverse) is broadcast to the batch. Raises
    :class:`ShapeError` (shape or dtype), :class:`NumericalError` (NaN/Inf) or
    :class:`ConfigError` (non-positive focal length, skew, non-rigid pose, bad size), each naming
    the argument. ``fx, fy, cx, cy`` read ``K`` (floats for one camera, [B] tensors for a batch).
    """

    K: torch.Tensor
    cam_to_world: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        width, height = _size(self.width, "width"), _size(self.height, "height")
        k = _matrix(self.K, "K", 3).detach().to(torch.float64)
        c2w = _matrix(self.cam_to_world, "cam_to_world", 4)
        if k.dim() != c2w.dim():
            if k.dim() == 2:
                k = k.expand(c2w.shape[0], 3, 3)
            else:
                c2w = c2w.expand(k.shape[0], 4, 4)
        elif k.dim() == 3 and k.shape[0] != c2w.shape[0]:
            raise ShapeError(f"K: batch of {k.shape[0]} does not match cam_to_world's {c2w.shape[0]}")
        if bool((k[..., 0, 0] <= 0).any()) or bool((k[..., 1, 1] <= 0).any()):
            raise ConfigError(f"K: fx = K[0, 0] and fy = K[1, 1] must be > 0, got "
                              f"{k[..., 0, 0].tolist()} and {k[..., 1, 1].tolist()}")
        zero = torch.stack([k[..., 0, 1], k[..., 1, 0], k[..., 2, 0], k[..., 2, 1], k[..., 2, 2] - 1.0])
        if bool((zero != 0).any()):
            raise ConfigError("K: expected a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                              "(no skew)")
        c = c2w.detach().double()
        r = c[..., :3, :3]
        eye = torch.eye(3, dtype=torch.float64)
        last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
        if (not torch.allclose(r.transpose(-1, -2) @ r, eye.expand_as(r), atol=RIGID_ATOL)
                or bool(((torch.linalg.det(r) - 1.0).abs() > RIGID_ATOL).any())
                or not torch.allclose(c[..., 3, :], last.expand_as(c[..., 3, :]), atol=LAST_ROW_ATOL)):
            raise ConfigError("cam_to_world: expected a rigid transform (orthonormal rotation, det +1, "
                              "last row 0 0 0 1)")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "cam_to_world", c2w)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    # -- construction --------------------------------------------------------------------------

    @classmethod
    def from_intrinsics(cls, cam_to_world: Any, fx: Any, fy: Any, cx: Any, cy: Any, width: int,
                        height: int) -> "Camera":
        """One camera from a pose ([4, 4] camera-to-world, metres) and ``fx, fy, cx, cy`` in
        pixels (numbers or one-element tensors; errors name each of them)."""
        width, height = _size(width, "width"), _size(height, "height")
        fx, fy = _scalar(fx, "fx", positive=True), _scalar(fy, "fy", positive=True)
        cx, cy = _scalar(cx, "cx"), _scalar(cy, "cy")
        k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        return cls(k, cam_to_world, width, height)

    @classmethod
    def from_bundle(cls, record: Any, pose: Any) -> "Camera":
        """The camera of a bundle frame: ``record`` is the bundle's intrinsics record
        (:class:`core.bundle.schema.Camera`, ``bundle.camera(frame)``), ``pose`` the frame
        (anything with ``cam_to_world``) or its [4, 4] camera-to-world. Distortion is ignored
        (every renderer here is pinhole)."""
        c2w = pose.cam_to_world if hasattr(pose, "cam_to_world") else pose
        return cls.from_intrinsics(c2w, record.fx, record.fy, record.cx, record.cy, record.width, record.height)

    @classmethod
    def of(cls, cam: Any) -> "Camera":
        """``cam`` itself if it is a :class:`Camera`, else one built from an object with
        ``cam_to_world, fx, fy, cx, cy, width, height`` attributes (pose as float64)."""
        if isinstance(cam, Camera):
            return cam
        return cls.from_intrinsics(np.asarray(cam.cam_to_world, np.float64), cam.fx, cam.fy, cam.cx, cam.cy,
                                   cam.width, cam.height)

    @classmethod
    def stack(cls, cameras: Sequence["Camera"]) -> "Camera":
        """A batch of the given cameras (each one camera or a batch), all of one image size."""
        cams = list(cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise ConfigError("cameras: expected a non-empty sequence of Camera")
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) != 1:
            raise ConfigError(f"cameras: a batch has one image size, got {sorted(sizes)} (width, height)")

        def rows(c: Camera, t: torch.Tensor) -> torch.Tensor:
            return t if c.is_batched else t[None]

        k = torch.cat([rows(c, c.K) for c in cams])
        c2w = torch.cat([rows(c, c.cam_to_world) for c in cams])
        return cls(k, c2w, cams[0].width, cams[0].height)

    def to_bundle(self, id: str, distortion: tuple[float, ...] = ()) -> Any:
        """The bundle's intrinsics record (:class:`core.bundle.schema.Camera`) of one camera."""
        self._require_single("to_bundle")
        return CameraRecord(id, self.width, self.height, self.fx, self.fy, self.cx, self.cy, tuple(distortion))

    # -- batches -------------------------------------------------------------------------------

    @property
    def is_batched(self) -> bool:
        """True when the camera holds a batch (``K`` [B, 3, 3], ``cam_to_world`` [B, 4, 4])."""
        return self.cam_to_world.dim() == 3

    def _require_single(self, what: str) -> None:
        if self.is_batched:
            raise ShapeError(f"camera: {what} needs one camera, got a batch of {len(self)} (index it)")

    def __len__(self) -> int:
        if not self.is_batched:
            raise TypeError("len() of a single Camera (not a batch)")
        return int(self.cam_to_world.shape[0])

    def __getitem__(self, index: int | slice) -> "Camera":
        if not self.is_batched:
            raise TypeError("a single Camera is not indexable (not a batch)")
        return Camera(self.K[index], self.cam_to_world[index], self.width, self.height)

    def __iter__(self) -> Iterator["Camera"]:
        return (self[i] for i in range(len(self)))

    # -- views of the parameters ---------------------------------------------------------------

    def _k(self, i: int, j: int) -> float | torch.Tensor:
        v = self.K[..., i, j]
        return v.clone() if self.is_batched else float(v)

    fx = property(lambda self: self._k(0, 0), doc="Focal length along x, pixels (a [B] tensor for a batch).")
    fy = property(lambda self: self._k(1, 1), doc="Focal length along y, pixels (a [B] tensor for a batch).")
    cx = property(lambda self: self._k(0, 2), doc="Principal point column, pixels (a [B] tensor for a batch).")
    cy = property(lambda self: self._k(1, 2), doc="Principal point row, pixels (a [B] tensor for a batch).")

    @property
    def center(self) -> torch.Tensor:
        """Camera centre [3] (or [B, 3]), world metres."""
        return self.cam_to_world[..., :3, 3]

    def pose_numpy(self) -> np.ndarray:
        """``cam_to_world`` as a float64 numpy array [4, 4] (or [B, 4, 4]), detached."""
        return self.cam_to_world.detach().cpu().numpy().astype(np.float64)

    def ray_directions(self) -> np.ndarray:
        """Unit world directions [H, W, 3] (float64) of the rays through every pixel centre
        (:func:`core.conventions.camera_ray_directions`); one camera."""
        self._require_single("ray_directions")
        return camera_ray_directions(self.pose_numpy(), self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(uv [N, 2] pixels, z [N] camera depth, metres) of world points [N, 3], metres; NaN uv
        behind the camera (:func:`core.conventions.project_points`); one camera."""
        self._require_single("project")
        return project_points(points_world, self.pose_numpy(), self.fx, self.fy, self.cx, self.cy)

    def to(self, dtype: torch.dtype) -> "Camera":
        """The same camera with ``cam_to_world`` in ``dtype`` (autograd graph kept; ``self``
        when it already is)."""
        if self.cam_to_world.dtype == dtype:
            return self
        return Camera(self.K, self.cam_to_world.to(dtype), self.width, self.height)

    def scaled(self, factor: float) -> "Camera":
        """The same pose with the image (and ``fx, fy, cx, cy``) ``factor`` times as large;
        ``width * factor`` and ``height * factor`` must be whole numbers."""
        w, h = self.width * factor, self.height * factor
        if w != int(w) or h != int(h):
            raise ConfigError(f"factor: {factor} does not scale {self.width}x{self.height} to whole pixels")
        k = self.K.clone()
        k[..., :2, :] *= factor
        return Camera(k, self.cam_to_world, int(w), int(h))


def require_one_camera(camera: Any, name: str = "camera") -> "Camera":
    """``camera`` if it is one (unbatched) :class:`Camera`; else ConfigError (not a Camera) or
    ShapeError (a batch) naming ``name``."""
    if not isinstance(camera, Camera):
        raise ConfigError(f"{name}: expected a core.camera.Camera, got {type(camera).__name__}")
    if camera.is_batched:
        raise ShapeError(f"{name}: expected one camera, got a batch of {len(camera)} (index it)")
    return camera
