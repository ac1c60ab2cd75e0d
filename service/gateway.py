"""``tactile gateway``: the REST API, WebSocket stream and dashboard for every
board of every host, fed by Zenoh instead of serial ports.

The gateway holds a RemoteBoard per board under ``tactile/`` whose service
declared its liveliness token or sent frames (a health sample alone makes no
board), and publishes their frames to the same fan-out hub as a live
service, so the API's routes serve it unchanged. A board lost (its token
withdrawn, or silent: remote_board.py) is reported lost for
``FORGET_AFTER_S`` and then forgotten, its sensors and history with it
(not while a service refused its name lives: the clash stays reported); a
name its service renamed (a bare board's provisional ``board``, at its first
INFO) is forgotten as soon as the service says so. At most ``MAX_BOARDS``
boards are live at once: a lost one gives its place to a new one, and a
board refused for want of a place is counted and named in /health. It
records nothing and changes nothing on a board: each board's own service
does (its API's mutations answer 409 here, naming the board).
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
from .recent import MostRecent
from .remote_board import RemoteBoard
from .sched import SliceRequest, current_slice_us

MAX_BOARDS = 64
FORGET_AFTER_S = 60.0  # a lost board is reported this long, then forgotten (as a refused service: board_claims.py)
PRUNE_PERIOD_S = 1.0
REFUSED_NAMED = 16  # refused boards named in /health; beyond, the least recently refused is not


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
        self.boards_refused = 0  # samples and tokens of boards refused for want of a place
        self._refused: MostRecent = MostRecent(REFUSED_NAMED)  # board → (times refused, last time), most recent last
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
        self._loop.call_later(PRUNE_PERIOD_S, self._prune_often)

    def stop(self) -> None:
        if self.zenoh is not None:
            self.zenoh.close()

    def health(self) -> dict:
        report = health_report(self)
        now = time.time()
        report["gateway"] = {"boards": len(self._boards), "boards_refused": self.boards_refused,
                             "forget_after_s": FORGET_AFTER_S}
        report["problems"] += [f"board {name}: refused {count} times, the last {now - at:.1f} s ago: this gateway "
                               f"serves at most {self.max_boards} live boards at once (a lost one gives its place)"
                               for name, (count, at) in self._refused.items()]
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

    def _remote(self, name: str, now: float) -> RemoteBoard | None:
        """The board ``name``, made if there is a place: fewer than
        ``max_boards`` are live (a lost one gives its place, the longest lost
        first); None, counted and named, when there is none."""
        board = self._boards.get(name)
        if board is not None:
            return board
        lost = sorted((b.lost_since(now), b.name) for b in self._boards.values() if b.lost(now))
        if len(self._boards) - len(lost) >= self.max_boards:
            self.boards_refused += 1
            count, _ = self._refused.pop(name, (0, now))
            self._refused[name] = (count + 1, now)
            return None
        for _, gone in lost[:max(0, len(self._boards) - self.max_boards + 1)]:
            self._forget(gone, now)
        self._refused.pop(name, None)
        board = self._boards[name] = RemoteBoard(name, Histories(self.history_share),
                                                 publishers=lambda at, n=name: self.claims.report(n, at))
        return board

    def _forget(self, name: str, now: float) -> None:
        """The board, its sensors and history gone from the API; its name free
        for whichever service comes, bar one it refused that still lives."""
        self._boards.pop(name, None)
        self.claims.forget(name, now)
        if self.zenoh is not None:
            self.zenoh.forget(name)

    def _prune(self, now: float) -> None:
        """Forget boards lost for more than FORGET_AFTER_S (but one whose name a
        live service was refused: its clash stays reported), refusals as old,
        and the claims of names that never became a board (a health sample alone)."""
        for board in list(self._boards.values()):
            since = board.lost_since(now)
            if since is not None and now - since > FORGET_AFTER_S and not self.claims.contested(board.name, now):
                self._forget(board.name, now)
        for name in [n for n, (_, at) in self._refused.items() if now - at > FORGET_AFTER_S]:
            del self._refused[name]
        for name in self.claims.prune(now, keep=set(self._boards), after_s=FORGET_AFTER_S):
            if self.zenoh is not None:
                self.zenoh.forget(name)

    def _prune_often(self) -> None:
        self._prune(time.time())
        self._loop.call_later(PRUNE_PERIOD_S, self._prune_often)

    def _receive(self, name: str, frames: list) -> None:
        if not frames:
            return
        now = time.time()
        board = self._remote(name, now)
        if board is None:
            return
        if board.alive is False and (alive := self.claims.liveliness(name)) is not False:
            # The name passed to a successor (board_claims.py) whose token came while it was refused: its
            # liveliness, not its predecessor's withdrawn one, is the board's.
            board.on_alive(alive, now)
        board.receive(frames, now)
        self.published_latency.add(now - frames[0].t_host)
        self.hub.publish(frames)

    def _on_health(self, name: str, document: dict) -> None:
        """A health sample updates a board; it makes none (anyone may put one
        under any name). One saying its board was renamed forgets the old name."""
        if isinstance(document.get("renamed_to"), str):
            self._forget(name, time.time())
            return
        board = self._boards.get(name)
        if board is not None:
            board.on_health(document, time.time())

    def _on_alive(self, name: str, alive: bool) -> None:
        """A token declared makes the board (if there is a place); one withdrawn makes none."""
        now = time.time()
        board = self._remote(name, now) if alive else self._boards.get(name)
        if board is not None:
            board.on_alive(alive, now)
