"""The inverse-rendering pipeline, described once: stage order, what each stage reads and writes,
the settings of every stage per profile, and the run directory they share.

The paper's chain (Sec. 3.3; supplement "Implementation Details"):

==================  =====================================  ======================================
stage               reads                                  writes (under ``<run>/<stage>/``)
==================  =====================================  ======================================
volume              frames, sky masks, LiDAR, priors       checkpoint/scene_graph.pt, sky.pt,
                    (inverse model, cached in priors/)     renders/, summary.json
generative_refine   volume's scene graph, frames           priors.npz (refined G-buffers),
                                                           preview.png, summary.json
volume2             volume's scene graph + sky,            checkpoint/scene_graph.pt, sky.pt,
                    generative_refine's priors             renders/, summary.json
pbr                 the latest scene graph, frames         envmap.exr, envmap_prior.exr,
                                                           preview.png, summary.json,
                                                           occluders.pt (unseen walls lifted)
joint               the latest scene graph + sky (with     checkpoint/scene_graph.pt, sky.pt,
                    pbr's occluders), pbr's envmap, the    envmap.exr, summary.json
                    latest priors
corrector           the latest scene graph and map, the    corrector.pt (the scene corrector),
(not the paper's)   training frames                        summary.json
==================  =====================================  ======================================

The CLI runs :func:`run_pipeline` in-process; the service's workers run each stage as its own RQ
job through :func:`run_stage` with the same :class:`RunDir` layout, so neither holds stage logic.

Each stage: frozen settings (the profile table :data:`PROFILES`), a checkpoint that resumes a
killed run (``<stage>/resume/``), a loss log and timings in ``<stage>/summary.json``, and a
``<stage>/done.json`` written last, when the stage's outputs are complete.

A stage skips what the scene does not have (no LiDAR: no depth term; no sky masks: no opacity
term; no objects: no nodes) and records that in its summary under ``skipped``. Work a stage may
leave out by a setting (the skips: an early stop once its validation error stops improving, no sun
search for an overcast or night capture; defaults measured by ``benchmarks/bench_skips.py``) is
recorded, when it fires, under ``skips_fired`` (what and why).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Callable

from core.errors import ConfigError, FormatError

#: The paper's stages in chain order, then the corrector (a departure: ``docs/DESIGN.md``).
STAGES = ("volume", "generative_refine", "volume2", "pbr", "joint", "corrector")
#: The paper's five stages alone (the chain without the corrector).
PAPER_STAGES = STAGES[:5]
#: What runs when no stages are named: the paper's five and the corrector. The corrector is applied
#: only under the light it was fitted at (the re-render, a new path or an edit under the capture's
#: light), so it moves nothing else; on the development scenes (quick profile, test views,
#: ``benchmarks/results/corrector_steps_dev.json``) it raised the re-render from 23.19 / 20.48 /
#: 22.47 dB (dev1, dev2, default; none) to 24.15 / 23.93 / 24.47 at 800 fit steps and 24.81 / 25.64
#: on dev1 / dev2 at 2400. The five alone (:data:`PAPER_STAGES`): ``--stages volume,generative_refine,volume2,pbr,joint``.
DEFAULT_STAGES = STAGES
#: Profiles: ``tiny`` (tests, CI), ``quick`` (the default: the knee of the run-time-against-error
#: front, ``benchmarks/results/runtime_vs_error.json``), ``benchmark`` (the figures: the cheapest
#: measured configuration within run-to-run spread of the best relight on that front), ``paper``
#: (the paper's iteration counts, rays and resolution, for a GPU host).
PROFILE_NAMES = ("tiny", "quick", "benchmark", "paper")
RUN_FILE = "run.json"
DONE_FILE = "done.json"
#: Stages that write a scene graph (``checkpoint/scene_graph.pt``), latest last.
GRAPH_STAGES = ("volume", "volume2", "joint")
#: Stages that write an environment map (``envmap.exr``), latest last.
ENVMAP_STAGES = ("pbr", "joint")
#: Stages that write G-buffer priors, latest last (``priors/`` holds the inverse model's).
PRIOR_STAGES = ("generative_refine",)
#: Stages that may replace the occluders of the graph before them (``occluders.pt``,
#: :mod:`core.stages.wall_heights`).
OCCLUDER_STAGES = ("pbr",)


@dataclass(frozen=True)
class StageSpec:
    """One stage of the chain."""

    name: str
    """Stage name (``STAGES``)."""
    paper: str
    """Where the paper describes it."""
    reads: tuple[str, ...]
    """Stages whose outputs it needs (must be done first)."""
    writes: tuple[str, ...]
    """Files it writes under ``<run>/<stage>/``."""
    settings_type: type
    """Its frozen settings dataclass."""
    module: str
    """The core module that runs it (``run_stage(ctx) -> summary``)."""


@dataclass
class StageContext:
    """What a stage function gets."""

    name: str
    bundle: Any
    """:class:`core.bundle.SceneBundle` (frames, masks, LiDAR; never its ground truth)."""
    run: "RunDir"
    settings: Any
    """The stage's frozen settings."""
    progress: bool = True
    """Show a progress bar."""
    on_progress: Callable[[int, int, dict], None] | None = None
    """``(step, total, record)`` callback (may raise to stop the stage: a cancel)."""

    @property
    def out_dir(self) -> Path:
        return self.run.stage_dir(self.name)

    @property
    def resume_dir(self) -> Path:
        return self.run.stage_dir(self.name) / "resume"


