"""MCAP logs: the writer the recorder uses, and a reader that survives a crash.

Channels: ``/raw`` (tactile.RawBytes, every read of the port), per sensor
``/sensor/{id}/raw`` (tactile.RawFrame), ``/sensor/{id}/forces``
(tactile.Forces), ``/sensor/{id}/grid`` (foxglove.Grid, grids only), and
``/diagnostics``. log_time is the host receive time (ns); publish_time the
board time of the frame where there is one.

Chunks are small (64 KiB, ~0.2 s at 1 kHz) and the file is flushed after
each, so a crash loses at most the open chunk: ``read_raw`` reads the file
as a stream and stops cleanly at the first incomplete record.
"""
from __future__ import annotations

import base64
import logging
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import orjson
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from ..fanout.encoding import to_export_dict
from ..reconstruct import ForceFrame
from . import schemas

log = logging.getLogger(__name__)

CHUNK_BYTES = 1 << 16
_JSON = orjson.OPT_SERIALIZE_NUMPY
PROFILE = ""
GRID_CELL_M = 0.004


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


class McapLog:
    """Writes a recording; not thread-safe (the recorder's thread owns it)."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="tactile")
        self._schemas = {
            name: self._writer.register_schema(schema["title"], "jsonschema", schemas.encoded(schema))
            for name, schema in (("raw", schemas.RAW_BYTES), ("frame", schemas.RAW_FRAME), ("forces", schemas.FORCES),
                                 ("diag", schemas.DIAGNOSTICS), ("grid", schemas.FOXGLOVE_GRID))
        }
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}

    def _channel(self, topic: str, schema: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._writer.register_channel(topic, "json", self._schemas[schema])
        return channel

    def _add(self, topic: str, schema: str, t_host: float, payload: dict, publish_ns: int | None = None) -> None:
        channel = self._channel(topic, schema)
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        log_ns = _ns(t_host)
        self._writer.add_message(channel, log_ns, orjson.dumps(payload, option=_JSON), publish_ns or log_ns, sequence)

    def raw(self, data: bytes, t_host: float) -> None:
        self._add("/raw", "raw", t_host, {"t_host": t_host, "data": base64.b64encode(data).decode()})

    def frame(self, frame: ForceFrame) -> None:
        sid = frame.sensor.id
        publish = frame.t_us * 1000
        self._add(f"/sensor/{sid}/raw", "frame", frame.t_host,
                  {"sensor": sid, "seq": frame.seq, "t_us": frame.t_us, "capacitance_pF": frame.capacitance_pF}, publish)
        self._add(f"/sensor/{sid}/forces", "forces", frame.t_host, to_export_dict(frame), publish)
        if frame.sensor.kind == "grid":
            self._add(f"/sensor/{sid}/grid", "grid", frame.t_host, foxglove_grid(frame), publish)

    def diagnostics(self, t_host: float, counters: dict) -> None:
        self._add("/diagnostics", "diag", t_host, counters)

    def close(self) -> None:
        self._writer.finish()


def foxglove_grid(frame: ForceFrame) -> dict:
    """A grid frame as foxglove.Grid: row-major FLOAT32 forces (NaN = no reading)."""
    info = frame.sensor
    sec, frac = divmod(frame.t_host, 1.0)
    return {
        "timestamp": {"sec": int(sec), "nsec": int(frac * 1e9)},
        "frame_id": f"tactile_sensor_{info.id}",
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "column_count": info.cols,
        "cell_size": {"x": GRID_CELL_M, "y": GRID_CELL_M},
        "row_stride": 4 * info.cols,
        "cell_stride": 4,
        "fields": [{"name": "force_N", "offset": 0, "type": schemas.FOXGLOVE_FLOAT32}],
        "data": base64.b64encode(np.asarray(frame.forces_N, dtype="<f4").tobytes()).decode(),
    }


def check_mcap(path: str | Path) -> None:
    """ValueError unless ``path`` begins as every MCAP file does."""
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP0_MAGIC))
    if head != MCAP0_MAGIC:
        raise ValueError(f"{path} is not an MCAP recording (it starts with {head!r}, not {MCAP0_MAGIC!r})")


def iter_messages(path: str | Path, topics: set[str] | None = None) -> Iterator[tuple[str, Message]]:
    """(topic, message) in file order, reading as a stream: a file cut short
    by a crash yields everything up to its last complete record, and says
    so in a warning; a file that is no MCAP at all is a ValueError, raised
    here rather than at the first read."""
    check_mcap(path)
    return _messages(path, topics)


def _messages(path: str | Path, topics: set[str] | None) -> Iterator[tuple[str, Message]]:
    channels: dict[int, str] = {}
    with open(path, "rb") as stream:
        reader = StreamReader(stream, validate_crcs=True)
        try:
            for record in reader.records:
                kind = type(record).__name__
                if kind == "Channel":
                    channels[record.id] = record.topic
                elif kind == "Message":
                    topic = channels.get(record.channel_id)
                    if topics is None or topic in topics:
                        yield topic, record
        except (McapError, EOFError, struct.error, ValueError) as exc:
            log.warning("%s ends early, near byte %d of %d (%s): read what was complete, as after a crash",
                        path, stream.tell(), Path(path).stat().st_size, str(exc) or type(exc).__name__)


def read_raw(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """(host receive time s, bytes) of every read the recording holds."""
    return (_raw_chunk(message) for _, message in iter_messages(path, {"/raw"}))


def _raw_chunk(message: Message) -> tuple[float, bytes]:
    doc = orjson.loads(message.data)
    return doc["t_host"], base64.b64decode(doc["data"])


def summary(path: str | Path) -> dict:
    """Message counts per topic, through mcap's indexed reader (checks the
    file is complete and well-formed)."""
    with open(path, "rb") as stream:
        stats = make_reader(stream).get_summary()
    topics = {c.id: c.topic for c in stats.channels.values()}
    return {topics[cid]: n for cid, n in stats.statistics.channel_message_counts.items()}
