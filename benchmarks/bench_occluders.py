"""Shadow casters the capture never saw (``core.stages.occluders``), measured before and after.

Each ``LABEL=RUN`` is a reconstruction run (``brdf reconstruct --out RUN``) of a bundle with ground
truth; it is evaluated with ``brdf evaluate`` (``core.synth.evaluate``: relight PSNR / SSIM / FLIP under
the bundle's held-back maps, the re-render under the recovered map, NVS) unless its
``evaluation.json`` exists. Written: ``benchmarks/results/occluders.json`` (one row per label, the
per-map relight figures and the occluder count of the run's scene graph) and a PNG of one relit
frame per label beside Mitsuba's.

    python benchmarks/bench_occluders.py before=RUN_A after=RUN_B [--frame test_003 --map sunset]

Reads ground truth: a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--frame", default="test_003")
    ap.add_argument("--map", default="sunset")
    ap.add_argument("--note", default="", help="how the runs were made (stored in the JSON)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "occluders.json"))
    a = ap.parse_args()
    from core.bundle import open_bundle
    from core.synth.evaluate import evaluate_run
    from core.io.exr import read_exr
    from core.io.images import write_png
    from core.render.scenario import Scenario, render_scenario, views_from_frames
    from core.stages.chain import RunDir
    from core.tonemap import hdr_to_ldr

    rows, pics, ref = {}, [], None
    for item in a.runs:
        if "=" not in item:
            ap.error(f"runs: expected LABEL=RUN_DIR, got {item!r}")
        label, path = item.split("=", 1)
        run = RunDir(path)
        ev_file = Path(path) / "evaluation.json"
        ev = json.loads(ev_file.read_text()) if ev_file.is_file() else evaluate_run(path)
        graph, _sky, stage = run.load_scene()
        b = open_bundle(run.scene_path())
        rows[label] = {"run": str(path), "graph_stage": stage,
                       "occluders": graph.occluders.num if graph.occluders is not None else 0,
                       **ev["summary"],
                       "relight_per_map": {k: {m: round(v[m], 4) for m in ("psnr", "ssim", "flip") if m in v}
                                           for k, v in ev.get("relight", {}).get("per_map", {}).items()}}
        rl = next(r for r in b.manifest.ground_truth.relit if r.name == a.map)
        view = next(v for v in views_from_frames(b, "test") if v.name == a.frame)
        sc = Scenario(views=(view,), envmap=np.asarray(b.load_envmap(a.map), np.float32),
                      base_exposure=b.manifest.ldr_exposure, gamma=b.manifest.ldr_gamma, denoiser="oidn",
                      denoiser_fallback=None, outputs=("png",))
        with tempfile.TemporaryDirectory() as tmp:
            pics.append(np.clip(render_scenario(graph, sc, tmp).result.frames[0], 0, 1))
        if ref is None:
            r = read_exr(b.path(rl.frames[a.frame]))
            ref = hdr_to_ldr(np.asarray(r["rgb"] if isinstance(r, dict) else r, np.float32)[..., :3],
                             b.manifest.ldr_exposure, b.manifest.ldr_gamma)
        print(label, {k: rows[label][k] for k in ("occluders", "rerender_psnr", "relight_psnr", "relight_ssim",
                                                 "relight_flip")}, flush=True)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    png = out.with_suffix(".png")
    write_png(png, np.concatenate(pics + [ref], 1))
    out.write_text(json.dumps({"what": __doc__.split("\n\n")[0], "note": a.note, "frame": a.frame, "map": a.map,
                               "picture": f"{png.name}: " + " | ".join(list(rows) + ["Mitsuba"]),
                               "rows": rows}, indent=1))
    print("written", out, png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
