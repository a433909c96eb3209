"""Training of the forward and inverse EDM denoisers on CPU, with checkpoints, ONNX export and a
model card (reproducible training, models/README.md). Trains on generated bundles' ground truth
(:mod:`core.synth.gen_data`); the inference side is :mod:`core.gen`.

    res = train_model("forward_denoiser", ["scenes/s1", "scenes/s2"], "runs/fwd", steps=20000,
                      settings=TrainSettings(data=DataSettings(forward_source="pbr",
                                                               held_out_seeds=(7,))))
    res.onnx_path, res.card_path, res.losses

Loss (EDM, Karras et al. 2022): ln sigma ~ N(p_mean, p_std^2), x_t = x_0 + sigma eps,
weight lambda(sigma) = (sigma^2 + sd^2) / (sigma sd)^2, loss = mean lambda |D(x_t; sigma) - x_0|^2.
Forward model, *paired* samples (a fraction ``paired_fraction`` of each batch): x_t is built from
the PBR input instead, x_t = x_in + sigma eps, with the ground truth as target: the denoiser
learns to move a noised PBR render to the path-traced truth, which is exactly what SDEdit asks
of it at inference (the other samples keep it a proper denoiser of clean data).

Checkpoints: ``<out_dir>/checkpoint.pt`` (model, EMA, optimiser, step, losses, RNG states) every
``checkpoint_every`` steps and at the end, written atomically; :func:`train_model` resumes from it
when the settings match (a crashed or stopped run continues). The exported model is the EMA
(``ema_decay`` > 0) or the raw weights.

Export: ``<out_dir>/<kind>.onnx`` (:func:`core.gen.nets.export_onnx`) + ``<kind>.card.json``
(:func:`write_model_card`): contract, inputs, network, data, steps, wall time, metrics.
"""

from __future__ import annotations

import copy
import datetime as _dt
import hashlib
import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from core.errors import ConfigError, ModelLoadError, NumericalError
from core.gen import contract as C
from core.gen.edm import GENERATE_SAMPLER, OnnxDenoiser, SamplerSettings, flicker, sdedit
from core.gen.gbuffer_ensemble import EnsembleSettings, generate_gbuffer
from core.gen.nets import UNetSettings, build_model, count_parameters, export_onnx
from core.gen.runtime import load_model
from core.io.atomic import atomic_output
from core.metrics import angular_error_deg, psnr, si_psnr
from core.synth.gen_data import ClipDataset, DataSettings, load_clips, split_bundles


