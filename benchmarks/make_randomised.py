"""Write randomised training / validation / OOD-test scene bundles (Mitsuba ground truth).

    .venv/bin/python benchmarks/make_randomised.py --split train --count 200 --out data/randomised
    .venv/bin/python benchmarks/make_randomised.py --split all --count 20 --out data/randomised
    .venv/bin/python benchmarks/make_randomised.py --split train --count 500 --set num_frames=4 --set relight_every=2

Scene ``i`` of a split is ``core.synth.splits.split_spec(split, i)`` rendered with the base
profile's frames, samples and LiDAR (``--profile``, default ``quick``); each bundle goes to
``<out>/<split>/<split>_<i:06d>``. Existing complete bundles are kept (resumable). ``--list``
prints the specs without rendering. The held-out regions are in ``core/synth/splits.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.synth import generate_scene, profile
from core.synth.randomise import RandomisationSettings, spec_config
from core.synth.splits import SPLITS, describe, split_spec


#: Per-bundle generation time (``{"seconds": s, "workers": n}``), written beside ``bundle.json``.
GENERATION_FILE = "generation_s.json"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", required=True, help=f"one of {', '.join(SPLITS)}, or 'all'")
    p.add_argument("--count", type=int, default=10, help="scenes per split")
    p.add_argument("--start", type=int, default=0, help="first scene index")
    p.add_argument("--profile", default="quick", help="base profile: frames, spp, LiDAR (tiny | quick | benchmark)")
    p.add_argument("--out", default="outputs/randomised")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                   help="override a SynthConfig field of every scene (e.g. num_frames=4, relight_every=2)")
    p.add_argument("--pinhole", action="store_true",
                   help="no lens distortion (the reconstruction pipeline assumes pinhole cameras); "
                        "every other axis is drawn as without it")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--list", action="store_true", help="print the specs only")
    a = p.parse_args(argv)
    splits = SPLITS if a.split == "all" else (a.split,)
    settings = RandomisationSettings(distortion_prob=0.0) if a.pinhole else RandomisationSettings()
    overrides = {}
    for kv in a.set:
        k, _, v = kv.partition("=")
        try:
            overrides[k] = json.loads(v)
        except json.JSONDecodeError:
            overrides[k] = v
        if isinstance(overrides[k], list):
            overrides[k] = tuple(overrides[k])
    out = Path(a.out)
    if not a.list:
        out.mkdir(parents=True, exist_ok=True)
        (out / "protocol.json").write_text(json.dumps({"held_out": describe(), "splits": list(SPLITS)}, indent=1))
    for split in splits:
        for i in range(a.start, a.start + a.count):
            spec = split_spec(split, i, settings)
            name = f"{split}_{i:06d}"
            if a.list:
                d = asdict(spec)
                d.pop("settings")
                print(json.dumps(d))
                continue
            root = out / split / name
            if (root / "bundle.json").is_file():
                continue
            t0 = time.time()
            generate_scene(spec_config(spec, profile(a.profile), **overrides), root, name=name, progress=False, workers=a.workers)
            seconds = time.time() - t0
            # the bundle's own generation time: benchmarks/train_generative.py ood sums them, however
            # (and in how many processes) the streets were made
            (root / GENERATION_FILE).write_text(json.dumps({"seconds": round(seconds, 1), "workers": a.workers}))
            print(f"{name}: {seconds:.1f} s ({spec.layout}, {spec.palette}, {spec.light}, "
                  f"h {spec.camera_height_m} m, fov {spec.hfov_deg})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
