"""Build (once, cached) and load the PBR kernels via ctypes: one shared object, ``_integrator.cpp``,
holds the C entry points of both the 4-wide shadow-ray BVH of :mod:`core.pbr.visibility`
(``bv_*``, kernel in ``native/trace4.hpp``) and the fused integrator (``pi_*``). The pieces are
the headers of ``native/``: the BVH (``bvh.hpp``, one template over the node width: 4-wide for
``trace4.hpp``, 8-wide for the integrator), and the integrator's shadow rays (``shadow.hpp``: up
to three BVHs, each with its own minimum ray distance), BRDF, environment map, random numbers,
visibility cache and work sharing.

Why C++ (as the rasterizer, :mod:`core.raster._native`): Warp's CPU backend runs a launch as one
serial loop with no control over the memory layout or SIMD; a BVH traversal with a per-ray stack,
early exit and a 16-wide AVX-512 leaf test is plain C++ that GCC compiles well. The build is
:mod:`core.native_build`: ``g++ -O3 -march=native -std=gnu++17 -shared -fPIC -pthread``, about
5 s once, cached under ``$BRDFUSION_CACHE_DIR/pbr`` (default ``~/.cache/brdfusion/pbr``) keyed
by a hash of the source and every file it includes with ``#include "..."``, the flags, the
compiler version and the CPU, written to a temporary file and renamed (safe for concurrent first
use). ``BRDFUSION_CXX`` overrides the compiler. ctypes releases the GIL for the duration of every
call; the kernels spread their work over ``std::thread`` workers themselves.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

from core.errors import DependencyError
from core.native_build import NativeLibrary

_DIR = Path(__file__).parent
#: The compiled source; it includes the ``native/`` headers, which the build finds and hashes
#: into the cache key.
_SRC = _DIR / "_integrator.cpp"
#: ABI of the shadow-ray entry points (``bv_abi_version``) and of the integrator (``pi_abi_version``).
_ABI_VERSION = 2
_PI_ABI_VERSION = 10
#: Most BVHs a shadow ray of the integrator goes through (``kMaxBvhs`` of native/shadow.hpp): the
#: static scene, moving nodes and edited objects.
MAX_BVHS = 3
#: Size in bytes of one 4-wide BVH node in the kernel (must match ``WideNode<4>`` of native/bvh.hpp).
NODE_BYTES = 128
#: Size in bytes of one 8-wide BVH node of the integrator (must match ``WideNode<8>``).
NODE8_BYTES = 256
#: float32 values per Gaussian record in the kernel (mu[3], M[9], opacity, r2max, pad[2]).
GAUSS_FLOATS = 16
#: float32 arrays of the SoA Gaussian layout of the integrator (mu xyz, M row-major, opacity, r2max).
SOA_ARRAYS = 14
#: padding (floats) after each SoA array, so a 16-lane load past the last leaf stays inside.
SOA_PAD = 16
#: float32 values per light record of ``pi_render``.
LIGHT_FLOATS = 16
#: int64 counters returned by ``pi_render``.
NUM_COUNTERS = 11


def _declare(lib: ctypes.CDLL) -> None:
    p, i32, i64, f32, f64, u64 = (ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_float, ctypes.c_double,
                                  ctypes.c_uint64)
    lib.bv_abi_version.restype = ctypes.c_int
    lib.bv_build.argtypes = [p, p, i64, i32, p, p, p]
    lib.bv_build.restype = i64
    lib.bv_trace.argtypes = [p, i64, p, p, p, p, i64, f64, f64, f64, i32, p, p]
    lib.bv_trace.restype = None
    lib.pi_build8.argtypes = [p, p, i64, i32, p, p, p]
    lib.pi_build8.restype = i64
    lib.pi_build_alias.argtypes = [p, i64, p, p]
    lib.pi_build_alias.restype = None
    lib.pi_cache_create.argtypes = [i64, i32]
    lib.pi_cache_create.restype = p
    lib.pi_cache_size.argtypes = [p]
    lib.pi_cache_size.restype = i64
    lib.pi_cache_free.argtypes = [p]
    lib.pi_cache_free.restype = None
    lib.pi_trace.argtypes = [p, p, p, p, p, i32, p, p, p, i64, f32, f32, i32, p, p]
    lib.pi_trace.restype = None
    lib.pi_eval.argtypes = [p, p, p, p, p, p, f32, i32, i64, p, p]
    lib.pi_eval.restype = None
    lib.pi_env_eval.argtypes = [i32, i32, p, p, p, f32, i32, p, i64, p, p]
    lib.pi_env_eval.restype = None
    lib.pi_env_sample.argtypes = [i32, i32, p, p, p, f32, i32, u64, i64, p, p, p]
    lib.pi_env_sample.restype = None
    lib.pi_render.argtypes = ([p] * 10 + [i64, p, p, p, p, p, p, p, p, p, p, i32, i32, i32] + [p] * 3
                              + [f32, i32, p, p, p, p, p, p, p])
    lib.pi_render.restype = None


_LIB = NativeLibrary(_SRC, name="brdfusion_pbr", subdir="pbr", what="the PBR kernels", declare=_declare,
                     abi_symbol="pi_abi_version", abi_version=_PI_ABI_VERSION)


def lib() -> ctypes.CDLL:
    """The loaded kernel library (built on first call)."""
    loaded = _LIB.get()
    if loaded.bv_abi_version() != _ABI_VERSION:
        raise DependencyError("shadow-ray kernel ABI mismatch; delete the kernel cache")
    return loaded
