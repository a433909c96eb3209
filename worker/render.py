"""The ``render`` job type: the scene's captured frames exported as EXR (linearised HDR; never the
ground truth), an MP4 and a PNG preview (:func:`core.export.export_frames`), uploaded as artifacts."""

from __future__ import annotations

import threading
from pathlib import Path

from api_schemas import OutputKind, RenderRequest
from core.bundle import open_bundle
from core.export import export_frames
from worker.runtime import JobContext, JobType
from worker.settings import QUEUE_RENDER


def _watch_frames(ctx: JobContext, frames_dir: Path, total: int, stop: threading.Event) -> None:
    """Progress of ``export_frames`` measured from the EXR files it has written."""
    while not stop.wait(0.2):
        try:
            n = sum(1 for p in frames_dir.iterdir() if p.suffix == ".exr") if frames_dir.is_dir() else 0
        except OSError:
            continue
        ctx.progress(0.9 * n / total, stage_fraction=n / total)


def run_render(ctx: JobContext, p: RenderRequest) -> None:
    """Export the scene's frames: multi-layer EXR per frame, MP4, a PNG preview (core.export)."""
    ctx.stage("fetch")
    bundle = open_bundle(ctx.scene_dir())
    frames = bundle.frames(None if p.split == "all" else p.split)
    ctx.progress(0.02)
    ctx.stage("export")
    out = ctx.workdir / "out"
    stop = threading.Event()
    watcher = threading.Thread(target=_watch_frames, args=(ctx, out / "frames", max(len(frames), 1), stop),
                               daemon=True)
    watcher.start()
    try:
        res = export_frames(bundle, out, split=p.split, fps=p.fps, progress=False)
    finally:
        stop.set()
        watcher.join()
    ctx.check_canceled()
    ctx.stage("upload")
    want = {o.value if isinstance(o, OutputKind) else o for o in p.outputs}
    files = []
    if "exr" in want:
        files += res.exr_files
    if "mp4" in want:
        files += res.videos
    if "png" in want and res.preview is not None:
        files.append(res.preview)
    for i, f in enumerate(files):
        ctx.check_canceled()
        ctx.add_artifact(f, f.relative_to(out).as_posix())
        ctx.progress(0.9 + 0.1 * (i + 1) / len(files), stage_fraction=(i + 1) / len(files))


JOB_TYPE = JobType("render", QUEUE_RENDER, RenderRequest, run_render, stages=("fetch", "export", "upload"))
