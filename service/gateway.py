"""``tactile gateway``: the REST API, WebSocket stream and dashboard for every
board of every host, fed by Zenoh instead of serial ports.

The gateway holds a RemoteBoard per board heard under ``tactile/`` (up to
``MAX_BOARDS``; more are counted and ignored) and publishes their frames to
the same fan-out hub as a live service, so the API's routes serve it
unchanged. It records nothing and changes nothing on a board: each board's
own service does (its API's mutations answer 409 here, naming the board).
Two services publishing one board name are not merged: the first heard is
served, the other refused and the clash reported (net/board_claims.py).
"""
from __future__ import annotations

import asyncio
import time

from .fanout.hub import Hub
from .health import health_report
from .history import DEFAULT_BUDGET_BYTES, Histories
from .latency import LatencyMeter
from .net.board_claims import BoardClaims
from .remote_board import RemoteBoard
from .sched import SliceRequest, current_slice_us

MAX_BOARDS = 64


class GatewayService:
    def __init__(self, config, history_budget_bytes: int = DEFAULT_BUDGET_BYTES, max_boards: int = MAX_BOARDS) -> None:
        """``config``: the zenoh.Config of the gateway's session (opened at start)."""
        self.config = config
        self.max_boards = max_boards
        self.history_share = max(1, history_budget_bytes // max_boards)
        self.hub = Hub()
        self.published_latency = LatencyMeter()  # the remote receive stamp → handed to the gateway's clients
        self.started_at = time.time()
        self.scheduling = SliceRequest(None, current_slice_us())
        self.recorder = None
        self.calibrations = None
        self.zenoh = None  # the ZenohFeed, from start
        self.boards_refused = 0
        self.claims = BoardClaims()  # which service each board name is served from
        self._boards: dict[str, RemoteBoard] = {}
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def all_boards(self) -> list[RemoteBoard]:
        return [self._boards[name] for name in sorted(self._boards)]

    def board(self, name: str) -> RemoteBoard | None:
        return self._boards.get(name)

    def start(self) -> None:
        """On the event loop: open the session and subscribe."""
        from .net.zenoh_feed import ZenohFeed

        self._loop = asyncio.get_running_loop()
        post = self._loop.call_soon_threadsafe
        self.zenoh = ZenohFeed(self.config, deliver=lambda board, frames: post(self._receive, board, frames),
                               on_health=lambda board, doc: post(self._on_health, board, doc),
                               on_alive=lambda board, alive: post(self._on_alive, board, alive),
                               claims=self.claims).start()

    def stop(self) -> None:
        if self.zenoh is not None:
            self.zenoh.close()

    def health(self) -> dict:
        report = health_report(self)
        report["gateway"] = {"boards": len(self._boards), "boards_refused": self.boards_refused}
        if self.zenoh is not None:
            report["problems"] += self.zenoh.problems(time.monotonic())
        report["status"] = "degraded" if report["problems"] else "ok"
        return report

    def start_recording(self, name: str | None = None) -> dict:
        raise RuntimeError("a gateway records nothing: record on each board's service (its POST /record/start)")

    def stop_recording(self) -> None:
        return None

    async def let_urgent_go_first(self) -> None:
        """As the live service's: an unbatched client's message goes before a batched send."""
        if self.hub.unbatched_due():
            await asyncio.sleep(0)

    def _remote(self, name: str) -> RemoteBoard | None:
        board = self._boards.get(name)
        if board is None:
            if len(self._boards) >= self.max_boards:
                self.boards_refused += 1
                return None
            board = self._boards[name] = RemoteBoard(name, Histories(self.history_share),
                                                     publishers=lambda now, n=name: self.claims.report(n, now))
        return board

    def _receive(self, name: str, frames: list) -> None:
        board = self._remote(name)
        if board is None or not frames:
            return
        now = time.time()
        board.receive(frames, now)
        self.published_latency.add(now - frames[0].t_host)
        self.hub.publish(frames)

    def _on_health(self, name: str, document: dict) -> None:
        board = self._remote(name)
        if board is not None:
            board.on_health(document, time.time())

    def _on_alive(self, name: str, alive: bool) -> None:
        board = self._remote(name)
        if board is not None:
            board.on_alive(alive, time.time())
