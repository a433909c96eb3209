"""Do the prior terms move the geometry? ``VolumeSettings.priors_move_geometry`` true against
false (the default), the whole pipeline, per street.

For each street of ``--data`` (made by ``benchmarks/eval_pipeline.py``) two runs are reconstructed
at ``--profile`` (kept under ``<data>/runs_pg/<street>_<profile>_geom_{on,off}`` and resumed, so a
run made otherwise can be linked there first) with ``--set volume.priors_move_geometry=...`` and
``volume2`` the same, then evaluated (``brdf evaluate``: the paper's metrics against Mitsuba).
Writes per-street figures and the means per role (development / test) to ``--out``, with the
colour-only stage's beside them where ``eval_pipeline.py --rows colour_only`` made it (the NVS
target: no lower than the colour-only stage on the same street).

    python benchmarks/bench_prior_geometry.py --data D --streets dev1,dev2,test1,test2 \\
        --out benchmarks/results/prior_geometry.json
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

from eval_pipeline import STREETS, machine, role_means  # noqa: E402

KEYS = ("nvs_psnr", "nvs_ssim", "relight_psnr", "relight_ssim", "relight_flip", "rerender_psnr", "albedo_si_psnr",
        "normal_mae_deg", "roughness_rmse", "metallic_rmse", "sun_error_deg")


def brdf(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "core", *args], check=True, cwd=REPO)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True, help="directory of the streets (benchmarks/eval_pipeline.py)")
    ap.add_argument("--streets", default="dev1,dev2,test1,test2")
    ap.add_argument("--profile", default="quick")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "prior_geometry.json"))
    a = ap.parse_args()
    data = Path(a.data)
    t0 = time.perf_counter()
    rows = {}
    for st in a.streets.split(","):
        if st not in STREETS:
            ap.error(f"--streets: unknown street {st!r} (choices: {sorted(STREETS)})")
        scene = data / st
        if not (scene / "bundle.json").is_file():
            ap.error(f"--data: no street {st!r} at {scene} (make it with benchmarks/eval_pipeline.py)")
        res = {}
        for variant, flag in (("geometry_moved", "true"), ("geometry_detached", "false")):
            run = data / "runs_pg" / f"{st}_{a.profile}_geom_{'on' if flag == 'true' else 'off'}"
            if not (run / "joint" / "done.json").is_file():
                extra = ["--resume"] if (run / "run.json").is_file() else []
                brdf("reconstruct", "--scene", str(scene), "--profile", a.profile, "--out", str(run), "--quiet",
                     "--set", f"volume.priors_move_geometry={flag}", "--set", f"volume2.priors_move_geometry={flag}",
                     *extra)
            if not (run / "evaluation.json").is_file():
                brdf("evaluate", str(run), "--out", str(run))
            ev = json.loads((run / "evaluation.json").read_text())["summary"]
            res[variant] = {k: ev.get(k) for k in KEYS}
            res[variant]["run"] = str(run.resolve())
        co = data / "runs" / f"{st}_{a.profile}_colour_only" / "evaluation.json"  # eval_pipeline's row
        if co.is_file():
            ev = json.loads(co.read_text())["summary"]
            res["colour_only"] = {k: ev.get(k) for k in KEYS}
        rows[st] = {"role": STREETS[st][0], **res}
        print(json.dumps({st: rows[st]}), flush=True)
    means = role_means(rows, ("geometry_moved", "geometry_detached", "colour_only"), KEYS)
    out = {"machine": machine(),
           "profile": a.profile, "what": "VolumeSettings.priors_move_geometry true (Eq. 4 as written) against false "
           "(the default: the normal and material prior terms move only those attributes), volume and volume2",
           "streets": rows, "means": means, "seconds": round(time.perf_counter() - t0, 1)}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(json.dumps(means, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