def _specs() -> dict[str, StageSpec]:
    from core.stages.corrector import CorrectorStageSettings
    from core.stages.generative_refine import RefineSettings
    from core.stages.joint import JointSettings
    from core.stages.pbr_settings import PBRStageConfig
    from core.stages.volume import VolumeSettings

    return {s.name: s for s in (
        StageSpec("volume", "Sec. 3.3 'Volume Rendering Stage', Eq. 4", (), ("checkpoint/scene_graph.pt",
                  "checkpoint/sky.pt", "renders/", "summary.json"), VolumeSettings, "core.stages.volume"),
        StageSpec("generative_refine", "Sec. 3.3 'Generative Refinement Stage'", ("volume",),
                  ("priors.npz", "preview.png", "summary.json"), RefineSettings, "core.stages.generative_refine"),
        StageSpec("volume2", "Sec. 3.3 (stages (a)(b) alternate), Eq. 4 with refined priors",
                  ("volume", "generative_refine"), ("checkpoint/scene_graph.pt", "checkpoint/sky.pt", "renders/",
                                                    "summary.json"), VolumeSettings, "core.stages.volume2"),
        StageSpec("pbr", "Sec. 3.3 'Physically-based Inverse Rendering Stage', Eq. 6", ("volume",),
                  ("envmap.exr", "envmap_prior.exr", "preview.png", "summary.json",
                   "occluders.pt (when it lifts a side's unseen walls)"), PBRStageConfig,
                  "core.stages.pbr"),
        StageSpec("joint", "Sec. 3.3 (d) and supplement: L_vol + 0.1 L_pbr", ("volume", "pbr"),
                  ("checkpoint/scene_graph.pt", "checkpoint/sky.pt", "envmap.exr", "summary.json"), JointSettings,
                  "core.stages.joint"),
        StageSpec("corrector", "not the paper's: a per-scene corrector of the PBR pass fitted on the capture "
                  "(docs/DESIGN.md, departures)", ("volume", "pbr"), ("corrector.pt", "summary.json"),
                  CorrectorStageSettings, "core.stages.corrector"),
    )}


def stage_spec(name: str) -> StageSpec:
    """The :class:`StageSpec` of ``name``; ConfigError naming the known stages."""
    specs = _specs()
    if name not in specs:
        raise ConfigError(f"stage: unknown stage {name!r} (stages: {list(STAGES)})")
    return specs[name]


