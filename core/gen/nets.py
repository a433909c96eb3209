"""Small conditional U-Nets for the forward (rendering) and inverse (G-buffer) EDM denoisers.

Why pixel space and not a learned autoencoder (decided for 2 CPU cores):
    * A latent model needs an autoencoder trained first (a second training run on these cores)
      and its reconstruction error is a ceiling on the forward pass's PSNR gain (the issue asks
      for >= 2 dB over the PBR render): a 4x-8x compressing AE small enough for CPU inference loses
      exactly the fine texture the denoiser must keep.
    * The compute saving of a latent space is had here by a space-to-depth stem: the first layer
      is ``pixel_unshuffle(2)`` (each 2x2 block becomes 4x the channels), the U-Net runs at
      H/2 x W/2 and below, and the head is ``pixel_shuffle(2)``. It is lossless (an exact
      rearrangement) and costs nothing to train.

Architecture (:class:`ConditionalUNet`), input [N, C_in, H, W] (N = B * F frames), H and W
multiples of :data:`SPATIAL_MULTIPLE` (8):
    stem      pixel_unshuffle(2), conv3x3 -> c0                               at H/2
    encoder   per level l: ``blocks`` residual blocks (FiLM by the embedding), stride-2 conv
              to the next level's width;                                     H/2, H/4, H/8
    middle    residual block, temporal mixing (the mean over the window's F frames, 1x1 conv,
              added back: the frames of a window see each other; works for any F, also 1),
              residual block
    decoder   nearest up-sampling, conv3x3, concatenation with the skip, residual blocks
    head      conv3x3 -> 4 C_out, pixel_shuffle(2)                            at H
    embedding sinusoidal features of c_noise -> MLP (emb_dim); for the forward model plus the
              global environment code (a 3-conv stride-2 encoder of the 9-channel 64x128 env
              encoding, mean-pooled, linear)
Residual blocks: ``x + conv(silu(film(conv(silu(x)))))`` with the second conv zero-initialised
(each block starts as the identity: stable training without normalisation layers, which also
keeps the ONNX graph to Conv/Mul/Add/Sigmoid).

EDM preconditioning (Karras et al. 2022, :mod:`core.gen.edm`) is part of the exported graph:
:class:`ForwardDenoiserModel` and :class:`InverseGBufferModel` take the contract's named inputs
(:mod:`core.gen.contract`) and return ``D(x_t; sigma) = c_skip x_t + c_out F(c_in x_t, c_noise)``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.errors import ConfigError, ShapeError
from core.gen import contract as C
from core.io.atomic import atomic_output

#: Total down-sampling of the U-Net (stem 2 x two stride-2 levels): H and W must be multiples.
SPATIAL_MULTIPLE = 8
#: ONNX opset of the exported files (onnxruntime 1.31 supports up to 23; 17 is what the legacy
#: TorchScript exporter of torch 2.13 covers completely).
ONNX_OPSET = 17


@dataclass(frozen=True)
class UNetSettings:
    """Width and depth of a :class:`ConditionalUNet`."""

    base_channels: int = 32
    """Channels at the first level (H/2 x W/2)."""
    channel_mult: tuple[int, ...] = (1, 2, 3)
    """Width multiplier per level; the number of levels (3) fixes the down-sampling to 8."""
    blocks: int = 1
    """Residual blocks per level in the encoder and in the decoder."""
    emb_dim: int = 128
    """Width of the noise (+ environment) embedding that modulates every block (FiLM)."""
    env_channels: int = 32
    """Width of the environment encoder (forward model only)."""
    temporal_mix: bool = True
    """Mix the frames of a window at the bottleneck (mean over F, 1x1 conv, add)."""
    mid_blocks: int = 0
    """Extra residual blocks at the bottleneck (H/8), after the second middle block: each 3x3
    convolution there widens the receptive field by 16 input pixels for little compute. 0 = the
    network of every model up to 2026-12-05 (same parameter names: their weights load into a
    network with more blocks, whose extra blocks start as the identity)."""

    def __post_init__(self) -> None:
        if (self.base_channels < 4 or self.blocks < 1 or self.emb_dim < 8 or self.env_channels < 4
                or not isinstance(self.mid_blocks, int) or self.mid_blocks < 0):
            raise ConfigError(f"UNetSettings: out of range: {self}")
        if len(self.channel_mult) != 3 or min(self.channel_mult) < 1:
            raise ConfigError(f"UNetSettings.channel_mult: need 3 levels >= 1, got {self.channel_mult}")


class _ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, emb_dim: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.film = nn.Linear(emb_dim, 2 * cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(x))
        scale, shift = self.film(emb)[:, :, None, None].chunk(2, dim=1)
        h = h * (1.0 + scale) + shift
        h = self.conv2(F.silu(h))
        return self.skip(x) + h


class _EnvEncoder(nn.Module):
    """[N, 9, 64, 128] env encoding -> [N, emb_dim] (three stride-2 convs, mean pool)."""

    def __init__(self, cin: int, width: int, emb_dim: int):
        super().__init__()
        self.c1 = nn.Conv2d(cin, width // 2, 3, stride=2, padding=1)
        self.c2 = nn.Conv2d(width // 2, width, 3, stride=2, padding=1)
        self.c3 = nn.Conv2d(width, 2 * width, 3, stride=2, padding=1)
        self.out = nn.Linear(2 * width, emb_dim)

    def forward(self, env: torch.Tensor) -> torch.Tensor:
        h = F.silu(self.c1(env))
        h = F.silu(self.c2(h))
        h = F.silu(self.c3(h))
        return self.out(h.mean(dim=(2, 3)))


class ConditionalUNet(nn.Module):
    """The raw network F of EDM: [N, x_ch + cond_ch, H, W] (+ c_noise [N], env [N, 9, h, w])
    -> [N, out_ch, H, W]. ``frames`` tells the temporal mixing how many consecutive items of N
    form one window (N = B * F, frames of a window adjacent)."""

    def __init__(self, x_channels: int, cond_channels: int, out_channels: int,
                 settings: UNetSettings | None = None, env_in_channels: int = 0):
        super().__init__()
        s = settings or UNetSettings()
        self.settings = s
        self.x_channels, self.cond_channels, self.out_channels = x_channels, cond_channels, out_channels
        self.env_in_channels = env_in_channels
        widths = [s.base_channels * m for m in s.channel_mult]
        cin = 4 * (x_channels + cond_channels)
        self.stem = nn.Conv2d(cin, widths[0], 3, padding=1)
        half = s.emb_dim // 2
        self.register_buffer("freqs", torch.exp(-math.log(1e4) * torch.arange(half) / half) * 100.0,
                             persistent=False)
        self.emb_mlp = nn.Sequential(nn.Linear(2 * half, s.emb_dim), nn.SiLU(), nn.Linear(s.emb_dim, s.emb_dim))
        self.env = _EnvEncoder(env_in_channels, s.env_channels, s.emb_dim) if env_in_channels else None
        self.enc = nn.ModuleList()
        self.down = nn.ModuleList()
        for li, w in enumerate(widths):
            self.enc.append(nn.ModuleList([_ResBlock(w, w, s.emb_dim) for _ in range(s.blocks)]))
            if li + 1 < len(widths):
                self.down.append(nn.Conv2d(w, widths[li + 1], 3, stride=2, padding=1))
        wb = widths[-1]
        self.mid1 = _ResBlock(wb, wb, s.emb_dim)
        self.tmix = nn.Conv2d(wb, wb, 1) if s.temporal_mix else None
        if self.tmix is not None:
            nn.init.zeros_(self.tmix.weight)
            nn.init.zeros_(self.tmix.bias)
        self.mid2 = _ResBlock(wb, wb, s.emb_dim)
        # only created when used, so that a mid_blocks = 0 network keeps its exported names
        if s.mid_blocks:
            self.mid_extra = nn.ModuleList([_ResBlock(wb, wb, s.emb_dim) for _ in range(s.mid_blocks)])
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for li in range(len(widths) - 2, -1, -1):
            self.up.append(nn.Conv2d(widths[li + 1], widths[li], 3, padding=1))
            blocks = [_ResBlock(2 * widths[li], widths[li], s.emb_dim)]
            blocks += [_ResBlock(widths[li], widths[li], s.emb_dim) for _ in range(s.blocks - 1)]
            self.dec.append(nn.ModuleList(blocks))
        self.head = nn.Conv2d(widths[0], 4 * out_channels, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor, c_noise: torch.Tensor, frames: torch.Tensor | int,
                env: torch.Tensor | None = None) -> torch.Tensor:
        """x: [N, x_ch + cond_ch, H, W]; c_noise: [N]; env: [N, env_in, h, w] or None.
        ``frames``: F (an int, or a 0-d tensor in traced graphs). Returns [N, out_ch, H, W]."""
        f = c_noise[:, None] * self.freqs[None, :]
        emb = self.emb_mlp(torch.cat([torch.cos(f), torch.sin(f)], dim=1))
        if self.env is not None:
            if env is None:
                raise ShapeError("env: this network needs the environment encoding")
            emb = emb + self.env(env)
        emb = F.silu(emb)
        h = self.stem(F.pixel_unshuffle(x, 2))
        skips = []
        for li, blocks in enumerate(self.enc):
            for b in blocks:
                h = b(h, emb)
            if li < len(self.down):
                skips.append(h)
                h = self.down[li](F.silu(h))
        h = self.mid1(h, emb)
        if self.tmix is not None:
            n, c, hh, ww = h.shape
            hv = h.reshape(-1, frames, c, hh, ww)
            m = hv.mean(dim=1)
            h = (hv + self.tmix(m)[:, None]).reshape(n, c, hh, ww)
        h = self.mid2(h, emb)
        for b in getattr(self, "mid_extra", ()):
            h = b(h, emb)
        for up, blocks in zip(self.up, self.dec):
            skip = skips.pop()
            h = up(F.interpolate(F.silu(h), scale_factor=2.0, mode="nearest"))
            h = torch.cat([h, skip], dim=1)
            for b in blocks:
                h = b(h, emb)
        return F.pixel_shuffle(self.head(F.silu(h)), 2)


def edm_coefficients(sigma: torch.Tensor, sigma_data: float):
    """EDM preconditioning (Karras et al. 2022, Table 1): (c_skip, c_out, c_in, c_noise) for
    noise levels ``sigma`` (any shape, > 0)."""
    sd2 = sigma_data * sigma_data
    s2 = sigma * sigma
    c_skip = sd2 / (s2 + sd2)
    c_out = sigma * sigma_data / torch.sqrt(s2 + sd2)
    c_in = 1.0 / torch.sqrt(s2 + sd2)
    c_noise = torch.log(sigma) / 4.0
    return c_skip, c_out, c_in, c_noise


class _EDMModel(nn.Module):
    """Shared body: preconditioning around a :class:`ConditionalUNet` on [B, F, C, H, W] clips."""

    kind = ""

    def __init__(self, net: ConditionalUNet, sigma_data: float = 0.5, frames: int = 1):
        super().__init__()
        self.net = net
        self.sigma_data = float(sigma_data)
        self.frames = int(frames)

    def _denoise(self, x_t: torch.Tensor, sigma: torch.Tensor, cond: torch.Tensor,
                 env: torch.Tensor | None) -> torch.Tensor:
        b, f, c, h, w = x_t.shape
        s = sigma.reshape(-1, 1, 1, 1, 1)
        c_skip, c_out, c_in, c_noise = edm_coefficients(s, self.sigma_data)
        inp = torch.cat([x_t * c_in, cond], dim=2).reshape(b * f, -1, h, w)
        cn = c_noise.reshape(-1, 1).expand(b, f).reshape(-1)
        env_n = None if env is None else env.reshape(b * f, env.shape[2], env.shape[3], env.shape[4])
        out = self.net(inp, cn, f, env_n).reshape(b, f, -1, h, w)
        return c_skip * x_t + c_out * out

    def settings_dict(self) -> dict:
        return {"unet": asdict(self.net.settings), "sigma_data": self.sigma_data, "frames": self.frames}


class ForwardDenoiserModel(_EDMModel):
    """``forward_denoiser`` contract (:data:`core.gen.contract.FORWARD_DENOISER`): named inputs in
    the contract's order -> ``x0`` [B, F, 3, H, W] (LDR data space)."""

    kind = "forward_denoiser"

    def __init__(self, settings: UNetSettings | None = None, sigma_data: float = 0.5, frames: int = 1):
        super().__init__(ConditionalUNet(3, 3 + 1 + 3 + 1 + 1, 3, settings, env_in_channels=9),
                         sigma_data, frames)

    def forward(self, x_t, sigma, normal, depth, albedo, roughness, metallic, env_ldr, env_log, env_dir):
        cond = torch.cat([normal, depth, albedo, roughness, metallic], dim=2)
        env = torch.cat([env_ldr, env_log, env_dir], dim=2)
        return self._denoise(x_t, sigma, cond, env)


