"""File input/output for ``core``: multi-layer EXR, Radiance HDR, environment maps, 8-bit
images and masks, and H.264 video. Every reader validates sizes before allocating and raises
:class:`core.errors.FormatError` naming the file for malformed input; every writer is atomic
(temporary file in the same directory, then :func:`os.replace`).
"""

from core.io.envmap_file import read_envmap, write_envmap
from core.io.exr import ExrHeader, exr_header, read_exr, write_exr
from core.io.hdr import read_hdr, write_hdr
from core.io.images import image_size, read_image, read_mask, write_png
from core.io.video import read_mp4_frames, write_mp4

__all__ = [
    "ExrHeader",
    "exr_header",
    "image_size",
    "read_envmap",
    "read_exr",
    "read_hdr",
    "read_image",
    "read_mask",
    "read_mp4_frames",
    "write_envmap",
    "write_exr",
    "write_hdr",
    "write_mp4",
    "write_png",
]
