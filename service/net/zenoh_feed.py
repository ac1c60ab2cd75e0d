"""A gateway's view of Zenoh: every board's frames, health and liveliness
under ``tactile/``.

Zenoh calls back on its own threads; those callbacks only queue the
sample. One thread (``run``) decodes frames (the binary encoding), asks a
board's sensor shapes once (``tactile/<board>/sensors``, again when an
unknown sensor appears), rebuilds ForceFrames and hands each board's batch
to ``deliver(board, frames)``; health documents go to
``on_health(board, document)``, liveliness to ``on_alive(board, alive)``.
A sample larger than ``MAX_SAMPLE_BYTES`` is dropped and counted unparsed:
what comes from the network is never parsed at any size, nor taken at its
word: a sensor announced with a shape no frame of the protocol can have
(more than ``MAX_CHANNELS`` channels, an id beyond ``MAX_SENSOR_ID``) is
refused, and so is a record whose forces do not fill its sensor's shape;
both are counted and named in ``problems`` (the gateway's /health). Each
sample and token names the service instance that sent it; ``claims`` (board_claims.py)
says which instance each board name is served from, and the others' samples
are dropped unparsed, their liveliness not passed on. A health sample
``{"renamed_to": NAME}`` is a service saying it renamed the board (a bare
board's provisional name, at its first INFO): what that instance sends
under the old name afterwards (frames in flight, its token's withdrawal) is
dropped, counted in ``samples_renamed``. When another instance takes a
board over (a restarted service: seq and board_time_us begin again), each
sensor's first frame from it is flagged ``board_restart``, as a service
flags a board's after its restart; every frame names its instance.
"""
from __future__ import annotations

import logging
import struct
import threading
import time
from collections import deque
from typing import Callable

import numpy as np
import orjson
import zenoh

from ..board_info import _is_int
from ..fanout.encoding import decode_binary
from ..readings import MAX_CHANNELS, MAX_SENSOR_ID, SensorInfo
from ..recent import MostRecent
from ..reconstruct import ForceFrame
from .board_claims import BoardClaims
from .zenoh_config import PREFIX, instance_of_alive, instance_of_sample, open_session, sensors_key

log = logging.getLogger(__name__)

MAX_SAMPLE_BYTES = 1 << 20  # a sample holds at most 32 frames of a 256-channel grid (~70 KiB)
QUEUE_SAMPLES = 8192  # ~4 s of two boards' grid and quad at 1 kHz, one frame a sample
SHAPES_RETRY_S = 1.0
REMOTE_LEVEL = "remote"  # a gateway's frames: reconstructed elsewhere, the level is the remote service's
QUAD_FORCES = 3  # Fx, Fy, Fz
REFUSALS_KEPT_S = 60.0  # a refusal's problem line stays this long after the last one
MAX_REFUSALS = 16  # boards with a refusal told; beyond, the least recent is forgotten
MAX_RENAMED = 64  # (old name, instance) pairs remembered; a service renames each board at most once


def _board_of(key) -> str:
    return str(key).split("/")[1]


