"""The ONNX input/output contracts of the learned models (paper Sec. 3.2-3.3): the interface of every model.

A model file is usable by this project when its graph inputs and outputs match one of the
contracts below (names, ranks, dtypes, and every dimension the contract fixes) and its ONNX
``metadata_props`` carry the contract name and a compatible version. Anything else about the model
(architecture, width, training) is free: a larger model with the same contract drops in without a
code change. :mod:`core.gen.runtime` enforces this when it opens a file.

Metadata keys (ONNX ``metadata_props``, all values strings)
    ``brdf.contract``           contract name: ``forward_denoiser``, ``inverse_gbuffer``, ``lighting``
    ``brdf.contract_version``   ``"<major>.<minor>"``; the loader accepts the same major and a minor
                                 <= the code's minor (minor versions only add optional metadata
                                 or optional inputs)
    ``brdf.frames``             frames per window F the model was trained with (int >= 1); inputs
                                 may have any F, the samplers cut clips into windows of this size
    ``brdf.spatial_multiple``   H and W must be multiples of this (the U-Net's total down-sampling);
                                 :meth:`core.gen.runtime.ModelSession.run` pads (replicate) and crops
    ``brdf.sigma_data``         EDM sigma_data of the data space (diffusion contracts)
    ``brdf.sigma_min``, ``brdf.sigma_max``   noise levels the model was trained on (diffusion)
    ``brdf.card``               optional: file name of the model card next to the ONNX file

Shapes use ``B`` (batch), ``F`` (frames of one window), ``H``, ``W`` (image rows, columns: any,
multiples of ``brdf.spatial_multiple``); every tensor is float32, channels first.

Data spaces (shared by training, sampling and the contracts)
    * LDR image:        ``x = 2 * ldr - 1`` in [-1, 1]; ``ldr = clip(exposure * hdr, 0, 1)^(1/2.2)``
                         (the bundle's tone map, :mod:`core.tonemap`).
    * normal:           unit vector in the **camera frame** (OpenCV axes: x right, y down,
                         z forward, :mod:`core.conventions`), components in [-1, 1]; a sky pixel
                         (no surface) is (0, 0, 0).
    * depth:            ``exp(-z / DEPTH_SCALE_M)`` of the camera z-depth z in metres, in (0, 1];
                         sky (depth 0 in the bundles: no surface) encodes as 0 (infinitely far).
    * albedo, roughness, metallic: [0, 1].
    * G-buffer diffusion space (``inverse_gbuffer``): the 9 channels ``albedo(3), roughness(1),
      metallic(1), normal(3), depth(1)`` mapped to [-1, 1]: ``2 v - 1`` for albedo, roughness,
      metallic and encoded depth; normals as they are.
    * environment encoding (``forward_denoiser``), as DiffusionRenderer: the HDR map E (linear
      radiance, project equirect convention, row 0 = zenith) area-averaged to ``ENV_H x ENV_W``;
      ``env_ldr = E / (1 + E)`` (Reinhard) in [0, 1); ``env_log = log1p(E) / log1p(1e4)`` in
      [0, ~1.2]; ``env_dir`` = the unit direction of each env pixel centre in the camera frame
      (``R_cam_to_world^T d_world``), so the network sees where each light is relative to the
      camera. The map is *not* resampled (no loss of the sun's energy): the rotation is in env_dir.

    * camera (``inverse_gbuffer`` 1.1, optional input ``view``): channels 0-2 the unit direction
      of the ray through each pixel centre, channels 3-5 the world up direction (+z), both in the
      camera frame. A posed capture knows both; with them the model need not guess the camera's
      pitch and field of view from the image to output camera-frame normals.

Versioning: bump the major version for any change of names, ranks, fixed dimensions or data
spaces; bump the minor version for added optional metadata or an added optional input.
"""

from __future__ import annotations

from dataclasses import dataclass

from core.errors import ConfigError

#: Depth encoding scale (metres): ``exp(-z / 20)`` keeps street depths (1-60 m) in (0.05, 0.95).
DEPTH_SCALE_M = 20.0
#: Environment encoding resolution (rows, columns): 64 x 128 equirect, area-averaged from 512x1024
#: (8x8 blocks). Enough for the sun's position (2.8 degrees per pixel) and the sky gradient;
#: the network consumes it through a small global encoder, so larger maps buy nothing here.
ENV_H, ENV_W = 64, 128
#: Normaliser of the log environment channel (DiffusionRenderer's ``log1p(E)/log1p(1e4)``).
ENV_LOG_MAX = 1.0e4
#: Number of G-buffer channels of the inverse model (albedo 3, roughness 1, metallic 1,
#: normal 3, depth 1).
GBUFFER_CHANNELS = 9
#: Slices of the 9 G-buffer channels.
GBUFFER_SLICES = {"albedo": slice(0, 3), "roughness": slice(3, 4), "metallic": slice(4, 5),
                  "normal": slice(5, 8), "depth": slice(8, 9)}
