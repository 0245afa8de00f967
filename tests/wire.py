"""A minimal, schema-free protobuf wire decoder used to cross-check our reader's counts."""

from __future__ import annotations

import struct
from collections import defaultdict


def varint(buf: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7


def fields(buf: bytes) -> dict[int, list]:
    """field number -> list of raw values (int for varint/fixed, bytes for length-delimited)."""
    out: dict[int, list] = defaultdict(list)
    pos = 0
    while pos < len(buf):
        key, pos = varint(buf, pos)
        num, wire = key >> 3, key & 7
        if wire == 0:
            val, pos = varint(buf, pos)
        elif wire == 1:
            val, pos = struct.unpack_from("<Q", buf, pos)[0], pos + 8
        elif wire == 5:
            val, pos = struct.unpack_from("<I", buf, pos)[0], pos + 4
        elif wire == 2:
            n, pos = varint(buf, pos)
            val, pos = buf[pos:pos + n], pos + n
        else:
            raise ValueError(f"wire type {wire}")
        out[num].append(val)
    return out


def field_bytes(num: int, payload: bytes) -> bytes:
    """Encode one length-delimited field."""
    return encode_varint(num << 3 | 2) + encode_varint(len(payload)) + payload


def encode_varint(v: int) -> bytes:
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        out.append(b | (0x80 if v else 0))
        if not v:
            return bytes(out)
