"""A crafted recording cannot make a replay inflate more than a chunk's bound.

A chunk of a recording declares its records' size and mcap's reader
allocates it: a 17 KB file of one zstd chunk of 512 MiB of "A"s took a
replay to 2.5 GB. Chunks are inflated here within MAX_CHUNK_BYTES and the
size they declare; one beyond either is a damaged chunk (its messages
skipped, said), the others are read.
"""
from __future__ import annotations

import logging

import orjson
import pytest
import zstandard
from mcap.records import Chunk
from mcap.writer import CompressionType, Writer

from service.record import mcap_reader
from service.record.mcap_reader import inflated, iter_messages

BOUND = 1 << 20  # the tests' bound: their files stay small


def recording(path, payloads: list[bytes], summary: bool = True) -> None:
    """An MCAP of /raw messages, one zstd chunk each (chunk_size 1 byte)."""
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=1, use_summary_offsets=summary,
                        use_chunking=True)
        writer.start("tactile", "tactile")
        schema = writer.register_schema("raw", "jsonschema", b"{}")
        channel = writer.register_channel("/raw", "json", schema)
        for i, payload in enumerate(payloads):
            writer.add_message(channel, log_time=i, publish_time=i, data=payload, sequence=i)
        writer.finish()


def raw(fill: int) -> bytes:
    return b'{"t_host": 1.0, "data": "' + b"A" * fill + b'"}'


@pytest.fixture
def bound(monkeypatch):
    monkeypatch.setattr(mcap_reader, "MAX_CHUNK_BYTES", BOUND)


def test_a_chunk_beyond_the_bound_is_skipped_and_said_the_others_read(tmp_path, bound, caplog):
    path = tmp_path / "bomb.mcap"
    recording(path, [raw(10), raw(2 * BOUND), raw(20)])
    assert path.stat().st_size < 10_000  # 2 MiB of "A"s, a few hundred bytes compressed
    with caplog.at_level(logging.WARNING):
        found = [orjson.loads(message.data)["data"] for _, message in iter_messages(path)]
    assert found == ["A" * 10, "A" * 20]
    assert f"more than a recording's chunk holds ({BOUND})" in caplog.text


def test_a_file_without_an_index_stops_at_such_a_chunk_with_a_warning(tmp_path, bound, caplog):
    whole = tmp_path / "whole.mcap"
    recording(whole, [raw(10), raw(2 * BOUND), raw(20)])
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 200])  # no summary: read as a stream, as after a crash
    with caplog.at_level(logging.WARNING):
        found = [orjson.loads(message.data)["data"] for _, message in iter_messages(cut)]
    assert found == ["A" * 10]
    assert "cannot be read past byte" in caplog.text and str(BOUND) in caplog.text


def test_a_chunk_inflating_to_more_than_it_declares_is_refused_unread():
    records = b"\x05" + (40).to_bytes(8, "little") + b"x" * 40  # one record of an unknown opcode: 49 bytes
    chunk = Chunk(compression="zstd", data=zstandard.ZstdCompressor().compress(records * 1000),
                  message_start_time=0, message_end_time=0, uncompressed_crc=0, uncompressed_size=len(records))
    with pytest.raises(ValueError, match=f"inflates to more than {len(records) + 1} bytes, not the {len(records)}"):
        inflated(chunk)
    honest = Chunk(compression="zstd", data=zstandard.ZstdCompressor().compress(records), message_start_time=0,
                   message_end_time=0, uncompressed_crc=0, uncompressed_size=len(records))
    assert inflated(honest).data == records and inflated(honest).compression == ""


def test_a_chunk_of_an_unknown_compression_is_named():
    chunk = Chunk(compression="brotli", data=b"", message_start_time=0, message_end_time=0, uncompressed_crc=0,
                  uncompressed_size=0)
    with pytest.raises(ValueError, match="'brotli'"):
        inflated(chunk)
