"""``brdf``: the command-line entry point of the BRDFusion library (no server needed).

Subcommands: generate, validate, import, render, info, pack, unpack. The installed ``brdf`` command
is :func:`services.cli.main`, which adds the rendering service's serve, worker, up and keys through
``extensions`` (so ``core`` imports no server code; ``python -m core`` has the library's commands
only).
Errors from ``core`` print one clear line (file, field, what is wrong) and exit with status 2;
never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from core.errors import CoreError

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
    res = export_frames(b, out, split=a.split, fps=a.fps, progress=not a.quiet)
    print(f"scene {b.name!r}: {len(res.exr_files)} frame(s)")
    print(f"  EXR (HDR beauty + G-buffer layers): {out / 'frames'}")
    for v in res.videos:
        print(f"  video: {v}")
    print(f"  preview: {res.preview}")
    return 0


def cmd_train(a: argparse.Namespace) -> int:
    from dataclasses import replace

    from core.train.nvs import NVS_PROFILES, train_nvs

    if a.profile not in NVS_PROFILES:
        raise CoreError(f"--profile: unknown profile {a.profile!r} (known: {sorted(NVS_PROFILES)})")
    cfg = NVS_PROFILES[a.profile]
    if a.iterations is not None:
        cfg = replace(cfg, iterations=a.iterations)
    b = _open_any(a.scene)
    out = Path(a.out) if a.out else REPO_ROOT / "runs" / f"{b.name}_nvs_{a.profile}"
    s = train_nvs(b, cfg, out, progress=not a.quiet)
    print(f"scene {b.name!r}, profile {a.profile}: {s['iterations']} iterations in {s['train_seconds']} s, "
          f"{s['gaussians']} Gaussians")
    print(f"  held-out (test trajectory) PSNR {s['test_psnr']:.2f} dB, SSIM {s['test_ssim']:.3f}; "
          f"train PSNR {s['train_psnr']:.2f} dB")
    print(f"  outputs: {out}")
    return 0


def cmd_info(a: argparse.Namespace) -> int:
    b = _open_any(a.path)
    m = b.manifest
    print(f"{m.name}: {len(m.frames)} frames ({len(m.split('train'))} train, {len(m.split('test'))} test), "
          f"{len(m.cameras)} camera(s), {len(m.times)} time steps, {len(m.lidar)} LiDAR sweeps, "
          f"{len(m.objects)} objects")
    for c in m.cameras.values():
        print(f"  camera {c.id}: {c.width}x{c.height} fx={c.fx:.1f} fy={c.fy:.1f} cx={c.cx:.1f} cy={c.cy:.1f}")
    if m.ground_truth:
        print(f"  ground truth: envmap {m.ground_truth.envmap_name}; relit: "
              f"{', '.join(r.name for r in m.ground_truth.relit) or 'none'}")
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

    r = sub.add_parser("render", help="render a scene's frames to multi-layer EXR + MP4")
    r.add_argument("--scene", default=str(DEFAULT_SCENE), help="bundle dir or archive (default: bundled scene)")
    r.add_argument("--out", default=None, help="output directory (default outputs/<scene name>)")
    r.add_argument("--split", default="all", choices=["all", "train", "test"])
    r.add_argument("--fps", type=float, default=10.0)
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(fn=cmd_render)

    t = sub.add_parser("train", help="fit Gaussians to a scene (volume stage without priors, NVS)")
    t.add_argument("--scene", default=str(DEFAULT_SCENE), help="bundle dir or archive (default: bundled scene)")
    t.add_argument("--profile", default="quick", help="tiny | quick | benchmark (default quick)")
    t.add_argument("--iterations", type=int, default=None, help="override the profile's iterations")
    t.add_argument("--out", default=None, help="output directory (default runs/<scene>_nvs_<profile>)")
    t.add_argument("--quiet", action="store_true")
    t.set_defaults(fn=cmd_train)

    n = sub.add_parser("info", help="summarise a scene bundle")
    n.add_argument("path")
    n.set_defaults(fn=cmd_info)

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
