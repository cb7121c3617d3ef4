"""Image sizes read from PNG/JPEG headers, so a decompression bomb is refused before it is decoded."""

from __future__ import annotations

import struct

from .errors import ProtocolError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...); C4, C8, CC are not frames
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def encoded_image_size(data: bytes, image_format: str) -> tuple[int, int]:
    """Returns (width, height) declared by a PNG or JPEG header; ProtocolError(bad_request) if unreadable."""
    if image_format == "png":
        if len(data) < 24 or not data.startswith(PNG_MAGIC) or data[12:16] != b"IHDR":
            raise ProtocolError("bad_request", "image is not a PNG (bad signature or IHDR)")
        width, height = struct.unpack(">II", data[16:24])
        return width, height
    if image_format == "jpeg":
        return _jpeg_size(data)
    raise ProtocolError("bad_request", f"unknown encoded image format {image_format!r}")


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """Returns (width, height) of the first JPEG frame header, walking the marker segments."""
    if not data.startswith(JPEG_MAGIC):
        raise ProtocolError("bad_request", "image is not a JPEG (no SOI marker)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            break
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _SOF:
            if i + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        if length < 2:
            break
        i += 2 + length
    raise ProtocolError("bad_request", "image is not a readable JPEG (no frame header)")
