"""The indirect bounce, the opaque occluder walls, the stages' shadow settings and the BRDF's diffuse
lobe, measured apart: pbr and joint re-run from one volume2 per street under each variant, then
``brdf evaluate``.

Variants (``VARIANTS``): what the PBR pass adds (``indirect_bounces``), how the occluders are
built (``core.stages.occluders``: the session-start walls are one layer, the observed facades not
backed, continued from whatever column ends a side), and how the pbr and joint stages trace
shadows (``old``: 0.01 m / 0.02 m, before they traced as a relight does; ``cons``: the relight's
0.5 m / 0.1 m), and the diffuse lobe of the stages and the evaluation's renders
and masking term (``core.pbr.brdf``: ``lambert`` / ``schlick``, the paper's, or ``burley`` /
``smith``, the principled BSDF's). ``base`` is the code at the start of the indirect-light change,
``cur`` the current defaults, ``lambert`` the current defaults with the paper's BRDF and the
paper's opacity blend (the code before the Burley change), ``burley`` with Burley's lobe and the
paper's masking, ``principled_blend`` the principled BRDF with the paper's blend
(``PBRSettings.opaque_above`` 1.0: the map shows through partly opaque surfaces).

    python benchmarks/bench_indirect.py make SEED_RUN OUT_DIR --scene BUNDLE --variants base,cur
    python benchmarks/bench_indirect.py table LABEL:ROLE:VARIANT=RUN ... --out benchmarks/results/indirect.json

``make`` copies SEED_RUN's volume, generative_refine, volume2 and priors into OUT_DIR/<variant>,
rebuilds the occluders of the volume2 scene graph with the variant's settings, runs the pbr and
joint stages with its settings and evaluates with its bounce count (64 rays, OIDN, FLIP off).
``table`` reads each run's ``evaluation.json`` and writes the rows and the means per role.

Reads ground truth (the evaluation): a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.eval_pipeline import machine  # noqa: E402

OLD_OCCLUDERS = {"layers": 1, "fill_observed": False, "wall_tolerance_m": 1000.0}
SHADOWS = {"old": (0.01, 0.02), "cons": (0.5, 0.1)}
class Variant(NamedTuple):
    """One row of the benchmark: what the pbr and joint stages and the evaluation run with."""

    bounces: int
    """``indirect_bounces``."""
    occluders: dict
    """``OccluderSettings`` overrides of the rebuilt occluders ({} = the defaults)."""
    shadows: str
    """Key of :data:`SHADOWS`: the stages' shadow t_min and normal offset."""
    diffuse: str
    """The BRDF's diffuse lobe."""
    masking: str
    """The BRDF's masking term."""
    opaque_above: float
    """Pixels at least this opaque are shaded as surfaces (1.0 = the paper's blend)."""


VARIANTS = {
    "base": Variant(0, OLD_OCCLUDERS, "old", "lambert", "schlick", 1.0),
    "cur": Variant(2, {}, "cons", "burley", "smith", 0.5),
    "lambert": Variant(2, {}, "cons", "lambert", "schlick", 1.0),
    "burley": Variant(2, {}, "cons", "burley", "schlick", 1.0),
    "principled_blend": Variant(2, {}, "cons", "burley", "smith", 1.0),
    "indirect_old_occluders": Variant(2, OLD_OCCLUDERS, "cons", "lambert", "schlick", 1.0),
    "cur_old_stage_shadows": Variant(2, {}, "old", "lambert", "schlick", 1.0),
}
KEYS = ("relight_psnr", "relight_ssim", "rerender_psnr", "nvs_psnr", "sun_error_deg")


