"""Uploaded archives: zip-slip, symlinks, bombs and corrupt files are refused, nothing escapes."""

from __future__ import annotations

import io
import tarfile
import zipfile

import pytest

from core.bundle import ArchiveLimits, pack_bundle, unpack_bundle
from core.errors import BundleError


def _zip(path, members: dict[str, bytes], symlink: str | None = None):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
        if symlink:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = (0o120777 << 16)
            zf.writestr(info, "/etc/passwd")
    return path


def test_zip_slip_refused(tmp_path):
    arc = _zip(tmp_path / "evil.zip", {"bundle.json": b"{}", "../../escaped.txt": b"x"})
    with pytest.raises(BundleError, match="unsafe path"):
        unpack_bundle(arc, tmp_path / "out")
    assert not (tmp_path / "escaped.txt").exists() and not (tmp_path / "out").exists()


def test_absolute_path_refused(tmp_path):
    arc = tmp_path / "abs.tar.gz"
    with tarfile.open(arc, "w:gz") as tf:
        data = b"x"
        info = tarfile.TarInfo("/tmp/abs_escape.txt")
        info.size = len(data)
        tf.addfile(info, io.BytesIO(data))
    with pytest.raises(BundleError, match="unsafe path"):
        unpack_bundle(arc, tmp_path / "out")


def test_zip_symlink_refused(tmp_path):
    arc = _zip(tmp_path / "link.zip", {"bundle.json": b"{}"}, symlink="images/link.png")
    with pytest.raises(BundleError, match="symlinks"):
        unpack_bundle(arc, tmp_path / "out")


def test_tar_symlink_refused(tmp_path):
    arc = tmp_path / "link.tar.gz"
    with tarfile.open(arc, "w:gz") as tf:
        info = tarfile.TarInfo("images/x.png")
        info.type = tarfile.SYMTYPE
        info.linkname = "/etc/passwd"
        tf.addfile(info)
    with pytest.raises(BundleError, match="symlinks"):
        unpack_bundle(arc, tmp_path / "out")


def test_zip_bomb_refused(tmp_path):
    # 50 MB of zeros compresses to ~50 KB; the cap is set below it
    arc = _zip(tmp_path / "bomb.zip", {"bundle.json": b"{}", "big.bin": b"\0" * (50 * 1024 * 1024)})
    with pytest.raises(BundleError, match="uncompressed bytes"):
        unpack_bundle(arc, tmp_path / "out", ArchiveLimits(max_total_bytes=10 * 1024 * 1024))
    assert not (tmp_path / "out").exists()


def test_too_many_entries_refused(tmp_path):
    arc = _zip(tmp_path / "many.zip", {f"f{i}.txt": b"x" for i in range(50)})
    with pytest.raises(BundleError, match="entries"):
        unpack_bundle(arc, tmp_path / "out", ArchiveLimits(max_entries=10))


def test_corrupt_and_foreign_archives(tmp_path):
    p = tmp_path / "x.zip"
    p.write_bytes(b"PK\x03\x04 this is not really a zip")
    with pytest.raises(BundleError, match="corrupt zip"):
        unpack_bundle(p, tmp_path / "out")
    q = tmp_path / "x.rar"
    q.write_bytes(b"Rar!\x1a\x07\x00")
    with pytest.raises(BundleError, match="not a .zip or .tar.gz"):
        unpack_bundle(q, tmp_path / "out2")


def test_archive_without_manifest(tmp_path):
    arc = _zip(tmp_path / "nomanifest.zip", {"images/a.png": b"x"})
    with pytest.raises(BundleError, match="no bundle.json"):
        unpack_bundle(arc, tmp_path / "out")


def test_single_top_folder_is_accepted(small_bundle, tmp_path):
    arc = tmp_path / "nested.tar.gz"
    with tarfile.open(arc, "w:gz") as tf:
        tf.add(small_bundle, arcname="myscene")
    root = unpack_bundle(arc, tmp_path / "out")
    assert root.name == "myscene" and (root / "bundle.json").is_file()


def test_pack_refuses_non_bundle(tmp_path):
    with pytest.raises(BundleError, match="no bundle.json"):
        pack_bundle(tmp_path, tmp_path / "x.zip")