def _profile_table() -> dict[str, dict[str, Any]]:
    from core.gen.scene_corrector import CorrectorSettings
    from core.stages.corrector import CorrectorStageSettings
    from core.stages.generative_refine import RefineSettings
    from core.stages.joint import JointSettings
    from core.stages.pbr_settings import PBRStageConfig
    from core.stages.volume import VolumeSettings
    from core.train.density import DensityConfig
    from core.train.init_lidar import LidarInitConfig

    tiny_init = LidarInitConfig(max_background_points=3000, max_object_points=300)
    # the corrector of quick and benchmark: 2400 fit steps (not 800), chosen on dev1 / dev2 at quick
    # (benchmarks/results/corrector_steps_dev.json)
    corrector_fit = CorrectorSettings(steps=2400)
    return {
        "tiny": {
            "volume": VolumeSettings(iterations=60, densify_from=20, densify_until=50, densify_every=15, init=tiny_init),
            "generative_refine": RefineSettings(),
            "volume2": VolumeSettings(iterations=30, densify_from=10**9, densify_until=0, init_from_graph=True),
            "pbr": PBRStageConfig(iterations=30, pixels=512, rays_per_pixel=8, env_height=32, max_frames=4,
                                  prior_points=2000, eval_pixels=512),
            "joint": JointSettings(iterations=20, pixels=256, rays_per_pixel=8, max_frames=4),
            "corrector": CorrectorStageSettings(fit=CorrectorSettings(width=8, steps=30, crop=32), max_frames=4,
                                                rays_per_pixel=8, checkpoint_every=10),
        },
        # quick: the knee of the front (Kneedle, log CPU seconds against relight PSNR; measured
        # as the benchmark profile's iterations x0.5: 170 CPU s, 18.3 dB on the default scene)
        "quick": {
            "volume": VolumeSettings(iterations=1000, densify_from=100, densify_until=700, densify_every=50,
                                     density=DensityConfig(max_gaussians=80_000)),
            "generative_refine": RefineSettings(),
            "volume2": VolumeSettings(iterations=400, densify_from=10**9, densify_until=0, densify_every=50,
                                      init_from_graph=True, density=DensityConfig(max_gaussians=80_000)),
            "pbr": PBRStageConfig(iterations=75),
            "joint": JointSettings(iterations=150),
            "corrector": CorrectorStageSettings(fit=corrector_fit),
        },
        # benchmark: the front's plateau (2x its iterations, or 7000 + 3000 volume iterations with
        # 200k Gaussians, scored within run-to-run spread of it; 335 CPU s, 18.9 dB on the default scene)
        "benchmark": {
            "volume": VolumeSettings(density=DensityConfig(max_gaussians=80_000)),
            "generative_refine": RefineSettings(),
            "volume2": VolumeSettings(iterations=800, densify_from=10**9, densify_until=0, init_from_graph=True,
                                      density=DensityConfig(max_gaussians=80_000)),
            "pbr": PBRStageConfig(),
            "joint": JointSettings(),
            "corrector": CorrectorStageSettings(fit=corrector_fit),
        },
        # The paper's counts (supplement): 30k + 30k volume iterations, 5k PBR, 20k joint,
        # 512 rays and 2048 pixels per step. For a GPU host; hours per stage on these CPUs.
        "paper": {
            "volume": VolumeSettings(iterations=30_000, densify_until=15_000, opacity_reset_every=3000,
                                     density=DensityConfig(max_gaussians=2_000_000)),
            "generative_refine": RefineSettings(),
            "volume2": VolumeSettings(iterations=30_000, densify_from=10**9, densify_until=0, init_from_graph=True,
                                      density=DensityConfig(max_gaussians=2_000_000)),
            "pbr": PBRStageConfig(iterations=5000, rays_per_pixel=512, max_frames=200),
            "joint": JointSettings(iterations=20_000, rays_per_pixel=512, max_frames=200, pixels=2048, lambda_pbr=0.1),
            "corrector": CorrectorStageSettings(fit=CorrectorSettings(steps=4000), max_frames=200),
        },
    }


def profile_settings(profile: str, stage: str, overrides: dict | None = None):
    """The frozen settings of ``stage`` in ``profile``, with field ``overrides``
    (ConfigError naming an unknown profile, stage or field)."""
    if profile not in PROFILE_NAMES:
        raise ConfigError(f"profile: unknown profile {profile!r} (profiles: {list(PROFILE_NAMES)})")
    stage_spec(stage)
    cfg = _profile_table()[profile][stage]
    return _override(cfg, {tuple(k.split(".")): v for k, v in (overrides or {}).items()}, stage) if overrides else cfg


