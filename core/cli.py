"""``brdf``: the command-line entry point of the BRDFusion library (no server needed).

Subcommands: generate, validate, import, render, reconstruct, relight, night, evaluate, info,
export-object, pack, unpack. The installed ``brdf`` command
is :func:`services.cli.main`, which adds the rendering service's serve, worker, up and keys through
``extensions`` (so ``core`` imports no server code; ``python -m core`` has the library's commands
only).
Errors from ``core`` print one clear line (file, field, what is wrong) and exit with status 2;
never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

from core.errors import ConfigError, CoreError

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENE = REPO_ROOT / "data" / "scenes" / "default"


def _open_any(path: str, validate: bool = True):
    """Open a bundle directory or archive (.zip/.tar.gz, unpacked to a temp dir)."""
    from core.bundle import open_bundle, unpack_bundle

    p = Path(path)
    if p.is_file():
        tmp = Path(tempfile.mkdtemp(prefix="brdf-bundle-"))
        root = unpack_bundle(p, tmp / "bundle")
        return open_bundle(root, validate=validate)
    return open_bundle(p, validate=validate)


def cmd_generate(a: argparse.Namespace) -> int:
    from core.synth import generate_scene, profile

    overrides = {}
    for kv in a.set or []:
        if "=" not in kv:
            raise CoreError(f"--set: expected key=value, got {kv!r}")
        k, v = kv.split("=", 1)
        overrides[k] = json.loads(v) if v[:1] in "0123456789-[{tfn\"" else v
        if isinstance(overrides[k], list):
            overrides[k] = tuple(overrides[k])
    if a.seed is not None:
        overrides["seed"] = a.seed
    if a.envmap:
        overrides["envmap"] = a.envmap
    if a.randomise or a.split:
        from core.synth.randomise import spec_config
        from core.synth.splits import split_spec

        index = overrides.pop("seed", 0)
        split = a.split or "train"
        spec = split_spec(split, index)
        cfg = spec_config(spec, profile(a.profile), **overrides)
        a.name = a.name or f"{split}_{index:06d}"
    else:
        cfg = profile(a.profile, **overrides)
    root = generate_scene(cfg, a.out, name=a.name, overwrite=a.overwrite, progress=not a.quiet,
                          workers=a.workers)
    print(f"wrote scene bundle: {root}")
    return 0


def cmd_validate(a: argparse.Namespace) -> int:
    from core.bundle import unpack_bundle, validate_bundle

    p = Path(a.path)
    if p.is_file():
        tmp = Path(tempfile.mkdtemp(prefix="brdf-validate-"))
        p = unpack_bundle(p, tmp / "bundle")
    issues = validate_bundle(p)
    if issues:
        print(f"INVALID: {a.path} ({len(issues)} problem(s))", file=sys.stderr)
        for i in issues:
            print(f"  {i}", file=sys.stderr)
        return 1
    print(f"OK: {a.path}")
    return 0


def cmd_import(a: argparse.Namespace) -> int:
    from core.adapters import import_drivestudio, import_nerfstudio

    if a.layout == "drivestudio":
        cams = a.cameras.split(",") if a.cameras else None
        root = import_drivestudio(a.src, a.out, cameras=cams, name=a.name, overwrite=a.overwrite,
                                  test_every=a.test_every, progress=not a.quiet)
    else:
        root = import_nerfstudio(a.src, a.out, name=a.name, overwrite=a.overwrite,
                                 test_every=a.test_every, progress=not a.quiet)
    print(f"wrote scene bundle: {root}")
    return 0


def cmd_render(a: argparse.Namespace) -> int:
    from core.export import export_frames

    b = _open_any(a.scene)
    out = Path(a.out) if a.out else REPO_ROOT / "outputs" / b.name
    if a.ground_truth:
        if b.manifest.ground_truth is None:
            raise CoreError(f"--ground-truth: scene {b.name!r} has no ground truth (only generated bundles do)")
        from core.synth.export import export_ground_truth

        res = export_ground_truth(b, out, split=a.split, fps=a.fps, progress=not a.quiet)
    else:
        res = export_frames(b, out, split=a.split, fps=a.fps, progress=not a.quiet)
    print(f"scene {b.name!r}: {len(res.exr_files)} frame(s)")
    what = "ground-truth HDR beauty + G-buffer layers" if a.ground_truth else "captured frames, linearised HDR"
    print(f"  EXR ({what}): {out / 'frames'}")
    for v in res.videos:
        print(f"  video: {v}")
    print(f"  preview: {res.preview}")
    return 0


def _parse_sets(items) -> dict[str, dict]:
    """``--set stage.field=value`` -> ``{stage: {field: value}}`` (values parsed as JSON when they
    look like numbers, booleans, lists or objects)."""
    out: dict[str, dict] = {}
    for kv in items or []:
        if "=" not in kv or "." not in kv.split("=", 1)[0]:
            raise CoreError(f"--set: expected stage.field=value, got {kv!r}")
        k, v = kv.split("=", 1)
        stage, fld = k.split(".", 1)
        try:
            val = json.loads(v) if v[:1] in "0123456789-[{tfn\"" else v
        except ValueError as exc:
            raise CoreError(f"--set {kv}: value is not valid JSON ({exc})") from None
        out.setdefault(stage, {})[fld] = val
    return out


def _stage_line(name: str, s: dict) -> str:
    bits = [f"{name}: {s.get('seconds', 0):.0f} s"]
    for k, label in (("test_psnr", "held-out PSNR {:.2f} dB"), ("gaussians", "{} Gaussians"),
                     ("photometric_psnr_fitted", "PBR photometric PSNR {:.2f} dB"),
                     ("sky_floaters_pruned", "{} sky floaters pruned")):
        v = s.get(k)
        if isinstance(v, float) and not math.isfinite(v):  # e.g. no test frames: never print "nan dB"
            bits.append(f"{label.split(' {')[0].replace('{} ', '')}: not measured")
        elif isinstance(v, (int, float)):
            bits.append(label.format(v))
    for sk in s.get("skipped") or []:
        bits.append(f"skipped: {sk}")
    return "  " + "; ".join(bits)


def cmd_reconstruct(a: argparse.Namespace) -> int:
    from core.stages.chain import RUN_FILE, RunDir, run_pipeline

    scene = a.scene
    if scene is None:  # the run's own scene when resuming one, else the bundled scene
        scene = (str(RunDir(a.out).scene_path()) if a.resume and a.out and (Path(a.out) / RUN_FILE).is_file()
                 else str(DEFAULT_SCENE))
    b = _open_any(scene)
    out = Path(a.out) if a.out else REPO_ROOT / "runs" / f"{b.name}_{a.profile}"

    def on_stage(name, what, summary):
        if a.quiet:
            return
        if what == "start":
            print(f"stage {name} ...", flush=True)
        elif what == "skip":
            print(f"stage {name}: done already (--resume)")
        else:
            print(_stage_line(name, summary), flush=True)

    res = run_pipeline(b.root, out, a.profile, stages=a.stages, resume=a.resume, progress=not a.quiet,
                       overrides=_parse_sets(a.set), iterations_scale=a.iterations_scale, on_stage=on_stage)
    total = sum(float(s.get("seconds") or 0) for s in res.values())
    print(f"reconstruction of {b.name!r} ({a.profile}): stages {list(res)} in {total:.0f} s")
    print(f"  run directory: {out}")
    return 0


def _scenario_common(a, bundle):
    """Views, fps, lights and edits of a relight / night request from the command line."""
    from core.relight import ObjectEdit
    from core.render.scenario import LightSpec, load_path_json, views_from_frames

    edited = any(x is not None for x in (a.lateral_shift, a.height_shift, a.time_start, a.time_stop, a.path_fps))
    if a.path in (None, "captured") and edited:
        from core.render.scenario import views_from_capture

        views = views_from_capture(bundle, split=a.split, lateral_shift_m=a.lateral_shift or 0.0,
                                   height_shift_m=a.height_shift or 0.0, start_s=a.time_start, stop_s=a.time_stop,
                                   fps=a.path_fps, what="--path captured")
        fps = a.path_fps or a.fps
    elif a.path in (None, "captured"):
        views, fps = views_from_frames(bundle, a.split, a.start, a.stop, a.step), a.fps
    else:
        views, fps = load_path_json(bundle, a.path)
    lights = []
    if a.lights:
        spec = _read_json(a.lights, "--lights")
        items = spec.get("lights", spec) if isinstance(spec, dict) else spec
        if not isinstance(items, list):
            raise CoreError(f"--lights {a.lights}: expected a list of lights (or {{\"lights\": [...]}})")
        lights = [LightSpec.from_dict(x, f"--lights[{i}]") for i, x in enumerate(items)]
    edits = []
    if getattr(a, "edits", None):
        spec = _read_json(a.edits, "--edits")
        items = spec.get("edits", spec) if isinstance(spec, dict) else spec
        if not isinstance(items, list):
            raise CoreError(f"--edits {a.edits}: expected a list of edits (or {{\"edits\": [...]}})")
        for i, e in enumerate(items):
            if not isinstance(e, dict) or "op" not in e or "object_id" not in e:
                raise CoreError(f"--edits[{i}]: needs op and object_id")
            known = {"op", "object_id", "source_object_id", "offset_m", "yaw_deg", "speed", "lateral_offset_m", "poses",
                     "asset", "crop_to_box", "solid", "fill_ground"}
            bad = sorted(set(e) - known)
            if bad:
                raise CoreError(f"--edits[{i}]: unknown field(s) {bad} (fields: {sorted(known)})")
            try:
                poses = tuple((int(x["time_index"]), x["obj_to_world"]) for x in e.get("poses", []))
            except (TypeError, KeyError, ValueError):
                raise CoreError(f"--edits[{i}].poses: expected [{{time_index, obj_to_world}}, ...]") from None
            edits.append(ObjectEdit(e["op"], e["object_id"], e.get("source_object_id"),
                                    tuple(e.get("offset_m", (0.0, 0.0, 0.0))), float(e.get("yaw_deg", 0.0)),
                                    speed=float(e.get("speed", 1.0)), lateral_offset_m=float(e.get("lateral_offset_m", 0.0)),
                                    poses=poses, asset=e.get("asset"), crop=bool(e.get("crop_to_box", True)),
                                    solid=bool(e.get("solid", True)), fill_ground=bool(e.get("fill_ground", True))))
    return views, fps, lights, edits


def _read_json(path: str, what: str):
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise CoreError(f"{what} {p}: not a readable JSON file ({exc})") from None


def _render_and_report(run, a, scenario, kind: str) -> int:
    from core.render.scenario import render_scenario
    from tqdm import tqdm

    from core.bundle import open_bundle
    from core.render.objects import attach_sizes

    graph, _sky, stage = run.load_scene()
    attach_sizes(graph, open_bundle(run.scene_path(), validate=False).manifest)
    out = Path(a.out)
    bar = tqdm(total=len(scenario.views), desc=kind, unit="frame", disable=a.quiet)
    try:
        res = render_scenario(graph, scenario, out, on_frame=lambda d, n: bar.update(1))
    finally:
        bar.close()
    r = res.result
    mt = res.metrics
    print(f"{kind}: {res.frames} frame(s) of the {stage} reconstruction, {res.lights} light(s), "
          f"{r.seconds_per_frame:.2f} s per frame, denoiser {r.denoiser}"
          + (f" ({r.denoiser_note})" if r.denoiser_note else ""))
    if mt.get("corrector", "none") != "none":
        print(f"  scene corrector: {mt['corrector']}")
    print(f"  exposure: {mt['exposure']} EV {mt['exposure_ev']:+.2f}"
          + (f" (limited by {mt['exposure_limited_by']})" if mt.get("exposure_limited_by") else ""))
    if scenario.street_lights:
        out.mkdir(parents=True, exist_ok=True)
        (out / "street_lights.json").write_text(json.dumps({"street_lights": mt["street_lights"]}, indent=1))
        print(f"  street lights: {len(mt['street_lights'])} at {out / 'street_lights.json'}")
    print(f"  EXR (HDR beauty + G-buffers): {out / 'frames'}")
    if r.video:
        print(f"  video: {r.video}")
    if r.preview:
        print(f"  preview: {r.preview}")
    return 0


#: ``brdf relight --envmap recovered``: the run's own recovered map (the capture's light).
RECOVERED_MAP = "recovered"


def cmd_relight(a: argparse.Namespace) -> int:
    from core.io.hdri import load_hdri
    from core.render.scenario import Scenario
    from core.stages.chain import RunDir

    run = RunDir(a.run)
    b = _open_any(str(run.scene_path()))
    views, fps, lights, edits = _scenario_common(a, b)
    m = b.manifest
    from core.render.scenario import scene_corrector

    corrector, note = scene_corrector(run) if a.corrector == "auto" else (None, "off (--corrector off)")
    if not a.quiet:
        print(f"scene corrector: {note}")
    if a.envmap == RECOVERED_MAP:
        env_path, _stage = run.latest_envmap()
        if env_path is None:
            raise ConfigError(f"--envmap {RECOVERED_MAP}: {run.root} has no recovered environment map (no pbr or "
                              f"joint stage)")
        envmap = load_hdri(str(env_path))
    else:
        envmap = load_hdri(a.envmap)
    sc = Scenario(tuple(views), envmap, rotation_deg=a.rotation, lights=tuple(lights), edits=tuple(edits),
                  exposure_ev=_relight_ev(a.exposure, a.envmap), base_exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                  rays_per_pixel=a.rays, shadows=not a.no_shadows, denoiser=a.denoiser, fps=fps, corrector=corrector)
    return _render_and_report(run, a, sc, "relight")


def _relight_ev(v: str | None, envmap: str) -> float | None:
    """Relight's ``--exposure``: as :func:`_ev`; not given, the capture's own exposure (0 stops) under
    the recovered map (the capture's light: a new path or an edit should look like the capture, and
    the scene corrector was fitted at that exposure), else automatic."""
    if v is None:
        return 0.0 if envmap == RECOVERED_MAP else None
    return _ev(v)


def _ev(v: str | None) -> float | None:
    """``--exposure``: ``auto`` (None) or stops."""
    if v is None or str(v).lower() == "auto":
        return None
    try:
        return float(v)
    except ValueError:
        raise CoreError(f"--exposure: expected 'auto' or a number of stops, got {v!r}") from None


def cmd_night(a: argparse.Namespace) -> int:
    from core.render.scenario import night_scenario
    from core.stages.chain import RunDir

    run = RunDir(a.run)
    b = _open_any(str(run.scene_path()))
    views, fps, lights, edits = _scenario_common(a, b)
    m = b.manifest
    positions = None
    if a.street_light_positions:
        spec = _read_json(a.street_light_positions, "--street-light-positions")
        positions = spec.get("positions", spec) if isinstance(spec, dict) else spec
        if not isinstance(positions, list):
            raise CoreError(f"--street-light-positions {a.street_light_positions}: expected a list of [x, y] / [x, y, z]")
    off = tuple(x for x in (a.lights_off or "").split(",") if x)
    sc, note = night_scenario(run, sky_scale=a.sky_scale, headlights=not a.no_headlights,
                              headlight_intensity=a.headlight_intensity, tail_lights=not a.no_tail_lights,
                              vehicle_lights_off=off, exposure_ev=_ev(a.exposure),
                              street_lights=a.street_lights != "none",
                              street_light_placement=a.street_lights if a.street_lights != "none" else "detect",
                              street_light_positions=positions, street_light_intensity=a.street_light_intensity,
                              street_light_spacing_m=a.street_light_spacing, bundle=b, views=tuple(views),
                              lights=tuple(lights), edits=tuple(edits), base_exposure=m.ldr_exposure,
                              gamma=m.ldr_gamma, rays_per_pixel=a.rays, denoiser=a.denoiser, fps=fps)
    if not a.quiet:
        print(f"night sky: {note}")
    return _render_and_report(run, a, sc, "night")


def cmd_evaluate(a: argparse.Namespace) -> int:
    from core.synth.evaluate import EvalSettings, evaluate_run

    b = _open_any(a.scene) if a.scene else None
    s = EvalSettings(rays_per_pixel=a.rays, denoiser=a.denoiser, max_frames=a.max_frames, corrector=not a.no_corrector)
    res = evaluate_run(a.run, b, s, out=a.out, on_step=None if a.quiet else (lambda m: print(f"  {m} done", flush=True)))
    print(json.dumps(res["summary"], indent=1))
    print(f"  written: {Path(a.out or a.run) / 'evaluation.json'}")
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    from core.demo import DemoSettings, run_demo

    b = _open_any(a.scene)
    out = Path(a.out) if a.out else REPO_ROOT / "outputs" / b.name
    res = run_demo(b.root, out, DemoSettings(profile=a.profile, envmap=a.envmap, rays_per_pixel=a.rays,
                                              denoiser=a.denoiser), progress=not a.quiet)
    sec = res["seconds"]
    print(f"main job on {b.name!r} ({a.profile}): {sec['total']:.0f} s "
          f"(reconstruct {sec['reconstruct']:.0f} s, relight {sec['relight']:.0f} s, night {sec['night']:.0f} s)")
    for k, v in res["outputs"].items():
        print(f"  {k}: {v}")
    if res["metrics"]:
        mt = res["metrics"]
        print("  measured against the bundle's Mitsuba ground truth (test trajectory):")
        for k, v in mt.items():
            if v is not None:
                print(f"    {k:28s} {v}")
    return 0


def cmd_info(a: argparse.Namespace) -> int:
    from core.render.objects import describe_objects

    p = Path(a.path)
    nodes = None
    if p.is_dir() and (p / "run.json").is_file():  # a reconstruction run: its scene and its nodes
        from core.stages.chain import RunDir

        run = RunDir(p)
        b = _open_any(str(run.scene_path()), validate=False)
        found = run.latest_graph_dir()
        if found is not None:
            graph, _sky, stage = run.load_scene()
            nodes = [n.name for n in graph.nodes]
            print(f"reconstruction {p}: profile {run.profile}, stages {run.done_stages()} (scene graph of {stage}: "
                  f"{graph.background.num} background Gaussians, {len(nodes)} object node(s))")
    else:
        b = _open_any(a.path)
    m = b.manifest
    objects = describe_objects(m, nodes)
    lamps = []
    if m.lidar:
        import numpy as np

        from core.render.streetlights import detect_poles

        frames = sorted(b.frames("train") or b.frames(None), key=lambda f: f.time_index)
        path = np.array([np.asarray(f.cam_to_world)[:3, 3] for f in frames]) if frames else None
        lamps = [lp.as_dict() for lp in detect_poles(b.load_lidar(), path_xyz=path)]
    if a.json:
        print(json.dumps({"name": m.name, "objects": objects, "street_lights": lamps}, indent=1))
        return 0
    print(f"{m.name}: {len(m.frames)} frames ({len(m.split('train'))} train, {len(m.split('test'))} test), "
          f"{len(m.cameras)} camera(s), {len(m.times)} time steps, {len(m.lidar)} LiDAR sweeps, "
          f"{len(m.objects)} objects")
    for c in m.cameras.values():
        print(f"  camera {c.id}: {c.width}x{c.height} fx={c.fx:.1f} fy={c.fy:.1f} cx={c.cx:.1f} cy={c.cy:.1f}")
    if m.ground_truth:
        print(f"  ground truth: envmap {m.ground_truth.envmap_name}; relit: "
              f"{', '.join(r.name for r in m.ground_truth.relit) or 'none'}")
    for o in objects:
        first, last = o["poses"][0], o["poses"][-1]
        xyz = lambda q: "(" + ", ".join(f"{q['obj_to_world'][k][3]:.2f}" for k in range(3)) + ")"  # noqa: E731
        extra = "" if nodes is None else ("" if o["reconstructed"] else ", not in the reconstruction")
        print(f"  object {o['id']}: {o['class']}, box {' x '.join(f'{x:.2f}' for x in o['size'])} m, "
              f"{'moving' if o['moving'] else 'parked'}, {len(o['poses'])} poses (t {first['time_s']:.2f} s "
              f"{xyz(first)} -> t {last['time_s']:.2f} s {xyz(last)}){extra}")
    for lp in lamps:
        print(f"  street light (detected in the LiDAR): head {lp['position']}, pole at {lp['pole_base']}")
    print("  (--json: every pose of every object)")
    return 0


def cmd_export_object(a: argparse.Namespace) -> int:
    from core.bundle import open_bundle
    from core.render.objects import attach_sizes, export_asset
    from core.stages.chain import RunDir

    run = RunDir(a.run)
    graph, _sky, stage = run.load_scene()
    attach_sizes(graph, open_bundle(run.scene_path(), validate=False).manifest)
    path = export_asset(graph, a.object_id, a.out, crop=not a.no_crop)
    node = graph.node(a.object_id)
    print(f"wrote object asset {path} ({node.cls} {a.object_id!r} of the {stage} reconstruction); insert it with an "
          f'edit {{"op": "insert", "object_id": "new_id", "asset": "{path}", "offset_m": [x, y, z], "yaw_deg": 0}}')
    return 0


def cmd_pack(a: argparse.Namespace) -> int:
    from core.bundle import pack_bundle

    print(f"wrote {pack_bundle(a.path, a.out)}")
    return 0


def cmd_unpack(a: argparse.Namespace) -> int:
    from core.bundle import unpack_bundle

    print(f"bundle root: {unpack_bundle(a.archive, a.dest)}")
    return 0


def build_parser(extensions=()) -> argparse.ArgumentParser:
    """The ``brdf`` parser; each of ``extensions`` is called with the subparsers to add commands
    (their ``fn`` runs them; a :class:`CoreError` they raise prints as one line)."""
    p = argparse.ArgumentParser(prog="brdf", description="BRDFusion: relightable driving scenes")
    sub = p.add_subparsers(dest="cmd", required=True)

    g = sub.add_parser("generate", help="render a synthetic street scene bundle with Mitsuba 3")
    g.add_argument("--profile", default="quick", help="tiny | quick | benchmark (default quick)")
    g.add_argument("--out", required=True, help="output bundle directory")
    g.add_argument("--seed", type=int, default=None)
    g.add_argument("--envmap", default=None, help="bundled HDRI name (city, sunset, ...) or a file")
    g.add_argument("--name", default=None)
    g.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a SynthConfig field")
    g.add_argument("--randomise", action="store_true",
                   help="a randomised street (core.synth.randomise) of --split, scene number --seed; "
                        "the profile gives frames, samples and LiDAR")
    g.add_argument("--split", default=None, help="train | val | test_id | test_ood_<axis> "
                   "(core.synth.splits; implies --randomise, default train)")
    g.add_argument("--workers", type=int, default=None, help="render processes (default 2)")
    g.add_argument("--overwrite", action="store_true")
    g.add_argument("--quiet", action="store_true")
    g.set_defaults(fn=cmd_generate)

    v = sub.add_parser("validate", help="check a scene bundle (directory, .zip or .tar.gz)")
    v.add_argument("path")
    v.set_defaults(fn=cmd_validate)

    i = sub.add_parser("import", help="convert a drivestudio or nerfstudio capture into a bundle")
    i.add_argument("layout", choices=["drivestudio", "nerfstudio"])
    i.add_argument("src")
    i.add_argument("out")
    i.add_argument("--name", default=None)
    i.add_argument("--cameras", default=None, help="drivestudio: comma-separated camera ids")
    i.add_argument("--test-every", type=int, default=None, help="put every n-th frame in the test split")
    i.add_argument("--overwrite", action="store_true")
    i.add_argument("--quiet", action="store_true")
    i.set_defaults(fn=cmd_import)

    r = sub.add_parser("render", help="export a scene's frames to EXR + MP4 (--ground-truth: Mitsuba frames and "
                                      "G-buffers of a generated bundle)")
    r.add_argument("--scene", default=str(DEFAULT_SCENE), help="bundle dir or archive (default: bundled scene)")
    r.add_argument("--out", default=None, help="output directory (default outputs/<scene name>)")
    r.add_argument("--split", default="all", choices=["all", "train", "test"])
    r.add_argument("--fps", type=float, default=10.0)
    r.add_argument("--ground-truth", action="store_true",
                   help="export the bundle's Mitsuba ground truth (HDR beauty + G-buffers) instead of its captured frames")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(fn=cmd_render)

    rc = sub.add_parser("reconstruct", help="run the inverse-rendering pipeline (the paper's five stages, then the scene corrector)")
    rc.add_argument("--scene", default=None, help="bundle dir or archive (default: with --resume, the run's own "
                    "scene; else the bundled scene)")
    rc.add_argument("--profile", default="quick", help="tiny | quick | benchmark | paper (default quick)")
    rc.add_argument("--stages", default=None, help="comma-separated subset of volume,generative_refine,volume2,"
                    "pbr,joint,corrector (default all six, in chain order; the corrector is applied only under the capture's light)")
    rc.add_argument("--resume", action="store_true", help="continue the run in --out (done stages are kept)")
    rc.add_argument("--out", default=None, help="run directory (default runs/<scene>_<profile>)")
    rc.add_argument("--set", action="append", metavar="STAGE.FIELD=VALUE", help="override a stage setting")
    rc.add_argument("--iterations-scale", type=float, default=1.0, help="scale every stage's iterations")
    rc.add_argument("--quiet", action="store_true")
    rc.set_defaults(fn=cmd_reconstruct)

    def shot_args(x):
        x.add_argument("run", help="a reconstruction run directory (brdf reconstruct --out)")
        x.add_argument("--out", required=True, help="output directory (EXR frames, MP4, preview PNG)")
        x.add_argument("--exposure", default=None, help="'auto' (one exposure for the clip from its HDR frames) or "
                       "stops on top of the capture's exposure; default auto, except relight under --envmap "
                       f"{RECOVERED_MAP}: 0, the capture's own exposure (where the scene corrector applies)")
        x.add_argument("--lights", default=None, help="JSON file: a list of lights (kind point|spot, position, "
                       "intensity in candela, direction, color, cone_inner_deg, cone_outer_deg, attach_to)")
        x.add_argument("--edits", default=None, help="JSON file: a list of object edits (op insert|move|remove, "
                       "object_id, source_object_id, offset_m, yaw_deg)")
        x.add_argument("--path", default="captured", help="'captured' (the capture's frames) or a camera path "
                       "JSON file {camera, fps, poses: [{cam_to_world, time_s}]}")
        x.add_argument("--split", default="test", choices=["train", "test", "all"], help="frames of --path captured")
        x.add_argument("--start", type=int, default=0)
        x.add_argument("--stop", type=int, default=None)
        x.add_argument("--step", type=int, default=1)
        x.add_argument("--fps", type=float, default=10.0)
        x.add_argument("--lateral-shift", type=float, default=None, help="--path captured: metres to the left "
                       "(negative: right), a lane change")
        x.add_argument("--height-shift", type=float, default=None, help="--path captured: metres up")
        x.add_argument("--time-start", type=float, default=None, help="--path captured: from this scene time (s)")
        x.add_argument("--time-stop", type=float, default=None, help="--path captured: to this scene time (s)")
        x.add_argument("--path-fps", type=float, default=None, help="--path captured: resample the path at this "
                       "frame rate (poses interpolated)")
        x.add_argument("--rays", type=int, default=64, help="PBR rays per pixel")
        x.add_argument("--denoiser", default="oidn", choices=["none", "oidn", "diffusion"])
        x.add_argument("--quiet", action="store_true")

    rl = sub.add_parser("relight", help="render a reconstruction under another sky, lights and edits")
    shot_args(rl)
    rl.add_argument("--envmap", required=True, help="bundled HDRI name (city, sunset, ...), an .exr/.hdr file, "
                    f"or '{RECOVERED_MAP}': the run's recovered map (the capture's light: a new path or an edit "
                    "under it; the scene corrector applies there)")
    rl.add_argument("--rotation", type=float, default=0.0, help="rotate the map about +z, degrees")
    rl.add_argument("--no-shadows", action="store_true", help="no ray-traced visibility (faster, no shadows)")
    rl.add_argument("--corrector", default="auto", choices=["auto", "off"], help="auto: apply the scene corrector "
                    "the run's corrector stage fitted on the capture, when it has one and the render is under the "
                    "light it was fitted at (--envmap recovered, no --rotation, no --lights, "
                    "--exposure 0); off: the denoised PBR frames")
    rl.set_defaults(fn=cmd_relight)

    nt = sub.add_parser("night", help="render a reconstruction at night (scaled sky, headlights, lights)")
    shot_args(nt)
    nt.add_argument("--sky-scale", type=float, default=0.02, help="multiplier on the recovered sky")
    nt.add_argument("--no-headlights", action="store_true")
    nt.add_argument("--headlight-intensity", type=float, default=3000.0, help="candela per headlight")
    nt.add_argument("--no-tail-lights", action="store_true")
    nt.add_argument("--lights-off", default=None, help="comma-separated object ids whose vehicle lights are off")
    nt.add_argument("--street-lights", default="detect", choices=["detect", "spacing", "none"],
                    help="detect: on the poles found in the LiDAR (or the Gaussians), rows by spacing when none; "
                         "spacing: rows along both sides of the road; none")
    nt.add_argument("--street-light-positions", default=None, help="JSON file: a list of [x, y] or [x, y, z] lamp "
                    "positions (instead of --street-lights)")
    nt.add_argument("--street-light-spacing", type=float, default=None, help="metres between lamps (default 25)")
    nt.add_argument("--street-light-intensity", type=float, default=None, help="candela per lamp (default 2000)")
    nt.set_defaults(fn=cmd_night)

    ev = sub.add_parser("evaluate", help="measure a reconstruction against a bundle's ground truth")
    ev.add_argument("run", help="a reconstruction run directory")
    ev.add_argument("--scene", default=None, help="bundle with ground truth (default: the run's scene)")
    ev.add_argument("--out", default=None, help="where evaluation.json goes (default: the run directory)")
    ev.add_argument("--rays", type=int, default=64, help="PBR rays per pixel")
    ev.add_argument("--denoiser", default="oidn", choices=["none", "oidn", "diffusion"])
    ev.add_argument("--max-frames", type=int, default=0, help="test frames evaluated (0 = all)")
    ev.add_argument("--no-corrector", action="store_true", help="score the denoised PBR frames without the run's "
                    "scene corrector")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(fn=cmd_evaluate)

    dm = sub.add_parser("demo", help="the main job: reconstruct, relight, night clip, evaluate, side-by-side sheet")
    dm.add_argument("--scene", default=str(DEFAULT_SCENE), help="bundle dir or archive (default: bundled scene)")
    dm.add_argument("--profile", default="quick", help="reconstruction profile (default quick)")
    dm.add_argument("--envmap", default=None, help="relighting map (default: the bundle's first held-back map)")
    dm.add_argument("--rays", type=int, default=64, help="PBR rays per pixel")
    dm.add_argument("--denoiser", default="oidn", choices=["none", "oidn", "diffusion"])
    dm.add_argument("--out", default=None, help="output directory (default outputs/<scene>)")
    dm.add_argument("--quiet", action="store_true")
    dm.set_defaults(fn=cmd_demo)

    n = sub.add_parser("info", help="summarise a scene bundle or a reconstruction run: cameras, objects (class, box, "
                       "parked/moving, poses), street lights detected in the LiDAR")
    n.add_argument("path", help="a bundle (directory or archive) or a run directory")
    n.add_argument("--json", action="store_true", help="print the objects (every pose) and lamps as JSON")
    n.set_defaults(fn=cmd_info)

    xo = sub.add_parser("export-object", help="write a reconstruction's object as an asset (Gaussians, materials, "
                        "box) to insert into another scene")
    xo.add_argument("run", help="a reconstruction run directory")
    xo.add_argument("object_id")
    xo.add_argument("--out", required=True, help="asset file (.pt)")
    xo.add_argument("--no-crop", action="store_true", help="keep the Gaussians outside the object's box")
    xo.set_defaults(fn=cmd_export_object)

    k = sub.add_parser("pack", help="pack a bundle directory as .zip or .tar.gz")
    k.add_argument("path")
    k.add_argument("out")
    k.set_defaults(fn=cmd_pack)

    u = sub.add_parser("unpack", help="safely unpack a bundle archive")
    u.add_argument("archive")
    u.add_argument("dest")
    u.set_defaults(fn=cmd_unpack)

    for extend in extensions:
        extend(sub)
    return p


def main(argv: list[str] | None = None, extensions=()) -> int:
    args = build_parser(extensions).parse_args(argv)
    try:
        return int(args.fn(args) or 0)
    except CoreError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
