"""Export a bundle's frames as render outputs: multi-layer EXR per frame, MP4 videos, a preview.

What ``brdf render`` and the service's render job produce for a bundle, a dataset export: its own
frames as stored, i.e. the ground-truth HDR frame and G-buffers of a synthetic scene (or the
linearised LDR frames of a real capture), in the output layout of the renderer. The method's
renders are ``brdf relight`` / ``brdf night`` (:mod:`core.render.scenario`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.bundle import SceneBundle
from core.errors import ConfigError
from core.io.exr import write_exr
from core.io.images import write_png
from core.io.video import write_mp4
from core.tonemap import hdr_to_ldr, ldr_to_hdr


@dataclass
class ExportResult:
    out_dir: Path
    exr_files: list[Path] = field(default_factory=list)
    videos: list[Path] = field(default_factory=list)
    preview: Path | None = None


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


def export_frames(bundle: SceneBundle, out_dir: str | Path, *, split: str = "all", fps: float = 10.0,
                  progress: bool = True) -> ExportResult:
    """Write ``frames/<id>.exr`` (layers: rgb HDR, albedo, roughness, metallic, normal, depth when
    the bundle has ground truth), ``<split>.mp4`` (LDR), ``<split>_gbuffers.mp4`` and
    ``preview.png`` into ``out_dir``."""
    from tqdm import tqdm

    if split not in ("all", "train", "test"):
        raise ConfigError(f"split: expected all, train or test, got {split!r}")
    frames = bundle.frames(None if split == "all" else split)
    if not frames:
        raise ConfigError(f"split: the bundle has no {split!r} frames")
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    res = ExportResult(out)
    m = bundle.manifest
    by_split: dict[str, tuple[list, list]] = {}
    for f in tqdm(frames, desc="export frames", unit="frame", disable=not progress):
        ldr = bundle.load_image(f)
        if f.ground_truth:
            layers = bundle.load_ground_truth(f)
            ldr_gt = hdr_to_ldr(layers["rgb"], m.ldr_exposure, m.ldr_gamma)
            mosaic = gbuffer_mosaic(layers, ldr_gt)
        else:
            layers = {"rgb": ldr_to_hdr(ldr, m.ldr_exposure, m.ldr_gamma)}
            mosaic = None
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
