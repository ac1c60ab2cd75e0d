"""The live service: per board source → readout → pipeline, into one fan-out hub.

``start`` runs on the event loop that serves the API: each board's readout
hands its bytes to the loop (handover.py), its pipeline reconstructs them
there and publishes to the hub and the recorder (board.py). /health is
assembled in health.py.
"""
from __future__ import annotations

import asyncio
import logging
import re
import threading
import time
from functools import partial
from pathlib import Path

from .board import BOARD_NAME, Board, BoardSpec
from .calibration.book import CalibrationBook
from .fanout.hub import Hub
from .health import health_report
from .history import DEFAULT_BUDGET_BYTES, Histories
from .latency import LatencyMeter
from .board_info import UNNAMED_BOARD, name_from_info
from .readout import DEFAULT_SILENCE_S
from .reconstruct import DEFAULT_LEVEL
from .record.recorder import Recorder
from .sched import SliceRequest, current_slice_us, tune_for_latency
from .sources import DEFAULT_SOURCE


log = logging.getLogger(__name__)

CYCLES_SAVE_S = 10.0  # a crash loses at most this much of the load-cycle counts, and zeros this much older
ACTIVE_POLL_S = 2.0  # a calibration activated in the registry by another process is in use within this (board.py)
RECORDING_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,122}\.mcap")


def recording_name(name: str | None) -> str:
    """A bare file name ending in .mcap — letters, digits, '.', '_', '-', at
    most 128 characters, not starting with a dot: nothing a file system could
    read as a directory, a device or a stream — or a timestamped default;
    ValueError naming what is wrong."""
    if name is None:
        return time.strftime("recording-%Y%m%d-%H%M%S.mcap")
    if not RECORDING_NAME.fullmatch(name):
        raise ValueError(f"{name[:130]!r} must be a bare file name ending in .mcap: letters, digits, '.', '_', '-' "
                         f"(not first), at most 128 characters")
    return name


