"""Sun-direction error of the lighting prior on the development and validation streets (the
figures quoted in ``core/lighting/prior.py`` and ``core/lighting/sky_transport.py``; choices are made on
these, never on the held-out h7, h8, h15-h17 of ``bench_generative.py``).

Streets (``quick`` profile, no relit ground truth; generated under ``--data`` when missing, about
70 s each): the sunny training-plan streets of ``train_generative.py`` (city, sunrise and sunset
at their plan rotations: s100, s101, s104, s105, s106, s109, s110, s111) and three validation
streets for the lighting prior, v12 (sunset, 150 deg), v13 (sunset, 120 deg), v14 (city,
105 deg). The true meshes are the occluders (``occluders="oracle"``).

Usage::

    python benchmarks/eval_lighting.py --data /work/gen/data                       # all 11
    python benchmarks/eval_lighting.py --data D --streets s100 v14 \\
        --set transport.free_interreflection_scale=true --set max_points=8000

Prints one line per street (error, sun source, seconds) and the mean / median / largest error,
and with ``--out`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

DEVELOPMENT = ("s100", "s101", "s104", "s105", "s106", "s109", "s110", "s111")
#: Validation streets of the lighting prior: (seed, HDRI, rotation in degrees).
VALIDATION = {"v12": (12, "sunset", 150.0), "v13": (13, "sunset", 120.0), "v14": (14, "city", 105.0)}


def street_plan() -> dict[str, tuple[int, str, float]]:
    from train_generative import scene_plan

    plan = {name: (seed, env, rot) for name, seed, env, rot in scene_plan(range(100, 112))}
    plan.update(VALIDATION)
    return plan


def parse_overrides(items: list[str]):
    """``key=value`` (``transport.key=value`` for the transport settings) -> LightingSettings."""
    from core.errors import ConfigError
    from core.lighting.prior import LightingSettings

    top, tr = {}, {}
    base = LightingSettings()
    for it in items:
        key, sep, val = it.partition("=")
        if not sep:
            raise ConfigError(f"--set: expected key=value, got {it!r}")
        target, obj = (tr, base.transport) if key.startswith("transport.") else (top, base)
        name = key.removeprefix("transport.")
        known = {f.name for f in fields(obj)}
        if name not in known:
            raise ConfigError(f"--set: unknown setting {key!r} (known: {', '.join(sorted(known))})")
        target[name] = json.loads(val)
        if isinstance(getattr(obj, name), tuple):
            target[name] = tuple(target[name])
    return replace(base, **top, transport=replace(base.transport, **tr))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="directory of the streets (made when missing)")
    ap.add_argument("--streets", nargs="+", default=list(DEVELOPMENT) + list(VALIDATION))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a LightingSettings field (transport.<field> for TransportSettings); JSON values")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    a = ap.parse_args(argv)

    from core.bundle import open_bundle
    from core.lighting.prior import brightest_direction, sun_direction_error_deg
    from lighting_harness import estimate_from_bundle
    from train_generative import generate_street

    from core.errors import CoreError

    try:
        settings = parse_overrides(a.set)
    except CoreError as e:
        ap.error(str(e))
    plan = street_plan()
    unknown = [s for s in a.streets if s not in plan]
    if unknown:
        ap.error(f"unknown streets {unknown} (known: {', '.join(sorted(plan))})")
    print(f"machine: {os.cpu_count()} cpus, load {os.getloadavg()[0]:.2f}; overrides: {a.set or 'none'}", flush=True)
    rows = {}
    for name in a.streets:
        root = a.data / name
        seed, env, rot = plan[name]
        generate_street(root, seed, env, rot)
        t = time.perf_counter()
        est = estimate_from_bundle(root, "train", settings=settings, occluders="oracle")
        err = sun_direction_error_deg(est.sun_dir, brightest_direction(open_bundle(root, validate=False).load_envmap()))
        rows[name] = {"envmap": env, "rotation_deg": rot, "sun_dir_err_deg": err, "sun_source": est.sun_source,
                      "seconds": time.perf_counter() - t}
        print(f"{name:5s} {env:8s} {rot:5.0f} deg  sun error {err:6.1f} deg  ({est.sun_source}, "
              f"{rows[name]['seconds']:.0f} s)", flush=True)
    errs = np.array([r["sun_dir_err_deg"] for r in rows.values()])
    summary = {"mean": float(errs.mean()), "median": float(np.median(errs)), "max": float(errs.max())}
    print(f"mean {summary['mean']:.1f}  median {summary['median']:.1f}  largest {summary['max']:.1f} deg")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"overrides": a.set, "streets": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
