"""G-buffer priors of the volume stage: the inverse model over sliding windows of the frames.

The paper (Sec. 3.3, "Volume Rendering Stage") regularises geometry and material toward the
G-buffers ``{N_g, D_g, A_g, R_g, M_g}`` that the inverse diffusion model generates from the input
frames, split into overlapping clips and blended by sliding-window averaging. Here the model is the
shipped ``models/inverse_gbuffer.onnx`` (contract ``inverse_gbuffer``), sampled with
:data:`core.gen.edm.GENERATE_SAMPLER` through :class:`core.gen.edm.WindowedDenoiser` (windows of
the model's ``brdf.frames``, half overlapping, ramp-blended), as the mean of an ensemble of noise
draws and mirrored frames (:mod:`core.gen.gbuffer_ensemble`).

Frames are grouped per camera and ordered by time, so a window holds consecutive frames of one
camera. Priors are computed once per scene and cached (:func:`load_or_compute_priors`): the cache
file names the bundle, the frame ids and the model file's size and modification time, and is
recomputed when any of them changes.

:class:`GBufferPriors` per frame (channels-last, float32):
    ``albedo``     [H, W, 3] in [0, 1]
    ``roughness``  [H, W, 1] in [0, 1] (``alpha = roughness^2`` in the BRDF)
    ``metallic``   [H, W, 1] in [0, 1]
    ``normal``     [H, W, 3] unit, **world** frame (zero where the model saw no surface)
    ``depth``      [H, W, 1] camera z-depth, metres (0 = sky); only relative: the volume stage
                   aligns it per frame with a closed-form scale and shift (the paper's ``u, v``)

The generative refinement stage (:mod:`core.stages.generative_refine`) produces the same type by
SDEdit of the rendered intrinsics, and the second volume stage reads it instead.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from core.errors import ConfigError, FormatError, ModelLoadError, NumericalError
from core.gen.edm import GENERATE_SAMPLER, OnnxDenoiser, SamplerSettings, sdedit
from core.gen.encoding import camera_to_world_dirs, decode_gbuffer, ldr_to_data, view_conditioning
from core.gen.gbuffer_ensemble import EnsembleSettings, generate_gbuffer
from core.gen.runtime import load_model
from core.io.atomic import atomic_output

REPO_ROOT = Path(__file__).resolve().parents[2]
#: The shipped inverse G-buffer model.
DEFAULT_INVERSE_MODEL = REPO_ROOT / "models" / "inverse_gbuffer.onnx"
PRIOR_LAYERS = ("albedo", "roughness", "metallic", "normal", "depth")


@dataclass
class GBufferPriors:
    """Per-frame G-buffer priors (module docstring): ``layers[frame_id][layer] -> [H, W, C]``."""

    layers: dict[str, dict[str, np.ndarray]]
    source: str
    """What made them: ``"inverse_model"`` or ``"generative_refine"``."""

    def frame(self, frame_id: str) -> dict[str, np.ndarray] | None:
        return self.layers.get(frame_id)

    def save(self, path: str | Path, meta: dict | None = None) -> None:
        """One ``.npz`` (``<frame>/<layer>`` arrays) plus a ``meta`` JSON string; written to a
        temporary name and renamed, so a crash never leaves a half-written cache."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f"{fid}/{k}": v.astype(np.float32) for fid, d in self.layers.items() for k, v in d.items()}
        arrays["__meta__"] = np.array(json.dumps({"source": self.source, **(meta or {})}))

        with atomic_output(p, suffix=".npz") as tmp:  # savez appends .npz to a name without it
            np.savez_compressed(tmp, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> tuple["GBufferPriors", dict]:
        """(priors, meta) of a file written by :meth:`save`; FormatError naming the file."""
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as z:
                meta = json.loads(str(z["__meta__"]))
                layers: dict[str, dict[str, np.ndarray]] = {}
                for key in z.files:
                    if key == "__meta__":
                        continue
                    fid, layer = key.rsplit("/", 1)
                    layers.setdefault(fid, {})[layer] = z[key]
        except (OSError, ValueError, KeyError) as exc:
            raise FormatError(f"{p}: unreadable G-buffer priors ({exc})") from exc
        return cls(layers, meta.get("source", "unknown")), meta


def _clips(bundle, split: str) -> list[list]:
    """Frames of ``split`` grouped per camera, each group ordered by time."""
    groups: dict[str, list] = {}
    for f in bundle.frames(split):
        groups.setdefault(f.camera, []).append(f)
    return [sorted(g, key=lambda f: (f.time_index, f.id)) for g in groups.values()]


def _model_key(model: Path) -> dict:
    st = model.stat()
    return {"model": str(model.resolve()), "model_bytes": st.st_size, "model_mtime": int(st.st_mtime)}


def decode_to_priors(x: np.ndarray, cam_to_world: np.ndarray) -> dict[str, np.ndarray]:
    """[9, H, W] G-buffer data space (camera-frame normals) -> the prior layers (world normals)."""
    d = decode_gbuffer(x)
    n = camera_to_world_dirs(d["normal"], cam_to_world)
    return {"albedo": d["albedo"], "roughness": d["roughness"], "metallic": d["metallic"],
            "normal": n.astype(np.float32), "depth": d["depth"][..., None] if d["depth"].ndim == 2 else d["depth"]}


def run_inverse_model(bundle, split: str = "train", *, model: str | Path = DEFAULT_INVERSE_MODEL,
                      threads: int = 2, anchors: dict[str, np.ndarray] | None = None, sigma_tau: float | None = None,
                      steps: int = 1, ensemble: EnsembleSettings | None = None,
                      on_clip: Callable[[int, int], None] | None = None) -> GBufferPriors:
    """G-buffer priors of every frame of ``split`` from the inverse model.

    Args:
        bundle: :class:`core.bundle.SceneBundle` (its LDR frames; never its ground truth).
        model: the ``inverse_gbuffer`` ONNX file.
        anchors: optional ``frame_id -> [9, H, W]`` G-buffer data-space renders of the
            reconstruction; with ``sigma_tau`` they are refined by SDEdit (the generative
            refinement stage) instead of sampled from noise.
        sigma_tau: SDEdit noise level of the anchors (needed with ``anchors``).
        steps: Euler steps of the SDEdit from ``sigma_tau``.
        ensemble: members averaged when sampling from noise (default
            :class:`core.gen.gbuffer_ensemble.EnsembleSettings`); the SDEdit of anchors is one call.
        on_clip: ``(done, total)`` after each camera clip.

    Raises:
        ModelLoadError: the model file is missing or does not match its contract.
        ConfigError: no frames in ``split``, or anchors without ``sigma_tau`` / missing a frame.
        NumericalError: a non-finite model output.
    """
    clips = _clips(bundle, split)
    if not clips:
        raise ConfigError(f"bundle: no {split!r} frames to compute G-buffer priors from")
    if anchors is not None and (sigma_tau is None or not sigma_tau > 0):
        raise ConfigError(f"sigma_tau: SDEdit of anchors needs a noise level > 0, got {sigma_tau!r}")
    sess = load_model(model, kind="inverse_gbuffer", threads=threads)
    den = OnnxDenoiser(sess)
    layers: dict[str, dict[str, np.ndarray]] = {}
    for ci, clip in enumerate(clips):
        rgb = torch.from_numpy(np.stack([ldr_to_data(bundle.load_image(f)).transpose(2, 0, 1) for f in clip]))
        shape = (len(clip), 9, rgb.shape[2], rgb.shape[3])
        cond = {"rgb": rgb}
        if sess.info.takes("view"):  # a model trained on the capture's camera (contract 1.1)
            cam = bundle.manifest.cameras[clip[0].camera]
            cond["view"] = torch.from_numpy(np.stack([
                view_conditioning(f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
                for f in clip]))
        if anchors is None:
            y = generate_gbuffer(den, shape, cond, GENERATE_SAMPLER, ensemble)
        else:
            missing = [f.id for f in clip if f.id not in anchors]
            if missing:
                raise ConfigError(f"anchors: no rendered intrinsics for frame(s) {missing[:5]}")
            x_in = torch.from_numpy(np.stack([anchors[f.id] for f in clip]).astype(np.float32))
            y = sdedit(den, x_in, cond, SamplerSettings(sigma_tau=float(sigma_tau), steps=steps))
        y = y.numpy()
        if not np.isfinite(y).all():
            raise NumericalError(f"inverse model: non-finite G-buffer output for camera {clip[0].camera}")
        for f, x in zip(clip, y):
            layers[f.id] = decode_to_priors(x, np.asarray(f.cam_to_world, np.float64))
        if on_clip is not None:
            on_clip(ci + 1, len(clips))
    return GBufferPriors(layers, "inverse_model" if anchors is None else "generative_refine")


def load_or_compute_priors(bundle, cache: str | Path, *, model: str | Path = DEFAULT_INVERSE_MODEL,
                           threads: int = 2, split: str = "train",
                           ensemble: EnsembleSettings | None = None) -> tuple[GBufferPriors, dict]:
    """The bundle's inverse-model priors, from ``cache`` when it matches (same bundle name, frame
    ids, model file and ensemble), else computed and written there. Returns (priors, info) where
    info says ``cached`` and ``seconds``."""
    model = Path(model)
    ensemble = ensemble or EnsembleSettings()
    if not model.is_file():
        raise ModelLoadError(f"{model}: inverse G-buffer model not found (the volume stage's priors need it; "
                             f"set lambda_normal = lambda_albedo = lambda_roughness = lambda_metallic = 0 "
                             f"and lambda_prior_depth = 0 to run without priors)")
    key = {"bundle": bundle.name, "frames": sorted(f.id for f in bundle.frames(split)), **_model_key(model),
           "ensemble": {"seeds": ensemble.seeds, "mirror": ensemble.mirror}}
    cache = Path(cache)
    if cache.is_file():
        try:
            pri, meta = GBufferPriors.load(cache)
        except FormatError:
            pri, meta = None, {}
        if pri is not None and all(meta.get(k) == v for k, v in key.items()):
            return pri, {"cached": True, "seconds": 0.0}
    t0 = time.perf_counter()
    pri = run_inverse_model(bundle, split, model=model, threads=threads, ensemble=ensemble)
    pri.save(cache, key)
    return pri, {"cached": False, "seconds": round(time.perf_counter() - t0, 2)}


__all__ = ["GBufferPriors", "PRIOR_LAYERS", "DEFAULT_INVERSE_MODEL", "run_inverse_model", "load_or_compute_priors",
           "decode_to_priors"]
