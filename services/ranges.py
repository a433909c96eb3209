"""Serving stored files with HTTP Range support (one byte range per request, RFC 9110)."""

from __future__ import annotations

import hashlib
import re
from typing import Iterator

from fastapi import HTTPException, Request
from fastapi.responses import Response, StreamingResponse

from worker.storage import ArtifactStore

CHUNK = 256 * 1024
_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """(first, last) inclusive, or None for the whole file. A malformed or multi-range header is
    ignored (the whole file is sent, as RFC 9110 allows); an unsatisfiable one raises 416."""
    if not header:
        return None
    m = _RANGE.match(header.strip())
    if not m:
        return None
    a, b = m.groups()
    if a == "" and b == "":
        return None
    if a == "":
        n = int(b)
        if n == 0:
            raise HTTPException(416, f"unsatisfiable range {header!r} for {size} bytes",
                                headers={"Content-Range": f"bytes */{size}"})
        return max(size - n, 0), size - 1
    first = int(a)
    last = int(b) if b else size - 1
    if first >= size or last < first:
        raise HTTPException(416, f"unsatisfiable range {header!r} for {size} bytes",
                            headers={"Content-Range": f"bytes */{size}"})
    return first, min(last, size - 1)


def _iter(store: ArtifactStore, key: str, first: int, length: int) -> Iterator[bytes]:
    with store.open(key) as fh:
        fh.seek(first)
        left = length
        while left > 0:
            chunk = fh.read(min(CHUNK, left))
            if not chunk:
                break
            left -= len(chunk)
            yield chunk


def file_response(request: Request, store: ArtifactStore, key: str, size: int, content_type: str,
                  filename: str) -> Response:
    etag = '"' + hashlib.sha256(f"{key}:{size}".encode()).hexdigest()[:32] + '"'
    headers = {"Accept-Ranges": "bytes", "ETag": etag,
               "Content-Disposition": f'inline; filename="{filename.replace(chr(34), "")}"',
               "Cache-Control": "private, max-age=3600"}
    rng = parse_range(request.headers.get("range"), size)
    if_range = request.headers.get("if-range")
    if rng is not None and if_range and if_range != etag:
        rng = None
    first, last = rng if rng is not None else (0, size - 1)
    length = max(last - first + 1, 0)
    headers["Content-Length"] = str(length)
    status = 200
    if rng is not None:
        status = 206
        headers["Content-Range"] = f"bytes {first}-{last}/{size}"
    if request.method == "HEAD" or length == 0:
        return Response(status_code=status, headers=headers, media_type=content_type)
    return StreamingResponse(_iter(store, key, first, length), status_code=status, headers=headers,
                             media_type=content_type)
