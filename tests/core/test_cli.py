"""The ``brdf`` command line: subcommands work end to end and errors are one clear line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from core.cli import main


def test_render_writes_exr_mp4_preview(small_bundle, tmp_path, capsys):
    """By default the captured frames, linearised: the product path reads no ground truth."""
    from core.bundle import open_bundle
    from core.io.exr import read_exr
    from core.io.video import read_mp4_frames
    from core.tonemap import hdr_to_ldr

    out = tmp_path / "out"
    assert main(["render", "--scene", str(small_bundle), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert str(out / "frames") in printed and "preview" in printed and "captured frames" in printed
    layers = read_exr(out / "frames" / "f000.exr")
    assert set(layers) == {"rgb"}
    b = open_bundle(small_bundle)
    m, f0 = b.manifest, b.frames()[0]
    back = hdr_to_ldr(layers["rgb"], m.ldr_exposure, m.ldr_gamma)
    assert np.abs(back - b.load_image(f0)).max() < 2e-3  # the stored frame, round-tripped
    frames = read_mp4_frames(out / "train.mp4")
    assert frames.shape[0] == 2
    assert not (out / "train_gbuffers.mp4").exists() and (out / "preview.png").is_file()


def test_render_ground_truth_exports_mitsuba_layers(small_bundle, tmp_path, capsys):
    from core.io.exr import read_exr

    out = tmp_path / "out"
    assert main(["render", "--scene", str(small_bundle), "--out", str(out), "--ground-truth", "--quiet"]) == 0
    assert "ground-truth HDR beauty + G-buffer layers" in capsys.readouterr().out
    layers = read_exr(out / "frames" / "f000.exr")
    assert {"rgb", "albedo", "normal", "depth", "roughness", "metallic"} <= set(layers)
    assert (out / "train_gbuffers.mp4").is_file() and (out / "preview.png").is_file()


def test_render_ground_truth_of_a_capture_is_a_clear_error(small_bundle, tmp_path, capsys):
    import json
    import shutil

    cap = tmp_path / "capture"
    shutil.copytree(small_bundle, cap)
    d = json.loads((cap / "bundle.json").read_text())
    d.pop("ground_truth", None)
    for f in d["frames"]:
        f.pop("ground_truth", None)
    (cap / "bundle.json").write_text(json.dumps(d))
    assert main(["render", "--scene", str(cap), "--out", str(tmp_path / "o"), "--ground-truth", "--quiet"]) == 2
    assert "--ground-truth" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_render_archive(small_bundle, tmp_path):
    from core.bundle import pack_bundle

    arc = pack_bundle(small_bundle, tmp_path / "s.zip")
    assert main(["render", "--scene", str(arc), "--out", str(tmp_path / "o"), "--split", "test", "--quiet"]) == 0
    assert (tmp_path / "o" / "test.mp4").is_file()


def test_info_and_pack(small_bundle, tmp_path, capsys):
    assert main(["info", str(small_bundle)]) == 0
    assert "3 frames (2 train, 1 test)" in capsys.readouterr().out
    assert main(["pack", str(small_bundle), str(tmp_path / "s.tar.gz")]) == 0
    assert main(["validate", str(tmp_path / "s.tar.gz")]) == 0


def test_errors_are_one_line_without_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "core", "render", "--scene", str(tmp_path / "missing")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "error:" in r.stderr and "Traceback" not in r.stderr and "missing" in r.stderr


def test_generate_bad_override(tmp_path, capsys):
    assert main(["generate", "--profile", "tiny", "--out", str(tmp_path / "x"), "--set", "width=1"]) == 2
    assert "width" in capsys.readouterr().err


def test_core_cli_imports_no_server_code():
    """``core.cli`` (``python -m core``) has the library's commands only and loads no server
    package; the installed ``brdf`` (``services.cli.main``) adds the service's commands."""
    code = ("import sys, core.cli; p = core.cli.build_parser(); "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('services', 'worker', 'fastapi', 'redis', 'rq', 'api_schemas')); "
            "print(bad)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]"
    r = subprocess.run([sys.executable, "-m", "core", "serve"], capture_output=True, text=True)
    assert r.returncode == 2 and "invalid choice" in r.stderr
    from services.cli import main as brdf

    with pytest.raises(SystemExit) as e:
        brdf(["keys", "create"])  # parsed by the full command: only --tenant is missing
    assert e.value.code == 2


