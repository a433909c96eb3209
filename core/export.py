"""Export a bundle's frames as render outputs: multi-layer EXR per frame, MP4 videos, a preview.

What the service's render job and ``brdf render`` produce for a bundle: its captured frames,
linearised from the stored LDR images (``rgb`` layer, HDR under the bundle's exposure and gamma),
in the output layout of the renderer. The product path never reads ground truth; the dataset
export of a synthetic bundle's Mitsuba frames and G-buffers is ``brdf render --ground-truth``
(:func:`core.synth.export.export_ground_truth`, which passes its own ``frame_layers``). The
method's renders are ``brdf relight`` / ``brdf night`` (:mod:`core.render.scenario`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from core.bundle import SceneBundle
from core.bundle.schema import Frame
from core.errors import ConfigError
from core.io.exr import write_exr
from core.io.images import write_png
from core.io.video import write_mp4
from core.tonemap import ldr_to_hdr

#: ``(bundle, frame, ldr [H, W, 3] in [0, 1]) -> (EXR layers, mosaic [H', W', 3] in [0, 1] or None)``
FrameLayers = Callable[[SceneBundle, Frame, np.ndarray], tuple[dict[str, np.ndarray], np.ndarray | None]]


@dataclass
class ExportResult:
    out_dir: Path
    exr_files: list[Path] = field(default_factory=list)
    videos: list[Path] = field(default_factory=list)
    preview: Path | None = None


def captured_layers(bundle: SceneBundle, frame: Frame, ldr: np.ndarray) -> tuple[dict[str, np.ndarray], None]:
    """The captured frame as the EXR's ``rgb`` layer: the LDR image linearised with the bundle's
    exposure and gamma ([H, W, 3] float32, relative radiance); no mosaic."""
    m = bundle.manifest
    return {"rgb": ldr_to_hdr(ldr, m.ldr_exposure, m.ldr_gamma)}, None


def export_frames(bundle: SceneBundle, out_dir: str | Path, *, split: str = "all", fps: float = 10.0,
                  progress: bool = True, frame_layers: FrameLayers = captured_layers) -> ExportResult:
    """Write ``frames/<id>.exr`` (the layers ``frame_layers`` returns; by default the captured
    frame's ``rgb``), ``<split>.mp4`` (the LDR frames), ``<split>_gbuffers.mp4`` when
    ``frame_layers`` returns mosaics, and ``preview.png`` (the first mosaic, else the first frame)
    into ``out_dir``."""
    if split not in ("all", "train", "test"):
        raise ConfigError(f"split: expected all, train or test, got {split!r}")
    frames = bundle.frames(None if split == "all" else split)
    if not frames:
        raise ConfigError(f"split: the bundle has no {split!r} frames")
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    res = ExportResult(out)
    by_split: dict[str, tuple[list, list]] = {}
    for f in tqdm(frames, desc="export frames", unit="frame", disable=not progress):
        ldr = bundle.load_image(f)
        layers, mosaic = frame_layers(bundle, f, ldr)
        p = out / "frames" / f"{f.id}.exr"
        write_exr(p, layers, precision={k: ("float" if k in ("rgb", "depth") else "half") for k in layers},
                  channel_names={"normal": ("X", "Y", "Z")} if "normal" in layers else None)
        res.exr_files.append(p)
        seq = by_split.setdefault(f.split, ([], []))
        seq[0].append((ldr * 255 + 0.5).astype(np.uint8))
        if mosaic is not None:
            seq[1].append((mosaic * 255 + 0.5).astype(np.uint8))
    for sp, (ldr_seq, mosaic_seq) in by_split.items():
        v = out / f"{sp}.mp4"
        write_mp4(v, ldr_seq, fps=fps)
        res.videos.append(v)
        if mosaic_seq:
            v = out / f"{sp}_gbuffers.mp4"
            write_mp4(v, mosaic_seq, fps=fps)
            res.videos.append(v)
            if res.preview is None:
                res.preview = out / "preview.png"
                write_png(res.preview, mosaic_seq[0])
    if res.preview is None:
        res.preview = out / "preview.png"
        write_png(res.preview, next(iter(by_split.values()))[0][0])
    return res
