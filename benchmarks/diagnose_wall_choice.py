"""Is a wall hypothesis's gain larger than its sampling noise? (a diagnostic of
:mod:`core.stages.wall_heights`; it reads no ground truth).

The pbr stage compares the hypotheses by the mean absolute shading residual of the lighting
prior's sun search, each at its own best sun, over the same surface samples
(:func:`core.lighting.prior.estimate_lighting`). This script re-runs that choice on a copy of a
run (the pbr stage is stopped right after it) and keeps every sample's absolute residual under each
hypothesis. The paired difference between two hypotheses then has a standard error, and
``z = mean difference / standard error`` says whether the gain is more than the choice of samples:
a paired test the fixed relative margin (:attr:`core.stages.pbr_settings.PBRStageConfig.wall_min_gain`)
does not make.

    cp -r RUN/{priors,volume,generative_refine,volume2,run.json} COPY
    python benchmarks/diagnose_wall_choice.py COPY --scene BUNDLE --profile P --out J
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import core.lighting.prior as prior  # noqa: E402
import core.stages.pbr as pbr_stage  # noqa: E402
from core.errors import ShapeError  # noqa: E402
from core.stages.chain import run_pipeline  # noqa: E402
from core.stages.wall_heights import HYPOTHESES  # noqa: E402


class _Stop(Exception):
    """Raised after the pbr stage has chosen its walls: the rest of the stage is not needed."""


def paired(res_a: np.ndarray, res_b: np.ndarray) -> dict:
    """Paired difference of two hypotheses' per-sample absolute residuals ([N] each, the same
    samples): mean, its standard error, z, and the mean relative to ``res_b``'s mean."""
    if res_a.shape != res_b.shape or res_a.ndim != 1 or len(res_a) < 2:
        raise ShapeError(f"paired: expected two [N] arrays of the same N >= 2, got {res_a.shape}, {res_b.shape}")
    d = res_a - res_b
    se = float(d.std(ddof=1) / math.sqrt(len(d)))
    m = float(d.mean())
    return {"mean_diff": m, "se": se, "z": (m / se) if se > 0 else None, "rel": m / max(float(res_b.mean()), 1e-12)}


def capture(run: str, scene: str, profile: str) -> tuple[dict, str]:
    """Per-sample absolute residuals of each hypothesis (name -> [N]) and the stage's choice."""
    searches: list[dict] = []
    orig_score, orig_search, orig_choose = prior._lambert_score, prior._search_sun, pbr_stage._choose_walls

    def score(nrm, shading, vis_of=None, *a, **k):
        searches.append({"nrm": nrm, "shade": shading, "vis_of": vis_of})
        return orig_score(nrm, shading, vis_of, *a, **k)

    def search(score_fn, s):
        sun, res, d = orig_search(score_fn, s)
        c = searches[-1]
        v = c["vis_of"](sun[None])[0] if c["vis_of"] is not None else None
        c["absres"] = np.abs(prior._shading_residuals(c["nrm"], c["shade"], sun, v)[0])
        return sun, res, d

    chosen = {}

    def choose(*a, **k):
        r = orig_choose(*a, **k)
        chosen["name"] = r[2]["chosen"]
        raise _Stop()

    prior._lambert_score, prior._search_sun, pbr_stage._choose_walls = score, search, choose
    try:
        run_pipeline(scene, run, profile, stages=["pbr"], resume=True, progress=False)
    except _Stop:
        pass
    finally:
        prior._lambert_score, prior._search_sun, pbr_stage._choose_walls = orig_score, orig_search, orig_choose
    done = [c["absres"] for c in searches if "absres" in c]
    if len(done) != len(HYPOTHESES):
        raise RuntimeError(f"expected {len(HYPOTHESES)} sun searches, captured {len(done)}")
    return dict(zip(HYPOTHESES, done)), chosen.get("name", "?")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a copy of a run with volume2 done and no pbr stage")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--profile", default="quick")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res, chosen = capture(a.run, a.scene, a.profile)
    out = {"chosen": chosen, "samples": int(len(next(iter(res.values())))),
           "mean_abs_residual": {h: float(r.mean()) for h, r in res.items()},
           "pairs": {f"{x} - {y}": paired(res[x], res[y]) for i, x in enumerate(HYPOTHESES) for y in HYPOTHESES[i + 1:]}}
    print(json.dumps({k: out["pairs"][k] for k in ("none - sky", "right - sky+right", "sky - sky+right")}, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
