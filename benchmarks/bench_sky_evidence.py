"""The observed sky held in the recovered map (``core.lighting.sky_evidence``): with against without.

For each run (its volume, generative_refine and volume2 stages finished), two copies of those
stages get the pbr and joint stages again with this code, ``pbr.sky_evidence.enabled`` true
(the default) and false; both are evaluated (``brdf evaluate``, the paper's metrics
against the bundle's Mitsuba ground truth). The geometry and materials before pbr are the same
files in both, so the difference is the held sky alone (plus the joint stage's small changes to
the Gaussians that follow from the map).

    python benchmarks/eval_pipeline.py --data D --profile quick --roles dev,test --out /tmp/q.json
    python benchmarks/bench_sky_evidence.py D/runs/dev1_quick_full ... --roles dev,... \\
        --out benchmarks/results/sky_evidence.json

Prints the machine, each run's figures with and without, and the means per role.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from eval_pipeline import machine, role_means, seed_run  # noqa: E402

KEYS = ("rerender_psnr", "relight_psnr", "relight_ssim", "relight_flip", "sun_error_deg", "nvs_psnr",
        "albedo_si_psnr", "normal_mae_deg")


def brdf(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "core", *args], check=True, cwd=REPO)


def evaluate(run: Path, out: Path) -> dict:
    if not (out / "evaluation.json").is_file():
        brdf("evaluate", str(run), "--out", str(out))
    return json.loads((out / "evaluation.json").read_text())["summary"]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", help="run directories with volume2 done")
    ap.add_argument("--roles", required=True, help="comma-separated role per run (dev / test)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "sky_evidence.json"))
    a = ap.parse_args()
    roles = a.roles.split(",")
    if len(roles) != len(a.runs):
        ap.error(f"--roles: one per run ({len(a.runs)}), got {len(roles)}")
    t0 = time.perf_counter()
    rows = {}
    for run, role in zip(a.runs, roles):
        run = Path(run).resolve()
        meta = json.loads((run / "run.json").read_text())
        res = {}
        for variant, enabled in (("with", "true"), ("without", "false")):
            d = run.parent / f"{run.name}_sky_{'on' if enabled == 'true' else 'off'}"
            if not (d / "joint" / "done.json").is_file():
                seed_run(run, d, ("volume", "generative_refine", "volume2"))
                brdf("reconstruct", "--scene", meta["scene"], "--profile", meta["profile"], "--stages", "pbr,joint",
                     "--resume", "--out", str(d), "--set", f"pbr.sky_evidence.enabled={enabled}", "--quiet")
            ev = evaluate(d, d.parent / f"{d.name}_eval")
            res[variant] = {k: ev.get(k) for k in KEYS}
        rows[run.name] = {"role": role, "profile": meta["profile"], **res}
        print(json.dumps({run.name: rows[run.name]}), flush=True)
    means = role_means(rows, ("with", "without"), KEYS)
    res = {"machine": machine(),
           "what": "pbr + joint with the observed sky held (with, the default) and without, from the same volume2",
           "runs": rows, "means": means, "seconds": round(time.perf_counter() - t0, 1)}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(json.dumps(means, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
