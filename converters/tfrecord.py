"""TFRecord framing (no TensorFlow): reading and writing length-prefixed, CRC-checked records.

Each record is ``u64 length | u32 masked_crc32c(length) | data | u32 masked_crc32c(data)``,
little-endian. Files may be gzip-compressed (detected from the magic bytes). Reading is lazy:
one record is held in memory at a time.
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from os import PathLike
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator

import google_crc32c

from converters.files import open_regular
from magail_sumo.errors import SceneFormatError

_MASK_DELTA = 0xA282EAD8
_GZIP_MAGIC = b"\x1f\x8b"
#: Upper bound on one record's length: guards against reading garbage lengths (4 GiB).
MAX_RECORD_BYTES = 1 << 32
#: A gzip-compressed file's records may each decompress to at most
#: ``max(GZIP_MIN_RECORD_BUDGET, GZIP_RATIO_BUDGET x compressed file size)`` bytes. Real WOMD
#: shards compress about 3-5x; this refuses a small "gzip bomb" whose one record claims (and
#: decompresses to) gigabytes, while any real shard stays far inside it.
GZIP_MIN_RECORD_BUDGET = 256 << 20
GZIP_RATIO_BUDGET = 64
#: record bodies are read in pieces of this size, so that memory follows the bytes actually
#: present, never a length claimed by the file
_CHUNK = 4 << 20


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC32C of ``data``."""
    crc = google_crc32c.value(data)
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + _MASK_DELTA) & 0xFFFFFFFF


def is_gzip(path: str | PathLike) -> bool:
    with open_regular(path) as fh:
        return fh.read(2) == _GZIP_MAGIC


def _read(fh: BinaryIO, n: int) -> bytes:
    """Up to ``n`` bytes; a long read is done in pieces so nothing is allocated ahead of data."""
    if n <= _CHUNK:
        return fh.read(n)
    parts = []
    while n > 0:
        part = fh.read(min(n, _CHUNK))
        if not part:
            break
        parts.append(part)
        n -= len(part)
    return b"".join(parts)


def iter_records(path: str | PathLike) -> Iterator[tuple[int, bytes | SceneFormatError]]:
    """Yield ``(index, data)`` for each record of a TFRecord file, lazily.

    A bad data CRC yields ``(index, SceneFormatError)`` and reading continues with the next
    record (the length was verified). A framing error (bad length CRC, truncation, a length
    larger than the rest of an uncompressed file or than the decompression budget of a gzip
    file) yields a fatal ``SceneFormatError`` and stops: nothing after it can be located.
    Errors about the file itself (missing, a directory or other non-regular file, empty,
    unreadable) are raised. Memory is bounded by one record of the bytes actually present.
    """
    p = Path(path)
    with open_regular(p, buffering=1 << 20, expected="a TFRecord file") as raw:
        size = os.fstat(raw.fileno()).st_size
        if size == 0:
            raise SceneFormatError(p, None, "empty file (no records)")
        compressed = raw.read(2) == _GZIP_MAGIC
        raw.seek(0)
        fh: BinaryIO = gzip.GzipFile(fileobj=raw, mode="rb") if compressed else raw  # type: ignore
        yield from _records(p, fh, size, compressed)


def _records(p: Path, fh: BinaryIO, size: int, compressed: bool
             ) -> Iterator[tuple[int, bytes | SceneFormatError]]:
    limit = (max(GZIP_MIN_RECORD_BUDGET, GZIP_RATIO_BUDGET * size) if compressed
             else MAX_RECORD_BYTES)
    index = 0
    offset = 0  # bytes consumed (of the decompressed stream for gzip)
    while True:
        try:
            header = fh.read(12)
        except (OSError, EOFError, zlib.error) as exc:  # corrupt gzip stream
            yield index, SceneFormatError(p, index, f"unreadable compressed data ({exc})", True)
            return
        if not header:
            return
        if len(header) < 12:
            yield index, SceneFormatError(
                p, index, f"truncated record header ({len(header)} of 12 bytes)", True)
            return
        offset += 12
        length, length_crc = struct.unpack("<QI", header)
        if masked_crc32c(header[:8]) != length_crc:
            what = "not a TFRecord file" if index == 0 else "corrupt record framing"
            yield index, SceneFormatError(
                p, index, f"{what}: length CRC mismatch (length field {length})", True)
            return
        if length > MAX_RECORD_BYTES:
            yield index, SceneFormatError(p, index, f"record length {length} too large", True)
            return
        if not compressed and length + 4 > size - offset:
            yield index, SceneFormatError(
                p, index, f"truncated record: length field {length} but only "
                          f"{size - offset} bytes left in the file", True)
            return
        if compressed and length > limit:
            yield index, SceneFormatError(
                p, index, f"record length {length} exceeds the decompression limit of {limit} "
                          f"bytes for this {size}-byte gzip file", True)
            return
        try:
            data = _read(fh, length)
            tail = fh.read(4) if len(data) == length else b""
        except (OSError, EOFError, zlib.error) as exc:
            yield index, SceneFormatError(p, index, f"unreadable compressed data ({exc})", True)
            return
        if len(data) + len(tail) < length + 4:
            yield index, SceneFormatError(
                p, index, f"truncated record: {len(data) + len(tail)} of {length + 4} bytes "
                          "present", True)
            return
        offset += length + 4
        (data_crc,) = struct.unpack("<I", tail)
        if masked_crc32c(data) != data_crc:
            yield index, SceneFormatError(p, index, "data CRC mismatch (record corrupted)")
        else:
            yield index, data
        index += 1


def encode_record(data: bytes) -> bytes:
    """One framed TFRecord record holding ``data``."""
    header = struct.pack("<Q", len(data))
    return b"".join((header, struct.pack("<I", masked_crc32c(header)), data,
                     struct.pack("<I", masked_crc32c(data))))


def write_records(path: str | PathLike, records: Iterable[bytes], compress: bool | None = None) -> int:
    """Write records to ``path`` (gzip when ``compress`` or the name ends in .gz); returns count."""
    p = Path(path)
    if compress is None:
        compress = p.suffix == ".gz"
    opener = gzip.open if compress else open
    n = 0
    with opener(p, "wb") as fh:  # type: ignore[operator]
        for data in records:
            fh.write(encode_record(data))
            n += 1
    return n
