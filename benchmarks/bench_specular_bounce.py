"""The specular bounce of the PBR pass (``PBRSettings.indirect_specular_rays``), on reconstructions.

    python benchmarks/bench_specular_bounce.py LABEL=RUN:K [LABEL=RUN:K ...] [--role dev|test] [--out J]

Each entry evaluates the run ``RUN`` (a ``brdf reconstruct`` directory) with ``brdf evaluate``'s
settings (:class:`core.synth.evaluate.EvalSettings`) and ``K`` GGX shadow rays per pixel of the
specular bounce in its re-render and relit frames (0 = the diffuse bounce only). Rows of a run
whose pbr and joint stages were themselves re-run with the bounce (``brdf reconstruct --resume
--stages pbr,joint --set pbr.indirect_specular_rays=K --set joint.indirect_specular_rays=K`` on a
copy) say so in their label. Reads ground truth (the evaluation): a benchmark, never the product.
Prints the machine, the evaluation seconds and the paper's metrics per entry; ``--out`` merges the
rows into a JSON file (existing keys of other labels kept).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.synth.evaluate import EvalSettings, evaluate_run  # noqa: E402

KEYS = ("rerender_psnr", "nvs_psnr", "relight_psnr", "relight_ssim", "relight_flip", "metallic_rmse",
        "albedo_si_psnr", "roughness_rmse", "normal_mae_deg", "sun_error_deg")


def _parse(entry: str) -> tuple[str, Path, int]:
    try:
        label, rest = entry.split("=", 1)
        run, k = rest.rsplit(":", 1)
        return label, Path(run), int(k)
    except ValueError as exc:
        raise SystemExit(f"entry {entry!r}: expected LABEL=RUN:K ({exc})") from exc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("entries", nargs="+", help="LABEL=RUN:K")
    ap.add_argument("--role", choices=("dev", "test"), required=True,
                    help="development (choices are made on it) or test street")
    ap.add_argument("--rays", type=int, default=EvalSettings.rays_per_pixel)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    entries = [_parse(e) for e in a.entries]
    for label, run, _k in entries:
        if not (run / "run.json").is_file():
            raise SystemExit(f"{label}: {run} is not a reconstruction run (no run.json)")
    machine = {"cpu_count": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}
    print(f"machine: {machine}  threads: {EvalSettings.threads}  rays: {a.rays}  role: {a.role}")
    rows = {}
    for label, run, k in entries:
        t0 = time.perf_counter()
        res = evaluate_run(run, settings=EvalSettings(rays_per_pixel=a.rays, indirect_specular_rays=k, flip=True),
                           out=run / f"eval_specular_{k}")
        row = {key: res["summary"].get(key) for key in KEYS}
        row.update({"run": str(run), "indirect_specular_rays": k, "role": a.role,
                    "relight_per_map_psnr": {m: round(v["psnr"], 3) for m, v in res.get("relight", {}).get("per_map", {}).items()},
                    "evaluation_seconds": round(time.perf_counter() - t0, 1)})
        rows[label] = row
        print(label, " ".join(f"{key}={row[key]:.4f}" for key in KEYS if row[key] is not None),
              f"eval_s={row['evaluation_seconds']}", flush=True)
    if a.out is not None:
        doc = json.loads(a.out.read_text()) if a.out.is_file() else {}
        doc["machine"] = machine
        doc.setdefault("rows", {}).update(rows)
        a.out.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
