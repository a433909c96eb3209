"""Read a versioned ``torch.save`` file (``{"format": name, "version": v, ...}``) with errors that
name the file and the field: the one reader of the project's torch formats (Gaussians, scene
graphs, object assets)."""

from __future__ import annotations

from pathlib import Path
from typing import Container

import torch

from core.errors import FormatError


def read_torch_file(path: str | Path, fmt: str, versions: Container[int], noun: str, *, label: str | None = None,
                    pass_missing: bool = False) -> dict:
    """The payload dict of ``path`` (``torch.load`` with ``weights_only``).

    Raises FormatError ``"<label>: not a readable <noun> (...)"`` for an unreadable file,
    ``"<label> [format]: expected <fmt>"`` and ``"<label> [version]: unsupported version v"``
    (``label`` defaults to the path). A missing file raises FileNotFoundError with
    ``pass_missing``, else the unreadable-file FormatError.
    """
    p = Path(path)
    label = str(p) if label is None else label
    try:
        d = torch.load(p, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        if pass_missing:
            raise
        raise FormatError(f"{label}: not a readable {noun} (no such file)") from None
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a bad file
        raise FormatError(f"{label}: not a readable {noun} ({exc})") from exc
    if not isinstance(d, dict) or d.get("format") != fmt:
        raise FormatError(f"{label} [format]: expected {fmt!r}")
    v = d.get("version")
    if isinstance(v, bool) or not isinstance(v, int) or v not in versions:
        raise FormatError(f"{label} [version]: unsupported version {v!r}")
    return d


__all__ = ["read_torch_file"]
