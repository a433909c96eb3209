"""Build (once, cached) and load the C++ rasterizer kernels in ``_kernels.cpp`` via ctypes.

Why C++ and not NVIDIA Warp
    DESIGN.md's spike measured the best Warp variant (tuned, two Python threads) at 237 ms
    forward / 330 ms backward for 320x213 with 50k Gaussians on these 2-core machines; the issue
    asks for <= 60 / 120 ms. Warp's CPU backend runs a launch as one scalar serial loop and gives
    no control over SIMD, so the two biggest wins named by the spike (processing a 16-pixel tile
    row as one AVX-512 vector, and Gaussian-outer loops with per-row state so each Gaussian is
    loaded and reduced once per tile) are out of reach. The kernels here are plain C++ with GCC
    vector extensions and ``std::thread`` (dynamic tile scheduling, per-thread gradient buffers
    reduced at the end), structured one-tile-per-work-item so the same algorithm maps to a CUDA
    block per tile later.

Build
    :mod:`core.native_build` (shared with the PBR kernels): ``g++ -O3 -march=native -std=gnu++17
    -shared -fPIC -pthread`` (about 8 s, once), cached under ``$BRDFUSION_CACHE_DIR/raster``
    (default ``~/.cache/brdfusion/raster``) keyed by a hash of the source, the flags, the compiler
    version and the CPU, written to a temporary file and renamed (safe for concurrent first use).
    The runtime image therefore needs ``g++`` (gcc >= 9). ``BRDFUSION_CXX`` overrides the
    compiler. No torch headers are used, which keeps the build short.

ctypes releases the GIL for the duration of every call.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

from core.native_build import NativeLibrary

_SRC = Path(__file__).with_name("_kernels.cpp")
_ABI_VERSION = 6


def _declare(lib: ctypes.CDLL) -> None:
    p, i32, i64, f64 = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_double
    for suf in ("f32", "f64"):
        sig = {
            "project": ([p] * 10 + [i32, i32, i64, i32, p, p], ctypes.c_int),
            "project_backward": ([p] * 5 + [i32, i32, i64, i32] + [p] * 11, None),
            "bin": ([p, p, i64, i32, i32, f64, i32, p, i64, p, p, p, p], ctypes.c_int64),
            "forward": ([p, p, p, p, p, i32, i32, i32, p, f64, f64, f64, i32, p, p, p, p], None),
            "backward": ([p, p, p, p, p, i32, i32, i32, p, f64, f64, f64, i32, p, p, p, i64, p], None),
        }
        for name, (args, res) in sig.items():
            fn = getattr(lib, f"br_{name}_{suf}")
            fn.argtypes = args
            fn.restype = res


_LIB = NativeLibrary(_SRC, name="brdfusion_raster", subdir="raster", what="the rasterizer kernels",
                     declare=_declare, abi_symbol="br_abi_version", abi_version=_ABI_VERSION)


def lib() -> ctypes.CDLL:
    """The loaded kernel library (built on first call)."""
    return _LIB.get()
