"""Build C++ sources into cached shared objects and load them with ctypes (shared by
:mod:`core.raster._native` and :mod:`core.pbr._native`).

Build
    ``g++ <flags> -o <so> <source>`` with the default flags
    ``-O3 -march=native -std=gnu++17 -shared -fPIC -pthread -Wno-psabi``. The shared object is
    cached under ``$BRDFUSION_CACHE_DIR/<subdir>`` (default ``~/.cache/brdfusion/<subdir>``; if
    that is not writable, the temporary directory) and keyed by a hash of the source, every file
    it includes with ``#include "..."`` (found by :func:`local_includes`, recursively, relative
    to the including file), any extra files listed in ``depends``, the flags, the compiler
    version and the CPU model and feature flags, so an edit of the source or of one of its
    headers, or a different machine, rebuilds (``-march=native`` code is only valid on the same
    kind of CPU). The build writes to a temporary file in the cache directory and renames it into
    place (:func:`core.io.atomic.atomic_output`), so concurrent first uses (pytest-xdist, several
    workers) are safe. ``BRDFUSION_CXX``
    overrides the compiler. Builds of older sources that have not been touched for a week are
    deleted.

Errors
    A missing compiler or a failed compilation raises :class:`core.errors.DependencyError` with
    the compiler's message (the tail of its stderr); an ABI version mismatch between the loaded
    library and its Python wrapper raises the same error, naming the cache to delete.

ctypes releases the GIL for the duration of every call into a loaded library.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import re
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

from core.errors import DependencyError
from core.io.atomic import atomic_output

#: Default compiler flags (kernels are plain C ABI: no torch headers, short builds).
DEFAULT_FLAGS = ("-O3", "-march=native", "-std=gnu++17", "-shared", "-fPIC", "-pthread", "-Wno-psabi")
#: Cached builds of other sources unused for this long are deleted.
STALE_SECONDS = 7 * 86400


def cache_dir(subdir: str) -> Path:
    """``$BRDFUSION_CACHE_DIR/<subdir>`` or ``$XDG_CACHE_HOME/brdfusion/<subdir>`` (default
    ``~/.cache/brdfusion/<subdir>``)."""
    root = os.environ.get("BRDFUSION_CACHE_DIR")
    base = Path(root) if root else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "brdfusion"
    return base / subdir


def cpu_signature() -> str:
    """CPU model name and feature flags from ``/proc/cpuinfo`` (``"unknown"`` elsewhere)."""
    found: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                key = line.split(":", 1)[0].strip()
                if key in ("model name", "flags") and key not in found:
                    found[key] = line.strip()
                if len(found) == 2:
                    break
    except OSError:
        pass
    return " | ".join(found.values()) or "unknown"


_LOCAL_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.MULTILINE)


def local_includes(sources: Sequence[str | os.PathLike]) -> list[Path]:
    """The files the sources include with ``#include "..."``, recursively: each name resolved
    relative to the directory of the file that includes it (as the compiler does without ``-I``),
    in first-seen order, without the sources themselves. Names that do not resolve to a file
    (system headers written with quotes, conditional includes of absent files) are skipped: the
    compiler reports them if they matter. ``<...>`` includes are not followed."""
    seen = {Path(s).resolve() for s in sources}
    out: list[Path] = []
    todo = [Path(s).resolve() for s in sources]
    while todo:
        f = todo.pop(0)
        for name in _LOCAL_INCLUDE.findall(f.read_text(encoding="utf-8", errors="replace")):
            h = (f.parent / name).resolve()
            if h in seen or not h.is_file():
                continue
            seen.add(h)
            out.append(h)
            todo.append(h)
    return out


def build_key(source: str | os.PathLike, *, depends: Sequence[str | os.PathLike] = (),
              flags: Sequence[str] = DEFAULT_FLAGS, compiler_version: str = "") -> str:
    """The cache key of a build: a hash of the source, the files it includes
    (:func:`local_includes`), ``depends``, the flags, the compiler version and the CPU."""
    src = Path(source)
    h = hashlib.sha256()
    for f in [src, *local_includes([src]), *(Path(d) for d in depends)]:
        h.update(f.read_bytes())  # (a source without local includes keeps its key of before)
    h.update(repr((list(flags), compiler_version, cpu_signature())).encode())
    return h.hexdigest()[:16]


def _writable_dir(subdir: str) -> Path:
    out_dir = cache_dir(subdir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        if not os.access(out_dir, os.W_OK):
            raise PermissionError(str(out_dir))
    except OSError:  # read-only home (containers): fall back to the temp directory
        out_dir = Path(tempfile.gettempdir()) / f"brdfusion-{subdir}"
        out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir


def build_shared_library(source: str | os.PathLike, *, name: str, subdir: str, what: str,
                         depends: Sequence[str | os.PathLike] = (),
                         flags: Sequence[str] = DEFAULT_FLAGS) -> Path:
    """Compile ``source`` (once per source/flags/compiler/CPU) and return the cached ``.so``.

    Args:
        source: the C++ file to compile.
        name: file name stem of the cached library (``<name>_<hash>.so``).
        subdir: cache sub-directory.
        what: what the kernels are, for error messages ("the rasterizer kernels").
        depends: further files the build depends on (hashed into the key, not compiled); the
            files ``source`` includes with ``#include "..."`` are found and hashed unlisted.
        flags: compiler flags.

    Raises:
        DependencyError: no compiler, or the compilation failed.
    """
    cxx = os.environ.get("BRDFUSION_CXX", "g++")
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise DependencyError(f"a C++ compiler ({cxx}) is needed to build {what}: {exc}") from exc
    src = Path(source)
    key = build_key(src, depends=depends, flags=flags, compiler_version=version)
    out_dir = _writable_dir(subdir)
    target = out_dir / f"{name}_{key}.so"
    if target.exists():
        return target
    with atomic_output(target, suffix=".so") as tmp:
        proc = subprocess.run([cxx, *flags, "-o", tmp, str(src)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise DependencyError(f"building {what} failed:\n{proc.stderr[-4000:]}")
    cutoff = time.time() - STALE_SECONDS
    for stale in out_dir.glob(f"{name}_*.so"):
        try:
            if stale != target and stale.stat().st_mtime < cutoff:
                stale.unlink()  # safe on Linux even if another process has it loaded
        except OSError:
            pass
    return target


class NativeLibrary:
    """Lazily built and loaded ctypes library (thread-safe, built on first :meth:`get`).

    Args: as :func:`build_shared_library`, plus ``declare(lib)`` (sets argtypes/restypes),
    ``abi_symbol`` (a C function returning the ABI version) and ``abi_version`` (expected).
    """

    def __init__(self, source, *, name: str, subdir: str, what: str, declare: Callable[[ctypes.CDLL], None],
                 abi_symbol: str, abi_version: int, depends: Sequence = (), flags: Sequence[str] = DEFAULT_FLAGS):
        self.source = Path(source)
        self.name, self.subdir, self.what = name, subdir, what
        self.declare, self.abi_symbol, self.abi_version = declare, abi_symbol, abi_version
        self.depends, self.flags = tuple(depends), tuple(flags)
        self._lock = threading.Lock()
        self._lib: ctypes.CDLL | None = None

    def path(self) -> Path:
        """Build if needed; the cached ``.so`` path."""
        return build_shared_library(self.source, name=self.name, subdir=self.subdir, what=self.what,
                                    depends=self.depends, flags=self.flags)

    def get(self) -> ctypes.CDLL:
        """The loaded library (built on first call)."""
        if self._lib is None:
            with self._lock:
                if self._lib is None:
                    loaded = ctypes.CDLL(str(self.path()))
                    self.declare(loaded)
                    fn = getattr(loaded, self.abi_symbol)
                    fn.restype = ctypes.c_int
                    if fn() != self.abi_version:
                        raise DependencyError(f"{self.what}: ABI mismatch (library {fn()}, expected "
                                              f"{self.abi_version}); delete {cache_dir(self.subdir)}")
                    self._lib = loaded
        return self._lib


def default_threads() -> int:
    """Cores this process may run on (``os.sched_getaffinity``), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)
