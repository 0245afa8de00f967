"""TFRecord framing (no TensorFlow): reading and writing length-prefixed, CRC-checked records.

Each record is ``u64 length | u32 masked_crc32c(length) | data | u32 masked_crc32c(data)``,
little-endian. Files may be gzip-compressed (detected from the magic bytes). Reading is lazy:
one record is held in memory at a time.
"""

from __future__ import annotations

import gzip
import io
import struct
from os import PathLike
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator

import google_crc32c

from magail_sumo.errors import SceneFormatError

_MASK_DELTA = 0xA282EAD8
_GZIP_MAGIC = b"\x1f\x8b"
#: Upper bound on one record's length: guards against reading garbage lengths (4 GiB).
MAX_RECORD_BYTES = 1 << 32


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC32C of ``data``."""
    crc = google_crc32c.value(data)
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + _MASK_DELTA) & 0xFFFFFFFF


def is_gzip(path: str | PathLike) -> bool:
    with open(path, "rb") as fh:
        return fh.read(2) == _GZIP_MAGIC


def _open(path: Path) -> BinaryIO:
    raw = open(path, "rb")
    if raw.read(2) == _GZIP_MAGIC:
        raw.close()
        return gzip.open(path, "rb")  # type: ignore[return-value]
    raw.seek(0)
    return io.BufferedReader(raw, buffer_size=1 << 20)  # type: ignore[arg-type]


def iter_records(path: str | PathLike) -> Iterator[tuple[int, bytes | SceneFormatError]]:
    """Yield ``(index, data)`` for each record of a TFRecord file, lazily.

    A bad data CRC yields ``(index, SceneFormatError)`` and reading continues with the next
    record (the length was verified). A framing error (bad length CRC, truncation) yields a
    fatal ``SceneFormatError`` and stops: nothing after it can be located. Errors about the
    file itself (missing, a directory, empty, unreadable) are raised.
    """
    p = Path(path)
    if p.is_dir():
        raise SceneFormatError(p, None, "is a directory, expected a TFRecord file")
    if not p.exists():
        raise SceneFormatError(p, None, "no such file")
    if p.stat().st_size == 0:
        raise SceneFormatError(p, None, "empty file (no records)")
    with _open(p) as fh:
        index = 0
        while True:
            try:
                header = fh.read(12)
            except (OSError, EOFError) as exc:  # corrupt gzip stream
                yield index, SceneFormatError(p, index, f"unreadable compressed data ({exc})", True)
                return
            if not header:
                return
            if len(header) < 12:
                yield index, SceneFormatError(
                    p, index, f"truncated record header ({len(header)} of 12 bytes)", True)
                return
            length, length_crc = struct.unpack("<QI", header)
            if masked_crc32c(header[:8]) != length_crc:
                what = "not a TFRecord file" if index == 0 else "corrupt record framing"
                yield index, SceneFormatError(
                    p, index, f"{what}: length CRC mismatch (length field {length})", True)
                return
            if length > MAX_RECORD_BYTES:
                yield index, SceneFormatError(p, index, f"record length {length} too large", True)
                return
            try:
                body = fh.read(length + 4)
            except (OSError, EOFError) as exc:
                yield index, SceneFormatError(p, index, f"unreadable compressed data ({exc})", True)
                return
            if len(body) < length + 4:
                yield index, SceneFormatError(
                    p, index, f"truncated record: {len(body)} of {length + 4} bytes present", True)
                return
            data = body[:length]
            (data_crc,) = struct.unpack("<I", body[length:])
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