class TactileService:
    """Owns the data path of one or several boards and what they share: the
    fan-out hub, the recorder, the calibration book, the Zenoh publisher."""

    def __init__(self, source: str = DEFAULT_SOURCE, level: str = DEFAULT_LEVEL, mounting: str = "flat",
                 sched_slice_us: int | None = None, recordings_dir: str | Path = "recordings",
                 silence_s: float = DEFAULT_SILENCE_S, calibrations: CalibrationBook | None = None,
                 boards: list[BoardSpec] | None = None, history_budget_bytes: int = DEFAULT_BUDGET_BYTES,
                 grid_batch_s: float = 0.0) -> None:
        """``boards``: the boards to read (default: one, ``source``, named
        from its INFO). ``calibrations``: where sensors' calibrations come
        from and uploads go (default: the registry at its default place,
        calibration/book.py). The history budget is shared equally by the
        boards. ``grid_batch_s``: how long grids may wait to be reconstructed
        with later reads (pipeline.py)."""
        specs = boards or [BoardSpec(source, level=level, mounting=mounting)]
        names = [spec.name for spec in specs if spec.name is not None]
        if len(set(names)) != len(names):
            raise ValueError(f"board names must differ: {sorted(names)}")
        self.recordings_dir = Path(recordings_dir).resolve()
        self.sched_slice_us = sched_slice_us
        self.scheduling = SliceRequest(None, current_slice_us())
        self.calibrations = calibrations if calibrations is not None else CalibrationBook(mounting=mounting)
        share = max(1, history_budget_bytes // len(specs))
        # Filled one by one: a served recording's board names itself from its recorded INFO while it is built
        # (_name_board then reads the boards before it).
        self._boards: list[Board] = []
        for k, spec in enumerate(specs):
            self._boards.append(Board(spec, self.calibrations.with_pinned(list(spec.calibration)) if spec.calibration
                                      else self.calibrations, Histories(share), partial(self._name_board, k),
                                      silence_s, grid_batch_s))
        # Boards without a name until their INFO settles one (never, if it is invalid) must not share
        # ``board``: /health showed one of two, and their sensors' addresses were the same.
        taken = set(names)
        for k, board in enumerate([b for b in self._boards if b.spec.name is None] if len(specs) > 1 else []):
            provisional, n = UNNAMED_BOARD, 2
            while provisional in taken:
                provisional, n = f"{UNNAMED_BOARD}-{n}", n + 1
            board.pipeline.interpreter.unnamed = provisional
            taken.add(provisional)
        self.hub = Hub()
        self.published_latency = LatencyMeter()  # receive stamp → decoded, reconstructed, handed to listeners
        self.started_at = time.time()
        self.recorder: Recorder | None = None
        self.zenoh = None  # a net.zenoh_publisher.ZenohPublisher to attach at start (tactile serve --zenoh)
        self._recording_lock = threading.Lock()  # start and stop come from the API's worker threads
        self._cycles_stop = threading.Event()

    @property
    def all_boards(self) -> list[Board]:
        """Every board, in the order given (named or not yet)."""
        return list(self._boards)

    def board(self, name: str) -> Board | None:
        for board in self._boards:
            if board.name == name:
                return board
        return None

    @property
    def primary(self) -> Board:
        """The first board: the only one of a one-board service."""
        return self._boards[0]

    @property
    def pipeline(self):
        """The first board's pipeline (one-board set-ups and tests)."""
        return self.primary.pipeline

    def _name_board(self, k: int, info: dict) -> str:
        """Bare source ``k``'s name from its first INFO, made unique among the
        boards' names, settled or not yet (``board-2`` until an INFO)."""
        name = name_from_info(info)
        if not BOARD_NAME.fullmatch(name):
            name = f"b{name}"[:32]
        taken = {b.pipeline.interpreter.name for i, b in enumerate(self._boards) if i != k}
        unique, n = name, 2
        while unique in taken:
            unique, n = f"{name[:28]}-{n}", n + 1
        return unique

    def start(self) -> None:
        """On the event loop: tune, wire the listeners, start reading every board."""
        loop = asyncio.get_running_loop()
        self.scheduling = tune_for_latency(self.sched_slice_us)
        for board in self._boards:
            board.pipeline.listeners += [self._measure_published, self.hub.publish]
            board.start(loop)
        self._cycles_stop.clear()
        threading.Thread(target=self._registry_work, name="tactile-registry", daemon=True).start()
        if self.zenoh is not None:
            self.zenoh.attach(self)

    def stop(self) -> None:
        self.stop_recording()
        if self.zenoh is not None:
            self.zenoh.close()
        self._cycles_stop.set()
        for board in self._boards:
            board.stop()
            for listener in (self._measure_published, self.hub.publish):
                if listener in board.pipeline.listeners:
                    board.pipeline.listeners.remove(listener)

    def start_recording(self, name: str | None = None) -> dict:
        """Record the live stream to ``name`` (a bare .mcap file name) in the
        recordings directory, the raw bytes beside it (.bin). ValueError for a
        name that is not a bare .mcap name (with several boards the raw bytes
        are only in the .mcap, one channel per board), FileExistsError for one taken,
        RuntimeError while recording."""
        path = self.recordings_dir / recording_name(name)
        with self._recording_lock:
            if self.recorder is not None and self.recorder.active:
                raise RuntimeError(f"already recording to {self.recorder.path}")
            self.recordings_dir.mkdir(parents=True, exist_ok=True)
            self.recorder = Recorder(path, path.with_suffix(".bin") if len(self._boards) == 1 else None,
                                     exclusive=True)
            for board in self._boards:
                self.recorder.attach(board.pipeline)
            return self.recorder.status()

    def save_cycles(self) -> None:
        for board in self._boards:
            board.save_cycles()
            board.save_zeros()

    def _registry_work(self) -> None:
        """Off the event loop (a registry query takes milliseconds): every
        ACTIVE_POLL_S each board follows its sensors' active calibrations,
        every CYCLES_SAVE_S the load-cycle counts and zeros are kept."""
        saved = time.monotonic()
        while not self._cycles_stop.wait(ACTIVE_POLL_S):
            for board in self._boards:
                board.follow_registry()
            if time.monotonic() - saved >= CYCLES_SAVE_S:
                saved = time.monotonic()
                self.save_cycles()

    def stop_recording(self) -> dict | None:
        with self._recording_lock:
            return None if self.recorder is None else self.recorder.stop()

    async def let_urgent_go_first(self) -> None:
        """Called by a batched client's sender before each send. Twenty
        batched clients flush in the same turn of the loop; a read that
        arrives meanwhile would wait behind all their sends, and so would the
        unbatched clients' frames of it. Instead a read waiting for the loop
        is drained now, and the sender steps back one turn while an unbatched
        client has a message to send."""
        for board in self._boards:
            if board.handover is not None and board.handover.pending:
                board.handover.drain()
        if self.hub.unbatched_due():
            await asyncio.sleep(0)

    def health(self) -> dict:
        return health_report(self)

    def _measure_published(self, frames: list) -> None:
        self.published_latency.add(time.time() - frames[0].t_host)  # frames come in arrival order
