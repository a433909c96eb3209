"""Run time against error for the whole pipeline (``core.stages.chain``) on the bundled default
scene, the development scene of the quick profile: each stage's error at its end against the
cumulative wall time, and a front of whole-pipeline configurations (profile, iteration scale,
Gaussian budget; rays per pixel of the render) with seconds against relight PSNR.

    python benchmarks/bench_runtime.py --data /root/brdf_data/runtime
    python benchmarks/bench_runtime.py --data D --configs tiny,quick,benchmark   # a subset

The profiles are set on this front: ``quick`` at its knee, ``benchmark`` at its plateau (the
cheapest point within the run-to-run spread of the best relight PSNR, costs within the VM's
timing spread counting as equal).

Per stage, the error is measured on a copy of the run cut after that stage (the later stages'
directories left out), so "after volume" is exactly what the volume stage handed on. Errors:
relight PSNR (held-back maps, through the relight path), albedo si-PSNR, normal MAE. Runs are kept
under ``<data>/<config>`` and resumed; evaluations are cached next to them. Writes
``benchmarks/results/runtime_vs_error.json`` and ``runtime_vs_error.png`` (the profiles marked).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.stages.chain import RUN_FILE, STAGES, RunDir, run_pipeline  # noqa: E402

SCENE = REPO / "data" / "scenes" / "default"
#: name -> (profile, iterations scale, stage overrides). Scales multiply every stage's iterations
#: (``run_pipeline(iterations_scale=)``), so a front point is a whole pipeline run on its own.
#: ``long`` is the benchmark profile with the counts it had before it was set on this front (7000 +
#: 3000 volume iterations, 200k Gaussians, 400 pbr and 600 joint iterations).
LONG = {"volume": {"iterations": 7000, "densify_until": 4000, "opacity_reset_every": 3000,
                   "density.max_gaussians": 200_000},
        "volume2": {"iterations": 3000, "density.max_gaussians": 200_000},
        "pbr": {"iterations": 400}, "joint": {"iterations": 600}}
CONFIGS = {
    "tiny": ("tiny", 1.0, {}),
    "benchmark_x0.25": ("benchmark", 0.25, {}),
    "quick": ("quick", 1.0, {}),
    "benchmark": ("benchmark", 1.0, {}),
    "benchmark_40k": ("benchmark", 1.0, {"volume": {"density.max_gaussians": 40_000},
                                         "volume2": {"density.max_gaussians": 40_000}}),
    "benchmark_x2": ("benchmark", 2.0, {}),
    "long": ("benchmark", 1.0, LONG),
}
#: Relight PSNR spread of one configuration run twice (test1, the benchmark profile's settings, two
#: sessions: 19.49 and 18.97 dB; ``eval.json`` ``notes``): differences below it are not read as gains.
RUN_SPREAD_DB = 0.52
#: Relative spread of this VM's speed between runs minutes apart (README, the PBR pass row): costs
#: closer than this are the same cost.
TIME_SPREAD = 0.15
#: Rays per pixel of the evaluation render swept on the ``benchmark`` run (render cost, not training).
RAYS = (16, 64, 256)
#: Stages after which the error is measured (generative_refine changes priors only; pbr changes
#: the map only, which relight under held-back maps does not use).
CUT_AFTER = ("volume", "volume2", "joint")
KEYS = ("relight_psnr", "relight_ssim", "albedo_si_psnr", "normal_mae_deg", "rerender_psnr", "nvs_psnr")


def machine() -> dict:
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), "unknown")
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}


def cut_copy(run_dir: Path, after: str, dst: Path) -> Path:
    """A copy of ``run_dir`` with only the stages up to ``after`` (hard links: no extra space)."""
    if (dst / RUN_FILE).is_file():
        return dst
    keep = STAGES[:STAGES.index(after) + 1]
    dst.mkdir(parents=True, exist_ok=True)
    for st in keep:
        if (run_dir / st).is_dir():
            shutil.copytree(run_dir / st, dst / st, copy_function=os.link, dirs_exist_ok=True)
    shutil.copy2(run_dir / RUN_FILE, dst / RUN_FILE)
    return dst


def evaluate(run_dir: Path, rays: int, max_frames: int) -> dict:
    """Cached :func:`core.synth.evaluate.evaluate_run` summary (and its seconds)."""
    from core.synth.evaluate import EvalSettings, evaluate_run

    f = run_dir / f"bench_eval_r{rays}_f{max_frames}.json"
    if f.is_file():
        return json.loads(f.read_text())
    ev = evaluate_run(run_dir, settings=EvalSettings(rays_per_pixel=rays, max_frames=max_frames, flip=False),
                      out=run_dir / f"eval_r{rays}")
    row = {**{k: ev["summary"].get(k) for k in KEYS}, "evaluation_seconds": ev["seconds"]}
    f.write_text(json.dumps(row, indent=1))
    return row


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both seconds (lower) and PSNR (higher)."""
    return [i for i, (s, p) in enumerate(points)
            if not any((s2 <= s and p2 >= p) and (s2 < s or p2 > p) for s2, p2 in points)]


