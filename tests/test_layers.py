"""The layer rules (pyproject.toml, [tool.importlinter]) hold, checked by import-linter."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _lint(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    if not exe.is_file():
        found = shutil.which("lint-imports")
        if found is None:
            pytest.fail("lint-imports is not installed (pip install -e '.[test]')")
        exe = Path(found)
    return subprocess.run([str(exe), "--no-cache", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_the_layer_contracts_are_kept():
    r = _lint()
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "6 kept, 0 broken" in r.stdout


def test_the_check_sees_imports_inside_functions(tmp_path):
    """A contract the code breaks on purpose is reported broken: core.stages.pbr imports the PBR
    pass inside a function."""
    cfg = tmp_path / "contracts.toml"
    cfg.write_text('[tool.importlinter]\nroot_packages = ["core"]\n\n[[tool.importlinter.contracts]]\n'
                   'name = "probe"\ntype = "forbidden"\nsource_modules = ["core.stages.pbr"]\n'
                   'forbidden_modules = ["core.pbr.render"]\n')
    r = _lint("--config", str(cfg))
    assert r.returncode != 0 and "BROKEN" in r.stdout, r.stdout[-2000:]


def test_the_cycle_check_sees_a_cycle_through_a_function_level_import(tmp_path):
    """The acyclic contract of worker/ reports a cycle like the one the worker had (the registry
    importing the job modules inside a function, the job modules importing the registry)."""
    pkg = tmp_path / "cyc"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "registry.py").write_text("def job_type():\n    import cyc.jobs  # noqa: F401\n")
    (pkg / "jobs.py").write_text("from cyc.registry import job_type  # noqa: F401\n")
    cfg = tmp_path / "contracts.toml"
    cfg.write_text('[tool.importlinter]\nroot_packages = ["cyc"]\n\n[[tool.importlinter.contracts]]\n'
                   'name = "probe"\ntype = "acyclic_siblings"\nancestors = ["cyc"]\n')
    r = _lint("--config", str(cfg), cwd=tmp_path)
    assert r.returncode != 0 and "BROKEN" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]


def test_the_gateway_never_loads_torch():
    """The gateway imports the worker's registry (job types and their schemas) but never torch or
    the passes: that is why the job modules import the core inside their functions (measured: the
    gateway's imports peak at 91 MB resident, 284 MB with torch and the passes)."""
    code = ("import sys, services.app; bad = [m for m in ('torch', 'core.pbr', 'core.raster', 'core.stages.volume', "
            "'onnxruntime', 'mitsuba') if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-2000:]
    assert r.stdout.strip() == "[]"


#: The bundle's ground-truth readers (:class:`core.bundle.reader.SceneBundle`) and the manifest
#: paths of ground-truth files: only core.synth (and the format layer core.bundle, which defines and
#: validates them) may use them.
_GT_READERS = {"load_ground_truth", "load_envmap", "load_relit_frame"}


def _ground_truth_uses(path: Path) -> list[str]:
    """``file:line name`` of every call of a ground-truth reader, and every read of a ground-truth
    file path (``<x>.ground_truth.envmap`` / ``.relit`` / ``<frame>.ground_truth`` handed to a file
    reader), in one source file."""
    import ast

    tree = ast.parse(path.read_text(), str(path))
    name = path.relative_to(REPO) if path.is_relative_to(REPO) else path.name
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in _GT_READERS:
            out.append(f"{name}:{node.lineno} {node.func.attr}()")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "path"
                and node.args and "ground_truth" in ast.unparse(node.args[0])):
            out.append(f"{name}:{node.lineno} path({ast.unparse(node.args[0])})")
    return out


def test_only_core_synth_reads_ground_truth():
    """No module outside core.synth (and the bundle format, benchmarks/ and tests/) reads a bundle's
    ground truth; core.synth is imported only by the commands that show it (a contract above)."""
    allowed = (REPO / "core" / "synth", REPO / "core" / "bundle")
    found = []
    for pkg in ("core", "worker", "services", "api_schemas"):
        for p in sorted((REPO / pkg).rglob("*.py")):
            if not any(p.is_relative_to(a) for a in allowed):
                found += _ground_truth_uses(p)
    assert found == [], found
    # and the scan sees what it looks for
    uses = _ground_truth_uses(REPO / "core" / "synth" / "evaluate.py")
    assert any("load_ground_truth()" in u for u in uses) and any("load_relit_frame()" in u for u in uses)


def test_the_ground_truth_scan_sees_a_path_read(tmp_path):
    p = tmp_path / "probe.py"
    p.write_text("def f(b, fr, m):\n    b.path(fr.ground_truth)\n    return b.path(m.ground_truth.envmap)\n")
    assert [u.split(" ", 1)[1] for u in _ground_truth_uses(p)] == ["path(fr.ground_truth)",
                                                                     "path(m.ground_truth.envmap)"]
