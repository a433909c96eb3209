"""The inverse-rendering pipeline measured end to end: reconstruct (``core.stages.chain``) and
evaluate (``core.synth.evaluate``, the paper's metrics) on development and test streets made by
``brdf generate``, plus the bundled default scene; writes ``benchmarks/results/eval.json``.

Protocol: choices are made on the development streets (and the default scene, which is the
development scene of the quick profile); the test streets are run once at the end. Each street's
seed, map and rotation are used nowhere else in the project (not in the generative models'
training data, not in the lighting prior's development streets).

    python benchmarks/eval_pipeline.py --data /path/to/streets --profile benchmark   # the figures
    python benchmarks/eval_pipeline.py --data /path/to/streets --profile quick --roles dev   # a cheaper look

Missing streets are generated first (about 8 min each on 2 cores). Runs are kept under
``<data>/runs/<street>_<profile>_<row>`` and resumed, so an interrupted benchmark continues.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.stages.chain import DEFAULT_STAGES, PAPER_STAGES  # noqa: E402

#: name -> (role, seed, map, rotation in degrees). City and sunrise are the sunny maps.
STREETS = {
    "dev1": ("dev", 101, "city", 60.0),
    "dev2": ("dev", 102, "sunrise", 200.0),
    "test1": ("test", 201, "city", 130.0),
    "test2": ("test", 202, "sunrise", 300.0),
}
#: How the streets are generated: the quick synth profile at 16 + 16 frames, 128 samples per
#: pixel, relit ground truth under three held-back maps on every 4th test frame.
STREET_SETTINGS = ("relight_every=4", "num_frames=16", "spp=128")
#: Pipeline variants (the paper's Table 2 rows): stages, stage overrides, the denoiser of the
#: evaluation's renders, and ``seed``: ``(row, stages)`` whose finished stage directories are copied
#: from that row's run of the same street first (the same stage with the same settings is not
#: run twice: an ablation row differs from its seed only in what it leaves out).
ALL_STAGES = DEFAULT_STAGES  # the paper's five and the corrector: what the full row runs
NO_PRIORS = {"lambda_normal": 0.0, "lambda_albedo": 0.0, "lambda_roughness": 0.0, "lambda_metallic": 0.0}
ROWS = {
    "full": {"stages": None, "overrides": {}, "denoiser": "oidn", "seed": None},
    "colour_only": {"stages": ["volume"], "overrides": {"volume": {**NO_PRIORS, "lambda_prior_depth": 0.0}},
                    "denoiser": "oidn", "seed": None},
    # Table 2 "w/o PBR optim.": volume, refinement and volume2 only; materials from the Gaussians,
    # no recovered lighting (no re-render, no sun)
    "no_pbr_optim": {"stages": ["volume", "generative_refine", "volume2"], "overrides": {}, "denoiser": "oidn",
                     "seed": ("full", ("volume", "generative_refine", "volume2"))},
    # Table 2 "w/o gen. optim.": no inverse-model priors and no refinement: the colour-only volume
    # stage, then pbr and joint with every prior weight at 0
    "no_gen_optim": {"stages": ["volume", "pbr", "joint"],
                     "overrides": {"volume": {**NO_PRIORS, "lambda_prior_depth": 0.0},
                                   "joint": {**NO_PRIORS, "lambda_prior_depth": 0.0}},
                     "denoiser": "oidn", "seed": ("colour_only", ("volume",))},
    # Table 2 "w/o gen. rendering": the full reconstruction, its physical render shown as it is
    # (no generative forward pass, no denoiser) ...
    "no_gen_render": {"stages": None, "overrides": {}, "denoiser": "none", "seed": ("full", ALL_STAGES)},
    # ... and with the generative forward pass (the diffusion model, SDEdit from the physical
    # render) instead of the product's default OIDN denoiser
    "gen_render": {"stages": None, "overrides": {}, "denoiser": "diffusion", "seed": ("full", ALL_STAGES)},
    # the full row without the corrector stage (core/stages/corrector.py, not the paper's; applied
    # only under the light it was fitted at, so it moves the re-render and nothing else)
    "no_corrector": {"stages": list(PAPER_STAGES), "overrides": {}, "denoiser": "oidn",
                     "seed": ("full", PAPER_STAGES)},
}
KEYS = ("albedo_si_psnr", "roughness_rmse", "metallic_rmse", "normal_mae_deg", "nvs_psnr", "nvs_ssim", "nvs_flip",
        "rerender_psnr", "relight_psnr", "relight_ssim", "relight_flip", "relight_unrelit_input_ssim",
        "sun_error_deg")


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}


def make_street(data: Path, name: str) -> Path:
    role, seed, envmap, rot = STREETS[name]
    out = data / name
    if (out / "bundle.json").is_file():
        return out
    cmd = [sys.executable, "-m", "core", "generate", "--profile", "quick", "--seed", str(seed), "--envmap", envmap,
           "--set", f"envmap_rotation_deg={rot}", "--out", str(out), "--workers", "2", "--quiet"]
    for kv in STREET_SETTINGS:
        cmd += ["--set", kv]
    print("generating", name, ":", " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO)
    return out


def seed_run(src: Path, dst: Path, stages) -> None:
    """Copy ``stages``' finished directories (and the cached priors) of the run ``src`` into a new
    run ``dst``; nothing is copied into an existing run."""
    import shutil

    from core.stages.chain import RUN_FILE, RunDir

    if (dst / RUN_FILE).is_file():
        return
    run = RunDir(src)
    missing = [s for s in stages if not run.is_done(s)]
    if missing:
        raise SystemExit(f"{src}: stages {missing} are not done (run its row first)")
    dst.mkdir(parents=True, exist_ok=True)
    for st in stages:
        shutil.copytree(src / st, dst / st, dirs_exist_ok=True)
    if (src / "priors").is_dir():
        shutil.copytree(src / "priors", dst / "priors", dirs_exist_ok=True)
    shutil.copy2(src / RUN_FILE, dst / RUN_FILE)


def run_row(scene: Path, runs: Path, prefix: str, profile: str, row: str) -> dict:
    """Reconstruct (resuming a kept run; a seeded row first copies its seed row's stages, running
    the seed row when needed) and evaluate; the evaluation summary plus timings."""
    from core.synth.evaluate import EvalSettings, evaluate_run
    from core.stages.chain import RUN_FILE, RunDir, run_pipeline

    spec = ROWS[row]
    run_dir = runs / f"{prefix}_{profile}_{row}"
    seeded: tuple = ()
    if spec["seed"] is not None:
        src_row, seeded = spec["seed"]
        src = runs / f"{prefix}_{profile}_{src_row}"
        if not ((src / RUN_FILE).is_file() and all(RunDir(src).is_done(st) for st in seeded)):
            print(f"    seed row {src_row} first", flush=True)
            run_pipeline(scene, src, profile, stages=ROWS[src_row]["stages"], overrides=ROWS[src_row]["overrides"],
                         resume=(src / RUN_FILE).is_file(), progress=False)
        seed_run(src, run_dir, seeded)
    t0 = time.perf_counter()
    res = run_pipeline(scene, run_dir, profile, stages=spec["stages"], overrides=spec["overrides"],
                       resume=(run_dir / RUN_FILE).is_file(), progress=False,
                       on_stage=lambda n, w, s: print(f"    {n}: {w}", flush=True))
    wall = time.perf_counter() - t0
    ev = evaluate_run(run_dir, settings=EvalSettings(denoiser=spec["denoiser"]))
    run = RunDir(run_dir)
    stage_seconds = {n: float((run.summary(n) or {}).get("seconds") or 0.0) for n in res}
    return {**{k: ev["summary"].get(k) for k in KEYS}, "stage_seconds": stage_seconds,
            "pipeline_seconds": round(sum(stage_seconds.values()), 1), "wall_seconds_this_call": round(wall, 1),
            "stages_reused_from": spec["seed"][0] if seeded else None,
            "evaluation_seconds": ev["seconds"], "denoiser": spec["denoiser"]}


def role_means(rows: dict[str, dict], variants, keys) -> dict:
    """Means per role of per-street rows ``{street: {"role": ..., variant: {key: value}}}``: for
    each role, each variant's mean of every key (None values left out) and the role's streets."""
    means = {}
    for role in sorted({r["role"] for r in rows.values()}):
        sel = [r for r in rows.values() if r["role"] == role]
        means[role] = {v: {k: round(float(np.mean([r[v][k] for r in sel if r[v].get(k) is not None])), 4)
                           for k in keys if any(r[v].get(k) is not None for r in sel)}
                       for v in variants if all(v in r for r in sel)}
        means[role]["streets"] = [s for s, r in rows.items() if r["role"] == role]
    return means


def mean_row(rows: list[dict]) -> dict:
    out = {}
    for k in KEYS:
        v = [r[k] for r in rows if isinstance(r.get(k), (int, float)) and math.isfinite(r[k])]
        out[k] = round(float(np.mean(v)), 4) if v else None
    st: dict[str, list] = {}
    for r in rows:
        for n, s in r["stage_seconds"].items():
            st.setdefault(n, []).append(s)
    out["stage_seconds"] = {n: round(float(np.mean(v)), 1) for n, v in st.items()}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="directory of the streets (generated when missing) and runs; not needed "
                                   "with --merge-from")
    ap.add_argument("--profile", default="benchmark", help="reconstruction profile of the streets")
    ap.add_argument("--roles", default="dev,test", help="which streets: dev, test or both")
    ap.add_argument("--streets", default="", help=f"comma-separated subset of {sorted(STREETS)} (default: all of --roles), run in this order")
    ap.add_argument("--rows", default="full", help=f"comma-separated rows of {sorted(ROWS)}")
    ap.add_argument("--default-scene", action="store_true", help="also the bundled default scene at --default-profile")
    ap.add_argument("--default-profile", default="quick")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "eval.json"))
    ap.add_argument("--merge-from", nargs="+", default=[], metavar="STREET=JSON",
                    help="only merge: copy STREET's per-street rows (every row and profile) from JSON, the --out "
                         "of a run of this script beside another (e.g. streets run side by side), into --out and "
                         "recompute the means; no street is run")
    a = ap.parse_args()
    if not a.data and (not a.merge_from or a.default_scene):
        ap.error("--data: required unless only merging with --merge-from (the directory of the streets and "
                 "their runs)")
    data = Path(a.data) if a.data else None
    roles = set(a.roles.split(","))
    rows = [r for r in a.rows.split(",") if r]
    bad = [r for r in rows if r not in ROWS]
    if bad:
        ap.error(f"--rows: unknown {bad} (rows: {sorted(ROWS)})")
    out_path = Path(a.out)
    result = json.loads(out_path.read_text()) if out_path.is_file() else {}
    result.update({"machine": machine(), "protocol": __doc__.split("\n\n")[1].replace("\n", " "),
                   "streets_generated_with": {"profile": "quick", "settings": list(STREET_SETTINGS),
                                              "streets": {n: {"role": r, "seed": s, "envmap": m, "rotation_deg": d}
                                                          for n, (r, s, m, d) in STREETS.items()}}})
    per = result.setdefault("per_street", {})
    for spec in a.merge_from:
        street, _, src = spec.partition("=")
        if street not in STREETS or not src:
            ap.error(f"--merge-from: expected STREET=JSON with STREET in {sorted(STREETS)}, got {spec!r}")
        if not Path(src).is_file():
            ap.error(f"--merge-from: {src}: no such results file (for street {street})")
        other = json.loads(Path(src).read_text()).get("per_street", {})
        for row, by_profile in other.items():
            for prof, streets in by_profile.items():
                if street in streets:
                    per.setdefault(row, {}).setdefault(prof, {})[street] = streets[street]
    names = [] if a.merge_from else ([n for n in a.streets.split(",") if n] or list(STREETS))
    unknown = [n for n in names if n not in STREETS]
    if unknown:
        ap.error(f"--streets: unknown {unknown} (streets: {sorted(STREETS)})")
    for name in names:
        role = STREETS[name][0]
        if role not in roles:
            continue
        scene = make_street(data, name)
        for row in rows:
            print(f"{name} ({role}) {row} at {a.profile} ...", flush=True)
            r = run_row(scene, data / "runs", name, a.profile, row)
            per.setdefault(row, {}).setdefault(a.profile, {})[name] = {"role": role, **r}
            out_path.write_text(json.dumps(result, indent=1))
    if a.default_scene:
        for row in rows:
            print(f"default scene {row} at {a.default_profile} ...", flush=True)
            r = run_row(REPO / "data" / "scenes" / "default", data / "runs", "default", a.default_profile, row)
            result.setdefault("default_scene", {}).setdefault(row, {})[a.default_profile] = r
            out_path.write_text(json.dumps(result, indent=1))
    # the rows: means over the test streets (dev beside, as <row>_dev), per profile; the row's
    # top-level figures are those of the benchmark profile when measured, else of the largest
    for row, by_profile in per.items():
        for prof, streets in by_profile.items():
            for role in ("test", "dev"):
                sel = {n: v for n, v in streets.items() if v["role"] == role}
                if not sel:
                    continue
                key = row if role == "test" else f"{row}_dev"
                by = result.get(key, {}).get("by_profile", {})
                by[prof] = {**mean_row(list(sel.values())), "profile": prof, "scene_count": len(sel),
                            "streets": sorted(sel)}
                pick = next(p for p in ("benchmark", "paper", "quick", "tiny") if p in by)
                new = {**by[pick], "by_profile": by}
                # what was written by hand beside the figures (``how``, notes) stays
                kept = {k: v for k, v in result.get(key, {}).items() if k not in new}
                result[key] = {**kept, **new}
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: result.get(k) for k in ("full", "full_dev")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
