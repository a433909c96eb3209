"""Settings and output types of the tile rasterizer."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from core.errors import ConfigError

#: Order of the 12 composited feature channels inside the kernels (and of ``RasterOutput.packed``;
#: channel 12 of ``packed`` is the opacity O).
FEATURE_CHANNELS = (
    ("color", 3),
    ("depth", 1),
    ("normal", 3),
    ("albedo", 3),
    ("roughness", 1),
    ("metallic", 1),
)
NUM_FEATURES = 12
NUM_OUTPUTS = 13


from core.native_build import default_threads  # noqa: E402,F401 - one definition, re-exported


@dataclass(frozen=True)
class RasterSettings:
    """How the EWA splatting rasterizer culls, composites and parallelises. All lengths in pixels
    unless stated. The defaults are those of 3D Gaussian Splatting (Kerbl et al. 2023)."""

    tile_size: int = 16
    """Side of a square screen tile in pixels. The kernels process one 16-pixel tile row as one
    SIMD vector, so only 16 is supported."""

    alpha_min: float = 1.0 / 255.0
    """A Gaussian whose alpha at a pixel is below this is skipped there. Also defines the
    opacity-aware footprint used for tile culling: the ellipse where ``o * g >= alpha_min``."""

    alpha_max: float = 0.99
    """Alpha is clamped to at most this, so the transmittance stays invertible in the backward."""

    transmittance_min: float = 1e-4
    """Early stop: a pixel stops compositing before the Gaussian that would bring its
    transmittance below this value (that Gaussian is not composited)."""

    low_pass: float = 0.3
    """Added to both diagonal entries of every 2D covariance (pixels squared): the anti-aliasing
    dilation of 3DGS, which also guarantees an invertible 2D covariance."""

    near: float = 0.01
    """Near plane in metres: Gaussians whose camera z-depth is <= near are culled."""

    guard_band: float = 1.3
    """The projected mean used inside the EWA Jacobian is clamped to this multiple of the field
    of view (centred on the image), as 3DGS does, so Gaussians far outside the view do not get
    huge, distorted footprints."""

    max_scale: float = 1e4
    """Per-axis Gaussian scales (metres) are clamped to [0, max_scale] before the covariance is
    formed, so a huge scale cannot overflow to Inf/NaN. Clamped entries get zero gradient."""

    threads: int | None = None
    """Worker threads for binning, forward and backward (None: every core this process may use)."""

    collect_stats: bool = False
    """Also return per-pixel counts of evaluated and contributing Gaussians (``RasterOutput.stats``)."""

    def __post_init__(self) -> None:
        if self.tile_size != 16:
            raise ConfigError(f"tile_size: only 16 is supported (SIMD row width), got {self.tile_size}")
        checks = {
            "alpha_min": 0.0 < self.alpha_min < 1.0,
            "alpha_max": 0.0 < self.alpha_max < 1.0 and self.alpha_max > self.alpha_min,
            "transmittance_min": 0.0 <= self.transmittance_min < 1.0,
            "low_pass": self.low_pass > 0.0 and math.isfinite(self.low_pass),
            "near": self.near > 0.0 and math.isfinite(self.near),
            "guard_band": self.guard_band >= 1.0 and math.isfinite(self.guard_band),
            "max_scale": self.max_scale > 0.0 and math.isfinite(self.max_scale),
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"{name}: invalid value {getattr(self, name)!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise ConfigError(f"threads: expected None or an int >= 1, got {self.threads!r}")

    @property
    def num_threads(self) -> int:
        """Resolved thread count."""
        return self.threads if self.threads is not None else default_threads()


@dataclass
class RasterOutput:
    """Per-pixel G-buffers, each ``[H, W, C]`` in the dtype of the inputs, all differentiable.

    Every channel is the front-to-back alpha composite ``sum_i T_i alpha_i x_i`` (not divided by
    the opacity), as in the paper; ``color`` additionally gets ``T_final * background``.
    ``depth`` composites the camera z-depth (metres) of the Gaussian means; ``normal`` is in the
    world frame. Divide by ``opacity`` for expected values given a hit.
    """

    color: "torch.Tensor"  # noqa: F821  [H, W, 3]
    opacity: "torch.Tensor"  # noqa: F821  [H, W, 1], O = sum T_i alpha_i = 1 - T_final
    depth: "torch.Tensor"  # noqa: F821  [H, W, 1]
    normal: "torch.Tensor"  # noqa: F821  [H, W, 3]
    albedo: "torch.Tensor"  # noqa: F821  [H, W, 3]
    roughness: "torch.Tensor"  # noqa: F821  [H, W, 1]
    metallic: "torch.Tensor"  # noqa: F821  [H, W, 1]
    packed: "torch.Tensor"  # noqa: F821  [H, W, 13]: the 12 features in FEATURE_CHANNELS order, then O
    transmittance: "torch.Tensor"  # noqa: F821  [H, W] final transmittance (no gradient)
    num_visible: int = 0
    """Gaussians in front of the near plane with a non-empty footprint in the image."""
    num_tile_pairs: int = 0
    """Gaussian-tile pairs after culling (length of the sorted list)."""
    stats: "torch.Tensor | None" = None  # noqa: F821
    """``[H, W, 2]`` int32 (only with ``collect_stats``): Gaussians evaluated at the pixel (alpha
    computed before its early stop) and Gaussians composited into it."""

    def as_dict(self) -> dict:
        """The seven G-buffers by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)[:7]}
