"""What a command says on stderr about a board's link (``serve``, ``replay
--serve``, ``record``): a LinkWatcher per board, once per change, and the
readout's own lines for the same events dropped.
"""
from __future__ import annotations

import sys
import threading
import time

_SAYING = threading.Lock()


class LinkWatcher:
    """Says on stderr what a readout's link does, once per change: waiting for
    a source that is not there (once per outage, with the error), connected,
    lost and back within one look, stale (connected, silent), finished (a
    replay's end). ``link`` returns the readout's LinkState (or None before
    there is one); ``poll`` looks once, ``start`` every ``period_s`` from a
    daemon thread. ``board`` returns the board's name, said on each line
    when a service reads several (two `connected to sim://` say nothing)."""

    def __init__(self, link, stale_after_s=lambda: 0.5, out=None, period_s: float = 0.5, board=None) -> None:
        self._link = link
        self._board = board
        self._stale_after_s = stale_after_s
        self._out = out
        self._period_s = period_s
        self._shown: str | None = None
        self._connects = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tactile-link-watcher", daemon=True)

    def say(self, text: str) -> None:
        out = self._out or sys.stderr
        board = f"board {self._board()}: " if self._board is not None else ""
        with _SAYING:  # one line at a time: two boards' watchers ran their lines together
            out.write(f"tactile: {board}{text}\n")
            out.flush()

    def poll(self, now: float | None = None) -> None:
        link = self._link()
        if link is None:
            return
        now = time.time() if now is None else now
        state = link.state(now, self._stale_after_s())
        connects, url = link.connects, link.url
        if connects > self._connects:
            if self._connects and self._shown in ("up", "stale"):  # lost and back between two looks
                self.say(f"link to {url} lost ({link.last_error}); connected again")
            else:
                self.say(f"connected to {url}")
            self._connects = connects
            self._shown = "up"
        if state == "down" and self._shown != "down":
            if link.last_error is None:  # not tried yet
                return
            if self._connects:
                self.say(f"link to {url} lost: {link.last_error}; waiting for it")
            else:
                self.say(f"waiting for {url}: {link.last_error}")
            self._shown = "down"
        elif state == "stale" and self._shown == "up":
            silent = link.silent_s(now)
            self.say(f"no bytes from {url} for {silent:.1f} s (link stale)")
            self._shown = "stale"
        elif state == "up" and self._shown == "stale":
            self.say(f"bytes from {url} again")
            self._shown = "up"
        elif state == "finished" and self._shown != "finished":
            self.say(f"replay of {url} finished (the service keeps serving; Ctrl-C to stop)")
            self._shown = "finished"

    def start(self) -> "LinkWatcher":
        self._thread.start()
        return self

    def stop(self, final_look: bool = True) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2)
        if final_look:  # what happened since the last look
            self.poll()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            try:
                self.poll()
            except Exception as exc:  # a watcher must never take the command down
                self.say(f"link watcher failed: {exc!r}")
                return


def quiet_readout_transitions() -> None:
    """The LinkWatcher says when the link comes up or is lost; drop the readout's
    own log lines for those two events, keep its others (asking INFO?, …)."""
    import logging

    logger = logging.getLogger("service.readout")
    if _drop_transitions not in logger.filters:
        logger.addFilter(_drop_transitions)


def _drop_transitions(record) -> bool:
    return not str(record.msg).startswith(("connected to ", "link to "))
