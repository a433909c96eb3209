"""The 3D Gaussian container: unconstrained parameters + activations (the paper's attributes).

Stored (unconstrained, what an optimizer updates)          activated (what the renderer uses)
--------------------------------------------------------    -----------------------------------
``means``           [N, 3] world, metres                    identity
``quats``           [N, 4] wxyz                             unit quaternion; a (near-)zero
                                                            quaternion is the identity, never NaN
``log_scales``      [N, 3]                                  ``exp`` (log-scale clamped to
                                                            [-30, ln 1e4] first: finite values
                                                            and gradients for any input)
``opacity_logits``  [N, 1]                                  ``sigmoid``
``normals``         [N, 3] world                            unit vector (zero stays zero)
``color_logits``    [N, 3]                                  ``sigmoid``: base RGB in (0, 1)
``view_dep``        [N, 9] (optional, default zeros)        view-dependent colour: a 3x3 matrix
                                                            W (row = R, G, B; columns = world
                                                            x, y, z), added in logit space:
                                                            ``sigmoid(color_logits + W d)`` for
                                                            the unit direction d from the camera
                                                            to the Gaussian (degree-1 spherical
                                                            harmonics written in Cartesian form,
                                                            so a rigid rotation R maps W -> W R^T)
``albedo_logits``   [N, 3]                                  ``sigmoid``
``roughness_logits``[N, 1]                                  ``sigmoid``
``metallic_logits`` [N, 1]                                  ``sigmoid``

All fields share one floating dtype and the CPU/CUDA device. :meth:`Gaussians.from_activated`
inverts the activations, clamping sigmoid inputs to ``[LOGIT_EPS, 1 - LOGIT_EPS]`` (so logit(0)
and logit(1) stay finite) and scales to ``>= MIN_SCALE``.

File format (:meth:`Gaussians.save` / :meth:`Gaussians.load`): ``torch.save`` of a plain dict,
loaded with ``weights_only=True``::

    {"format": "brdfusion.gaussians", "version": 1, "num": N,
     "means": Tensor[N, 3], "quats": Tensor[N, 4], "log_scales": Tensor[N, 3],
     "opacity_logits": Tensor[N, 1], "normals": Tensor[N, 3], "color_logits": Tensor[N, 3],
     "albedo_logits": Tensor[N, 3], "roughness_logits": Tensor[N, 1],
     "metallic_logits": Tensor[N, 1], "view_dep": Tensor[N, 9]}

Version 1 files (no ``view_dep``) load with view-independent colour.

Tensors are saved detached, contiguous, on the CPU, in their dtype. Unknown extra keys are
ignored on load; a different ``format`` or a newer ``version`` is a :class:`FormatError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Iterable

import torch

from core.errors import FormatError, ShapeError
from core.io.atomic import atomic_output
from core.io.torchfile import read_torch_file
from core.numerics import require_finite, safe_normalize
from core.raster.splat import safe_normalize_quat

FORMAT_NAME = "brdfusion.gaussians"
FORMAT_VERSION = 2
#: Sigmoid inputs are built from activated values clamped to [LOGIT_EPS, 1 - LOGIT_EPS]: in
#: float32, 1 - 1e-6 is still distinguishable from 1, and logit(1e-6) = -13.8 is finite.
LOGIT_EPS = 1e-6
#: Activated scales are clamped to at least this (metres) before the log.
MIN_SCALE = 1e-12
#: Log-scales are clamped to [LOG_SCALE_MIN, LOG_SCALE_MAX] inside :meth:`Gaussians.scales`.
LOG_SCALE_MIN = -30.0
LOG_SCALE_MAX = math.log(1e4)

_WIDTHS = {
    "means": 3,
    "quats": 4,
    "log_scales": 3,
    "opacity_logits": 1,
    "normals": 3,
    "color_logits": 3,
    "albedo_logits": 3,
    "roughness_logits": 1,
    "metallic_logits": 1,
    "view_dep": 9,
}


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(LOGIT_EPS, 1.0 - LOGIT_EPS)
    return torch.log(p) - torch.log1p(-p)


@dataclass
class Gaussians:
    """N 3D Gaussians with geometry and material, stored as unconstrained parameters."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    normals: torch.Tensor
    color_logits: torch.Tensor
    albedo_logits: torch.Tensor
    roughness_logits: torch.Tensor
    metallic_logits: torch.Tensor
    view_dep: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.view_dep is None and isinstance(self.means, torch.Tensor):
            self.view_dep = torch.zeros(self.means.shape[0], 9, dtype=self.means.dtype, device=self.means.device)
        self.validate()

    @classmethod
    def _trusted(cls, **fields_) -> "Gaussians":
        """Build without :meth:`validate`: only for results of operations on already validated
        containers (cat, index, rigid transforms), where a full finiteness scan per call would
        cost more than the operation itself in a training step."""
        g = object.__new__(cls)
        for k, v in fields_.items():
            object.__setattr__(g, k, v)
        if fields_.get("view_dep") is None:
            m = fields_["means"]
            g.view_dep = torch.zeros(m.shape[0], 9, dtype=m.dtype, device=m.device)
        return g

    # -- validation ----------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise ShapeError / NumericalError naming the field if shapes, dtypes, devices or
        values are wrong."""
        n = None
        dtype = device = None
        for name, width in _WIDTHS.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor):
                raise ShapeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
            if not t.is_floating_point():
                raise ShapeError(f"{name}: expected a floating-point tensor, got {t.dtype}")
            if t.dim() != 2 or t.shape[1] != width:
                raise ShapeError(f"{name}: expected shape [N, {width}], got {list(t.shape)}")
            if n is None:
                n, dtype, device = t.shape[0], t.dtype, t.device
            elif t.shape[0] != n:
                raise ShapeError(f"{name}: has {t.shape[0]} rows, means has {n}")
            elif t.dtype != dtype:
                raise ShapeError(f"{name}: dtype {t.dtype} differs from means.dtype {dtype}")
            elif t.device != device:
                raise ShapeError(f"{name}: device {t.device} differs from means.device {device}")
            require_finite(t.detach(), name)

    # -- basic properties ----------------------------------------------------------------------
    @property
    def num(self) -> int:
        """Number of Gaussians."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, torch.Tensor]:
        """The stored (unconstrained) tensors by field name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def parameters(self) -> list[torch.Tensor]:
        """The stored tensors as a list (e.g. for an optimizer)."""
        return list(self.tensors().values())

    def requires_grad_(self, flag: bool = True) -> "Gaussians":
        for t in self.parameters():
            t.requires_grad_(flag)
        return self

    # -- activations ---------------------------------------------------------------------------
    def opacities(self) -> torch.Tensor:
        """[N, 1] in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def rotations(self) -> torch.Tensor:
        """[N, 4] unit quaternions wxyz (zero quaternion -> identity)."""
        return safe_normalize_quat(self.quats)

    def scales(self) -> torch.Tensor:
        """[N, 3] metres, ``exp`` of the clamped log-scales."""
        return torch.exp(self.log_scales.clamp(LOG_SCALE_MIN, LOG_SCALE_MAX))

    def unit_normals(self) -> torch.Tensor:
        """[N, 3] unit world normals (zero vectors stay zero)."""
        return safe_normalize(self.normals)

    def colors(self, cam_center: torch.Tensor | None = None) -> torch.Tensor:
        """[N, 3] RGB in (0, 1): the base colour, or the colour seen from ``cam_center`` [3]
        (world, metres) including the view-dependent term."""
        if cam_center is None:
            return torch.sigmoid(self.color_logits)
        d = safe_normalize(self.means - cam_center.to(self.means.dtype))
        w = self.view_dep.reshape(-1, 3, 3)
        return torch.sigmoid(self.color_logits + (w @ d[:, :, None])[:, :, 0])

    def albedo(self) -> torch.Tensor:
        """[N, 3] in (0, 1)."""
        return torch.sigmoid(self.albedo_logits)

    def roughness(self) -> torch.Tensor:
        """[N, 1] in (0, 1)."""
        return torch.sigmoid(self.roughness_logits)

    def metallic(self) -> torch.Tensor:
        """[N, 1] in (0, 1)."""
        return torch.sigmoid(self.metallic_logits)

    def activated(self, cam_center: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Every activated attribute, keyed as :func:`core.raster.rasterize` names its arguments
        (colours as seen from ``cam_center`` when given)."""
        return {
            "means": self.means,
            "quats": self.rotations(),
            "scales": self.scales(),
            "opacities": self.opacities(),
            "colors": self.colors(cam_center),
            "normals": self.unit_normals(),
            "albedo": self.albedo(),
            "roughness": self.roughness(),
            "metallic": self.metallic(),
        }

    # -- construction --------------------------------------------------------------------------
    @classmethod
    def from_activated(cls, means, quats, scales, opacities, colors, normals, albedo, roughness,
                       metallic) -> "Gaussians":
        """Build from activated values (inverse activations with clamping). ``opacities``,
        ``roughness``, ``metallic`` may be [N] or [N, 1]."""

        def col(x, name):
            if not isinstance(x, torch.Tensor):
                raise ShapeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
            return x[:, None] if x.dim() == 1 else x

        for name, x in (("means", means), ("quats", quats), ("scales", scales), ("colors", colors),
                        ("normals", normals), ("albedo", albedo)):
            if not isinstance(x, torch.Tensor):
                raise ShapeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
            require_finite(x, name)
        return cls(
            means=means,
            quats=quats,
            log_scales=torch.log(scales.clamp_min(MIN_SCALE)),
            opacity_logits=_logit(col(opacities, "opacities")),
            normals=normals,
            color_logits=_logit(colors),
            albedo_logits=_logit(albedo),
            roughness_logits=_logit(col(roughness, "roughness")),
            metallic_logits=_logit(col(metallic, "metallic")),
        )

    @classmethod
    def empty(cls, dtype: torch.dtype = torch.float32) -> "Gaussians":
        """A container with N = 0."""
        return cls(**{k: torch.zeros(0, w, dtype=dtype) for k, w in _WIDTHS.items()})

    # -- manipulation --------------------------------------------------------------------------
    def to(self, dtype: torch.dtype | None = None, device=None) -> "Gaussians":
        """A copy converted to ``dtype`` and/or ``device`` (differentiable, like Tensor.to)."""
        return Gaussians._trusted(**{k: v.to(device=device, dtype=dtype) for k, v in self.tensors().items()})

    def detach(self) -> "Gaussians":
        return Gaussians._trusted(**{k: v.detach() for k, v in self.tensors().items()})

    #: The fields that place and shape a Gaussian (what alpha blending weights depend on).
    GEOMETRY_FIELDS = ("means", "quats", "log_scales", "opacity_logits")

    def geometry_detached(self) -> "Gaussians":
        """The same Gaussians with the geometry (:attr:`GEOMETRY_FIELDS`) detached and every
        attribute (colour, normal, materials) still in the graph: a loss on its render moves the
        attributes only."""
        return Gaussians._trusted(**{k: (v.detach() if k in self.GEOMETRY_FIELDS else v)
                                     for k, v in self.tensors().items()})

    def clone(self) -> "Gaussians":
        return Gaussians._trusted(**{k: v.clone() for k, v in self.tensors().items()})

    def index(self, idx) -> "Gaussians":
        """Subset by a bool mask [N], an index tensor/list, or a slice."""
        if isinstance(idx, torch.Tensor):
            if idx.dtype == torch.bool and (idx.dim() != 1 or idx.shape[0] != self.num):
                raise ShapeError(f"idx: bool mask must have shape [{self.num}], got {list(idx.shape)}")
            if idx.dtype != torch.bool and idx.is_floating_point():
                raise ShapeError(f"idx: expected a bool or integer tensor, got {idx.dtype}")
        elif isinstance(idx, (list, tuple)):
            idx = torch.as_tensor(idx, dtype=torch.long)
        elif not isinstance(idx, slice):
            raise ShapeError(f"idx: expected a mask, indices or a slice, got {type(idx).__name__}")
        return Gaussians._trusted(**{k: v[idx] for k, v in self.tensors().items()})

    select = index
    __getitem__ = index

    @staticmethod
    def cat(items: Iterable["Gaussians"]) -> "Gaussians":
        """Concatenate containers (same dtype and device)."""
        items = list(items)
        if not items:
            raise ShapeError("items: need at least one Gaussians to concatenate")
        for i, g in enumerate(items):
            if not isinstance(g, Gaussians):
                raise ShapeError(f"items[{i}]: expected Gaussians, got {type(g).__name__}")
            if g.dtype != items[0].dtype:
                raise ShapeError(f"items[{i}]: dtype {g.dtype} differs from items[0] ({items[0].dtype})")
        return Gaussians._trusted(**{k: torch.cat([getattr(g, k) for g in items], 0) for k in _WIDTHS})

    # -- files ---------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the documented ``torch.save`` dict (see the module docstring)."""
        payload: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "num": self.num}
        for k, v in self.tensors().items():
            payload[k] = v.detach().to("cpu").contiguous()
        path = Path(path)

        with atomic_output(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, path: str | Path) -> "Gaussians":
        """Read a file written by :meth:`save`; FormatError names the file and field if it is bad."""
        path = Path(path)
        payload = read_torch_file(path, FORMAT_NAME, range(1, FORMAT_VERSION + 1), "Gaussians file", pass_missing=True)
        version = payload["version"]
        kwargs = {}
        for k in _WIDTHS:
            if k == "view_dep" and version == 1:
                continue  # version 1: view-independent colour (zeros)
            if k not in payload or not isinstance(payload[k], torch.Tensor):
                raise FormatError(f"{path} [{k}]: missing or not a tensor")
            kwargs[k] = payload[k]
        try:
            g = cls(**kwargs)
        except (ShapeError, ArithmeticError) as exc:
            raise FormatError(f"{path}: {exc}") from exc
        if payload.get("num", g.num) != g.num:
            raise FormatError(f"{path} [num]: says {payload.get('num')}, tensors have {g.num}")
        return g
