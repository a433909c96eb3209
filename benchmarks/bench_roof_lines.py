"""Occluder columns (``core.stages.occluders``) against the true building heights of a generated street.

For each ``LABEL=RUN`` (a reconstruction of a ``brdf generate`` bundle; the generator is
deterministic, so the street's buildings are rebuilt from the bundle's recorded config), every
0.5 m cell holding completed occluder Gaussians that lies over a true building of its side of
the street is compared with that building's height: the cell's highest occluder minus the true
roof, metres. Reported per run: the mean, median, 10th and 90th percentiles of that difference,
the mean absolute difference and the shares more than 2 m over and under.

    python benchmarks/bench_roof_lines.py uncapped=RUN_A capped=RUN_B --out benchmarks/results/roof_lines.json

Reads ground truth: a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def roof_errors(run_dir: str) -> dict:
    from core.bundle import open_bundle
    from core.stages.chain import RunDir
    from core.synth import profile
    from core.synth.generate import ego_positions
    from core.synth.street import make_street

    run = RunDir(run_dir)
    b = open_bundle(run.scene_path(), validate=False)
    src = b.manifest.source.get("config")
    if src is None:
        raise SystemExit(f"{run_dir}: its bundle records no generator config (not a brdf generate street)")
    cfg = profile("quick", **{k: tuple(v) if isinstance(v, list) else v for k, v in src.items()})
    blds = []
    for p in make_street(cfg, ego_positions(cfg)).static_parts:
        if p.name.startswith("building"):
            v = np.asarray(p.vertices)
            blds.append((v[:, 0].min(), v[:, 0].max(), v[:, 1].min(), v[:, 1].max(), v[:, 2].max()))
    blds = np.array(blds)
    graph, _sky, stage = run.load_scene()
    if graph.occluders is None or graph.occluders.num == 0:
        raise SystemExit(f"{run_dir}: no occluders in its scene graph")
    m = graph.occluders.means.detach().double().numpy()
    keys, inv = np.unique(np.floor(m[:, :2] / 0.5).astype(np.int64), axis=0, return_inverse=True)
    top = np.full(len(keys), -np.inf)
    np.maximum.at(top, inv.reshape(-1), m[:, 2])
    centres = (keys + 0.5) * 0.5
    diffs = []
    for (x, y), t in zip(centres, top):
        hit = (blds[:, 0] <= x) & (x <= blds[:, 1]) & (np.sign(blds[:, 2] + blds[:, 3]) == np.sign(y))
        if hit.any():
            diffs.append(t - blds[hit][0, 4])
    d = np.asarray(diffs)
    return {"graph_stage": stage, "cells": int(len(d)), "mean_m": round(float(d.mean()), 3),
            "median_m": round(float(np.median(d)), 3), "p10_m": round(float(np.percentile(d, 10)), 3),
            "p90_m": round(float(np.percentile(d, 90)), 3), "mean_abs_m": round(float(np.abs(d).mean()), 3),
            "share_over_2m": round(float((d > 2).mean()), 3), "share_under_2m": round(float((d < -2).mean()), 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--note", default="")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "roof_lines.json"))
    a = ap.parse_args()
    rows = {}
    for item in a.runs:
        label, _, run = item.partition("=")
        if not run:
            ap.error(f"runs: expected LABEL=RUN_DIR, got {item!r}")
        rows[label] = {"run": run, **roof_errors(run)}
        print(label, rows[label])
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"what": __doc__.splitlines()[0], "note": a.note, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
