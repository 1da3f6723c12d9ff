"""The size (width, height in pixels) that a compressed frame's own header gives, read without
decoding it: a decoder allocates what the frame says, whatever the file around it claims."""

from __future__ import annotations

import struct

JPEG_START = b"\xff\xd8"
J2K_START = b"\xff\x4f\xff\x51"  # SOC then SIZ
JP2_SIGNATURE = b"\x00\x00\x00\x0cjP  \r\n\x87\n"
# JPEG's start-of-frame markers (baseline to lossless, arithmetic ones too) and JPEG-LS's.
SOF_MARKERS = frozenset([*range(0xC0, 0xC4), *range(0xC5, 0xC8), *range(0xC9, 0xCC), *range(0xCD, 0xD0), 0xF7])
STANDALONE = frozenset([0x01, *range(0xD0, 0xD9)])  # markers with no length after them


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) px from the header of a JPEG (or JPEG-LS) stream, a JPEG 2000 codestream or
    a JP2 file; None when ``data`` is none of them or its header is cut short."""
    try:
        if data.startswith(JPEG_START):
            return _jpeg_size(data)
        if data.startswith(J2K_START):
            return _j2k_size(data)
        if data.startswith(JP2_SIGNATURE):
            return _jp2_size(data)
    except struct.error:  # a header cut short
        return None
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # a fill byte
            at += 1
            continue
        if marker in STANDALONE:
            at += 2
            continue
        (length,) = struct.unpack_from(">H", data, at + 2)
        if marker in SOF_MARKERS:
            height, width = struct.unpack_from(">HH", data, at + 5)
            return width, height
        if marker == 0xDA:  # the scan begins and no frame header came first
            return None
        at += 2 + length
    return None


def _j2k_size(data: bytes) -> tuple[int, int]:
    """SIZ: Lsiz, Rsiz, then the image's right and bottom edges and its offsets on the grid."""
    x, y, x_offset, y_offset = struct.unpack_from(">IIII", data, 8)
    return x - x_offset, y - y_offset


def _jp2_size(data: bytes) -> tuple[int, int] | None:
    """The size of the codestream in a JP2 file's ``jp2c`` box."""
    at = 0
    while at + 8 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, at)
        header = 8
        if length == 1:  # a 64-bit length follows
            (length,) = struct.unpack_from(">Q", data, at + 8)
            header = 16
        elif length == 0:  # the last box: to the end of the file
            length = len(data) - at
        if kind == b"jp2c":
            codestream = data[at + header : at + length]
            return _j2k_size(codestream) if codestream.startswith(J2K_START) else None
        if length < header:
            return None
        at += length
    return None
