"""MCAP recordings, read as a stream, so that a file cut short by a crash
still yields everything up to its last complete record; a complete file's
raw bytes are read through its index instead (``read_boards``)."""
from __future__ import annotations

import base64
import dataclasses
import io
import logging
import struct
from collections.abc import Iterator
from pathlib import Path

import orjson
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Chunk, Message, MessageIndex
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream
from mcap.writer import MCAP0_MAGIC

from ..physics.mountings import MOUNTINGS
from ..reconstruct.levels import LEVELS

log = logging.getLogger(__name__)

# A chunk's records, inflated, at most this: ours hold 64 KiB (mcap_writer.CHUNK_BYTES) or one message
# a little larger (a read of the port, the calibrations in force); mcap's own reader inflates whatever
# size a chunk declares, and a crafted 17 KB file took a replay to 2.5 GB.
MAX_CHUNK_BYTES = 64 << 20


def check_mcap(path: str | Path) -> None:
    """ValueError unless ``path`` begins as every MCAP file does."""
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP0_MAGIC))
    if head != MCAP0_MAGIC:
        raise ValueError(f"{path} is not an MCAP recording (it starts with {head!r}, not {MCAP0_MAGIC!r})")


_WARNED: set[tuple[str, int, int]] = set()  # (file, size, where) of damage already reported


def _first_report(path: str | Path, where: int) -> bool:
    """Whether damage at byte ``where`` of ``path`` (as it is now) is new: a
    replay reads a file once per kind of message it needs (raw reads, tares,
    zeros, settings, /resume, …), and the damage is said once, not each time."""
    key = (str(path), Path(path).stat().st_size, where)
    if key in _WARNED:
        return False
    _WARNED.add(key)
    return True


def iter_messages(path: str | Path, topics: set[str] | None = None) -> Iterator[tuple[str, Message]]:
    """(topic, message) in file order: a complete file through its index
    (only the messages asked for are parsed: mcap's readers parse every
    record of a chunk in Python, 90 % of a replay's time), a file cut short
    by a crash as a stream, everything up to its last complete record, with
    a warning; a file that is no MCAP at all is a ValueError, raised here
    rather than at the first read."""
    check_mcap(path)
    indexed = _indexed_messages(path, lambda topic: topics is None or topic in topics)
    return indexed if indexed is not None else _messages(path, topics)


def _messages(path: str | Path, topics: set[str] | None) -> Iterator[tuple[str, Message]]:
    channels: dict[int, str] = {}
    with open(path, "rb") as stream:
        reader = StreamReader(stream, validate_crcs=True, emit_chunks=True)
        try:
            for record in _unchunked(reader.records):
                kind = type(record).__name__
                if kind == "Channel":
                    channels[record.id] = record.topic
                elif kind == "Message":
                    topic = channels.get(record.channel_id)
                    if topics is None or topic in topics:
                        yield topic, record
        except (McapError, EOFError, struct.error, ValueError) as exc:
            size, at = Path(path).stat().st_size, stream.tell()
            if _first_report(path, at):
                lost = "" if size - at < 4096 else f"; the {size - at} bytes after it are not read"
                log.warning("%s cannot be read past byte %d of %d (%s): read what came before it, as after a "
                            "crash%s", path, at, size, str(exc) or type(exc).__name__, lost)


def _unchunked(records: Iterator) -> Iterator:
    """``records`` with each chunk's own records in its place (inflated within MAX_CHUNK_BYTES)."""
    for record in records:
        if isinstance(record, Chunk):
            yield from breakup_chunk(inflated(record), validate_crc=True)
        else:
            yield record


def inflated(chunk: Chunk) -> Chunk:
    """``chunk`` with its records decompressed (compression ""), read no
    further than MAX_CHUNK_BYTES and the size it declares: ValueError naming
    either, rather than memory for whatever a crafted file claims."""
    declared = chunk.uncompressed_size
    if declared > MAX_CHUNK_BYTES:
        raise ValueError(f"a chunk declares {declared} bytes of records, more than a recording's chunk holds "
                         f"({MAX_CHUNK_BYTES})")
    if chunk.compression == "":
        return chunk
    if chunk.compression == "zstd":
        import zstandard

        source = zstandard.ZstdDecompressor().stream_reader(chunk.data)
    elif chunk.compression == "lz4":
        import lz4.frame

        source = lz4.frame.open(io.BytesIO(chunk.data))
    else:
        raise ValueError(f"a chunk is compressed with {chunk.compression!r}, not zstd or lz4")
    parts, size = [], 0
    while size <= declared:
        part = source.read(min(1 << 20, declared + 1 - size))
        if not part:
            break
        parts.append(part)
        size += len(part)
    if size != declared:
        raise ValueError(f"a chunk inflates to {'more than ' if size > declared else ''}{size} bytes, not the "
                         f"{declared} it declares")
    return dataclasses.replace(chunk, compression="", data=b"".join(parts))