def knee(points: list[tuple[float, float]], front: list[int]) -> int | None:
    """The front point farthest above the chord from its cheapest to its best point, with seconds
    on a log axis (Kneedle on the normalised front)."""
    if len(front) < 3:
        return None
    f = sorted(front, key=lambda i: points[i][0])
    x = np.log([points[i][0] for i in f])
    y = np.array([points[i][1] for i in f])
    xn = (x - x[0]) / max(x[-1] - x[0], 1e-9)
    yn = (y - y[0]) / max(y[-1] - y[0], 1e-9)
    return f[int(np.argmax(yn - xn))]


def plateau(points: list[tuple[float, float]], front: list[int], spread: float,
            time_spread: float = TIME_SPREAD) -> int | None:
    """Where the front stops rising by more than a run-to-run difference: of the front points
    whose PSNR is within ``spread`` of the best, the cheapest, where costs within ``time_spread``
    (relative) of the cheapest count as equal and the higher PSNR among them wins."""
    if not front:
        return None
    best = max(points[i][1] for i in front)
    near = [i for i in front if points[i][1] >= best - spread]
    cheapest = min(points[i][0] for i in near)
    return max((i for i in near if points[i][0] <= cheapest * (1 + time_spread)), key=lambda i: points[i][1])


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.6))
    for name, c in result["configs"].items():
        cpu = c.get("stage_cpu_seconds") or {}
        use = all(cpu.get(st) is not None for st in STAGES)
        cum = np.cumsum([cpu[st] if use else c["stage_seconds"][st] for st in STAGES])
        xs = [float(cum[STAGES.index(st)]) for st in c["after_stage"]]
        for k, a in (("relight_psnr", ax[0]), ("albedo_si_psnr", ax[1]), ("normal_mae_deg", ax[2])):
            a.plot(xs, [s[k] for s in c["after_stage"].values()], "o-", label=name)
    for a, t in zip(ax, ("relight PSNR (dB)", "albedo si-PSNR (dB)", "normal MAE (deg)")):
        a.set_xscale("log")
        a.set_xlabel("cumulative pipeline CPU seconds (points: after volume, volume2, joint)")
        a.set_ylabel(t)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7)
    fr = result["front"]
    pts = fr["points"]
    ax[0].scatter([p["seconds"] for p in pts], [p["relight_psnr"] for p in pts], marker="x", c="k", zorder=5)
    on = sorted((p for p in pts if p["on_front"]), key=lambda p: p["seconds"])
    ax[0].plot([p["seconds"] for p in on], [p["relight_psnr"] for p in on], "k--", lw=1, label="front")
    if fr.get("knee"):
        k = next(p for p in pts if p["name"] == fr["knee"])
        ax[0].annotate(f"knee: {k['name']}", (k["seconds"], k["relight_psnr"]), textcoords="offset points",
                       xytext=(-90, 25), arrowprops={"arrowstyle": "->"})
    if fr.get("plateau"):
        k = next(p for p in pts if p["name"] == fr["plateau"])
        ax[0].annotate(f"plateau (within {fr['spread_db']} dB of the best): {k['name']}",
                       (k["seconds"], k["relight_psnr"]), textcoords="offset points", xytext=(-20, -70),
                       arrowprops={"arrowstyle": "->"}, fontsize=8)
    for p in pts:  # the profiles as shipped (iteration scale 1, no overrides)
        c = result["configs"][p["name"]]
        if c["iterations_scale"] == 1.0 and not c["overrides"]:
            ax[0].scatter([p["seconds"]], [p["relight_psnr"]], s=140, facecolors="none", edgecolors="r", zorder=6)
            ax[0].annotate(f"profile {c['profile']}", (p["seconds"], p["relight_psnr"]), textcoords="offset points",
                           xytext=(6, -14), color="r", fontsize=8)
    ax[0].set_title("relight PSNR (x: front configurations, red: profiles)", fontsize=10)
    fig.suptitle(f"run time against error, default scene ({result['machine']['cores']} cores)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="directory of the runs (kept and resumed)")
    ap.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated of {list(CONFIGS)}")
    ap.add_argument("--max-frames", type=int, default=4, help="test frames evaluated per point (0 = all)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "runtime_vs_error.json"))
    a = ap.parse_args()
    names = [n for n in a.configs.split(",") if n]
    bad = [n for n in names if n not in CONFIGS]
    if bad:
        ap.error(f"--configs: unknown {bad} (configs: {list(CONFIGS)})")
    data = Path(a.data)
    out = Path(a.out)
    result = json.loads(out.read_text()) if out.is_file() else {}
    result.update({"machine": machine(), "load_average_at_start": round(os.getloadavg()[0], 2), "scene": "data/scenes/default (development scene)",
                   "threads": int(os.environ.get("OMP_NUM_THREADS", 0)) or None,
                   "max_frames": a.max_frames, "note": __doc__.split("\n\n")[1].replace("\n", " ")})
    configs = result.setdefault("configs", {})
    for name in names:
        prof, scale, ov = CONFIGS[name]
        run_dir = data / name
        print(f"{name}: {prof} x{scale} {ov or ''}", flush=True)
        t0 = time.perf_counter()
        run_pipeline(SCENE, run_dir, prof, overrides=ov, iterations_scale=scale,
                     resume=(run_dir / RUN_FILE).is_file(), progress=False,
                     on_stage=lambda n, w, s: print(f"    {n}: {w}", flush=True))
        run = RunDir(run_dir)
        secs = {st: float(run.summary(st)["seconds"]) for st in STAGES}
        cpu = {st: run.summary(st).get("cpu_seconds") for st in STAGES}
        load = {st: run.summary(st).get("load_average") for st in STAGES}
        after, cum = {}, 0.0
        for st in STAGES:
            cum += secs[st]
            if st in CUT_AFTER:
                d = run_dir if st == STAGES[-1] else cut_copy(run_dir, st, data / "cuts" / f"{name}_{st}")
                after[st] = {"cumulative_seconds": round(cum, 1), **evaluate(d, 64, a.max_frames)}
                print(f"    after {st}: {after[st]}", flush=True)
        configs[name] = {"profile": prof, "iterations_scale": scale, "overrides": ov, "stage_seconds": secs,
                         "stage_cpu_seconds": cpu, "stage_load_average": load,
                         "pipeline_cpu_seconds": (round(sum(cpu.values()), 1) if all(v is not None for v in cpu.values())
                                                  else None),
                         "pipeline_seconds": round(cum, 1), "after_stage": after,
                         "wall_seconds_this_call": round(time.perf_counter() - t0, 1)}
        if name == "benchmark":
            configs[name]["rays_per_pixel"] = {str(r): evaluate(run_dir, r, a.max_frames) for r in RAYS}
        out.write_text(json.dumps(result, indent=1))
    # the front: every configuration's whole pipeline (training seconds) against relight PSNR
    # seconds: the pipeline's CPU seconds when every configuration has them (wall seconds on a
    # shared machine measure the other jobs as much as the pipeline), else wall seconds
    done = {n: c for n, c in configs.items() if c["after_stage"].get("joint", {}).get("relight_psnr") is not None}
    use_cpu = bool(done) and all(c.get("pipeline_cpu_seconds") for c in done.values())
    pts = [{"name": n, "seconds": c["pipeline_cpu_seconds"] if use_cpu else c["pipeline_seconds"],
            "wall_seconds": c["pipeline_seconds"], "relight_psnr": c["after_stage"]["joint"]["relight_psnr"]}
           for n, c in done.items()]
    xy = [(p["seconds"], p["relight_psnr"]) for p in pts]
    fr = pareto(xy)
    for i, p in enumerate(pts):
        p["on_front"] = i in fr
    k = knee(xy, fr)
    pl = plateau(xy, fr, RUN_SPREAD_DB)
    result["front"] = {"points": pts, "knee": pts[k]["name"] if k is not None else None,
                       "plateau": pts[pl]["name"] if pl is not None else None, "spread_db": RUN_SPREAD_DB,
                       "seconds": "process CPU seconds of the pipeline" if use_cpu else "wall seconds of the pipeline",
                       "knee_rule": "Kneedle on the front, log seconds against relight PSNR, both normalised",
                       "plateau_rule": ("the cheapest front point within the run-to-run spread of the best relight "
                                        f"PSNR; costs within {TIME_SPREAD:.0%} of it count as equal (the higher "
                                        "PSNR wins)"),
                       "profiles_rule": "quick is set at the knee, benchmark at the plateau"}
    out.write_text(json.dumps(result, indent=1))
    plot(result, out.with_suffix(".png"))
    print(json.dumps(result["front"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