def _override(cfg, items: dict[tuple[str, ...], object], what: str):
    """``cfg`` with the fields ``items`` set (keys are paths: ``("occluders", "max_height_m")``),
    all in one ``replace`` per settings group, so fields checked against each other
    (``coarse_height <= env_height``) may change together in any order."""
    names = {f.name for f in fields(cfg)}
    direct: dict[str, object] = {}
    nested: dict[str, dict] = {}
    for path, value in items.items():
        if path[0] not in names:
            raise ConfigError(f"{what} settings: unknown field {path[0]!r} (fields: {sorted(names)})")
        if len(path) == 1:
            direct[path[0]] = value
        else:
            nested.setdefault(path[0], {})[path[1:]] = value
    for head, sub_items in nested.items():
        sub = direct.get(head, getattr(cfg, head))
        if not is_dataclass(sub):
            raise ConfigError(f"{what}.{head}: not a group of settings (no field "
                              f"{'.'.join(next(iter(sub_items)))!r})")
        direct[head] = _override(sub, sub_items, f"{what}.{head}")
    return replace(cfg, **direct)


def scale_iterations(cfg, scale: float):
    """``cfg`` with its iteration counts (and the volume stage's density schedule) scaled."""
    if not (isinstance(scale, (int, float)) and scale > 0 and scale < float("inf")):
        raise ConfigError(f"iterations_scale: must be a finite number > 0, got {scale!r}")
    if scale != 1.0 and is_dataclass(getattr(cfg, "fit", None)) and hasattr(cfg.fit, "steps"):
        return replace(cfg, fit=replace(cfg.fit, steps=max(1, round(cfg.fit.steps * scale))))  # the corrector
    if scale == 1.0 or not hasattr(cfg, "iterations"):
        return cfg  # a stage without iterations (generative_refine) is not scaled
    upd = {"iterations": max(1, round(cfg.iterations * scale))}
    for k in ("densify_from", "densify_until", "densify_every"):
        if hasattr(cfg, k) and getattr(cfg, k) < 10**8:
            upd[k] = max(1 if k == "densify_every" else 0, round(getattr(cfg, k) * scale))
    return replace(cfg, **upd)


def _jsonable(x):
    if is_dataclass(x):
        return {f.name: _jsonable(getattr(x, f.name)) for f in fields(x)}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, float) and x != x:
        return None
    return x