@dataclass(frozen=True)
class TrainSettings:
    """Optimisation settings of :func:`train_model`."""

    batch: int = 4
    """Windows per step."""
    crop: int = 64
    """Square crop size in pixels (multiple of 8)."""
    frames: int = 1
    """Frames per window F (the model's ``brdf.frames``)."""
    lr: float = 2e-4
    """Adam learning rate (constant after a linear warm-up of ``warmup`` steps)."""
    warmup: int = 100
    """Warm-up steps."""
    grad_clip: float = 1.0
    """Gradient norm clip."""
    ema_decay: float = 0.999
    """EMA of the weights that is exported (0 = export the raw weights)."""
    p_mean: float = -1.2
    """Mean of ln sigma during training (EDM: -1.2)."""
    p_std: float = 1.2
    """Std of ln sigma (EDM: 1.2)."""
    sigma_data: float = 0.5
    """EDM sigma_data of the data spaces ([-1, 1])."""
    sigma_min: float = 0.002
    """Smallest noise level written to the model metadata (sampling range)."""
    sigma_max: float = 80.0
    """Largest noise level written to the model metadata."""
    paired_fraction: float = 0.5
    """Forward model: fraction of samples noised from the PBR input (see module docstring)."""
    paired_sigma_min: float = 0.2
    """Forward model: a paired sample's noise level is at least this. Below it the PBR input's own
    error (not the noise) separates it from the target, a correction the EDM skip connection
    leaves to a network output scaled by ~sigma, so the loss (weighted ~1/sigma^2) would be
    dominated by samples SDEdit never sees: its late steps start from the model's own estimate.
    Measured on the first run (0 = no floor): the loss stayed at ~43 after 700 steps."""
    checkpoint_every: int = 200
    """Steps between checkpoints."""
    seed: int = 0
    """Seed of initialisation, batches and noise."""
    threads: int = 2
    """torch intra-op threads during training (restored afterwards)."""
    unet: UNetSettings = field(default_factory=UNetSettings)
    """Network width/depth."""
    init_from: str | None = None
    """An exported ONNX model of the same contract and network whose weights start the training
    (fine-tuning; the training data, held-out split and data recipe are the caller's to record).
    The network may also be the file's grown by whole residual blocks (``unet.blocks``,
    ``unet.mid_blocks``): they start as the identity (:func:`load_onnx_weights` ``grow``).
    Ignored when a checkpoint is resumed."""
    data: DataSettings = field(default_factory=DataSettings)
    """How bundles become tensors (forward source, held-out seeds/rotations)."""
    rare_fraction: float = 0.0
    """Inverse model only: fraction of a batch's windows drawn as the rarest-material crop of
    ``rare_candidates`` random ones (:class:`core.synth.gen_data.ClipDataset`); 0 = uniform crops
    (every run before 2026-12-05)."""
    rare_candidates: int = 4
    """Random windows a rare-material draw chooses from (>= 2)."""
    rare_loss_max: float = 0.0
    """Inverse model only: weigh each pixel's loss by its material's weight
    (:func:`core.synth.gen_data.rarity_table`) clipped to ``[1 / rare_loss_max, rare_loss_max]``
    (sky 1); 0 = unweighted (every run before 2026-12-05)."""
    view: bool = False
    """Inverse model only: also condition on the capture's camera (the contract's optional
    ``view`` input: per-pixel ray and world up, camera frame). With ``init_from`` a model made
    without it, the new input's stem weights start at zero (the start model's outputs exactly)."""

    def __post_init__(self) -> None:
        if self.batch < 1 or self.crop < 8 or self.crop % 8 or self.frames < 1:
            raise ConfigError(f"batch/crop/frames out of range: {self.batch}, {self.crop}, {self.frames}")
        if not (self.lr > 0 and 0 <= self.ema_decay < 1 and 0 <= self.paired_fraction <= 1
                and 0 <= self.paired_sigma_min < self.sigma_max):
            raise ConfigError(f"lr/ema_decay/paired_fraction out of range: {self.lr}, {self.ema_decay}, "
                              f"{self.paired_fraction}")
        if self.checkpoint_every < 1 or self.threads < 1:
            raise ConfigError("checkpoint_every and threads must be >= 1")
        if self.rare_loss_max != 0 and not self.rare_loss_max >= 1:
            raise ConfigError(f"rare_loss_max: must be 0 (off) or >= 1, got {self.rare_loss_max!r}")
        if not 0.0 <= self.rare_fraction <= 1.0 or self.rare_candidates < 2:
            raise ConfigError(f"rare_fraction / rare_candidates: need [0, 1] / >= 2, got "
                              f"{self.rare_fraction!r} / {self.rare_candidates!r}")
        if not isinstance(self.view, bool):
            raise ConfigError(f"view: must be a bool, got {self.view!r}")


@dataclass
class TrainResult:
    """What :func:`train_model` produced."""

    kind: str
    """Contract of the trained model."""
    steps: int
    """Total optimisation steps done (including resumed ones)."""
    losses: list[float]
    """Loss of every step, in order (across resumes)."""
    wall_s: float
    """Wall time of this call, seconds."""
    checkpoint: Path
    """The checkpoint file."""
    onnx_path: Path | None
    """Exported model (None when ``export=False``)."""
    card_path: Path | None
    """Model card JSON (None when ``export=False``)."""
    metrics: dict = field(default_factory=dict)
    """Held-out metrics (when held-out bundles were given and ``evaluate=True``)."""