@pytest.mark.mitsuba
def test_reconstruct_killed_with_sigkill_resumes_from_its_checkpoint(tiny_scene, tmp_path):
    """``brdf reconstruct`` killed with kill -9 in the middle of a stage; ``--resume`` continues
    from that stage's checkpoint and finishes."""
    import json
    import signal
    import time

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "core", "reconstruct", "--scene", str(tiny_scene), "--profile", "tiny",
           "--stages", "volume", "--iterations-scale", "40", "--out", str(out), "--quiet"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    state = out / "volume" / "resume" / "train_state.pt"
    t0 = time.time()
    while not state.is_file() and p.poll() is None and time.time() - t0 < 240:
        time.sleep(0.2)
    assert state.is_file(), p.stderr.read().decode() if p.poll() is not None else "no checkpoint in 240 s"
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert not (out / "volume" / "done.json").exists()
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    s = json.loads((out / "volume" / "summary.json").read_text())
    assert s["resumed_from_iteration"] > 0 and s["iterations"] == 2400
    assert "reconstruction of" in r.stdout


@pytest.mark.mitsuba
def test_demo_writes_the_sheet_outputs_and_metrics(tiny_scene, tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--scene", str(tiny_scene), "--profile", "tiny", "--rays", "8", "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    for name in ("sheet.png", "evaluation.json", "relit/relit.mp4", "relit/preview.png", "night/relit.mp4"):
        assert (out / name).is_file(), name
    assert any((out / "relit" / "frames").glob("*.exr"))
    assert "relight_psnr" in printed and "albedo_si_psnr" in printed
    from core.io.images import read_image

    sheet = read_image(str(out / "sheet.png"))
    assert sheet.shape[1] > 6 * 48  # input, novel view, albedo, normal, roughness, relit, ground truth
    assert main(["relight", str(out / "run"), "--envmap", "nope", "--out", str(tmp_path / "x")]) == 2
    assert "nope" in capsys.readouterr().err


def test_stage_line_never_prints_nan():
    """A stage without test frames has no held-out PSNR: the line says so instead of 'nan dB'."""
    from core.cli import _stage_line

    line = _stage_line("volume", {"seconds": 3.0, "test_psnr": float("nan"), "gaussians": 100})
    assert "held-out PSNR: not measured" in line and "nan" not in line and "100 Gaussians" in line
    assert "held-out PSNR 21.23 dB" in _stage_line("volume", {"seconds": 3.0, "test_psnr": 21.234})


def test_set_reaches_a_nested_group_of_stage_settings():
    """``--set pbr.prior_gains.enabled=false`` turns the prior gains off; a value of the wrong type
    is refused with the field's name."""
    from core.cli import _parse_sets
    from core.errors import ConfigError
    from core.stages.chain import profile_settings

    sets = _parse_sets(["pbr.prior_gains.enabled=false", "pbr.prior_gains.steps=11"])
    assert sets == {"pbr": {"prior_gains.enabled": False, "prior_gains.steps": 11}}
    cfg = profile_settings("quick", "pbr", sets["pbr"])
    assert cfg.prior_gains.enabled is False and cfg.prior_gains.steps == 11
    assert profile_settings("quick", "pbr").prior_gains.enabled is True
    with pytest.raises(ConfigError, match="enabled"):
        profile_settings("quick", "pbr", _parse_sets(["pbr.prior_gains.enabled=maybe"])["pbr"])
