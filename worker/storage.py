"""Artifact storage behind one interface: a local directory by default, any fsspec filesystem
(S3-compatible via s3fs, GCS, memory for tests) by configuration.

Keys are relative POSIX paths (``jobs/<id>/frames/f000.exr``, ``scenes/<id>/bundle.zip``). A key
that is absolute or contains ``..`` is refused, so a stored name can never escape the store.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import fsspec

from core.io.atomic import atomic_output


class StorageError(Exception):
    """A storage key is invalid or the store failed; the message names the key."""


def check_key(key: str) -> str:
    p = PurePosixPath(key)
    if not key or p.is_absolute() or any(part in ("..", "") for part in key.split("/")) or "\\" in key:
        raise StorageError(f"invalid storage key {key!r}: must be a relative path without '..'")
    return key


def _in_progress(path: str) -> bool:
    """A file :meth:`ArtifactStore.put_file` is still writing (an ``atomic_output`` temporary,
    ``.<name>.<random>.tmp``, or a ``.part`` file of the writer before it)."""
    name = path.rsplit("/", 1)[-1]
    return (name.startswith(".") and name.endswith(".tmp")) or name.endswith(".part")


class ArtifactStore:
    """``url``: ``file:///var/brdf/artifacts``, ``s3://bucket/prefix``, ``memory://name``, ..."""

    def __init__(self, url: str, options: dict | None = None):
        self.url = url.rstrip("/")
        try:
            self.fs, self.root = fsspec.core.url_to_fs(self.url, **(options or {}))
        except (ImportError, ValueError) as e:
            raise StorageError(f"artifact store {url!r}: {e}") from None
        self.local = "file" in (self.fs.protocol if isinstance(self.fs.protocol, tuple) else (self.fs.protocol,))
        if self.local:
            os.makedirs(self.root, exist_ok=True)

    def _path(self, key: str) -> str:
        return f"{self.root.rstrip('/')}/{check_key(key)}"

    def put_file(self, local_path: str | os.PathLike, key: str) -> int:
        """Copy a local file to ``key`` (atomically on a local store); returns its size."""
        dst = self._path(key)
        size = os.path.getsize(local_path)
        if self.local:
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            with atomic_output(dst) as tmp:
                shutil.copyfile(local_path, tmp)
        else:
            self.fs.put_file(os.fspath(local_path), dst)
        return size

    def get_file(self, key: str, local_path: str | os.PathLike) -> None:
        src = self._path(key)
        if not self.fs.exists(src):
            raise StorageError(f"no such artifact: {key}")
        Path(local_path).parent.mkdir(parents=True, exist_ok=True)
        self.fs.get_file(src, os.fspath(local_path))

    def open(self, key: str) -> BinaryIO:
        """A seekable binary file object for reading."""
        try:
            return self.fs.open(self._path(key), "rb")
        except FileNotFoundError:
            raise StorageError(f"no such artifact: {key}") from None

    def size(self, key: str) -> int:
        try:
            return int(self.fs.size(self._path(key)))
        except FileNotFoundError:
            raise StorageError(f"no such artifact: {key}") from None

    def exists(self, key: str) -> bool:
        return bool(self.fs.exists(self._path(key)))

    def delete_prefix(self, prefix: str) -> None:
        """Remove every object under ``prefix`` (a folder key); missing is fine."""
        p = self._path(prefix)
        if self.fs.exists(p):
            self.fs.rm(p, recursive=True)

    def list(self, prefix: str) -> list[str]:
        p = self._path(prefix)
        if not self.fs.exists(p):
            return []
        base = self.root.rstrip("/") + "/"
        return sorted(f[len(base):] if f.startswith(base) else f
                      for f in self.fs.find(p) if not _in_progress(f))

    def ping(self) -> None:
        """Raise if the store cannot be listed."""
        self.fs.ls(self.root) if self.fs.exists(self.root) else self.fs.makedirs(self.root, exist_ok=True)


_stores: dict[tuple[str, str], ArtifactStore] = {}


def get_store(url: str, options: dict | None = None) -> ArtifactStore:
    k = (url, repr(sorted((options or {}).items())))
    if k not in _stores:
        _stores[k] = ArtifactStore(url, options)
    return _stores[k]
