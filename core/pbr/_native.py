"""Build (once, cached) and load the C++ shadow-ray kernels in ``_visibility.cpp`` via ctypes.

Same build approach as :mod:`core.raster._native` (and for the same reason: Warp's CPU backend
runs a launch as one serial loop with no control over the memory layout, and a BVH traversal
with a per-ray stack and early exit is plain scalar code that GCC compiles well):
``g++ -O3 -march=native -std=gnu++17 -shared -fPIC -pthread``, about 3 s once, cached under
``$BRDFUSION_CACHE_DIR/pbr`` (default ``~/.cache/brdfusion/pbr``) keyed by a hash of the source,
the flags, the compiler version and the CPU, written to a temporary file and renamed (safe for
concurrent first use). ``BRDFUSION_CXX`` overrides the compiler. ctypes releases the GIL for
the duration of every call; the kernel spreads rays over ``std::thread`` workers itself.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
import threading
from pathlib import Path

from core.errors import DependencyError

_SRC = Path(__file__).with_name("_visibility.cpp")
_FLAGS = ["-O3", "-march=native", "-std=gnu++17", "-shared", "-fPIC", "-pthread", "-Wno-psabi"]
_ABI_VERSION = 2
#: Size in bytes of one 4-wide BVH node in the kernel (must match ``struct Node4``).
NODE_BYTES = 128
#: float32 values per Gaussian record in the kernel (mu[3], M[9], opacity, r2max, pad[2]).
GAUSS_FLOATS = 16

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None


def _cache_dir() -> Path:
    root = os.environ.get("BRDFUSION_CACHE_DIR")
    base = Path(root) if root else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "brdfusion"
    return base / "pbr"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name") or line.startswith("flags"):
                    return line.strip()
    except OSError:
        pass
    return "unknown"


def _build() -> Path:
    cxx = os.environ.get("BRDFUSION_CXX", "g++")
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise DependencyError(f"a C++ compiler ({cxx}) is needed to build the shadow-ray kernels: {exc}") from exc
    src = _SRC.read_bytes()
    key = hashlib.sha256(src + repr((_FLAGS, version, _cpu_model())).encode()).hexdigest()[:16]
    out_dir = _cache_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"brdfusion_visibility_{key}.so"
    if target.exists():
        return target
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out_dir)
    os.close(fd)
    try:
        proc = subprocess.run([cxx, *_FLAGS, "-o", tmp, str(_SRC)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise DependencyError(f"building the shadow-ray kernels failed:\n{proc.stderr[-4000:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _declare(lib: ctypes.CDLL) -> None:
    p, i32, i64, f64 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_double
    lib.bv_abi_version.restype = ctypes.c_int
    lib.bv_build.argtypes = [p, p, i64, i32, p, p, p]
    lib.bv_build.restype = i64
    lib.bv_trace.argtypes = [p, i64, p, p, p, p, i64, f64, f64, f64, i32, p, p]
    lib.bv_trace.restype = None


def lib() -> ctypes.CDLL:
    """The loaded kernel library (built on first call)."""
    global _lib
    if _lib is None:
        with _lock:
            if _lib is None:
                loaded = ctypes.CDLL(str(_build()))
                _declare(loaded)
                if loaded.bv_abi_version() != _ABI_VERSION:
                    raise DependencyError("shadow-ray kernel ABI mismatch; delete the kernel cache")
                _lib = loaded
    return _lib