class InverseGBufferModel(_EDMModel):
    """``inverse_gbuffer`` contract: (x_t [B, F, 9, H, W], sigma [B], rgb [B, F, 3, H, W]
    [, view [B, F, 6, H, W]]) -> ``x0`` [B, F, 9, H, W] (G-buffer data space). ``view=True``
    builds the network that also takes the contract's optional camera input."""

    kind = "inverse_gbuffer"

    def __init__(self, settings: UNetSettings | None = None, sigma_data: float = 0.5, frames: int = 1,
                 view: bool = False):
        cond = 3 + (C.VIEW_CHANNELS if view else 0)
        super().__init__(ConditionalUNet(C.GBUFFER_CHANNELS, cond, C.GBUFFER_CHANNELS, settings), sigma_data, frames)
        self.view = bool(view)

    def forward(self, x_t, sigma, rgb, view=None):
        """A ``view`` given to a network built without it is ignored, as the runtime does for a
        file without the optional input."""
        if not self.view:
            return self._denoise(x_t, sigma, rgb, None)
        if view is None:
            raise ShapeError("view: this network was built with the camera input; give view [B, F, 6, H, W]")
        return self._denoise(x_t, sigma, torch.cat([rgb, view], dim=2), None)

    def settings_dict(self) -> dict:
        return {**super().settings_dict(), "view": self.view}