class ZenohFeed:
    """Subscribes on start, closes the session on ``close``."""

    def __init__(self, config: zenoh.Config, deliver: Callable[[str, list[ForceFrame]], None],
                 on_health: Callable[[str, dict], None], on_alive: Callable[[str, bool], None],
                 queue_samples: int = QUEUE_SAMPLES, claims: BoardClaims | None = None) -> None:
        self.session = open_session(config)
        self.claims = BoardClaims() if claims is None else claims
        self._deliver, self._on_health, self._on_alive = deliver, on_health, on_alive
        self._samples: deque = deque(maxlen=queue_samples)
        self._ready = threading.Event()
        self._closing = threading.Event()
        self._shapes: dict[tuple[str, str], dict[int, SensorInfo]] = {}  # by (board, instance)
        self._asked: dict[tuple[str, str], float] = {}
        self.frames_received = 0
        self.samples_received = 0
        self.samples_dropped = 0  # the queue overflowed: the decoding thread fell behind
        self.samples_refused = 0  # from an instance publishing a board name another one holds
        self.oversized = 0
        self.undecodable = 0
        self.unshaped_frames = 0  # frames of sensors whose shape the board's service did not tell
        self.shapes_refused = 0  # sensors announced with a shape no frame can have
        self.misfit_frames = 0  # records whose forces do not fill their sensor's announced shape
        self._refusals: MostRecent = MostRecent(MAX_REFUSALS)  # board → (monotonic time, why), the latest
        self._refusals_lock = threading.Lock()  # written by the feed's thread, read by the event loop's
        self._renamed: MostRecent = MostRecent(MAX_RENAMED)  # (old name, instance) → when its service said so
        self._forgotten: deque[str] = deque()  # boards the gateway forgot, for the feed's thread to forget
        self.samples_renamed = 0
        # board → (the instance whose frames were last taken, whether it took over from another, its sensors since)
        self._instances: dict[str, tuple[str, bool, set[int]]] = {}
        self._subscriptions: list = []
        self._thread = threading.Thread(target=self._run, name="tactile-gateway-feed", daemon=True)

    def start(self) -> "ZenohFeed":
        self._subscriptions = [
            self.session.declare_subscriber(f"{PREFIX}/*/*/frame", lambda s: self._queue("frame", s)),
            self.session.declare_subscriber(f"{PREFIX}/*/health", lambda s: self._queue("health", s)),
            self.session.liveliness().declare_subscriber(f"{PREFIX}/*/alive/**", lambda s: self._queue("alive", s),
                                                         history=True),
        ]
        self._thread.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        self._closing.set()
        self._ready.set()
        self._thread.join(timeout)
        self.session.close()

    def status(self) -> dict:
        """What the gateway's /health shows under "zenoh"."""
        info = self.session.info
        return {"zid": str(info.zid()), "peers": len(info.peers_zid()), "routers": len(info.routers_zid()),
                "frames_received": self.frames_received, "samples_received": self.samples_received,
                "samples_dropped": self.samples_dropped,
                "samples_refused": self.samples_refused, "oversized": self.oversized,
                "undecodable": self.undecodable, "unshaped_frames": self.unshaped_frames,
                "shapes_refused": self.shapes_refused, "misfit_frames": self.misfit_frames,
                "samples_renamed": self.samples_renamed}

    def forget(self, board: str) -> None:
        """From any thread: the gateway forgot ``board``; its shapes and refusals go too (on the feed's thread)."""
        self._forgotten.append(board)
        self._ready.set()

    def problems(self, now: float) -> list[str]:
        """A line per board whose service announced a shape no frame can have
        or sent forces that do not fill one, within ``REFUSALS_KEPT_S`` before
        ``now`` (time.monotonic())."""
        with self._refusals_lock:
            refusals = sorted(self._refusals.items())
        return [f"board {board}: {why}" for board, (at, why) in refusals if now - at <= REFUSALS_KEPT_S]

    def _refuse(self, board: str, why: str) -> None:
        with self._refusals_lock:
            self._refusals[board] = (time.monotonic(), why)

    def _queue(self, kind: str, sample: zenoh.Sample) -> None:
        """On Zenoh's thread: only queue (the oldest sample goes when full, counted)."""
        if len(self._samples) == self._samples.maxlen:
            self.samples_dropped += 1
        self._samples.append((kind, sample, time.time()))
        self._ready.set()

    def _run(self) -> None:
        while not self._closing.is_set():
            self._ready.wait()
            self._ready.clear()
            while self._forgotten:
                self._drop(self._forgotten.popleft())
            batches: dict[str, list[ForceFrame]] = {}
            while self._samples:
                kind, sample, at = self._samples.popleft()
                try:
                    self._take(kind, sample, at, batches)
                except Exception as exc:  # noqa: BLE001 — one bad sample never stops the feed
                    self.undecodable += 1
                    log.warning("gateway: a %s sample on %s not taken: %r", kind, sample.key_expr, exc)
            for board, frames in batches.items():
                self._deliver(board, frames)

    def _drop(self, board: str) -> None:
        for known in [k for k in self._shapes if k[0] == board]:
            del self._shapes[known]
        for known in [k for k in self._asked if k[0] == board]:
            del self._asked[known]
        self._instances.pop(board, None)
        with self._refusals_lock:
            self._refusals.pop(board, None)

    def _take(self, kind: str, sample: zenoh.Sample, at: float, batches: dict) -> None:
        board = _board_of(sample.key_expr)
        instance = instance_of_alive(sample.key_expr) if kind == "alive" else instance_of_sample(sample)
        if (board, instance) in self._renamed:
            self.samples_renamed += 1
            return
        if kind == "alive":
            alive = sample.kind == zenoh.SampleKind.PUT
            if self.claims.heard(board, instance, at, alive):
                self._on_alive(board, alive)
            return
        if not self.claims.heard(board, instance, at):
            self.samples_refused += 1
            return
        payload = sample.payload
        if len(payload) > MAX_SAMPLE_BYTES:
            self.oversized += 1
            return
        if kind == "health":
            document = orjson.loads(payload.to_bytes())
            if isinstance(document, dict):
                if isinstance(document.get("renamed_to"), str):
                    self._renamed_by(board, instance, at, batches)
                self._on_health(board, document)
            return
        self.samples_received += 1
        try:
            records = decode_binary(payload.to_bytes())
        except (ValueError, IndexError, UnicodeDecodeError, struct.error):
            self.undecodable += 1
            return
        frames = []
        for record in records:
            info = self._sensor(board, instance, record["sensor_id"], record["kind"])
            if info is None:
                self.unshaped_frames += 1
                continue
            misfit = _misfit(info, record)
            if misfit is not None:
                self.misfit_frames += 1
                self._refuse(board, f"{misfit}, from {instance or 'a service without instance'}: its frames are "
                                    f"dropped ({self.misfit_frames} so far, zenoh.misfit_frames)")
                continue
            frames.append(_frame(info, record, instance, self._restarted(board, instance, info.id)))
        if frames:  # a board is made of frames taken, never of refused ones
            batches.setdefault(board, []).extend(frames)
        self.frames_received += len(records)

    def _restarted(self, board: str, instance: str, sensor_id: int) -> bool:
        """Whether this is the sensor's first frame from an instance that took
        ``board`` over from another (the name passes only once its holder is
        gone: board_claims.py), which is a restart, not a gap."""
        served = self._instances.get(board)
        if served is None or served[0] != instance:
            self._instances[board] = (instance, served is not None, {sensor_id})
            return served is not None
        _, took_over, seen = served
        if sensor_id in seen:
            return False
        seen.add(sensor_id)
        return took_over

    def _renamed_by(self, board: str, instance: str, at: float, batches: dict) -> None:
        """``instance`` renamed ``board``: its frames taken so far go first (the
        gateway then forgets the name), what it sends under it later is dropped."""
        frames = batches.pop(board, None)
        if frames:
            self._deliver(board, frames)
        self._renamed[(board, instance)] = at
        self._drop(board)

    def _sensor(self, board: str, instance: str, sensor_id: int, kind: str) -> SensorInfo | None:
        """The sensor's shape as the board's service ``instance`` announced it
        (asked once, again at most every SHAPES_RETRY_S while a sensor is
        missing; another instance of that name may answer too, with its own)."""
        known = (board, instance)
        info = self._shapes.get(known, {}).get(sensor_id)
        if info is not None and info.kind == kind:
            return info
        if time.monotonic() - self._asked.get(known, -SHAPES_RETRY_S) < SHAPES_RETRY_S:
            return None
        self._asked[known] = time.monotonic()
        # Every service's answer, not one consolidated: the one asked about may not be Zenoh's pick.
        for reply in self.session.get(sensors_key(board), target=zenoh.QueryTarget.ALL,
                                      consolidation=zenoh.ConsolidationMode.NONE, timeout=1.0):
            if reply.ok is not None and len(reply.ok.payload) <= MAX_SAMPLE_BYTES:
                document = orjson.loads(reply.ok.payload.to_bytes())
                if not isinstance(document, dict) or document.get("instance", "") != instance:
                    continue
                self._shapes[known], refused = announced_shapes(document, board)
                self.shapes_refused += len(refused)
                if refused:
                    self._refuse(board, f"{'; '.join(refused)}, announced by {instance or 'a service without instance'}"
                                        f": its frames are dropped (zenoh.unshaped_frames)")
                for old in [k for k in self._shapes if k[0] == board and k != known]:  # a restarted service's
                    del self._shapes[old]
                    self._asked.pop(old, None)
        info = self._shapes.get(known, {}).get(sensor_id)
        return info if info is not None and info.kind == kind else None