def make(seed: Path, out: Path, scene: str, name: str) -> Path:
    import torch

    from core.bundle import open_bundle
    from core.raster import RasterSettings
    from core.scene_graph import SceneGraph
    from core.stages.chain import RunDir
    from core.stages.occluders import OccluderSettings, capture_views, complete_occluders
    from core.stages.volume import _views
    from core.synth.evaluate import EvalSettings, evaluate_run

    bounces, occ, shadows, diffuse, masking, opaque = VARIANTS[name]
    dst = out / name
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for part in ("volume", "generative_refine", "volume2", "priors", "run.json"):
        src = seed / part
        if src.is_dir():
            shutil.copytree(src, dst / part)
        elif src.is_file():
            shutil.copy2(src, dst / part)
    found = RunDir(dst).latest_graph_dir()
    if found is None or found[1] != "volume2":
        raise SystemExit(f"{seed}: its volume2 stage is not done")
    gfile = found[0] / "scene_graph.pt"
    graph = SceneGraph.load(gfile)
    b = open_bundle(scene)
    graph.occluders = complete_occluders(graph._static_part().detach(),
                                         capture_views(graph, _views(b, "train", False), RasterSettings(threads=2)),
                                         OccluderSettings(**occ))
    graph.save(gfile)
    t_min, offset = SHADOWS[shadows]
    sets = []
    for st in ("pbr", "joint"):
        sets += ["--set", f"{st}.indirect_bounces={bounces}", "--set", f"{st}.shadow_t_min_m={t_min}",
                 "--set", f"{st}.normal_offset_m={offset}", "--set", f"{st}.diffuse={diffuse}",
                 "--set", f"{st}.masking={masking}", "--set", f"{st}.opaque_above={opaque}"]
    subprocess.run([sys.executable, "-m", "core", "reconstruct", "--scene", scene, "--profile", "quick", "--stages",
                    "pbr,joint", "--resume", "--out", str(dst), "--quiet", *sets], check=True, cwd=REPO)
    torch.set_num_threads(2)
    evaluate_run(dst, settings=EvalSettings(flip=False, indirect_bounces=bounces, diffuse=diffuse,
                                                               masking=masking, opaque_above=opaque))
    return dst


def table(items: list[str], out: Path, note: str) -> dict:
    rows, by_role = {}, {}
    for item in items:
        label, path = item.split("=", 1)
        street, role, variant = label.split(":")
        ev = json.loads((Path(path) / "evaluation.json").read_text())
        s = ev["summary"]
        row = {k: (round(s[k], 4) if isinstance(s.get(k), float) else s.get(k)) for k in KEYS}
        row["relight_per_map"] = {m: round(v["psnr"], 3) for m, v in ev.get("relight", {}).get("per_map", {}).items()}
        rows.setdefault(street, {"role": role})[variant] = row
        by_role.setdefault((role, variant), []).append(row)
    means = {}
    for (role, variant), rs in sorted(by_role.items()):
        means.setdefault(role, {})[variant] = {
            k: round(sum(r[k] for r in rs) / len(rs), 4) for k in KEYS if all(r[k] is not None for r in rs)}
        means[role][variant]["streets"] = [st for st, v in rows.items() if v["role"] == role and variant in v]
    res = {"machine": machine(), "profile": "quick",
           "variants": {k: {"indirect_bounces": v.bounces, "occluders": v.occluders or "defaults",
                            "stage_shadows": SHADOWS[v.shadows], "diffuse": v.diffuse, "masking": v.masking,
                            "opaque_above": v.opaque_above} for k, v in VARIANTS.items()},
           "streets": rows, "means": means, "note": note}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make")
    m.add_argument("seed", help="a run whose volume2 is done")
    m.add_argument("out")
    m.add_argument("--scene", required=True)
    m.add_argument("--variants", default="base,cur")
    t = sub.add_parser("table")
    t.add_argument("runs", nargs="+", help="STREET:ROLE:VARIANT=RUN_DIR")
    t.add_argument("--note", default="")
    t.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "indirect.json"))
    a = ap.parse_args()
    if a.cmd == "make":
        for v in a.variants.split(","):
            if v not in VARIANTS:
                ap.error(f"--variants: unknown {v!r} (choices: {', '.join(VARIANTS)})")
        for v in a.variants.split(","):
            print(v, "->", make(Path(a.seed), Path(a.out), a.scene, v), flush=True)
        return 0
    res = table(a.runs, Path(a.out), a.note)
    for role, vs in res["means"].items():
        for v, r in vs.items():
            print(f"{role:5s} {v:24s} relit {r['relight_psnr']:.2f} / {r['relight_ssim']:.3f}  re-render "
                  f"{r['rerender_psnr']:.2f}  NVS {r['nvs_psnr']:.2f}  sun {r['sun_error_deg']:.1f}  ({', '.join(r['streets'])})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
