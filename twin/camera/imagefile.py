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

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Frame headers (SOF0-SOF15) carry the size; C4 (DHT), C8 (reserved) and CC (DAC) share the range.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7, SOI.
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8), 0xD8})
MAX_FILE_BYTES = 64 << 20  # an uncompressed 8192×8192 RGB PNG is 192 MiB; a camera frame (1280×720) is a few MB at most


class ImageFileError(ValueError):
    """The file is no image the detector can take; the message says why."""


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of a PNG or JPEG from its header alone, nothing decoded."""
    if data[:8] == PNG_SIGNATURE:
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ImageFileError("a PNG without its IHDR header")
        width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        if width == 0 or height == 0:
            raise ImageFileError(f"a PNG of {width}×{height} px")
        return "png", width, height
    if data[:3] == b"\xff\xd8\xff":
        return ("jpeg", *_jpeg_size(data))
    raise ImageFileError("not a readable image (neither a PNG nor a JPEG)")


def _jpeg_size(data: bytes) -> tuple[int, int]:
    i, n = 2, len(data)
    while i < n:
        if data[i] != 0xFF:
            raise ImageFileError(f"a damaged JPEG (no marker at byte {i})")
        while i < n and data[i] == 0xFF:  # fill bytes may pad any marker
            i += 1
        if i >= n:
            break
        marker = data[i]
        i += 1
        if marker in _JPEG_STANDALONE:
            continue
        if marker in (0xD9, 0xDA):  # end of image, or the first scan: the frame header should have come before
            break
        if i + 2 > n:
            break
        length = int.from_bytes(data[i:i + 2], "big")
        if length < 2:
            raise ImageFileError(f"a damaged JPEG (segment length {length} at byte {i})")
        if marker in _JPEG_SOF:
            if length < 8 or i + 7 > n:
                raise ImageFileError("a damaged JPEG (truncated frame header)")
            height, width = int.from_bytes(data[i + 3:i + 5], "big"), int.from_bytes(data[i + 5:i + 7], "big")
            if width == 0 or height == 0:  # height 0: given later by a DNL marker, which OpenCV does not take either
                raise ImageFileError(f"a JPEG of {width}×{height} px")
            return width, height
        i += length
    raise ImageFileError("a JPEG with no frame header (SOF) before its image data")


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
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as exc:
        raise ImageFileError(f"OpenCV cannot decode it ({str(exc).strip().splitlines()[-1]})") from None
    if image is None:
        raise ImageFileError(f"not a readable image (a damaged {kind.upper()})")
    return image
