"""H.264 MP4 video via PyAV (libx264, yuv420p), for turntables and relighting sequences."""

from __future__ import annotations

import os
from collections.abc import Iterable
from fractions import Fraction

import numpy as np

from core.errors import ConfigError, FormatError, ShapeError
from core.io.atomic import atomic_output


def _check_frame(frame: np.ndarray, index: int, size: tuple[int, int] | None) -> np.ndarray:
    a = np.asarray(frame)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ShapeError(f"frames[{index}]: expected [H, W, 3], got shape {a.shape}")
    if a.dtype != np.uint8:
        raise ShapeError(f"frames[{index}]: dtype {a.dtype}, expected uint8")
    if size is not None and a.shape[:2] != size:
        raise ShapeError(f"frames[{index}]: size {a.shape[:2]} differs from frame 0's {size}")
    return a


def _pad_even(a: np.ndarray) -> np.ndarray:
    """Pad [H, W, 3] by edge replication to even H and W (yuv420p halves both)."""
    ph, pw = a.shape[0] % 2, a.shape[1] % 2
    if ph or pw:
        a = np.pad(a, ((0, ph), (0, pw), (0, 0)), mode="edge")
    return np.ascontiguousarray(a)


def write_mp4(
    path: str | os.PathLike,
    frames: Iterable[np.ndarray] | np.ndarray,
    fps: float = 10,
    crf: int = 18,
) -> None:
    """Encode frames as an H.264 (libx264, yuv420p) MP4 at ``path``, atomically.

    Args:
        frames: an iterable of [H, W, 3] uint8 RGB frames (or a [T, H, W, 3] array), all the
            same size. Odd H or W are padded by one replicated edge row/column to even, so the
            video is then (H + H % 2) x (W + W % 2).
        fps: frames per second, > 0 (fractions like 30000/1001 are kept exactly up to 1/1001).
        crf: x264 constant rate factor, int in [0, 51] (0 lossless luma, 18 visually lossless).

    Raises:
        ConfigError: no frames, or fps/crf out of range.
        ShapeError: a frame is not [H, W, 3] uint8 or differs in size from frame 0.
        FormatError: the encoder fails.
    """
    import av

    if isinstance(fps, bool) or not isinstance(fps, (int, float, Fraction, np.integer, np.floating)) \
            or not np.isfinite(float(fps)) or fps <= 0:
        raise ConfigError(f"fps: must be a positive finite number, got {fps!r}")
    if isinstance(crf, bool) or not isinstance(crf, (int, np.integer)) or not 0 <= crf <= 51:
        raise ConfigError(f"crf: must be an int in [0, 51], got {crf!r}")
    rate = Fraction(float(fps) if isinstance(fps, np.floating) else fps)
    rate = rate.limit_denominator(1001)
    target = os.fspath(path)
    iterator = iter(frames)
    try:
        first = next(iterator)
    except StopIteration:
        raise ConfigError("frames: at least one frame is needed") from None
    first = _check_frame(first, 0, None)
    size = first.shape[:2]
    height, width = size[0] + size[0] % 2, size[1] + size[1] % 2

    with atomic_output(target, suffix=".mp4") as tmp:
        try:
            container = av.open(tmp, mode="w", format="mp4")
        except Exception as exc:
            raise FormatError(f"{target}: cannot create MP4 ({exc})") from exc
        try:
            stream = container.add_stream("libx264", rate=rate)
            stream.width, stream.height = width, height
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": str(int(crf))}
            index = 0
            frame = first
            while True:
                vf = av.VideoFrame.from_ndarray(_pad_even(frame), format="rgb24")
                for packet in stream.encode(vf):
                    container.mux(packet)
                index += 1
                try:
                    frame = _check_frame(next(iterator), index, size)
                except StopIteration:
                    break
            for packet in stream.encode(None):  # flush delayed frames
                container.mux(packet)
        except (ShapeError, ConfigError):
            raise
        except Exception as exc:
            raise FormatError(f"{target}: H.264 encoding failed ({exc})") from exc
        finally:
            container.close()


def read_mp4_frames(path: str | os.PathLike) -> np.ndarray:
    """Decode every video frame of ``path`` as [T, H, W, 3] uint8 RGB (meant for tests).

    Raises:
        FormatError: (naming the file) not a decodable video or no video frames.
        FileNotFoundError: ``path`` does not exist.
    """
    import av

    p = os.fspath(path)
    if not os.path.exists(p):
        raise FileNotFoundError(p)
    try:
        with av.open(p, mode="r") as container:
            if not container.streams.video:
                raise FormatError(f"{p}: no video stream")
            frames = [f.to_ndarray(format="rgb24")
                      for f in container.decode(container.streams.video[0])]
    except FormatError:
        raise
    except Exception as exc:
        raise FormatError(f"{p}: cannot decode video ({exc})") from exc
    if not frames:
        raise FormatError(f"{p}: video has no frames")
    return np.stack(frames)