MODEL_CLASSES = {"forward_denoiser": ForwardDenoiserModel, "inverse_gbuffer": InverseGBufferModel}


def build_model(kind: str, settings: UNetSettings | None = None, sigma_data: float = 0.5,
                frames: int = 1, view: bool = False) -> _EDMModel:
    """A fresh (random-weight) model of contract ``kind`` (``view``: the inverse model's optional
    camera input)."""
    if kind not in MODEL_CLASSES:
        raise ConfigError(f"kind: no network for {kind!r} (networks exist for {sorted(MODEL_CLASSES)})")
    if view and kind != "inverse_gbuffer":
        raise ConfigError(f"view: only the inverse_gbuffer network takes the camera input, not {kind!r}")
    return MODEL_CLASSES[kind](settings, sigma_data, frames, **({"view": True} if view else {}))


def model_input_names(model: _EDMModel) -> list[str]:
    """The contract inputs this network takes, in contract order (optional ones it was built
    without left out)."""
    con = C.get_contract(model.kind)
    return [s.name for s in con.inputs if not s.optional or getattr(model, s.name, False)]


def example_inputs(kind: str, batch: int = 1, frames: int = 1, height: int = 32, width: int = 48,
                   seed: int = 0) -> dict[str, torch.Tensor]:
    """Random inputs of a contract (for export, parity and speed tests): values in each input's
    documented range (sigma log-uniform in [0.01, 10], unit normals and directions)."""
    con = C.get_contract(kind)
    g = torch.Generator().manual_seed(seed)
    dims = {"B": batch, "F": frames, "H": height, "W": width}
    out = {}
    for spec in con.inputs:
        shape = tuple(dims[d] if isinstance(d, str) else d for d in spec.dims)
        if spec.name == "sigma":
            t = torch.exp(torch.empty(shape).uniform_(math.log(0.01), math.log(10.0), generator=g))
        elif spec.name in ("normal", "env_dir", "ray_dir"):
            t = torch.randn(shape, generator=g)
            t = t / t.norm(dim=-3, keepdim=True).clamp_min(1e-6)
        elif spec.name == "view":  # two unit directions (ray, up)
            t = torch.randn(shape, generator=g).unflatten(-3, (2, 3))
            t = (t / t.norm(dim=-3, keepdim=True).clamp_min(1e-6)).flatten(-4, -3)
        elif spec.name in ("x_t", "rgb"):
            t = torch.randn(shape, generator=g)
        else:
            t = torch.rand(shape, generator=g)
        out[spec.name] = t.float()
    return out


