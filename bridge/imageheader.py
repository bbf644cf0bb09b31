"""The size a PNG or JPEG states in its header, read in plain Python before anything decodes it.

A decoder allocates the size a header declares before it reads the compressed data: a 629-byte
JPEG declaring 32000×32000 px drove ``xneck camera detect`` to 3 GB (audit of 2026-11-26). Here,
in the lowest layer, so that the bus contract checks a frame's JPEG against its ``width`` and
``height`` (:func:`bridge.bus.check_camera_frame`) and a file reader checks it against a
calibration (:mod:`twin.camera.imagefile`).
"""

from __future__ import annotations

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Frame headers (SOF0-SOF15) carry the size; C4 (DHT), C8 (reserved) and CC (DAC) share the range.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7, SOI.
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8), 0xD8})


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


__all__ = ["PNG_SIGNATURE", "ImageFileError", "image_size"]
