"""Tracked objects filled for shadow rays (``Scenario.object_solids``), measured off and on.

Each ``LABEL=RUN`` is a reconstruction run (``brdf reconstruct --out RUN``) of a bundle with ground
truth. The run is evaluated twice (``core.synth.evaluate``: relight PSNR / SSIM / FLIP under the
bundle's held-back maps, the re-render under the recovered map) with
``EvalSettings.object_solids`` false and true; nothing else differs, the reconstruction is the
same. Evaluations already in ``--work/LABEL/{off,on}/evaluation.json`` are reused. Written:
``--out`` (one row per label with both summaries, the per-map relight PSNR and the differences,
and the mean over the labels).

    python benchmarks/bench_object_solids.py default=RUN_A dev1=RUN_B --work DIR

Reads ground truth: a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.eval_pipeline import machine  # noqa: E402

KEYS = ("relight_psnr", "relight_ssim", "relight_flip", "rerender_psnr", "nvs_psnr")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--work", required=True, help="where the two evaluations of each run go")
    ap.add_argument("--note", default="", help="how the runs were made (stored in the JSON)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "object_solids.json"))
    a = ap.parse_args()
    from core.synth.evaluate import EvalSettings, evaluate_run

    rows = {}
    for item in a.runs:
        if "=" not in item:
            ap.error(f"runs: expected LABEL=RUN_DIR, got {item!r}")
        label, run = item.split("=", 1)
        row = {"run": run}
        for key, on in (("off", False), ("on", True)):
            out = Path(a.work) / label / key
            f = out / "evaluation.json"
            if f.is_file():
                ev = json.loads(f.read_text())
                got = ev.get("settings", {}).get("object_solids", False)
                if bool(got) != on:
                    raise SystemExit(f"{f}: made with object_solids={got}, expected {on}")
            else:
                out.mkdir(parents=True, exist_ok=True)
                ev = evaluate_run(run, settings=EvalSettings(object_solids=on), out=out)
            row[key] = {k: round(float(ev["summary"][k]), 4) for k in KEYS if ev["summary"].get(k) is not None}
            row[key]["relight_per_map"] = {m: round(float(v["psnr"]), 3)
                                           for m, v in ev.get("relight", {}).get("per_map", {}).items()}
        row["on_minus_off"] = {k: round(row["on"][k] - row["off"][k], 4) for k in KEYS
                               if k in row["on"] and k in row["off"]}
        rows[label] = row
        print(label, row["on_minus_off"])
    mean = {k: round(float(np.mean([r["on_minus_off"][k] for r in rows.values() if k in r["on_minus_off"]])), 4)
            for k in KEYS}
    res = {"what": __doc__.splitlines()[0], "machine": machine(), "note": a.note,
           "eval_settings": {k: v for k, v in dataclasses.asdict(EvalSettings()).items() if k != "object_solids"},
           "rows": rows, "mean_on_minus_off": mean}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(mean))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