def export_onnx(model: _EDMModel, path: str | Path, *, extra_metadata: dict[str, str] | None = None,
                sigma_min: float = 0.002, sigma_max: float = 80.0, example_hw: tuple[int, int] = (32, 48)) -> Path:
    """Export ``model`` to ONNX (opset :data:`ONNX_OPSET`) with dynamic B, F, H, W and write the
    contract metadata (:mod:`core.gen.contract`). The file is written atomically. Returns the path."""
    import onnx

    con = C.get_contract(model.kind)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ex = example_inputs(model.kind, 1, model.frames, *example_hw)
    names = model_input_names(model)
    dyn: dict[str, dict[int, str]] = {}
    for spec in (*[s for s in con.inputs if s.name in names], *con.outputs):
        dyn[spec.name] = {i: d for i, d in enumerate(spec.dims) if isinstance(d, str)}
    model = model.eval()
    with atomic_output(path, suffix=".onnx") as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with torch.no_grad():
                torch.onnx.export(model, tuple(ex[n] for n in names), tmp, dynamo=False,
                                  input_names=names, output_names=[s.name for s in con.outputs],
                                  dynamic_axes=dyn, opset_version=ONNX_OPSET, do_constant_folding=True)
        m = onnx.load(tmp)
        meta = {C.META_CONTRACT: con.kind, C.META_VERSION: con.version_str, C.META_FRAMES: str(model.frames),
                C.META_MULTIPLE: str(SPATIAL_MULTIPLE), C.META_SIGMA_DATA: repr(model.sigma_data),
                C.META_SIGMA_MIN: repr(float(sigma_min)), C.META_SIGMA_MAX: repr(float(sigma_max))}
        meta.update(extra_metadata or {})
        onnx.helper.set_model_props(m, meta)
        onnx.save(m, tmp)
    return path


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
