"""Pack a bundle directory as .zip / .tar.gz, and unpack an uploaded archive safely.

Unpacking refuses, before writing anything outside a fresh staging directory: absolute paths and
``..`` components (zip-slip), symlinks, hard links and device files, more than ``max_entries``
members, more than ``max_total_bytes`` uncompressed in total (zip bombs: checked against the
declared sizes first and against the bytes actually written while extracting).
"""

from __future__ import annotations

import os
import shutil
import stat
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from core.bundle.schema import MANIFEST_NAME
from core.errors import BundleError, ConfigError
from core.io.atomic import atomic_output


@dataclass(frozen=True)
class ArchiveLimits:
    """Caps applied when unpacking an uploaded bundle archive."""

    max_entries: int = 100_000
    """Most members (files and directories) an archive may hold."""
    max_total_bytes: int = 8 * 1024**3
    """Most uncompressed bytes in total (8 GiB)."""
    max_ratio: float = 200.0
    """Largest uncompressed/compressed ratio accepted for the whole archive (zip bomb guard)."""


def _safe_member(name: str) -> PurePosixPath:
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or any(part == ".." for part in p.parts) or (p.parts and ":" in p.parts[0]):
        raise BundleError(f"unsafe path in archive: {name!r} (absolute or leaves the bundle)", name)
    return p


def archive_kind(path: str | Path) -> str:
    """'zip' or 'tar.gz' from the file's magic bytes; BundleError otherwise."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head[:4] == b"PK\x03\x04" or head[:4] == b"PK\x05\x06":
        return "zip"
    if head[:2] == b"\x1f\x8b":
        return "tar.gz"
    raise BundleError("not a .zip or .tar.gz archive", str(path))


def unpack_bundle(archive: str | Path, dest: str | Path, limits: ArchiveLimits = ArchiveLimits()) -> Path:
    """Extract ``archive`` into the new directory ``dest`` (must not exist) and return the bundle
    root inside it (``dest`` itself, or its single top-level folder holding bundle.json)."""
    archive = Path(archive)
    dest = Path(dest)
    if dest.exists():
        raise ConfigError(f"dest: {dest} already exists")
    kind = archive_kind(archive)
    compressed = max(archive.stat().st_size, 1)
    stage = Path(tempfile.mkdtemp(prefix=".unpack-", dir=dest.parent if dest.parent.exists() else None))
    try:
        if kind == "zip":
            _unpack_zip(archive, stage, limits, compressed)
        else:
            _unpack_tar(archive, stage, limits, compressed)
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage, dest)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    if (dest / MANIFEST_NAME).is_file():
        return dest
    subdirs = [p for p in dest.iterdir() if p.is_dir()]
    if len(subdirs) == 1 and (subdirs[0] / MANIFEST_NAME).is_file():
        return subdirs[0]
    raise BundleError(f"archive holds no {MANIFEST_NAME} at its root or in a single top folder", MANIFEST_NAME)


def _copy_limited(src, dst_path: Path, budget: list[int], name: str) -> None:
    with open(dst_path, "wb") as out:
        while True:
            chunk = src.read(1 << 20)
            if not chunk:
                break
            budget[0] -= len(chunk)
            if budget[0] < 0:
                raise BundleError("archive expands beyond the uncompressed size limit (zip bomb?)", name)
            out.write(chunk)


def _check_totals(n: int, total: int, limits: ArchiveLimits, compressed: int, where: str) -> None:
    if n > limits.max_entries:
        raise BundleError(f"archive has {n} entries, more than the limit {limits.max_entries}", where)
    if total > limits.max_total_bytes:
        raise BundleError(f"archive declares {total} uncompressed bytes, more than the limit "
                          f"{limits.max_total_bytes}", where)
    if total / compressed > limits.max_ratio and total > 64 * 1024**2:
        raise BundleError(f"compression ratio {total / compressed:.0f} exceeds {limits.max_ratio:.0f} "
                          "(zip bomb?)", where)


def _unpack_zip(archive: Path, stage: Path, limits: ArchiveLimits, compressed: int) -> None:
    try:
        zf = zipfile.ZipFile(archive)
    except zipfile.BadZipFile as e:
        raise BundleError(f"corrupt zip: {e}", str(archive)) from None
    with zf:
        infos = zf.infolist()
        _check_totals(len(infos), sum(i.file_size for i in infos), limits, compressed, str(archive))
        budget = [limits.max_total_bytes]
        for info in infos:
            rel = _safe_member(info.filename)
            mode = (info.external_attr >> 16) & 0xFFFF
            if stat.S_ISLNK(mode):
                raise BundleError("symlinks are not allowed in a bundle archive", info.filename)
            target = stage.joinpath(*rel.parts)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src:
                    _copy_limited(src, target, budget, info.filename)
            except (zipfile.BadZipFile, OSError, EOFError) as e:
                raise BundleError(f"corrupt member: {e}", info.filename) from None


def _unpack_tar(archive: Path, stage: Path, limits: ArchiveLimits, compressed: int) -> None:
    try:
        tf = tarfile.open(archive, "r:gz")
    except (tarfile.TarError, OSError, EOFError) as e:
        raise BundleError(f"corrupt tar.gz: {e}", str(archive)) from None
    with tf:
        try:
            members = tf.getmembers()
        except (tarfile.TarError, OSError, EOFError) as e:
            raise BundleError(f"corrupt tar.gz: {e}", str(archive)) from None
        _check_totals(len(members), sum(m.size for m in members if m.isfile()), limits, compressed, str(archive))
        budget = [limits.max_total_bytes]
        for m in members:
            rel = _safe_member(m.name)
            if m.issym() or m.islnk():
                raise BundleError("symlinks and hard links are not allowed in a bundle archive", m.name)
            if not (m.isfile() or m.isdir()):
                raise BundleError("only regular files and directories are allowed", m.name)
            target = stage.joinpath(*rel.parts)
            if m.isdir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            src = tf.extractfile(m)
            if src is None:
                raise BundleError("unreadable member", m.name)
            try:
                _copy_limited(src, target, budget, m.name)
            except (tarfile.TarError, OSError, EOFError) as e:
                raise BundleError(f"corrupt member: {e}", m.name) from None


def pack_bundle(root: str | Path, out: str | Path) -> Path:
    """Pack bundle directory ``root`` into ``out`` (.zip or .tar.gz by suffix); returns ``out``."""
    root = Path(root)
    out = Path(out)
    if not (root / MANIFEST_NAME).is_file():
        raise BundleError(f"no {MANIFEST_NAME} in {root}", str(root))
    is_zip = out.name.endswith(".zip")
    if not is_zip and not out.name.endswith((".tar.gz", ".tgz")):
        raise ConfigError(f"out: expected a .zip or .tar.gz path, got {out}")
    files = sorted(p for p in root.rglob("*") if p.is_file())
    with atomic_output(out) as tmp:
        if is_zip:
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
                for p in files:
                    zf.write(p, p.relative_to(root).as_posix())
        else:
            with tarfile.open(tmp, "w:gz") as tf:
                for p in files:
                    tf.add(p, p.relative_to(root).as_posix(), recursive=False)
    return out