#: Channels of the inverse model's optional camera input ``view``: the pixel's unit ray direction
#: (3) and the world up direction (3), both in the camera frame.
VIEW_CHANNELS = 6
#: Lighting contract: resolution of the low-frequency sky output (the sun is a separate output).
LIGHT_SKY_H, LIGHT_SKY_W = 32, 64

META_CONTRACT = "brdf.contract"
META_VERSION = "brdf.contract_version"
META_FRAMES = "brdf.frames"
META_MULTIPLE = "brdf.spatial_multiple"
META_SIGMA_DATA = "brdf.sigma_data"
META_SIGMA_MIN = "brdf.sigma_min"
META_SIGMA_MAX = "brdf.sigma_max"
META_CARD = "brdf.card"


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output of a contract."""

    name: str
    """Graph input/output name (exact)."""
    dims: tuple[int | str, ...]
    """Dimensions: an int is fixed (the model must declare that value or a symbolic dimension);
    a string names a free dimension (``B``, ``F``, ``H``, ``W``); equal strings must agree at run
    time."""
    dtype: str = "float32"
    """Element type (numpy name); every contract tensor is float32."""
    doc: str = ""
    """Meaning, range and frame of the tensor."""
    optional: bool = False
    """A model file may leave this input out (an older minor version, or a model trained without
    it). When the file declares it, callers must feed it; when it does not, a fed value is
    ignored (:meth:`core.gen.runtime.ModelSession.run`)."""

    @property
    def rank(self) -> int:
        return len(self.dims)


@dataclass(frozen=True)
class Contract:
    """A versioned model interface: the graph inputs and outputs a model of one kind must have."""

    kind: str
    """Contract name, stored in the ONNX metadata under ``brdf.contract``."""
    version: tuple[int, int]
    """(major, minor) version, stored as ``"major.minor"`` under ``brdf.contract_version``."""
    inputs: tuple[TensorSpec, ...]
    """Graph inputs, in order (the loader matches them by name, not by position)."""
    outputs: tuple[TensorSpec, ...]
    """Graph outputs (by name)."""
    diffusion: bool
    """True for EDM denoisers: the model maps (x_t, sigma, conditioning) to the denoised estimate
    D(x_t; sigma) with the EDM preconditioning inside the graph, and the sigma metadata is
    required."""
    doc: str = ""
    """What the model does."""

    @property
    def version_str(self) -> str:
        return f"{self.version[0]}.{self.version[1]}"

    def input(self, name: str) -> TensorSpec:
        for s in self.inputs:
            if s.name == name:
                return s
        raise ConfigError(f"contract {self.kind}: no input named {name!r}")

    def describe(self) -> dict:
        """JSON-ready description (used in model cards)."""
        def spec(s: TensorSpec) -> dict:
            return {"name": s.name, "shape": list(s.dims), "dtype": s.dtype, "doc": s.doc}

        return {"contract": self.kind, "version": self.version_str,
                "inputs": [spec(s) for s in self.inputs], "outputs": [spec(s) for s in self.outputs]}


_GB = "B", "F"

FORWARD_DENOISER = Contract(
    kind="forward_denoiser",
    version=(1, 0),
    diffusion=True,
    doc="Generative rendering pass: EDM denoiser of an LDR clip conditioned on G-buffers and the "
        "environment map; sampled by SDEdit from the PBR render (paper Eq. 5).",
    inputs=(
        TensorSpec("x_t", (*_GB, 3, "H", "W"), doc="noisy LDR frames in the LDR data space "
                   "(2 ldr - 1, [-1, 1]) plus Gaussian noise of std sigma"),
        TensorSpec("sigma", ("B",), doc="EDM noise level of each clip (data units), > 0"),
        TensorSpec("normal", (*_GB, 3, "H", "W"), doc="unit normals, camera frame (OpenCV), 0 on sky"),
        TensorSpec("depth", (*_GB, 1, "H", "W"), doc="exp(-z / 20 m), camera z-depth; 0 on sky"),
        TensorSpec("albedo", (*_GB, 3, "H", "W"), doc="base colour, [0, 1]"),
        TensorSpec("roughness", (*_GB, 1, "H", "W"), doc="[0, 1]"),
        TensorSpec("metallic", (*_GB, 1, "H", "W"), doc="[0, 1]"),
        TensorSpec("env_ldr", (*_GB, 3, ENV_H, ENV_W), doc="Reinhard E/(1+E) of the 64x128 "
                   "area-averaged HDR map, world equirect, [0, 1)"),
        TensorSpec("env_log", (*_GB, 3, ENV_H, ENV_W), doc="log1p(E)/log1p(1e4), [0, ~1.2]"),
        TensorSpec("env_dir", (*_GB, 3, ENV_H, ENV_W), doc="camera-frame unit direction of each "
                   "env pixel centre"),
    ),
    outputs=(TensorSpec("x0", (*_GB, 3, "H", "W"), doc="denoised estimate D(x_t; sigma), LDR "
                        "data space"),),
)

INVERSE_GBUFFER = Contract(
    kind="inverse_gbuffer",
    version=(1, 1),
    diffusion=True,
    doc="G-buffer prior: EDM denoiser of the 9 G-buffer channels conditioned on the RGB clip; "
        "sampled from noise (prior) or by SDEdit from rendered intrinsics (generative refinement).",
    inputs=(
        TensorSpec("x_t", (*_GB, GBUFFER_CHANNELS, "H", "W"), doc="noisy G-buffer, G-buffer data "
                   "space (albedo 3, roughness, metallic, normal 3, depth; [-1, 1]) + noise"),
        TensorSpec("sigma", ("B",), doc="EDM noise level, > 0"),
        TensorSpec("rgb", (*_GB, 3, "H", "W"), doc="input LDR frames, LDR data space [-1, 1]"),
        TensorSpec("view", (*_GB, VIEW_CHANNELS, "H", "W"), optional=True,
                   doc="the capture's camera (since 1.1, optional): unit ray direction of each pixel "
                       "and the world up (+z) direction, both in the camera frame (OpenCV axes; "
                       "core.gen.encoding.view_conditioning)"),
    ),
    outputs=(TensorSpec("x0", (*_GB, GBUFFER_CHANNELS, "H", "W"), doc="denoised G-buffer "
                        "estimate, G-buffer data space"),),
)

LIGHTING = Contract(
    kind="lighting",
    version=(1, 0),
    diffusion=False,
    doc="Lighting prior E_g (paper Eq. 6): frames + per-pixel world ray directions + sky masks -> "
        "a low-frequency sky and a sun; composed into a 512x1024 HDR map by "
        "core.lighting.prior.compose_envmap.",
    inputs=(
        TensorSpec("rgb", (*_GB, 3, "H", "W"), doc="LDR frames, LDR data space [-1, 1]"),
        TensorSpec("ray_dir", (*_GB, 3, "H", "W"), doc="unit world direction of each pixel's ray "
                   "(core.conventions.camera_ray_directions)"),
        TensorSpec("sky_mask", (*_GB, 1, "H", "W"), doc="1 = sky, 0 = not sky"),
    ),
    outputs=(
        TensorSpec("sky_log", ("B", 3, LIGHT_SKY_H, LIGHT_SKY_W), doc="log1p of the sky radiance "
                   "without the sun, world equirect (project convention)"),
        TensorSpec("sun_dir", ("B", 3), doc="unit world direction towards the sun"),
        TensorSpec("sun_log", ("B", 3), doc="log1p of the sun disc radiance (disc of radius "
                   "core.lighting.prior.SUN_RADIUS_DEG)"),
    ),
)

CONTRACTS: dict[str, Contract] = {c.kind: c for c in (FORWARD_DENOISER, INVERSE_GBUFFER, LIGHTING)}


def get_contract(kind: str) -> Contract:
    """The contract named ``kind``; :class:`ConfigError` listing the known ones otherwise."""
    if kind not in CONTRACTS:
        raise ConfigError(f"model kind: unknown contract {kind!r} (known: {sorted(CONTRACTS)})")
    return CONTRACTS[kind]


def parse_version(text: str) -> tuple[int, int]:
    """``"1.0"`` -> (1, 0); :class:`ValueError` for anything else."""
    parts = str(text).strip().split(".")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise ValueError(f"not a 'major.minor' version: {text!r}")
    return int(parts[0]), int(parts[1])
