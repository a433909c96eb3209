"""core.native_build: the cached C++ build of the kernels (cache key, rebuilds, errors)."""

from __future__ import annotations

import pytest

from core import native_build
from core.errors import DependencyError


def _lib(src, **kw):
    return native_build.NativeLibrary(src, name="k", subdir="t", what="test kernels", declare=lambda l: None,
                                      abi_symbol="k_abi", **kw)


def test_caches_by_source_and_reports_compiler_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("BRDFUSION_CACHE_DIR", str(tmp_path))
    src = tmp_path / "k.cpp"
    src.write_text('extern "C" int k_abi() { return 7; }\n')
    a = native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    assert a.exists() and a.parent == tmp_path / "t"
    assert native_build.build_shared_library(src, name="k", subdir="t", what="test kernels") == a  # cached
    assert _lib(src, abi_version=7).get().k_abi() == 7
    src.write_text('extern "C" int k_abi() { return 8; }\n')
    b = native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    assert b != a  # a source edit rebuilds
    with pytest.raises(DependencyError, match="ABI mismatch"):
        _lib(src, abi_version=7).get()
    src.write_text("this is not C++\n")
    with pytest.raises(DependencyError, match="building test kernels failed"):
        native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    monkeypatch.setenv("BRDFUSION_CXX", str(tmp_path / "no-such-compiler"))
    with pytest.raises(DependencyError, match="C\\+\\+ compiler"):
        native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    left = sorted(p.name for p in (tmp_path / "t").iterdir())
    assert left == sorted({a.name, b.name}), left  # no temporary files left behind


def test_a_header_edit_rebuilds(tmp_path, monkeypatch):
    """Headers included with quotes, directly or through another header, are part of the key:
    editing one rebuilds (and the new library has the header's new content)."""
    monkeypatch.setenv("BRDFUSION_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "inc").mkdir()
    src = tmp_path / "k.cpp"
    src.write_text('#include <cstdint>\n#include "inc/outer.hpp"\nextern "C" int k_abi() { return kValue; }\n')
    (tmp_path / "inc" / "outer.hpp").write_text('#pragma once\n#include "inner.hpp"  // relative to inc/\n')
    inner = tmp_path / "inc" / "inner.hpp"
    inner.write_text("#pragma once\nconstexpr int kValue = 3;\n")
    assert native_build.local_includes([src]) == [(tmp_path / "inc" / "outer.hpp").resolve(), inner.resolve()]
    a = native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    assert native_build.build_shared_library(src, name="k", subdir="t", what="test kernels") == a
    assert _lib(src, abi_version=3).get().k_abi() == 3
    inner.write_text("#pragma once\nconstexpr int kValue = 4;\n")  # only the nested header changes
    b = native_build.build_shared_library(src, name="k", subdir="t", what="test kernels")
    assert b != a
    assert _lib(src, abi_version=4).get().k_abi() == 4


def test_build_key_follows_headers_and_depends(tmp_path):
    src = tmp_path / "k.cpp"
    src.write_text('#include "shared.hpp"\nextern "C" int k_abi() { return twice(5); }\n')
    header = tmp_path / "shared.hpp"
    header.write_text("#pragma once\nnamespace { inline int twice(int x) { return 2 * x; } }\n")
    extra = tmp_path / "extra.txt"
    extra.write_text("a")
    key = native_build.build_key(src)
    assert native_build.build_key(src) == key
    header.write_text("#pragma once\nnamespace { inline int twice(int x) { return x + x; } }\n")
    assert native_build.build_key(src) != key
    key = native_build.build_key(src, depends=[extra])
    extra.write_text("b")
    assert native_build.build_key(src, depends=[extra]) != key
    assert native_build.build_key(src, flags=("-O2",)) != native_build.build_key(src)


def test_include_scan_skips_system_and_missing_headers_and_cycles(tmp_path):
    src = tmp_path / "k.cpp"
    src.write_text('#include <vector>\n#include "cstdio"\n  #  include "a.hpp"\n// #include "gone.hpp"\n')
    (tmp_path / "a.hpp").write_text('#pragma once\n#include "b.hpp"\n#include "k.cpp"\n')
    (tmp_path / "b.hpp").write_text('#pragma once\n#include "a.hpp"\n')
    assert native_build.local_includes([src]) == [(tmp_path / "a.hpp").resolve(), (tmp_path / "b.hpp").resolve()]


def test_pbr_kernels_key_covers_every_header():
    """Every header of core/pbr/native is reached from the PBR sources, so editing any of them
    rebuilds the kernels."""
    from core.pbr import _native

    included = set(native_build.local_includes([_native._SRC]))
    on_disk = {p.resolve() for p in (_native._DIR / "native").glob("*.hpp")}
    assert on_disk and on_disk == included