def raw_board(topic: str, channel: str = "raw") -> str | None | bool:
    """The board a raw-bytes topic (or another per-board ``channel``'s)
    belongs to: None for ``/raw`` (a one-board recording), NAME for
    ``/NAME/raw``; False for any other topic."""
    if topic == f"/{channel}":
        return None
    parts = topic.split("/")
    return parts[1] if len(parts) == 3 and parts[0] == "" and parts[2] == channel else False


def read_changes(path: str | Path) -> dict[str | None, list[tuple[int, int | None, bool | dict | str]]]:
    """What was changed while recording, per board (as ``read_boards`` names
    them), to make again where it was made (Pipeline.redo): (reads of that
    board before it took effect, sensor id, change: a tare's ``judge``, or
    the document of a calibration set; or None, the link's event: /link),
    by read and in the order made."""
    changes: dict[str | None, list[tuple[int, int | None, bool | dict | str]]] = {}

    def recorded(topic: str) -> bool:
        return any(raw_board(topic, channel) is not False for channel in ("tare", "calibration_set", "link"))

    for topic, message in _topics_of(path, recorded):
        doc = orjson.loads(message.data)
        if topic.endswith("/tare"):
            changes.setdefault(raw_board(topic, "tare"), []).extend(
                (int(s["after_reads"]), int(s["sensor"]), bool(doc["judge"])) for s in doc["sensors"])
        elif topic.endswith("/link"):
            changes.setdefault(raw_board(topic, "link"), []).append((int(doc["after_reads"]), None, str(doc["event"])))
        elif not isinstance(doc["document"], dict):  # a list would be taken for a tare's judge (Pipeline.redo)
            log.warning("%s: the /calibration_set of sensor %s before read %s: its document %.80r is no object: "
                        "skipped", path, doc["sensor"], doc["after_reads"], doc["document"])
        else:
            changes.setdefault(raw_board(topic, "calibration_set"), []).append(
                (int(doc["after_reads"]), int(doc["sensor"]), doc["document"]))
    return {board: sorted(made, key=lambda change: change[0]) for board, made in changes.items()}


def read_calibrations_set(path: str | Path) -> set[tuple[int | str, str]]:
    """(sensor address: board/id, or the id in a recording of an unnamed
    board; calibration id) of each calibration set while recording."""
    found = set()
    for _, message in _topics_of(path, lambda topic: raw_board(topic, "calibration_set") is not False):
        doc = orjson.loads(message.data)
        if not isinstance(doc["document"], dict):  # skipped by read_changes, said there
            continue
        found.add((f"{doc['board']}/{int(doc['sensor'])}" if doc.get("board") else int(doc["sensor"]),
                   doc["document"]["id"]))
    return found


def read_settings(path: str | Path) -> dict[str | None, dict]:
    """{board (as ``read_boards`` names them): {"level", "mounting"}} its
    forces were reconstructed with while recording (the first said; none
    in a recording made before they were recorded), with "identify": its
    frames' wait for the board's INFO when the recording began, where it
    had one (Identification.state)."""
    settings: dict[str | None, dict] = {}
    for topic, message in _topics_of(path, lambda topic: raw_board(topic, "settings") is not False):
        doc = orjson.loads(message.data)
        wait = {"identify": doc["identify"]} if "identify" in doc else {}
        settings.setdefault(raw_board(topic, "settings"), _known_settings(path, doc) | wait)
    return settings


def _known_settings(path: str | Path, doc: dict) -> dict:
    """{"level", "mounting"} of a /settings document, each one that is none
    the service knows said and left out (the replay's own or default is used)."""
    known = {}
    for name, values in (("level", LEVELS), ("mounting", MOUNTINGS)):
        value = doc[name]
        if isinstance(value, str) and value in values:  # a list is no key of MOUNTINGS: TypeError
            known[name] = value
        else:
            log.warning("%s: the recorded /settings' %s %.80r is not one of %s: skipped, replayed at the one given "
                        "or the default", path, name, value, ", ".join(values))
    return known


def read_baselines(path: str | Path) -> dict[str | None, dict]:
    """The zeros in force when the recording began, per board (as
    ``read_boards`` names them): {"board": its name then, "sensors": [...],
    "info": the INFO then in force (if any), "left": the zeros of sensors
    that had left their address}; none for a recording that
    began with its stream (its sensors tare in it, and its INFO names the
    board)."""
    zeros: dict[str | None, dict] = {}
    for topic, message in _topics_of(path, lambda topic: raw_board(topic, "baselines") is not False):
        doc = orjson.loads(message.data)
        began = zeros.setdefault(raw_board(topic, "baselines"), {"board": doc["board"], "sensors": []})
        began["sensors"] += doc["sensors"]
        began.setdefault("left", []).extend(doc.get("left", []))
        if doc.get("info") is not None:
            began.setdefault("info", doc["info"])
    return zeros


