"""MCAP recordings, read as a stream, so that a file cut short by a crash
still yields everything up to its last complete record."""
from __future__ import annotations

import base64
import logging
import struct
from collections.abc import Iterator
from pathlib import Path

import orjson
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC

log = logging.getLogger(__name__)


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


def raw_board(topic: str) -> str | None | bool:
    """The board a raw-bytes topic belongs to: None for ``/raw`` (a one-board
    recording), NAME for ``/NAME/raw``; False for any other topic."""
    if topic == "/raw":
        return None
    parts = topic.split("/")
    return parts[1] if len(parts) == 3 and parts[0] == "" and parts[2] == "raw" else False


def read_raw(path: str | Path, board: str | None = None) -> Iterator[tuple[float, bytes]]:
    """(host receive time s, bytes) of every read of one board the recording
    holds: ``board`` None, the only board's; ValueError naming the boards
    when there are several and none was chosen, or the chosen one is not there."""
    check_mcap(path)
    boards = boards_in(path)
    if board is None and len(boards) > 1:
        raise ValueError(f"{path} holds boards {', '.join(map(str, boards))}: choose one")
    if board is not None and board not in boards:
        raise ValueError(f"{path} holds no board {board!r}; it holds {', '.join(map(str, boards)) or 'none'}")
    return ((t, chunk) for name, t, chunk in read_boards(path) if board is None or name == board)


def read_boards(path: str | Path) -> Iterator[tuple[str | None, float, bytes]]:
    """(board, host receive time s, bytes) of every read of every board, in
    file order (the order they were received); board None for a one-board
    recording's ``/raw``."""
    for topic, message in iter_messages(path):
        board = raw_board(topic)
        if board is not False:
            yield (board, *_raw_chunk(message))


def boards_in(path: str | Path) -> list[str | None]:
    """The boards with raw bytes in a recording, from its summary (a file
    cut short has none: then by reading it)."""
    try:
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        topics = [c.topic for c in summary.channels.values()] if summary is not None else None
    except Exception:  # noqa: BLE001 — no usable summary: read the records themselves
        topics = None
    if topics is None:
        topics = list(dict.fromkeys(topic for topic, _ in iter_messages(path)))
    return [board for board in map(raw_board, topics) if board is not False]


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
