"""Which service a gateway serves each board name from.

Board names are chosen per service (``--source NAME=URL``), so two services,
on two hosts or one, may publish the same name. Merged, one address would
carry frames alternating between two physical sensors, and either service's
death would hide behind the other's liveliness. A gateway instead serves one
publishing instance per name, the first it hears, and refuses the others'
frames and health for as long as they live, reporting the clash in /health.

The name passes to another instance only once its holder is gone (its
liveliness token withdrawn, or nothing heard for ``LOST_AFTER_S``): a
restarted service. An instance that was refused is never given it: a
clashing service does not slip in, unannounced, when the other one stops —
unless it is on the holder's host and was first heard after the holder's
last sample (``SUCCESSION_SLACK_S`` allowed for samples in flight): the
holder restarted, the new process heard before the old one was declared
gone (its token withdrawn late: a lease expiring, a link blip).
A refused instance that went is still reported for ``FORGET_GONE_S``.

A ZenohClient (``hand_over=True``) differs in one thing: once the holder is
gone, a refused instance still alive may take the name. Its user is told
(a warning naming both instances), and a controller left without frames
would stop, where a gateway's users read the clash in its /health.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

LOST_AFTER_S = 2.5  # as a RemoteBoard's: health comes every second
FORGET_GONE_S = 60.0
SUCCESSION_SLACK_S = 0.25  # a holder's last samples may arrive after its successor's first
MAX_PUBLISHERS = 16  # per name; beyond, the least recently heard refused one is forgotten
ADVICE = "give each board a unique name (--source NAME=URL, --board-name, or name in robot.toml)"


@dataclass
class Publisher:
    instance: str  # host:pid:random (zenoh_config.instance_id); "" for a service from before instances
    heard_at: float
    first_heard: float
    alive: bool | None = None  # its liveliness token; None: not heard
    gone_at: float | None = None
    refused: bool = False
    samples_refused: int = 0

    def gone_since(self, now: float) -> float | None:
        if self.alive is False:
            return self.gone_at
        return None if now - self.heard_at <= LOST_AFTER_S else self.heard_at


class BoardClaims:
    """Thread-safe: the gateway's Zenoh thread asks ``heard``, its event loop ``report``."""

    def __init__(self, hand_over: bool = False) -> None:
        self.hand_over = hand_over
        self._lock = threading.Lock()
        self._publishers: dict[str, dict[str, Publisher]] = {}  # board → instance → publisher
        self._holders: dict[str, str] = {}  # board → the instance served

    def heard(self, board: str, instance: str, now: float, alive: bool | None = None) -> bool:
        """A sample (``alive`` None) or a liveliness change of ``instance``
        under ``board``: True when it is the instance served (after taking
        the name, if it was free)."""
        with self._lock:
            publishers = self._publishers.setdefault(board, {})
            publisher = publishers.get(instance)
            if publisher is None:
                if alive is False:
                    return False  # the token of one never heard went: nothing to tell
                publisher = publishers[instance] = Publisher(instance, now, now)
                self._forget(board, publishers, now)
            if alive is None or alive:
                publisher.heard_at = now
            if alive is not None:
                publisher.alive, publisher.gone_at = alive, None if alive else now
            if self._holders.get(board) == instance:
                return True
            holder = publishers.get(self._holders.get(board))
            gone = None if holder is None else holder.gone_since(now)
            successor = (gone is not None and publisher.alive is not False and _host(holder.instance) == _host(instance)
                         and holder.heard_at <= publisher.first_heard + SUCCESSION_SLACK_S)
            may_hold = not publisher.refused or successor or (self.hand_over and publisher.alive is not False)
            if may_hold and alive is not False and (holder is None or gone is not None):
                self._holders[board] = instance
                publisher.refused = False
                return True
            publisher.refused = True
            if alive is None:
                publisher.samples_refused += 1
            return False

    def holder(self, board: str) -> str | None:
        """The instance served under ``board`` (None: none heard yet)."""
        with self._lock:
            return self._holders.get(board)

    def liveliness(self, board: str) -> bool | None:
        """The token of the instance served under ``board``: True declared,
        False withdrawn, None not heard (or none served)."""
        with self._lock:
            holder = self._publishers.get(board, {}).get(self._holders.get(board))
            return None if holder is None else holder.alive

    def report(self, board: str, now: float) -> dict:
        """The board's ``publisher`` (the instance served), ``publishers``
        (each with whether it is served, alive and how many samples were
        refused) and ``problems`` (each clash, naming both instances)."""
        with self._lock:
            self._forget(board, self._publishers.get(board, {}), now)
            publishers = list(self._publishers.get(board, {}).values())
            holder = self._holders.get(board)
        problems = []
        for p in publishers:
            if not p.refused:
                continue
            gone = p.gone_since(now)
            clash = (f"name clash: board {board} is published by two services, {holder} (served) and {p.instance} "
                     f"(refused, {p.samples_refused} samples ignored)")
            if gone is not None:
                why = "its liveliness token went" if p.alive is False else f"nothing heard for {LOST_AFTER_S} s"
                clash += f"; {p.instance} is gone ({why}, {now - gone:.1f} s ago)"
            problems.append(f"{clash}: {ADVICE}")
        return {"publisher": holder, "problems": problems, "publishers": [
            {"instance": p.instance, "served": p.instance == holder, "alive": p.alive,
             "last_heard_age_s": round(now - p.heard_at, 3),
             "gone_for_s": None if p.gone_since(now) is None else round(now - p.gone_since(now), 3),
             "samples_refused": p.samples_refused} for p in publishers]}

    def forget(self, board: str, now: float) -> None:
        """The gateway forgot ``board`` (lost for long, or renamed by its
        service): its holder and the publishers gone go; a refused one still
        alive stays, refused, so that it never takes the name it was refused."""
        with self._lock:
            publishers = self._publishers.get(board, {})
            holder = self._holders.pop(board, None)
            for p in list(publishers.values()):
                if p.instance == holder or not p.refused or p.gone_since(now) is not None:
                    del publishers[p.instance]
            if not publishers:
                self._publishers.pop(board, None)

    def contested(self, board: str, now: float) -> bool:
        """Whether a service refused ``board`` still lives (its clash is still to be reported)."""
        with self._lock:
            return any(p.refused and p.gone_since(now) is None for p in self._publishers.get(board, {}).values())

    def prune(self, now: float, keep: set[str], after_s: float) -> list[str]:
        """Forget the names outside ``keep`` whose publishers are all gone for
        more than ``after_s`` (a name heard once, in a health sample, that
        never became a board); the names forgotten."""
        with self._lock:
            stale = [board for board, publishers in self._publishers.items() if board not in keep and all(
                (gone := p.gone_since(now)) is not None and now - gone > after_s for p in publishers.values())]
            for board in stale:
                del self._publishers[board]
                self._holders.pop(board, None)
        return stale

    def _forget(self, board: str, publishers: dict[str, Publisher], now: float) -> None:
        """Refused publishers gone for FORGET_GONE_S, and the least recently
        heard beyond MAX_PUBLISHERS (never the one served)."""
        holder = self._holders.get(board)
        for p in list(publishers.values()):
            gone = p.gone_since(now)
            if p.instance != holder and gone is not None and now - gone > FORGET_GONE_S:
                del publishers[p.instance]
        others = sorted((p for p in publishers.values() if p.instance != holder), key=lambda p: p.heard_at)
        for p in others[:max(0, len(publishers) - MAX_PUBLISHERS)]:
            del publishers[p.instance]


def _host(instance: str) -> str:
    """The host part of an instance id (zenoh_config.instance_id: host:pid:random)."""
    return instance.split(":", 1)[0]