def read_resumes(path: str | Path) -> dict[str | None, list[dict]]:
    """Per board (as ``read_boards`` names them), the points a replay can
    begin at (``/resume``, once a second of reads; none in a recording made
    before they were recorded): {"after_reads", "board", "sensors" (zeros),
    "described", "info" (if any)} in read order."""
    resumes: dict[str | None, list[dict]] = {}
    for topic, message in _topics_of(path, lambda topic: raw_board(topic, "resume") is not False):
        resumes.setdefault(raw_board(topic, "resume"), []).append(orjson.loads(message.data))
    return resumes


def read_raw(path: str | Path, board: str | None = None, from_read: int = 0) -> Iterator[tuple[float, bytes]]:
    """(host receive time s, bytes) of every read of one board the recording
    holds (from its read ``from_read`` on): ``board`` None, the only board's;
    ValueError naming the boards when there are several and none was
    chosen, or the chosen one is not there."""
    check_mcap(path)
    boards = boards_in(path)
    if board is None and len(boards) > 1:
        raise ValueError(f"{path} holds boards {', '.join(map(str, boards))}: choose one")
    if board is not None and board not in boards:
        raise ValueError(f"{path} holds no board {board!r}; it holds {', '.join(map(str, boards)) or 'none'}")
    return ((t, chunk) for name, number, t, chunk in read_numbered(path)
            if (board is None or name == board) and number >= from_read)


def read_boards(path: str | Path) -> Iterator[tuple[str | None, float, bytes]]:
    """(board, host receive time s, bytes) of every read of every board, in
    file order (the order they were received); board None for a one-board
    recording's ``/raw``. A complete recording is read through its index:
    only the raw messages are parsed, not the forces recorded beside them."""
    return ((board, t, data) for board, _, t, data in read_numbered(path))


def read_numbered(path: str | Path) -> Iterator[tuple[str | None, int, float, bytes]]:
    """``read_boards`` with each read's number on its board (0 for the
    recording's first: the raw channel's message sequence), which a damaged
    chunk that lost reads does not shift."""
    for topic, message in _topics_of(path, lambda topic: raw_board(topic) is not False):
        yield (raw_board(topic), message.sequence, *_raw_chunk(message))


def _topics_of(path: str | Path, wanted) -> Iterator[tuple[str, Message]]:
    """(topic, message) of the topics ``wanted`` accepts: through the index,
    or as a stream for a file without one."""
    check_mcap(path)
    messages = _indexed_messages(path, wanted)
    if messages is not None:
        return messages
    return ((topic, message) for topic, message in _messages(path, None) if wanted(topic))


def _indexed_messages(path: str | Path, wanted) -> Iterator[tuple[str, Message]] | None:
    """(topic, message) of the topics ``wanted`` accepts, in file order,
    from the chunks' message indexes; None for a file without a summary
    (cut short: read it as a stream) or whose summary does not index every
    chunk's messages (MCAP makes message indexes optional)."""
    try:
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
    except Exception:  # noqa: BLE001 — no usable summary: the stream reader says what is wrong
        return None
    if summary is None or not summary.chunk_indexes or not summary.channels or \
            not all(chunk.message_index_offsets for chunk in summary.chunk_indexes):
        return None
    topics = {cid: channel.topic for cid, channel in summary.channels.items() if wanted(channel.topic)}
    return _chunk_messages(path, sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset), topics)


def _chunk_messages(path: str | Path, chunk_indexes: list, topics: dict[int, str]) -> Iterator[tuple[str, Message]]:
    with open(path, "rb") as stream:
        for chunk_index in chunk_indexes:
            found = []
            try:
                for cid, offset in chunk_index.message_index_offsets.items():
                    if cid in topics:
                        stream.seek(offset + 9)  # past the record's opcode and length
                        found += [(at, cid) for _, at in MessageIndex.read(ReadDataStream(stream)).records]
                if not found:
                    continue
                stream.seek(chunk_index.chunk_start_offset + 9)
                chunk_stream, size = get_chunk_data_stream(inflated(Chunk.read(ReadDataStream(stream))),
                                                           validate_crc=True)
                data = memoryview(chunk_stream.read(size))
                messages = []
                for at, cid in sorted(found):
                    length = int.from_bytes(data[at + 1 : at + 9], "little")
                    messages.append((topics[cid], Message.read(ReadDataStream(io.BytesIO(data[at + 9 : at + 9 + length])),
                                                               length)))
            except Exception as exc:  # noqa: BLE001 — whatever the decompressor raises: one chunk lost, not the file
                if _first_report(path, chunk_index.chunk_start_offset):
                    log.warning("%s: the chunk at byte %d (or its index) is damaged (%s): its messages skipped", path,
                                chunk_index.chunk_start_offset, str(exc) or type(exc).__name__)
                continue
            yield from messages


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