def write_json(path: Path, obj) -> None:
    """JSON written to a temporary name and renamed (NaN -> null: the file is always valid JSON)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    from core.io.atomic import atomic_output

    text = json.dumps(_jsonable(obj), indent=1, allow_nan=False)
    with atomic_output(path) as tmp:
        Path(tmp).write_text(text)


@dataclass
class RunDir:
    """A reconstruction run: ``run.json`` (scene, profile, stages) and one directory per stage."""

    root: Path
    _meta: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)

    @classmethod
    def create(cls, root: str | Path, scene: str | Path, profile: str) -> "RunDir":
        r = cls(Path(root))
        r.root.mkdir(parents=True, exist_ok=True)
        write_json(r.root / RUN_FILE, {"format": "brdfusion-run", "version": 1, "scene": str(Path(scene).resolve()),
                                       "profile": profile, "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
        return r

    @property
    def meta(self) -> dict:
        if not self._meta:
            f = self.root / RUN_FILE
            if not f.is_file():
                raise ConfigError(f"{self.root}: not a reconstruction run (no {RUN_FILE}); make one with "
                                  f"'brdf reconstruct --scene S --out {self.root}'")
            try:
                self._meta = json.loads(f.read_text())
            except ValueError as exc:
                raise FormatError(f"{f}: not valid JSON ({exc})") from exc
        return self._meta

    def scene_path(self) -> Path:
        return Path(self.meta["scene"])

    @property
    def profile(self) -> str:
        return str(self.meta.get("profile", "quick"))

    def stage_dir(self, name: str) -> Path:
        return self.root / name

    def is_done(self, name: str) -> bool:
        return (self.stage_dir(name) / DONE_FILE).is_file()

    def done_stages(self) -> list[str]:
        return [s for s in STAGES if self.is_done(s)]

    def mark_done(self, name: str, summary: dict) -> None:
        write_json(self.stage_dir(name) / "summary.json", summary)
        write_json(self.stage_dir(name) / DONE_FILE, {"stage": name, "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                                      "seconds": summary.get("seconds")})

    def summary(self, name: str) -> dict | None:
        f = self.stage_dir(name) / "summary.json"
        return json.loads(f.read_text()) if f.is_file() else None

    # -- the latest outputs ------------------------------------------------------------------
    def latest_graph_dir(self, before: str | None = None) -> tuple[Path, str] | None:
        """``(checkpoint dir, stage)`` of the latest done stage with a scene graph (only stages
        before ``before`` in chain order when given)."""
        limit = STAGES.index(before) if before is not None else len(STAGES)
        for st in reversed(GRAPH_STAGES):
            if STAGES.index(st) < limit and self.is_done(st):
                return self.stage_dir(st) / "checkpoint", st
        return None

    def load_scene(self, before: str | None = None):
        """(SceneGraph, SkyDome, stage) of the latest reconstructed scene (its occluders replaced by
        a later stage's choice, :data:`OCCLUDER_STAGES`, when there is one before ``before``)."""
        import torch

        from core.scene_graph import SceneGraph
        from core.stages.wall_heights import OCCLUDERS_FILE, load_occluders
        from core.train.sky import SkyDome

        found = self.latest_graph_dir(before)
        if found is None:
            raise ConfigError(f"{self.root}: no finished stage with a scene graph (run the volume stage first)")
        d, st = found
        graph = SceneGraph.load(d / "scene_graph.pt")
        # occluders a later stage chose for this graph (the pbr stage's wall heights)
        limit = STAGES.index(before) if before is not None else len(STAGES)
        for ost in reversed(OCCLUDER_STAGES):
            f = self.stage_dir(ost) / OCCLUDERS_FILE
            if STAGES.index(st) < STAGES.index(ost) < limit and self.is_done(ost) and f.is_file():
                graph.occluders = load_occluders(f)
                break
        f = d / "sky.pt"
        sky = (SkyDome.from_state(torch.load(f, map_location="cpu", weights_only=True)["sky"]) if f.is_file()
               else SkyDome(64, 128))
        return graph, sky, st

    def latest_envmap(self, before: str | None = None) -> tuple[Path | None, str | None]:
        limit = STAGES.index(before) if before is not None else len(STAGES)
        for st in reversed(ENVMAP_STAGES):
            if STAGES.index(st) < limit and self.is_done(st) and (self.stage_dir(st) / "envmap.exr").is_file():
                return self.stage_dir(st) / "envmap.exr", st
        return None, None

    def latest_priors(self, bundle, before: str, threads: int = 2):
        """(GBufferPriors, source) for a stage: the latest refined priors before it, else the
        inverse model's (computed once and cached in ``priors/``)."""
        from core.stages.priors import GBufferPriors, load_or_compute_priors

        limit = STAGES.index(before)
        for st in reversed(PRIOR_STAGES):
            if STAGES.index(st) < limit and self.is_done(st):
                return GBufferPriors.load(self.stage_dir(st) / "priors.npz")[0], st
        pri, _ = load_or_compute_priors(bundle, self.root / "priors" / "priors.npz", threads=threads)
        return pri, "inverse_model"


def scene_skips(bundle, stage: str) -> list[str]:
    """What ``stage`` leaves out because the bundle does not have it (for the stage summary)."""
    m = bundle.manifest
    out = []
    if not m.lidar and stage in ("volume", "volume2", "joint"):
        out.append("LiDAR depth term: the bundle has no LiDAR")
    if not any(f.sky_mask for f in m.frames) and stage in ("volume", "volume2", "pbr", "joint"):
        out.append("sky masks: the bundle has no sky masks; non-sky pixels come from the render's opacity"
                   + (" and the prior's surfaces" if stage != "pbr" else ""))
    if not m.objects:
        out.append("object nodes: the bundle has no tracked objects (background only)")
    return out


def _load() -> float:
    """The 1-minute load average (0 where the platform has none)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return 0.0


def run_stage(name: str, bundle, run: RunDir, settings=None, *, progress: bool = True,
              on_progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """Run one stage on ``run`` (its inputs must be done) and mark it done. Returns its summary.
    A stage killed part-way resumes from ``<stage>/resume/`` when run again."""
    import importlib

    spec = stage_spec(name)
    missing = [r for r in spec.reads if not run.is_done(r)]
    if missing:
        raise ConfigError(f"stage {name!r}: needs the stage(s) {missing} to be done first in {run.root}")
    cfg = settings if settings is not None else profile_settings(run.profile, name)
    if not isinstance(cfg, spec.settings_type):
        raise ConfigError(f"settings: stage {name!r} takes {spec.settings_type.__name__}, got {type(cfg).__name__}")
    mod = importlib.import_module(spec.module)
    ctx = StageContext(name, bundle, run, cfg, progress, on_progress)
    ctx.out_dir.mkdir(parents=True, exist_ok=True)
    t0, c0, load0 = time.perf_counter(), time.process_time(), _load()
    summary = mod.run_stage(ctx)
    summary = {"stage": name, "paper": spec.paper, "settings": _jsonable(cfg), **summary}
    summary.setdefault("skipped", scene_skips(bundle, name))
    summary.setdefault("seconds", round(time.perf_counter() - t0, 2))
    # CPU seconds of this process (all its threads) and the machine's load: wall seconds alone
    # mislead on a shared machine (a stage run beside other jobs takes longer for no fault of its own)
    summary.setdefault("cpu_seconds", round(time.process_time() - c0, 2))
    summary.setdefault("load_average", [round(load0, 2), round(_load(), 2)])
    run.mark_done(name, summary)
    return summary


def resolve_stages(stages) -> tuple[str, ...]:
    """Requested stages in chain order, each once (None = :data:`DEFAULT_STAGES`); ConfigError
    naming unknown ones."""
    if stages is None:
        return DEFAULT_STAGES
    stages = [s.strip() for s in (stages.split(",") if isinstance(stages, str) else stages) if s.strip()]
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise ConfigError(f"stages: unknown stage(s) {bad} (stages: {list(STAGES)})" if bad
                          else "stages: at least one stage is needed")
    return tuple(s for s in STAGES if s in stages)


def run_pipeline(scene: str | Path, run_dir: str | Path, profile: str = "quick", *, stages=None,
                 resume: bool = False, progress: bool = True, overrides: dict[str, dict] | None = None,
                 iterations_scale: float = 1.0,
                 on_stage: Callable[[str, str, dict | None], None] | None = None) -> dict:
    """Run the chain (or ``stages`` of it) on the bundle at ``scene`` into ``run_dir``.

    ``resume``: continue an existing run (done stages are kept, a killed stage resumes from its
    checkpoint). Without it, an existing run directory is an error (nothing stored is lost).
    ``overrides``: ``{stage: {field: value}}``. ``on_stage(stage, "start"|"done"|"skip",
    summary)``. Returns ``{stage: summary}`` of the stages run or kept."""
    from core.bundle import open_bundle

    if profile not in PROFILE_NAMES:
        raise ConfigError(f"profile: unknown profile {profile!r} (profiles: {list(PROFILE_NAMES)})")
    wanted = resolve_stages(stages)
    root = Path(run_dir)
    if (root / RUN_FILE).is_file():
        if not resume:
            raise ConfigError(f"{root}: a run already exists there (stages done: {RunDir(root).done_stages()}); "
                              f"pass --resume to continue it or choose another --out")
        run = RunDir(root)
        if run.profile != profile:
            raise ConfigError(f"profile: the run in {root} was made with profile {run.profile!r}, not {profile!r}")
        recorded, given = run.scene_path(), Path(scene).resolve()
        if recorded != given and recorded.is_dir():  # (an archive's unpacked copy may be gone: not checked)
            raise ConfigError(f"scene: the run in {root} reconstructs {recorded}, not {given}; resume it with "
                              f"that scene (the CLI takes it from the run when --scene is left out)")
    else:
        run = RunDir.create(root, scene, profile)
    bundle = open_bundle(scene)
    out: dict = {}
    for name in wanted:
        if run.is_done(name) and resume:
            out[name] = run.summary(name)
            if on_stage:
                on_stage(name, "skip", out[name])
            continue
        cfg = scale_iterations(profile_settings(profile, name, (overrides or {}).get(name)), iterations_scale)
        if on_stage:
            on_stage(name, "start", None)
        out[name] = run_stage(name, bundle, run, cfg, progress=progress)
        if on_stage:
            on_stage(name, "done", out[name])
    return out


__all__ = ["STAGES", "PAPER_STAGES", "DEFAULT_STAGES", "PROFILE_NAMES", "StageSpec", "StageContext", "RunDir", "stage_spec", "profile_settings",
           "run_stage", "run_pipeline", "resolve_stages", "scale_iterations", "write_json"]