def edm_weight(sigma: torch.Tensor, sigma_data: float) -> torch.Tensor:
    """EDM loss weight lambda(sigma) = (sigma^2 + sd^2) / (sigma sd)^2."""
    return (sigma ** 2 + sigma_data ** 2) / (sigma * sigma_data) ** 2


def edm_loss(model, batch: dict[str, torch.Tensor], s: TrainSettings, gen: torch.Generator) -> torch.Tensor:
    """The weighted EDM loss of one batch (module docstring)."""
    x0 = batch["x0"]
    b = x0.shape[0]
    sigma = torch.exp(s.p_mean + s.p_std * torch.randn(b, generator=gen))
    noise = torch.randn(x0.shape, generator=gen)
    base = x0
    if model.kind == "forward_denoiser" and s.paired_fraction > 0:
        pf = (torch.rand(b, generator=gen) < s.paired_fraction).float()
        sigma = torch.where(pf > 0, sigma.clamp_min(s.paired_sigma_min), sigma)
        paired = pf.reshape(b, 1, 1, 1, 1)
        base = paired * batch["x_in"] + (1 - paired) * x0
    x_t = base + sigma.reshape(b, 1, 1, 1, 1) * noise
    if model.kind == "forward_denoiser":
        cond = {k: batch[k] for k in ("normal", "depth", "albedo", "roughness", "metallic",
                                      "env_ldr", "env_log", "env_dir")}
    else:
        cond = {"rgb": batch["rgb"]}
        if getattr(model, "view", False):
            cond["view"] = batch["view"]
    d = model(x_t=x_t, sigma=sigma, **cond)
    w = edm_weight(sigma, s.sigma_data).reshape(b, 1, 1, 1, 1)
    if "pixel_weight" in batch:  # [B, F, 1, H, W], rare materials weigh more (TrainSettings.rare_loss_max)
        w = w * batch["pixel_weight"]
    return (w * (d - x0) ** 2).mean()


def _atomic_save(obj, path: Path) -> None:
    with atomic_output(path) as tmp:
        torch.save(obj, tmp)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_model_card(onnx_path: str | Path, kind: str, *, network: dict, training: dict,
                     metrics: dict | None = None) -> Path:
    """Write ``<stem>.card.json`` next to ``onnx_path`` and return its path. Fields: contract
    (name, version, inputs/outputs with shapes and dtypes), file (name, bytes, sha256), network,
    training (data, held-out seeds, steps, wall time, machine), metrics, created (UTC)."""
    p = Path(onnx_path)
    con = C.get_contract(kind)
    card = {
        **con.describe(),
        "file": {"name": p.name, "bytes": p.stat().st_size, "sha256": _sha256(p)},
        "network": network,
        "training": training,
        "metrics": metrics or {},
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__},
    }
    out = p.with_name(p.stem + ".card.json")

    text = json.dumps(card, indent=2, default=str)
    with atomic_output(out) as tmp:
        Path(tmp).write_text(text)
    return out


def _config_key(kind: str, s: TrainSettings) -> str:
    key = {"kind": kind, "unet": asdict(s.unet), "frames": s.frames, "sigma_data": s.sigma_data}
    if s.view:
        key["view"] = True  # absent when False: checkpoints made before the field still resume
    return json.dumps(key, sort_keys=True)


def _new_identity_blocks(model: torch.nn.Module, present: set[str]) -> set[str]:
    """Module paths of the residual blocks of ``model`` none of whose weights are in ``present``:
    blocks a grown network has and the file's network had not (:func:`load_onnx_weights`)."""
    from core.gen.nets import _ResBlock

    out = set()
    for name, mod in model.named_modules():
        if isinstance(mod, _ResBlock) and not any(f"{name}.{k}" in present for k in mod.state_dict()):
            if bool(mod.conv2.weight.any()) or bool(mod.conv2.bias.any()):
                raise ModelLoadError(f"model: residual block {name!r} is not in the file and is not the identity "
                                     "(its second convolution is not zero): grow only a freshly built network")
            out.add(name)
    return out


