"""Frames held until the board on a live link has said what it is.

After a link (re)opens, the board on it may be another one (a USB
re-enumeration gives the port to the next board), and after a restart whose
power-up INFO was lost its sensors may be others: until the board's INFO
comes (the reply to the ``INFO?`` the readout sends on connect, or the one
asked at such a restart), the description in force may be another board's
and the zeros another sensor's. ``Identification`` holds the decoded frames
meanwhile. The first INFO frame releases them, to be read after it (under
it, or under the description in force when it is refused as invalid), in
their order; a board that has not answered ``wait_s`` after the first frame
held is read as before, under the description in force. A board that
answers at once costs nothing: its INFO comes before or with its first scans.
Live links (board.py); a recording keeps the state when it began and the
link's events (record/recorder.py), and its replay holds as live did
(``as_recorded``): the same frames, released at the same read.
"""
from __future__ import annotations

import math

from .protocol import Frame, FrameType

Held = list[tuple[list[Frame], float]]  # frames with the receive time of their read, in order


class Identification:
    """Which frames wait for the board's INFO; the pipeline reads the rest."""

    def __init__(self, wait_s: float, timed: bool = True) -> None:
        """``timed`` False (a replay): a hold ends at its INFO, or where the
        recording says its wait passed (``expire``), never by receive times."""
        if not wait_s > 0:
            raise ValueError(f"wait_s must be > 0, got {wait_s}")
        self.wait_s = wait_s
        self.timed = timed
        self._expecting: str | None = "opened"  # why the next frames wait: a link opened (the first connect too), or
        # the board restarted without its INFO
        self._held: Held = []
        self._until: float | None = None  # holding: the receive time from which frames go on unidentified
        self.holds = 0  # holds begun, each one's number (a timer knows whether its hold is still on)
        self.unanswered = 0  # holds that ended without an INFO (their wait passed, or their link dropped)
        self._restarts_seen = 0  # the decoder's restarts_without_info, as last seen

    @classmethod
    def as_recorded(cls, state: dict) -> Identification:
        """A replay's, from ``state`` (``state()`` when the recording began):
        its holds end at their INFO or at the recording's events, whose
        times the live loop's timer decided (no recorded time gives them).
        ValueError naming a ``state`` no recording writes (a recording is any file)."""
        try:
            wait_s, expecting, holding = state["wait_s"], state["expecting"], state["holding"]
        except (KeyError, TypeError):
            raise ValueError(f"the wait's state {state!r} lacks wait_s, expecting or holding") from None
        if expecting not in (None, "opened") or not isinstance(holding, bool) or not isinstance(wait_s, (int, float)):
            raise ValueError(f"the wait's state {state!r} is none a recording writes (wait_s a number, expecting "
                             f"null or \"opened\", holding true or false)")
        identification = cls(wait_s, timed=False)
        identification._expecting = expecting
        if holding:  # the frames held before the recording are not in it: those after it wait as live
            identification._until = math.inf
            identification.holds = 1
        return identification

    def state(self) -> dict:
        """{"wait_s", "expecting": why the next frames will wait, or None,
        "holding": frames wait now}: what a recording begun now replays from."""
        return {"wait_s": self.wait_s, "expecting": self._expecting, "holding": self.holding}

    @property
    def holding(self) -> bool:
        return self._until is not None

    def expect(self) -> None:
        """A link (re)opened: hold its frames from the first until its board's INFO."""
        self._expecting = "opened"

    def wants(self, restarts_without_info: int) -> bool:
        """Whether a read's frames must come here: a hold is on or expected, or
        a restart without INFO was found (one int compared per read otherwise)."""
        return self._expecting is not None or self._until is not None or restarts_without_info != self._restarts_seen

    def take(self, frames: list[Frame], t_host: float, restarts_without_info: int) -> tuple[Held, Held, str | None]:
        """(the frames no hold kept, to read now; those of a hold that ended
        with this read, by its INFO (first) or its wait, to read after them:
        each with its receive time, in order; why a hold began with this
        read: "opened", "restarted", or None). A restart whose INFO was lost
        holds from its first frame on: those before it are the run before,
        read now."""
        now: Held = []
        if restarts_without_info != self._restarts_seen:
            self._restarts_seen = restarts_without_info
            if not self.holding and self._expecting is None:  # else all this read's frames wait already
                cut = next(i for i, frame in enumerate(frames) if frame.board_restart)
                now.append((frames[:cut], t_host))
                frames = frames[cut:]
                self._expecting = "restarted"
        began = self._expecting if frames else None
        if began:
            self._expecting = None
            self._until = t_host + self.wait_s
            self.holds += 1
        if self._until is None:
            return now + [(frames, t_host)], [], None
        self._held.append((frames, t_host))
        if any(frame.type == FrameType.INFO for frame in frames):
            return now, self._release(info_first=True), began
        if self.timed and t_host >= self._until:
            self.unanswered += 1
            return now, self._release(info_first=False), began
        return now, [], began

    def expire(self, hold: int) -> Held:
        """The frames of hold number ``hold``, if it is still on, to be read
        under the description in force (its ``wait_s`` passed without INFO)."""
        if hold != self.holds or not self.holding:
            return []
        self.unanswered += 1
        return self._release(info_first=False)

    def lost(self) -> Held:
        """The link dropped: what it held goes on unidentified, the next link's frames wait for its INFO."""
        held = []
        if self.holding:
            self.unanswered += 1
            held = self._release(info_first=False)
        self._expecting = "opened"
        return held

    def _release(self, info_first: bool) -> Held:
        """Everything held, in order; with ``info_first`` the INFO frames ahead
        of the rest (the data frames are read under the INFO that identified them)."""
        held, self._held, self._until = self._held, [], None
        if not info_first:
            return held
        infos = [(frame, t_host) for frames, t_host in held for frame in frames if frame.type == FrameType.INFO]
        rest = [([frame for frame in frames if frame.type != FrameType.INFO], t_host) for frames, t_host in held]
        return [([frame for frame, _ in infos], infos[-1][1])] + rest
