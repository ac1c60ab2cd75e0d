"""Which service a ZenohClient follows under each board name, and telling its user.

The gateway's rule (board_claims.BoardClaims): the first instance heard
under a name, by its liveliness token or a sample, is followed; the
samples of other instances publishing that name are dropped and counted.
A sample without an attachment comes from a service older than instances,
the instance "" (as in the gateway). One difference: when the followed
instance is gone (token withdrawn, or silent for ``LOST_AFTER_S``), one
still alive takes the name (``hand_over``), and the user is told.

Told through the ``service.client_zenoh`` logger: a warning once per clash
naming the board and both instances, a warning when the client moves to a
service that clashed (another sensor, maybe), and an info line when it
moves to one that did not (a restarted service).
"""
from __future__ import annotations

import logging
import threading
import time

from .board_claims import ADVICE, LOST_AFTER_S, BoardClaims

log = logging.getLogger("service.client_zenoh")


def named(instance: str) -> str:
    return instance or "a service older than instance ids (no attachment)"


class Following:
    """Thread-safe: Zenoh calls ``admit`` on its own threads."""

    def __init__(self) -> None:
        self.claims = BoardClaims(hand_over=True)
        self._lock = threading.Lock()  # one board's followed instance and warnings change together
        self._followed: dict[str, str] = {}
        self._clashing: set[tuple[str, str]] = set()  # (board, instance) told as clashing

    def admit(self, board: str, instance: str, alive: bool | None = None) -> bool:
        """A sample (``alive`` None) or a liveliness change of ``instance``
        under ``board``: True when it is the instance followed."""
        now = time.monotonic()
        with self._lock:
            followed = self.claims.heard(board, instance, now, alive)
            holder = self.claims.holder(board)
            before = self._followed.get(board)
            if holder is not None and holder != before:
                self._followed[board] = holder
                if before is not None:
                    self._moved(board, before, holder, now)
            if not followed and alive is not False and (board, instance) not in self._clashing:
                self._clashing.add((board, instance))
                log.warning("board %s is published by two services: following %s, dropping the frames and health "
                            "of %s (ZenohClient.clashes() counts them): %s", board, named(holder), named(instance),
                            ADVICE)
            return followed

    def _moved(self, board: str, before: str, holder: str, now: float) -> None:
        gone = next((p for p in self.claims.report(board, now)["publishers"] if p["instance"] == before), None)
        why = ("its liveliness token went" if gone is not None and gone["alive"] is False
               else f"nothing heard for {LOST_AFTER_S} s")
        if (board, holder) in self._clashing:
            log.warning("board %s: following %s now, %s having gone (%s); its frames are another service's, of "
                        "another sensor maybe", board, named(holder), named(before), why)
        else:
            log.info("board %s: following %s now, %s having gone (%s): a restarted service",
                     board, named(holder), named(before), why)

    def followed(self, board: str) -> str | None:
        return self.claims.holder(board)

    def clashes(self) -> dict[str, dict]:
        """Each board published by another live (or lately gone) service
        besides the one followed: board_claims' report (``publisher`` the
        instance followed; ``publishers`` each with ``samples_refused``,
        the samples dropped; ``problems`` naming both instances)."""
        now = time.monotonic()
        with self._lock:
            boards = list(self._followed)
        reports = {board: self.claims.report(board, now) for board in boards}
        return {board: report for board, report in reports.items() if report["problems"]}