def _onnx_initializers(onnx_path: str | Path) -> dict:
    """The initializers of an exported ONNX model by name (they carry the state-dict names);
    ModelLoadError naming the file when it cannot be read."""
    import onnx

    try:
        return {i.name: i for i in onnx.load(str(onnx_path)).graph.initializer}
    except Exception as e:  # noqa: BLE001 - any parse failure is a load error of that file
        raise ModelLoadError(f"{onnx_path}: cannot read the ONNX model: {e}") from None


def onnx_unet_depth(onnx_path: str | Path) -> tuple[int, int]:
    """``(blocks, mid_blocks)`` (``core.gen.nets.UNetSettings``) of the network an exported ONNX
    model was built with, read off its initializer names (``net.enc.<level>.<block>.*``,
    ``net.mid_extra.<i>.*``): the depth to build before :func:`load_onnx_weights`.
    ModelLoadError naming the file when it cannot be read or has no encoder blocks."""
    names = list(_onnx_initializers(onnx_path))
    enc = {int(n.split(".")[3]) for n in names if n.startswith("net.enc.") and n.count(".") >= 4}
    mid = {int(n.split(".")[2]) for n in names if n.startswith("net.mid_extra.") and n.count(".") >= 3}
    if not enc:
        raise ModelLoadError(f"{onnx_path}: no encoder blocks (net.enc.*): not a core.gen.nets U-Net")
    return max(enc) + 1, len(mid)


def load_onnx_weights(model: torch.nn.Module, onnx_path: str | Path, *, grow: bool = False) -> None:
    """Copy the weights of an exported ONNX model into ``model`` (its initializers carry the
    state-dict names); ModelLoadError naming the file when it cannot be read or a tensor is
    missing or of another shape. One widening is allowed: a stem convolution with more input
    channels than the file's (a network built with more conditioning channels appended, e.g. the
    inverse model's ``view``) gets the file's weights for the first channels and zeros for the
    rest, so it computes exactly what the file's model did.

    ``grow``: ``model`` may also have whole residual blocks the file has not (more ``blocks`` per
    level, or ``mid_blocks``); they keep their initialisation, the identity (their second
    convolution is zero), so the grown network computes exactly what the file's model did. Any
    other missing weight is still an error, and so is a weight of the file the network has no
    place for (never silently dropped)."""
    from onnx import numpy_helper

    init = _onnx_initializers(onnx_path)
    sd = model.state_dict()
    new_blocks = _new_identity_blocks(model, set(init)) if grow else set()
    new = {}
    for k, v in sd.items():
        if k not in init and any(k.startswith(f"{b}.") for b in new_blocks):
            new[k] = v  # a grown block's own (identity) initialisation
            continue
        if k not in init:
            raise ModelLoadError(f"{onnx_path}: no weight {k!r} (another network?)")
        a = torch.from_numpy(numpy_helper.to_array(init[k]).copy())
        if (k == "net.stem.weight" and a.ndim == 4 and a.shape[0] == v.shape[0] and a.shape[1] < v.shape[1]
                and a.shape[2:] == v.shape[2:]):
            # pixel_unshuffle keeps channel blocks in order: appended inputs are the last channels
            a = torch.cat([a, torch.zeros(v.shape[0], v.shape[1] - a.shape[1], *v.shape[2:], dtype=a.dtype)], 1)
        if tuple(a.shape) != tuple(v.shape):
            raise ModelLoadError(f"{onnx_path}: weight {k!r} has shape {tuple(a.shape)}, the network "
                                 f"{tuple(v.shape)}")
        new[k] = a.to(v.dtype)
    # the other direction: a weight of the file the network has no place for (a smaller network
    # than the file's would otherwise silently drop whole blocks)
    prefixes = {k.split(".", 1)[0] + "." for k in sd}
    unused = sorted(n for n in init if n not in sd and n.startswith(tuple(prefixes)))
    if unused:
        raise ModelLoadError(f"{onnx_path}: the network has no place for the file's weight(s) "
                             f"{', '.join(map(repr, unused[:3]))}{' ...' if len(unused) > 3 else ''} "
                             "(a smaller network than the file's? build it with the file's blocks / mid_blocks)")
    model.load_state_dict(new)


