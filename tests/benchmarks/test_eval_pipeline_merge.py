"""``benchmarks/eval_pipeline.py --merge-from``: streets run side by side, each into a results file
of its own, are merged street by street and the means recomputed, without running any street."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from benchmarks.eval_pipeline import KEYS

REPO = Path(__file__).resolve().parents[2]


def _row(role: str, relight: float) -> dict:
    return {"role": role, **{k: 1.0 for k in KEYS}, "relight_psnr": relight, "stage_seconds": {"volume": 10.0}}


def _write(path: Path, streets: dict) -> None:
    path.write_text(json.dumps({"per_street": {"full": {"benchmark": streets}}}))


def test_merge_takes_each_street_from_its_own_file_and_recomputes_the_means(tmp_path):
    out, a, b = tmp_path / "eval.json", tmp_path / "a.json", tmp_path / "b.json"
    _write(out, {"test1": _row("test", 10.0), "test2": _row("test", 12.0), "dev1": _row("dev", 5.0)})
    first = json.loads(out.read_text())
    first["full"] = {"how": "written by hand", "relight_psnr": 11.0}
    out.write_text(json.dumps(first))
    # a.json holds test1's new row and a stale copy of test2; b.json test2's new row
    _write(a, {"test1": _row("test", 20.0), "test2": _row("test", 12.0)})
    _write(b, {"test2": _row("test", 22.0), "test1": _row("test", 10.0)})
    r = subprocess.run([sys.executable, "benchmarks/eval_pipeline.py",
                        "--out", str(out), "--merge-from", f"test1={a}", f"test2={b}"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(out.read_text())
    streets = res["per_street"]["full"]["benchmark"]
    assert streets["test1"]["relight_psnr"] == 20.0 and streets["test2"]["relight_psnr"] == 22.0
    assert streets["dev1"]["relight_psnr"] == 5.0
    assert res["full"]["relight_psnr"] == 21.0 and res["full_dev"]["relight_psnr"] == 5.0
    assert res["full"]["how"] == "written by hand"  # the hand-written fields beside the figures stay
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "eval.json"]  # nothing run


def test_merge_names_a_bad_spec(tmp_path):
    r = subprocess.run([sys.executable, "benchmarks/eval_pipeline.py", "--data", str(tmp_path), "--out",
                        str(tmp_path / "e.json"), "--merge-from", "nowhere.json"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "--merge-from" in r.stderr and "STREET=JSON" in r.stderr


def test_running_streets_needs_data(tmp_path):
    r = subprocess.run([sys.executable, "benchmarks/eval_pipeline.py", "--out", str(tmp_path / "e.json"),
                        "--streets", "test1"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "--data" in r.stderr
    assert not (tmp_path / "e.json").exists()
