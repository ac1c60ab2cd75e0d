"""Per-sensor error isolation for the Reconstructor.

A sensor whose reconstruction raises (any exception) gets its frames of the
batch out with null forces and the frame flag ``reconstruction_error``;
every other sensor's frames are reconstructed as if it were absent.
Sensors are batched (grids of a level in one call, quads sharing a model in
one call); when a batched call raises, every sensor's state is rolled back
and each is run alone to find the culprit, which then runs alone until it
succeeds again, so a failing sensor costs the others nothing.
``Isolation.errors()`` reports per sensor the last error, how often and
when; the log gets at most one line per sensor per minute.
"""
from __future__ import annotations

import logging
import traceback
from typing import Callable

from ..readings import Reading, SensorInfo
from .force_frame import ForceFrame

RECONSTRUCTION_ERROR = "reconstruction_error"  # frame flag of a sensor whose reconstruction raised
ERROR_LOG_INTERVAL_S = 60.0  # at most one log line per failing sensor per interval

# A sensor's state (info, baseline, processor) with its readings of the batch.
Member = tuple[object, list[Reading]]
NullFrames = Callable[[SensorInfo, list[Reading], str], list[ForceFrame]]


class Isolation:
    """Which sensors failed, how often and when; runs batches so that a
    failing sensor's frames come out null and flagged and the others' as
    without it. ``null_frames(info, readings, flag)`` makes a failed
    sensor's frames, ``clock`` (seconds) times the errors and paces their
    lines in ``log``."""

    def __init__(self, null_frames: NullFrames, clock: Callable[[], float], log: logging.Logger) -> None:
        self._null_frames = null_frames
        self._clock = clock
        self._log = log
        self._errors: dict[int, dict] = {}
        self.failing: set[int] = set()  # sensors whose last attempt raised: they run alone

    def errors(self) -> dict[int, dict]:
        """Per sensor that ever failed: ``error`` (the last exception, as
        text), ``where`` (its innermost frame), ``count`` (failed calls),
        ``frames`` (frames sent out null), ``first_s``/``last_s`` (on the
        clock), ``age_s`` (since the last) and ``active`` (its last attempt
        failed)."""
        now = self._clock()
        return {sid: {key: value for key, value in entry.items() if not key.startswith("_")}
                | {"age_s": now - entry["last_s"], "active": sid in self.failing}
                for sid, entry in self._errors.items()}

    def error_frames(self, info: SensorInfo, readings: list[Reading], exc: BaseException) -> list[ForceFrame]:
        """The sensor's frames null and flagged ``reconstruction_error``; the error counted and logged."""
        self._record(info.id, exc, len(readings))
        return self._null_frames(info, readings, RECONSTRUCTION_ERROR)

    def _record(self, sensor_id: int, exc: BaseException, frames: int) -> None:
        now = self._clock()
        text = f"{type(exc).__name__}: {exc}"
        last = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ is not None else []
        where = f"{last[0].filename}:{last[0].lineno} in {last[0].name}" if last else ""
        entry = self._errors.get(sensor_id)
        if entry is None:
            entry = self._errors[sensor_id] = {"error": text, "where": where, "count": 0, "frames": 0,
                                               "first_s": now, "last_s": now, "_logged_s": None, "_logged_count": 0}
        entry.update(error=text, where=where, last_s=now)
        entry["count"] += 1
        entry["frames"] += frames
        self.failing.add(sensor_id)
        if entry["_logged_s"] is None or now - entry["_logged_s"] >= ERROR_LOG_INTERVAL_S:
            since = entry["count"] - entry["_logged_count"]
            self._log.warning("sensor %s: reconstruction failed %d time(s) since the last report (%d in all), "
                              "frames sent null: %s (%s)", sensor_id, since, entry["count"], text, where)
            entry["_logged_s"], entry["_logged_count"] = now, entry["count"]

    def with_rollback(self, members: list[Member], run: Callable[[list[Member]], list[list[ForceFrame]]]) \
            -> list[list[ForceFrame]]:
        """Frames per sensor of stateful processors: the sensors not failing
        through one ``run``; if it raises, every processor is rolled back and
        each sensor runs alone, so the culprit's frames come out null and
        flagged and the others' exactly as without it."""
        together = [m for m in members if m[0].info.id not in self.failing] if self.failing else members
        results: dict[int, list[ForceFrame]] = {}
        if len(together) > 1:
            checkpoints = [state.processor.checkpoint() for state, _ in together]
            try:
                frames = run(together)
            except Exception:  # noqa: BLE001 — find the culprit below
                for (state, _), checkpoint in zip(together, checkpoints):
                    state.processor.rollback(checkpoint)
            else:
                if len(together) == len(members):  # the usual case
                    return frames
                results = {id(state): f for (state, _), f in zip(together, frames)}
        out = []
        for member in members:
            frames = results.get(id(member[0]))
            if frames is None:
                frames = self._alone(member, lambda m: run([m])[0])
            out.append(frames)
        return out

    def without_state(self, members: list[Member], run: Callable[[list[Member]], list[ForceFrame]]) -> list[ForceFrame]:
        """Frames in member order of processors that keep no state but
        caches: one ``run``, or each alone if it raises."""
        if len(members) > 1:
            try:
                return run(members)
            except Exception:  # noqa: BLE001 — find the culprit below
                pass
        return [frame for member in members for frame in self._alone(member, lambda m: run([m]))]

    def _alone(self, member: Member, run: Callable[[Member], list[ForceFrame]]) -> list[ForceFrame]:
        """``run(member)``; null, flagged frames if it raises."""
        state, readings = member
        try:
            frames = run(member)
        except Exception as exc:  # noqa: BLE001 — isolated: null frames, counted, logged at most once a minute
            return self.error_frames(state.info, readings, exc)
        self.failing.discard(state.info.id)
        return frames
