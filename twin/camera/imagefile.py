"""A camera frame read from a file with its size checked before anything decodes it.

A PNG or JPEG states its size in its header (PNG: the IHDR chunk; JPEG: the frame header, an SOF
marker), and a decoder allocates that size before it reads the compressed data: a 629-byte JPEG
declaring 32000×32000 px drove ``xneck camera detect`` to 3 GB and an OpenCV traceback (audit of
2026-11-26). :func:`image_size` reads the header in plain Python, and :func:`read_frame` refuses
a size other than the one the caller expects (the calibration's: the detector refuses any other
anyway) before OpenCV sees a byte.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bridge.imageheader import ImageFileError, image_size

MAX_FILE_BYTES = 64 << 20  # an uncompressed 8192×8192 RGB PNG is 192 MiB; a camera frame (1280×720) is a few MB at most


def read_frame(path: str | Path, width: int, height: int) -> np.ndarray:
    """The H×W×3 BGR image of a PNG or JPEG file that is ``width``×``height`` px, else
    :class:`ImageFileError` (the header's size is checked before decoding; OpenCV's own errors
    become one too)."""
    import cv2

    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ImageFileError(f"{size} bytes, more than the {MAX_FILE_BYTES >> 20} MiB a camera frame can take")
        data = path.read_bytes()
    except OSError as exc:
        raise ImageFileError(f"cannot read it ({exc.strerror or exc})") from None
    kind, w, h = image_size(data)
    if (w, h) != (width, height):
        raise ImageFileError(f"the {kind.upper()} image is {w}×{h} px (its header says), the calibration's "
                             f"{width}×{height}: refused before decoding")
    try:
        # the pixels as stored: an EXIF orientation would turn the image away from the size its header
        # says and the calibration's (user audit of session 45: 'frame is 720×1280')
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as exc:
        raise ImageFileError(f"OpenCV cannot decode it ({str(exc).strip().splitlines()[-1]})") from None
    if image is None:
        raise ImageFileError(f"not a readable image (a damaged {kind.upper()})")
    return image


__all__ = ["MAX_FILE_BYTES", "ImageFileError", "image_size", "read_frame"]