def train_model(kind: str, data_dirs, out_dir: str | Path, steps: int, *, settings: TrainSettings | None = None,
                clips: list | None = None, export: bool = True, evaluate: bool = False,
                progress: bool = False) -> TrainResult:
    """Train (or resume training of) a model of contract ``kind`` for ``steps`` total steps.

    Args:
        kind: ``forward_denoiser`` or ``inverse_gbuffer``.
        data_dirs: scene bundle directories; bundles with held-out seeds/rotations
            (``settings.data``) are used only for evaluation.
        out_dir: checkpoint, ONNX file and model card go here.
        steps: total optimisation steps (a resumed run continues up to this number).
        clips: pre-loaded training clips (skips reading ``data_dirs`` for training; tests).
        export: write ``<kind>.onnx`` and its model card at the end.
        evaluate: compute held-out metrics (:func:`evaluate_model`) for the card.

    Returns:
        :class:`TrainResult`.
    """
    if kind not in ("forward_denoiser", "inverse_gbuffer"):
        raise ConfigError(f"kind: trainable kinds are forward_denoiser, inverse_gbuffer; got {kind!r}")
    if steps < 1:
        raise ConfigError(f"steps: must be >= 1, got {steps}")
    s = settings or TrainSettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(s.threads)
    try:
        train_dirs, held_dirs = split_bundles(data_dirs, s.data.held_out_seeds, s.data.held_out_rotations)
        kinds = ("forward",) if kind == "forward_denoiser" else ("inverse",)
        if clips is None:
            if not train_dirs:
                raise ConfigError(f"no training bundles left after holding out seeds {s.data.held_out_seeds} "
                                  f"/ rotations {s.data.held_out_rotations} (of {len(list(data_dirs))})")
            clips = [c for d in train_dirs for c in load_clips(d, s.data, kinds)]
        if s.view and kind != "inverse_gbuffer":
            raise ConfigError(f"view: only the inverse model takes the camera input, not {kind!r}")
        ds = ClipDataset(clips, kind, s.frames, s.crop, view=s.view, rare_fraction=s.rare_fraction,
                         rare_candidates=s.rare_candidates, rare_loss_max=s.rare_loss_max)

        torch.manual_seed(s.seed)
        model = build_model(kind, s.unet, s.sigma_data, s.frames, view=s.view)
        if s.init_from:
            load_onnx_weights(model, s.init_from, grow=True)
        ema = copy.deepcopy(model).requires_grad_(False) if s.ema_decay > 0 else None
        opt = torch.optim.Adam(model.parameters(), lr=s.lr)
        rng = np.random.default_rng(s.seed)
        gen = torch.Generator().manual_seed(s.seed)
        losses: list[float] = []
        step = 0
        ckpt = out / "checkpoint.pt"
        key = _config_key(kind, s)
        if ckpt.is_file():
            st = torch.load(ckpt, weights_only=False)
            if st.get("config_key") == key:
                model.load_state_dict(st["model"])
                if ema is not None and st.get("ema") is not None:
                    ema.load_state_dict(st["ema"])
                opt.load_state_dict(st["opt"])
                step, losses = st["step"], list(st["losses"])
                rng.bit_generator.state = st["np_rng"]
                gen.set_state(st["torch_gen"])
            else:
                raise ConfigError(f"{ckpt}: checkpoint of a different model/config; use another out_dir "
                                  "or delete it")

        def save():
            _atomic_save({"config_key": key, "model": model.state_dict(),
                          "ema": ema.state_dict() if ema is not None else None, "opt": opt.state_dict(),
                          "step": step, "losses": losses, "np_rng": rng.bit_generator.state,
                          "torch_gen": gen.get_state(), "settings": repr(s)}, ckpt)

        bar = None
        if progress:
            bar = tqdm(total=steps, initial=step, desc=f"train {kind}", unit="step")
        model.train()
        while step < steps:
            batch = ds.sample(s.batch, rng)
            for g in opt.param_groups:
                g["lr"] = s.lr * min(1.0, (step + 1) / max(s.warmup, 1))
            loss = edm_loss(model, batch, s, gen)
            if not torch.isfinite(loss):
                save()
                raise NumericalError(f"training loss is {float(loss)} at step {step} (checkpoint {ckpt} "
                                     "holds the last finite state)")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), s.grad_clip)
            opt.step()
            if ema is not None:
                with torch.no_grad():
                    d = min(s.ema_decay, (1 + step) / (10 + step))
                    for pe, pm in zip(ema.parameters(), model.parameters()):
                        pe.mul_(d).add_(pm.detach(), alpha=1 - d)
            losses.append(loss.item())
            step += 1
            if bar is not None:
                bar.update()
                bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}")
            if step % s.checkpoint_every == 0:
                save()
        if bar is not None:
            bar.close()
        save()
        wall = time.perf_counter() - t_start
        onnx_path = card_path = None
        metrics: dict = {}
        final = (ema if ema is not None else model).eval()
        if export:
            onnx_path = export_onnx(final, out / f"{kind}.onnx", sigma_min=s.sigma_min, sigma_max=s.sigma_max,
                                    extra_metadata={C.META_CARD: f"{kind}.card.json"})
            if evaluate and held_dirs:
                metrics = evaluate_model(kind, onnx_path, held_dirs, s.data, threads=s.threads)
            card_path = write_model_card(
                onnx_path, kind,
                network={"class": type(final).__name__, "parameters": count_parameters(final), **final.settings_dict()},
                training={"data_dirs": [str(d) for d in train_dirs], "held_out_dirs": [str(d) for d in held_dirs],
                          "held_out_seeds": list(s.data.held_out_seeds),
                          "held_out_rotations": list(s.data.held_out_rotations),
                          "forward_source": s.data.forward_source, "windows_available": len(ds),
                          "steps": step, "batch": s.batch, "crop": s.crop, "lr": s.lr,
                          "wall_s_this_run": round(wall, 1), "final_loss_mean50": float(np.mean(losses[-50:])),
                          "ema_decay": s.ema_decay, "paired_fraction": s.paired_fraction,
                          **({"rare_fraction": s.rare_fraction, "rare_candidates": s.rare_candidates,
                              "rare_loss_max": s.rare_loss_max,
                              "rarity_table": [round(float(w), 4) for w in ds.rarity]}
                             if ds.rarity is not None else {})},
                metrics=metrics)
        return TrainResult(kind, step, losses, wall, ckpt, onnx_path, card_path, metrics)
    finally:
        torch.set_num_threads(prev_threads)


