"""TFRecord framing: CRCs, gzip, every framing error, and lengths a file claims (a
record length, a gzip bomb) that never become allocations."""

from __future__ import annotations

import gzip
import struct

import pytest

from conftest import WOMD_DIR, peak_memory
from converters.tfrecord import (
    GZIP_MIN_RECORD_BUDGET, encode_record, iter_records, masked_crc32c, write_records,
)
from magail_sumo.errors import SceneFormatError


def test_masked_crc_matches_reference_values():
    # CRC32C("123456789") = 0xE3069283 (RFC 3720 check value), masked as TFRecord does.
    crc = 0xE3069283
    expected = ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + 0xA282EAD8) & 0xFFFFFFFF
    assert masked_crc32c(b"123456789") == expected
    # The length CRC of a real WOMD record header, as stored in the file.
    head = (WOMD_DIR / "850c48d8bbfa008f.tfrecord").read_bytes()[:12]
    assert masked_crc32c(head[:8]) == struct.unpack("<I", head[8:12])[0]


@pytest.mark.parametrize("compress", [False, True])
def test_write_then_read_records(tmp_path, compress):
    path = tmp_path / ("r.tfrecord.gz" if compress else "r.tfrecord")
    payloads = [b"", b"a", b"x" * 100_000]
    assert write_records(path, payloads) == 3
    assert (path.read_bytes()[:2] == b"\x1f\x8b") is compress
    assert [d for _, d in iter_records(path)] == payloads


def _errors(path):
    return [(i, d) for i, d in iter_records(path) if isinstance(d, SceneFormatError)]


def test_truncated_record(tmp_path):
    path = tmp_path / "t.tfrecord"
    path.write_bytes(encode_record(b"hello") + encode_record(b"world" * 10)[:-7])
    items = list(iter_records(path))
    assert items[0] == (0, b"hello")
    err = items[1][1]
    assert isinstance(err, SceneFormatError) and err.record == 1 and err.fatal_for_file
    assert "truncated record" in str(err) and str(path) in str(err)


def test_length_crc_mismatch(tmp_path):
    rec = bytearray(encode_record(b"payload"))
    rec[8] ^= 0xFF
    path = tmp_path / "l.tfrecord"
    path.write_bytes(encode_record(b"ok") + bytes(rec) + encode_record(b"after"))
    [(index, err)] = _errors(path)
    assert index == 1 and "length CRC mismatch" in str(err) and "record 1" in str(err)


def test_data_crc_mismatch_skips_only_that_record(tmp_path):
    rec = bytearray(encode_record(b"payload"))
    rec[14] ^= 0x01
    path = tmp_path / "d.tfrecord"
    path.write_bytes(encode_record(b"first") + bytes(rec) + encode_record(b"third"))
    items = list(iter_records(path))
    assert items[0] == (0, b"first") and items[2] == (2, b"third")
    assert isinstance(items[1][1], SceneFormatError) and "data CRC mismatch" in str(items[1][1])
    assert not items[1][1].fatal_for_file


def test_not_a_tfrecord(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("this is a text file, not a TFRecord\n" * 3)
    [(index, err)] = _errors(path)
    assert index == 0 and "not a TFRecord file" in str(err)


def test_empty_file_and_directory(tmp_path):
    empty = tmp_path / "empty.tfrecord"
    empty.write_bytes(b"")
    with pytest.raises(SceneFormatError, match="empty file"):
        list(iter_records(empty))
    with pytest.raises(SceneFormatError, match="is a directory"):
        list(iter_records(tmp_path))


def test_corrupt_gzip_stream(tmp_path):
    path = tmp_path / "c.tfrecord.gz"
    data = gzip.compress(encode_record(b"x" * 5000))
    path.write_bytes(data[: len(data) // 2])
    errs = _errors(path)
    assert len(errs) == 1 and errs[0][1].fatal_for_file


# --------------------------------------------------------- claimed lengths never become allocations
MiB = 1 << 20


def _header(length: int) -> bytes:
    head = struct.pack("<Q", length)
    return head + struct.pack("<I", masked_crc32c(head))


def test_28_byte_file_claiming_2gib_is_truncated_without_allocating(tmp_path):
    path = tmp_path / "claim.tfrecord"
    path.write_bytes(_header(2**31) + b"x" * 16)
    assert path.stat().st_size == 28
    recs, peak = peak_memory(lambda: list(iter_records(path)))
    [(index, err)] = recs
    assert index == 0 and err.fatal_for_file
    assert str(err) == (f"{path}: record 0: truncated record: length field 2147483648 but only "
                        "16 bytes left in the file")
    assert peak < 16 * MiB


def test_gzip_record_is_read_in_pieces(tmp_path):
    """A gzip record claiming 200 MiB (inside the budget) with 1 kB present costs ~chunk size."""
    path = tmp_path / "claim.tfrecord.gz"
    path.write_bytes(gzip.compress(_header(200 * MiB) + b"x" * 1000))
    recs, peak = peak_memory(lambda: list(iter_records(path)))
    [(_, err)] = recs
    assert "record 0: truncated record: 1000 of 209715204 bytes present" in str(err)
    assert peak < 32 * MiB


def test_gzip_bomb_is_refused_before_decompressing(tmp_path):
    path = tmp_path / "bomb.tfrecord.gz"
    path.write_bytes(gzip.compress(_header(GZIP_MIN_RECORD_BUDGET + 1) + b"\0" * 1000))
    recs, peak = peak_memory(lambda: list(iter_records(path)))
    [(_, err)] = recs
    assert err.fatal_for_file and "\n" not in str(err)
    assert (f"record 0: record length {GZIP_MIN_RECORD_BUDGET + 1} exceeds the decompression "
            f"limit of {GZIP_MIN_RECORD_BUDGET} bytes") in str(err)
    assert peak < 16 * MiB


def test_real_records_still_read_plain_and_gzip(tmp_path):
    records = [d for _, d in iter_records(WOMD_DIR / "850c48d8bbfa008f.tfrecord")]
    for name in ("x.tfrecord", "x.tfrecord.gz"):
        write_records(tmp_path / name, records * 2)
        back = [d for _, d in iter_records(tmp_path / name)]
        assert back == records * 2


def test_second_record_truncated_names_its_index(tmp_path):
    good = encode_record(b"hello")
    path = tmp_path / "two.tfrecord"
    path.write_bytes(good + _header(10**9) + b"abc")
    recs = list(iter_records(path))
    assert recs[0] == (0, b"hello")
    assert "record 1: truncated record: length field 1000000000 but only 3 bytes left" \
        in str(recs[1][1])