def announced_shapes(document: dict, board: str) -> tuple[dict[int, SensorInfo], list[str]]:
    """The sensors a ``tactile/<board>/sensors`` document announces, by id,
    and why each one refused was (a shape or id no frame of the protocol can
    have: the document comes from the network, unauthenticated, and a frame
    is given as many channels as its shape says). Kinds other than grid and
    quad are left out, as a service leaves them out."""
    entries = document.get("sensors")
    if not isinstance(entries, list):
        return {}, [f"a sensors document without a list of sensors ({type(entries).__name__})"]
    shapes: dict[int, SensorInfo] = {}
    refused = []
    for entry in entries:
        info = _announced(entry, board)
        if isinstance(info, str):
            refused.append(info)
        elif info is not None:
            shapes[info.id] = info
    return shapes, refused


def _announced(entry, board: str) -> SensorInfo | str | None:
    """One announced sensor as a SensorInfo, why it is refused, or None (a kind not read here)."""
    if not isinstance(entry, dict):
        return f"no sensor entry: {entry!r:.40}"
    sid, kind, rows, cols = entry.get("id"), entry.get("kind"), entry.get("rows"), entry.get("cols")
    if kind not in ("grid", "quad"):
        return None
    if not _is_int(sid) or not 0 <= sid <= MAX_SENSOR_ID:
        return f"a sensor announced with id {sid!r:.20} (ids are 0..{MAX_SENSOR_ID})"
    shape = f"{rows!r:.20}x{cols!r:.20} {kind}"
    if kind == "quad" and (rows, cols) != (2, 2):
        return f"sensor {sid} announced as a {shape} (a quad is 2x2)"
    if kind == "grid" and not (_is_int(rows) and _is_int(cols) and rows >= 1 and cols >= 1
                               and rows * cols <= MAX_CHANNELS):
        return f"sensor {sid} announced as a {shape}: no frame has that shape (each 1 or more, at most " \
               f"{MAX_CHANNELS} channels)"
    return SensorInfo(sid, kind, rows, cols, board=board)


