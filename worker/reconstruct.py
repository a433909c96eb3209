"""The ``reconstruct`` job type: the paper's chain of stages (:mod:`core.stages.chain`), each stage
its own RQ job, run from the same description the CLI uses. No stage logic lives here: a stage job

1. lays out the job's run directory in this machine's data directory (``runs/<job id>``) and
   restores from the artifact store whatever earlier stages wrote that is not on this disk (a
   stage may run on another worker than the one before it);
2. calls :func:`core.stages.chain.run_stage` with the profile's settings (scaled by
   ``iterations_scale``) and a progress callback that reports to the database and honours a
   cancel; a killed stage resumes from ``<stage>/resume/`` when its retry runs on the same disk;
3. uploads the stage's outputs as artifacts named ``<stage>/<path>`` (and the inverse-model prior
   cache as ``priors/priors.npz``), and its summary's figures and loss curve as stage metrics.
"""

from __future__ import annotations

import json
from pathlib import Path

from sqlalchemy import select

from api_schemas import ReconstructRequest
from core.bundle import open_bundle
from core.stages.chain import (RUN_FILE, STAGES, RunDir, profile_settings, resolve_stages, run_stage, scale_iterations,
                               stage_spec, write_json)
from worker.db import Artifact, Job
from worker.runtime import JobContext, JobType
from worker.settings import QUEUE_TRAIN

#: Artifact name of a stage's scene graph: ``<stage>/checkpoint/scene_graph.pt``.
GRAPH_SUFFIX = "/checkpoint/scene_graph.pt"
#: Figures of a stage summary copied into the stage metrics (the dashboard shows them).
SUMMARY_FIGURES = ("test_psnr", "test_ssim", "train_psnr", "gaussians", "sky_floaters_pruned", "seconds",
                   "photometric_psnr_prior", "photometric_psnr_fitted", "prior_source", "skipped",
                   "resumed_from_iteration")


def reconstruct_stages(p: ReconstructRequest) -> tuple[str, ...]:
    """The requested stages in chain order (each once)."""
    return resolve_stages(list(p.stages))


def reconstruct_unavailable(p: ReconstructRequest) -> str | None:
    """Why this build cannot run ``p``, or None. A chain must start where its inputs exist: the
    first requested stage may only read stages that are also requested (a new job has no earlier
    outputs)."""
    asked = reconstruct_stages(p)
    missing = sorted({r for s in asked for r in stage_spec(s).reads if r not in asked})
    if missing:
        return (f"stages: {list(asked)} need the stage(s) {missing} of the same chain (a reconstruct job starts "
                f"from the capture); add them")
    return None


def run_dir_path(ctx: JobContext, job_id: str) -> Path:
    return ctx.settings.data_dir / "runs" / job_id


def restore_run(ctx: JobContext, job_id: str, scene_dir: Path, profile: str, stages=None):
    """The run directory of reconstruct job ``job_id`` on this disk, with every registered
    artifact of the given ``stages`` (None: all) fetched where missing. Returns a
    :class:`core.stages.chain.RunDir`."""
    root = run_dir_path(ctx, job_id)
    root.mkdir(parents=True, exist_ok=True)
    # the scene path is this machine's cache of the bundle: written on every restore
    write_json(root / RUN_FILE, {"format": "brdfusion-run", "version": 1, "scene": str(Path(scene_dir).resolve()),
                                 "profile": profile, "job": job_id})
    with ctx.db.session() as s:
        rows = s.execute(select(Artifact.name, Artifact.storage_key, Artifact.size_bytes)
                         .where(Artifact.job_id == job_id)).all()
    for name, key, size in rows:
        top = name.split("/", 1)[0]
        if stages is not None and top not in stages and top != "priors":
            continue
        local = root / name
        if local.is_file() and local.stat().st_size == size:
            continue
        local.parent.mkdir(parents=True, exist_ok=True)
        ctx.store.get_file(key, local)
    return RunDir(root)


def _run_one(stage: str):
    def run(ctx: JobContext, p: ReconstructRequest) -> None:
        scene = ctx.scene_dir()
        earlier = STAGES[:STAGES.index(stage)]
        run_dir = restore_run(ctx, ctx.job.id, scene, p.profile, earlier)
        cfg = scale_iterations(profile_settings(p.profile, stage), p.iterations_scale)
        losses: list[float] = []

        def report(it: int, total: int, rec: dict) -> None:
            ctx.check_canceled()
            if "loss" in rec:
                losses.append(round(float(rec["loss"]), 5))
            ctx.stage_progress(0.95 * it / max(total, 1))
            if it == total or len(losses) % 5 == 0:
                ctx.stage_metrics({"loss": losses})

        summary = run_stage(stage, open_bundle(scene), run_dir, cfg, progress=False, on_progress=report)
        ctx.stage_metrics({"loss": losses or [round(h["loss"], 5) for h in summary.get("history", []) if "loss" in h],
                           **{k: summary[k] for k in SUMMARY_FIGURES if k in summary}})
        out = run_dir.stage_dir(stage)
        for f in sorted(x for x in out.rglob("*") if x.is_file() and "resume" not in x.relative_to(out).parts):
            ctx.check_canceled()
            ctx.add_artifact(f, f"{stage}/{f.relative_to(out).as_posix()}")
        cache = run_dir.root / "priors" / "priors.npz"
        if cache.is_file():
            ctx.add_artifact(cache, "priors/priors.npz")
        ctx.stage_progress(1.0)

    run.__name__ = f"run_{stage}_stage"
    run.__doc__ = f"The {stage!r} stage of the chain (core.stages.{stage}) as one job."
    return run


def latest_reconstruction(session, scene_id: str):
    """``(job id, profile)`` of the scene's newest finished reconstruct job that has a scene
    graph, or None."""
    row = session.execute(
        select(Job.id, Job.params).join(Artifact, Artifact.job_id == Job.id)
        .where(Job.scene_id == scene_id, Job.type == "reconstruct", Job.state == "done",
               Artifact.name.like(f"%{GRAPH_SUFFIX}"))
        .order_by(Job.finished_at.desc())).first()
    if row is None:
        return None
    params = row[1] if isinstance(row[1], dict) else json.loads(row[1] or "{}")
    return row[0], params.get("profile", "quick")


def needs_reconstruction(session, scene_id: str, tenant: str) -> str | None:
    """The gateway's precondition of relight and night: a finished reconstruct job."""
    if latest_reconstruction(session, scene_id) is None:
        return (f"scene {scene_id} has no finished reconstruction: run POST /scenes/{scene_id}/reconstruct "
                "and wait for it to finish")
    return None


JOB_TYPE = JobType("reconstruct", QUEUE_TRAIN, ReconstructRequest, _run_one(STAGES[0]), stages=STAGES,
                   unavailable=reconstruct_unavailable, stages_for=reconstruct_stages,
                   stage_fns={s: _run_one(s) for s in STAGES})
