"""Is the inverse model's roughness / metallic error at a floor set by what frames show?
(diagnostic; reads ground truth)

Each non-sky pixel of randomised streets (``benchmarks/make_randomised.py`` output,
``ROOT/<split>/<split>_<i>``) gets its material class: the ground-truth roughness and metallic
are matched to the street's materials, rebuilt from the split's spec
(:func:`core.synth.random_street.make_random_street`). The **floor** is a predictor that knows
each pixel's class and predicts the class's mean over the training streets' materials (metal-clad
walls are a class of their own). The model is scored as ``generative.json``'s ``ood`` key scores
it (the product's ensemble). Per street, per split and per class (pooled over the OOD streets).

    python benchmarks/diagnose_inverse_classes.py ROOT --out J [--train-streets 80]

Not part of the product: it reads the bundles' ground truth and the generator's materials.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: Tolerance of the match between a pixel's true roughness / metallic and a material's (the
#: G-buffers store the material's values; 4-decimal materials, float32 layers).
MATCH_TOL = 2e-3


def material_class(name: str, metallic: float) -> str:
    """The class of a generated material: its name without the side and index (``wallL3`` ->
    ``wall``, ``car_glass2`` -> ``glass``); walls with metallic > 0.5 are ``wall_metal``."""
    n = re.sub(r"[LR]?\d*$", "", name).lower()
    if "glass" in n:
        n = "glass"
    if n == "wall" and metallic > 0.5:
        n = "wall_metal"
    return n


def assign_classes(rough: np.ndarray, metal: np.ndarray, materials: dict) -> np.ndarray:
    """Class per pixel (object array, ``"?"`` where no material matches) of the true ``rough``
    and ``metal`` values ``[N]``; ``materials``: ``{name: (class, roughness, metallic)}``. The
    first matching material wins."""
    cls = np.full(rough.shape, "?", dtype=object)
    for _name, (k, r, m) in materials.items():
        hit = (np.abs(rough - r) < MATCH_TOL) & (np.abs(metal - m) < MATCH_TOL) & (cls == "?")
        cls[hit] = k
    return cls


def floor_rows(pred: np.ndarray, true: np.ndarray, cls: np.ndarray, prior: dict) -> dict:
    """``{class: [n, model squared error sum, floor squared error sum]}`` of one quantity:
    ``pred`` / ``true`` ``[N]``, ``cls`` ``[N]``, ``prior`` ``{class: mean}`` (0.5 for a class
    never seen in training)."""
    out: dict = {}
    for k in np.unique(cls):
        s = cls == k
        f = prior.get(k, 0.5)
        out[str(k)] = [int(s.sum()), float(((pred[s] - true[s]) ** 2).sum()), float(((f - true[s]) ** 2).sum())]
    return out


def pooled(rows: dict) -> dict:
    """RMSE of the model and of the floor over every class of ``rows`` (:func:`floor_rows`,
    possibly summed over frames), and per class with its share of the pixels."""
    n = sum(v[0] for v in rows.values())
    if n == 0:
        return {"model": float("nan"), "floor": float("nan"), "classes": {}}
    return {"model": (sum(v[1] for v in rows.values()) / n) ** 0.5,
            "floor": (sum(v[2] for v in rows.values()) / n) ** 0.5,
            "classes": {k: {"share": v[0] / n, "model": (v[1] / v[0]) ** 0.5, "floor": (v[2] / v[0]) ** 0.5}
                        for k, v in sorted(rows.items(), key=lambda kv: -kv[1][0]) if v[0]}}


def _add(acc: dict, rows: dict) -> dict:
    for k, v in rows.items():
        a = acc.setdefault(k, [0, 0.0, 0.0])
        for i in range(3):
            a[i] += v[i]
    return acc


def street_materials(split: str, index: int) -> dict:
    """``{name: (class, roughness, metallic)}`` of scene ``index`` of ``split`` as
    ``make_randomised.py --pinhole`` generates it (Lambert parts: roughness 1, metallic 0)."""
    from core.synth import profile
    from core.synth.generate import ego_positions
    from core.synth.random_street import make_random_street
    from core.synth.randomise import RandomisationSettings, spec_config
    from core.synth.splits import split_spec

    spec = split_spec(split, index, RandomisationSettings(distortion_prob=0.0))
    cfg = spec_config(spec, profile("quick"), num_frames=4)
    st = make_random_street(spec, ego_positions(cfg), cfg.street_length_m, cfg.frame_dt, cfg.ego_speed)
    out = {}
    for p in list(st.static_parts) + [q for c in st.cars for q in c.parts]:
        m = p.material
        r, mt = (1.0, 0.0) if m.model == "lambert" else (m.roughness, m.metallic)
        out[m.name] = (material_class(m.name, mt), r, mt)
    return out


def main(argv=None) -> int:
    from core.gen import contract as C
    from core.gen.edm import GENERATE_SAMPLER, OnnxDenoiser
    from core.gen.gbuffer_ensemble import generate_gbuffer
    from core.gen.runtime import load_model
    from core.synth.gen_data import DataSettings, load_clips

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", help="make_randomised.py output: ROOT/<split>/<split>_<i>")
    ap.add_argument("--out", required=True)
    ap.add_argument("--model", default=str(ROOT / "models" / "inverse_gbuffer.onnx"))
    ap.add_argument("--train-streets", type=int, default=80, help="training streets whose materials set the floor")
    a = ap.parse_args(argv)
    means: dict = defaultdict(list)
    for i in range(a.train_streets):
        for k, r, m in street_materials("train", i).values():
            means[k].append((r, m))
    prior_r = {k: float(np.mean([x[0] for x in v])) for k, v in means.items()}
    prior_m = {k: float(np.mean([x[1] for x in v])) for k, v in means.items()}
    sess = load_model(a.model, kind="inverse_gbuffer", threads=2)
    den = OnnxDenoiser(sess)
    res: dict = {"class_means_train": {k: [prior_r[k], prior_m[k]] for k in prior_r}, "streets": {}}
    ood_r: dict = {}
    ood_m: dict = {}
    for d in sorted(Path(a.root).glob("*/*_[0-9]*")):
        if not (d / "bundle.json").is_file():
            continue
        split, index = d.parent.name, int(d.name.rsplit("_", 1)[1])
        mats = street_materials(split, index)
        acc_r: dict = {}
        acc_m: dict = {}
        for clip in load_clips(d, DataSettings(), ("inverse",)):
            g = torch.from_numpy(np.stack([f["gbuffer"] for f in clip]))
            cond = {"rgb": torch.from_numpy(np.stack([f["rgb"] for f in clip]))}
            if sess.info.takes("view"):
                cond["view"] = torch.from_numpy(np.stack([f["view"] for f in clip]))
            y = generate_gbuffer(den, tuple(g.shape), cond, GENERATE_SAMPLER, None)
            mask = np.stack([f["sky"][0] for f in clip]) < 0.5
            sl = C.GBUFFER_SLICES

            def layer(t, k):
                return ((t[:, sl[k]].clamp(-1, 1) + 1) / 2)[:, 0].numpy()[mask]

            gr, gm = layer(g, "roughness"), layer(g, "metallic")
            cls = assign_classes(gr, gm, mats)
            _add(acc_r, floor_rows(layer(y, "roughness"), gr, cls, prior_r))
            _add(acc_m, floor_rows(layer(y, "metallic"), gm, cls, prior_m))
        res["streets"][d.name] = {"split": split, "roughness": pooled(acc_r), "metallic": pooled(acc_m)}
        if split.startswith("test_ood"):
            _add(ood_r, acc_r)
            _add(ood_m, acc_m)
        r = res["streets"][d.name]
        print(f"{d.name}: roughness {r['roughness']['model']:.3f} (floor {r['roughness']['floor']:.3f}), "
              f"metallic {r['metallic']['model']:.3f} (floor {r['metallic']['floor']:.3f})", flush=True)
    res["ood_pooled"] = {"roughness": pooled(ood_r), "metallic": pooled(ood_m)}
    Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
