"""Dataset export of a synthetic bundle: its Mitsuba ground-truth frames and G-buffers.

``brdf render --ground-truth``: the layout of :func:`core.export.export_frames` (EXR per frame,
MP4, preview) with each frame's ground-truth layers (``rgb`` HDR beauty, albedo, roughness,
metallic, normal, depth) and a G-buffer mosaic video. Here, in :mod:`core.synth`, because it reads
ground truth; the service's render job exports the captured frames only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.bundle import SceneBundle
from core.bundle.schema import Frame
from core.export import ExportResult, captured_layers, export_frames
from core.tonemap import hdr_to_ldr


def _colorize_depth(depth: np.ndarray) -> np.ndarray:
    """[H, W, 1] metres -> [H, W, 3] in [0, 1] (inverse depth, sky black)."""
    d = depth[..., 0]
    inv = np.where(d > 0, 1.0 / np.maximum(d, 1e-3), 0.0)
    hi = np.percentile(inv[d > 0], 99) if np.any(d > 0) else 1.0
    v = np.clip(inv / max(hi, 1e-6), 0, 1)
    return np.stack([v, v ** 0.5, 1 - v], -1) * (d > 0)[..., None]


def gbuffer_mosaic(layers: dict[str, np.ndarray], ldr: np.ndarray) -> np.ndarray:
    """A 3x2 mosaic [2H, 3W, 3] in [0, 1]: LDR | albedo | normal / depth | roughness | metallic."""
    g = lambda x: np.repeat(x, 3, -1) if x.shape[-1] == 1 else x  # noqa: E731
    top = [ldr, np.clip(layers["albedo"], 0, 1) ** (1 / 2.2), layers["normal"] * 0.5 + 0.5]
    bot = [_colorize_depth(layers["depth"]), g(layers["roughness"]), g(layers["metallic"])]
    return np.clip(np.concatenate([np.concatenate(top, 1), np.concatenate(bot, 1)], 0), 0, 1)


def ground_truth_layers(bundle: SceneBundle, frame: Frame, ldr: np.ndarray):
    """The frame's ground-truth layers and their mosaic (a frame without ground truth, e.g. of an
    imported capture: its captured ``rgb``, no mosaic)."""
    if not frame.ground_truth:
        return captured_layers(bundle, frame, ldr)
    layers = bundle.load_ground_truth(frame)
    m = bundle.manifest
    return layers, gbuffer_mosaic(layers, hdr_to_ldr(layers["rgb"], m.ldr_exposure, m.ldr_gamma))


def export_ground_truth(bundle: SceneBundle, out_dir: str | Path, *, split: str = "all", fps: float = 10.0,
                        progress: bool = True) -> ExportResult:
    """:func:`core.export.export_frames` with :func:`ground_truth_layers`."""
    return export_frames(bundle, out_dir, split=split, fps=fps, progress=progress, frame_layers=ground_truth_layers)