def predict_inverse_clip(sess, den, clip: list[dict], sampler=None, ensemble: EnsembleSettings | None = None):
    """The inverse model on one clip of :func:`core.synth.gen_data.load_clips` (kind inverse):
    ``(prediction, truth, rgb, mask)``: the ensemble-mean G-buffer and the true one [T, 9, H, W]
    (G-buffer data space), the input frames [T, 3, H, W] (LDR data space) and the non-sky mask
    [T, H, W] bool. ``sess`` / ``den``: the loaded model and its :class:`OnnxDenoiser`; the camera
    input is passed when the model takes it."""
    rgb = torch.from_numpy(np.stack([f["rgb"] for f in clip]))
    g = torch.from_numpy(np.stack([f["gbuffer"] for f in clip]))
    cond = {"rgb": rgb}
    if sess.info.takes("view"):
        cond["view"] = torch.from_numpy(np.stack([f["view"] for f in clip]))
    y = generate_gbuffer(den, tuple(g.shape), cond, sampler or GENERATE_SAMPLER, ensemble)
    mask = torch.from_numpy(np.stack([f["sky"][0] for f in clip])) < 0.5
    return y, g, rgb, mask


def evaluate_model(kind: str, onnx_path: str | Path, bundle_dirs, data: DataSettings | None = None, *,
                   threads: int = 2, sampler=None, max_frames: int | None = None,
                   ensemble: EnsembleSettings | None = None) -> dict:
    """Held-out metrics of an exported model on whole frames of ``bundle_dirs``.

    forward_denoiser: SDEdit of the input clip; ``psnr_input``, ``psnr_model`` (LDR, against the
    tone-mapped ground truth), ``flicker_input``, ``flicker_model``.
    inverse_gbuffer: sampling from noise conditioned on the frames; ``albedo_si_psnr``,
    ``roughness_rmse``, ``metallic_rmse``, ``normal_mae_deg`` over non-sky pixels (paper metrics),
    of the ensemble mean (``ensemble``, default the product's
    :class:`core.gen.gbuffer_ensemble.EnsembleSettings`; ``SINGLE`` for one call).
    """
    data = data or DataSettings()
    sess = load_model(onnx_path, kind=kind, threads=threads)
    den = OnnxDenoiser(sess)
    sampler = sampler or (SamplerSettings() if kind == "forward_denoiser" else GENERATE_SAMPLER)
    kinds = ("forward",) if kind == "forward_denoiser" else ("inverse",)
    acc: dict[str, list] = {}
    for d in bundle_dirs:
        for clip in load_clips(d, data, kinds):
            clip = clip[:max_frames] if max_frames else clip
            if kind == "forward_denoiser":
                x_in = torch.from_numpy(np.stack([f["input_ldr"] for f in clip]))
                tgt = torch.from_numpy(np.stack([f["target_ldr"] for f in clip]))
                cond = {k: torch.from_numpy(np.stack([f[k] for f in clip])) for k in
                        ("normal", "depth", "albedo", "roughness", "metallic", "env_ldr", "env_log", "env_dir")}
                y = sdedit(den, x_in, cond, sampler)
                to01 = lambda a: ((a.clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1)  # noqa: E731
                acc.setdefault("psnr_input", []).append(float(psnr(to01(x_in), to01(tgt))))
                acc.setdefault("psnr_model", []).append(float(psnr(to01(y), to01(tgt))))
                if len(clip) > 1:
                    acc.setdefault("flicker_input", []).append(flicker(to01(x_in)))
                    acc.setdefault("flicker_model", []).append(flicker(to01(y)))
            else:
                y, g, _, mask = predict_inverse_clip(sess, den, clip, sampler, ensemble)
                sl = C.GBUFFER_SLICES
                hw = lambda a, k: a[:, sl[k]].permute(0, 2, 3, 1)  # noqa: E731
                to01 = lambda a: ((a.clamp(-1, 1) + 1) / 2)  # noqa: E731
                acc.setdefault("albedo_si_psnr", []).append(float(si_psnr(to01(hw(y, "albedo")), to01(hw(g, "albedo")), mask)))
                for k in ("roughness", "metallic"):
                    err = (to01(hw(y, k)) - to01(hw(g, k)))[..., 0][mask]
                    acc.setdefault(f"{k}_rmse", []).append(float(torch.sqrt((err ** 2).mean())))
                acc.setdefault("normal_mae_deg", []).append(float(angular_error_deg(hw(y, "normal"), hw(g, "normal"), mask)))
    return {k: float(np.mean(v)) for k, v in acc.items() if v and all(math.isfinite(x) for x in v)}