def _misfit(info: SensorInfo, record: dict) -> str | None:
    """Why ``record`` cannot be a frame of ``info`` (None: it can): a grid's
    forces are one per taxel of its announced shape, a quad's three."""
    expected = info.channels if info.kind == "grid" else QUAD_FORCES
    n = len(record["force_N"])
    if n == expected:
        return None
    return f"sensor {info.id}'s records carry {n} forces where its announced {info.rows}x{info.cols} {info.kind} has " \
           f"{expected}"


def _frame(info: SensorInfo, record: dict, instance: str = "", restart: bool = False) -> ForceFrame:
    """A decoded binary record as the ForceFrame the service ``instance``
    published (raw channels are not in the published encoding); ``restart``:
    flagged board_restart."""
    forces = np.array(record["force_N"], dtype=np.float64)
    sigma = record.get("sigma_N")
    bits = record.get("taxel_flag_bits")
    flags = record["flags"] + ["board_restart"] if restart and "board_restart" not in record["flags"] \
        else record["flags"]
    return ForceFrame(info, record["seq"], record["board_time_us"], record["stamp"], forces,
                      np.full(info.channels, np.nan), flags, REMOTE_LEVEL,
                      taxel_flags=None if bits is None else bits.copy(), calibration=record["calibration"],
                      sigma_N=None if sigma is None else np.array(sigma, dtype=np.float64),
                      t_host_scan=record["scan_stamp"], instance=instance)
