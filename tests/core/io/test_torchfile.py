"""core.io.torchfile: the one reader of versioned torch files names the file and the field."""

from __future__ import annotations

import pytest
import torch

from core.errors import FormatError
from core.io.torchfile import read_torch_file


def test_reads_a_good_file_and_names_each_fault(tmp_path):
    good = tmp_path / "g.pt"
    torch.save({"format": "x.thing", "version": 2, "a": torch.ones(2)}, good)
    assert torch.equal(read_torch_file(good, "x.thing", (1, 2), "thing")["a"], torch.ones(2))
    with pytest.raises(FormatError, match=r"\[version\]: unsupported version 2"):
        read_torch_file(good, "x.thing", (1,), "thing")
    with pytest.raises(FormatError, match=r"g.pt \[format\]: expected 'y'"):
        read_torch_file(good, "y", (2,), "thing")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a pickle")
    with pytest.raises(FormatError, match="asset junk.pt: not a readable thing"):
        read_torch_file(junk, "x.thing", (2,), "thing", label="asset junk.pt")
    with pytest.raises(FormatError, match="not a readable thing"):
        read_torch_file(tmp_path / "missing.pt", "x.thing", (2,), "thing")
    with pytest.raises(FileNotFoundError):
        read_torch_file(tmp_path / "missing.pt", "x.thing", (2,), "thing", pass_missing=True)
    torch.save({"format": "x.thing", "version": True}, good)  # a bool is not a version
    with pytest.raises(FormatError, match="unsupported version True"):
        read_torch_file(good, "x.thing", (1,), "thing")
