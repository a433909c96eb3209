"""The README's main job (``brdf demo``: reconstruct, relight, night clip, evaluate, sheet) on the
bundled default scene, timed over several fresh runs (nothing resumed): per-part wall seconds,
process CPU seconds and the metrics, with their medians.

    python benchmarks/bench_demo.py --runs 2 [--profile quick] [--out benchmarks/results/demo.json]

The README's first command also sets up the environment (``scripts/setup.sh``, about 80 s on a
fresh clone with the package caches warm); this benchmark times the job alone.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.demo import DemoSettings, run_demo  # noqa: E402
from core.stages.chain import PROFILE_NAMES  # noqa: E402

SCENE = REPO / "data" / "scenes" / "default"
METRICS = ("relight_psnr", "relight_ssim", "relight_flip", "rerender_psnr", "nvs_psnr", "albedo_si_psnr",
           "normal_mae_deg", "roughness_rmse", "metallic_rmse", "sun_error_deg")


def machine() -> dict:
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), "unknown")
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=2, help="fresh runs (>= 1); medians over them")
    ap.add_argument("--profile", default="quick", choices=PROFILE_NAMES)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "demo.json"))
    a = ap.parse_args()
    if a.runs < 1:
        ap.error("--runs: must be >= 1")
    info = {"machine": machine(), "profile": a.profile, "scene": "data/scenes/default (development scene)",
            "threads": "2 (the stages' defaults: rasterizer and PBR threads 2, torch 1)",
            "load_average_at_start": round(os.getloadavg()[0], 2)}
    print(json.dumps(info, indent=1), flush=True)
    runs = []
    for i in range(a.runs):
        work = Path(tempfile.mkdtemp(prefix="brdf-bench-demo-"))
        try:
            c0, t0 = cpu_seconds(), time.perf_counter()
            res = run_demo(SCENE, work, DemoSettings(profile=a.profile), progress=False, say=lambda _m: None)
            row = {"seconds": res["seconds"], "cpu_seconds": round(cpu_seconds() - c0, 1),
                   "wall_seconds": round(time.perf_counter() - t0, 1),
                   "load_average_at_end": round(os.getloadavg()[0], 2),
                   "metrics": {k: (res["metrics"] or {}).get(k) for k in METRICS}}
        finally:
            shutil.rmtree(work, ignore_errors=True)
        runs.append(row)
        print(f"run {i + 1}/{a.runs}: {json.dumps(row)}", flush=True)
    parts = sorted({k for r in runs for k in r["seconds"]})
    med = {"seconds": {k: round(statistics.median(r["seconds"][k] for r in runs if k in r["seconds"]), 1)
                       for k in parts},
           "cpu_seconds": round(statistics.median(r["cpu_seconds"] for r in runs), 1),
           "metrics": {k: (round(statistics.median(v), 4) if (v := [r["metrics"][k] for r in runs
                                                                  if r["metrics"][k] is not None]) else None)
                       for k in METRICS}}
    result = {**info, "runs": runs, "median": med}
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({"median": med}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
