"""The Reconstructor: readings (capacitance) → ForceFrames (forces, σ, flags), per sensor.

Sensors are batched (grids of a level in one call, quads sharing a model in
one call: quad_batch.py), a failing sensor isolated from the others
(isolation.py). Each sensor's SensorCalibration comes from ``calibrations``
(the registry, a recording's own, ``--calibration``: chosen above this
layer) or is the built-in one (sensor_states.py keeps each sensor's
calibration, tare and load cycles).
"""
from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable

import numpy as np

from ..physics.mountings import MOUNTINGS
from ..protocol import FLAG_SATURATED
from ..readings import Reading, SensorInfo
from . import level0
from .baseline import DEFAULT_TARE_FRAMES
from .force_frame import ForceFrame
from .taxel_flags import FLAG_NAMES_BY_BITS, LOADED_AT_TARE, NO_READING
from .grid_full import GridJob, process_full
from .fatigue import update_many
from .isolation import Isolation
from .levels import DEFAULT_LEVEL, LEVELS, SceneConfig, choose_level
from .quad_batch import QuadBatches, QuadPlan
from .sensor_states import Resolver, SensorState, SensorStates

log = logging.getLogger(__name__)
HOLD_READINGS = 20_000  # ~20 MB of readings, and as many frames released at the end; 20 s of a grid at 1 kHz
SLICE_READINGS = 1024  # readings per call at most (~0.5 s of a grid and a quad at 1 kHz)


class Reconstructor(SensorStates):
    """Per-sensor tare and force reconstruction at a fidelity level.

    Live use returns each frame at once; until a sensor's baseline is ready
    its forces are null and flagged ``taring``. With ``hold_until_tared``
    (offline replay) readings are held until their sensor's baseline is ready
    and then released with forces, in arrival order, so no frame of a log
    lacks a value and the export keeps the order of the stream. At most
    HOLD_READINGS are held: a sensor that never completes its tare (it sent
    fewer frames than the window, then stopped) held every other sensor's
    readings behind its own until the end (2.8 GB for 300 s of a grid);
    past the limit the oldest go out, a taring sensor's null and flagged
    ``taring`` as they would live.
    """

    def __init__(self, tare_frames: int = DEFAULT_TARE_FRAMES, hold_until_tared: bool = False,
                 level: str = DEFAULT_LEVEL, mounting: str = "flat", scene: SceneConfig | None = None,
                 clock: Callable[[], float] = time.monotonic, calibrations: Resolver | None = None) -> None:
        """``level="auto"`` takes the cheapest level that meets ``scene``'s
        error budget (see levels.py). ``clock`` (seconds) times the errors
        and paces their log lines. ``calibrations`` gives a sensor's
        calibration when it is first seen (None: the built-in one)."""
        if level not in LEVELS:
            raise ValueError(f"unknown fidelity level {level!r}; known: {', '.join(LEVELS)}")
        if mounting not in MOUNTINGS:
            raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
        self.level_reason = "as configured"
        if level == "auto":
            scene = scene or SceneConfig(mounting=mounting)
            level, self.level_reason = choose_level(scene)
            mounting = scene.mounting
        super().__init__(level, mounting, tare_frames, calibrations)
        self.hold_until_tared = hold_until_tared
        self._held: deque[tuple[SensorState, Reading]] = deque()
        self._isolation = Isolation(self._null_frames, clock, log)
        self._quads = QuadBatches(self.level)
        self._quad_plan: QuadPlan | None = None  # the last read of tared quads, each once: how it went

    def _calibration_applied(self, sensor_id: int) -> None:
        self._isolation.failing.discard(sensor_id)

    def errors(self) -> dict[int, dict]:
        """Per sensor that ever failed, its last error, how often and when (Isolation.errors)."""
        return self._isolation.errors()

    def process(self, reading: Reading) -> list[ForceFrame]:
        return self.process_many([reading])

    def process_many(self, readings: list[Reading]) -> list[ForceFrame]:
        """Reconstruct a batch of readings (e.g. one read from the port), each
        sensor's frames together; returns ForceFrames in arrival order. A
        channel's late zero (it read nothing plausible while its sensor
        tared) completing inside the batch splits it there: the sensor's
        earlier frames had no zero for it, however reads were joined; so
        does the first plausible reading of a sensor whose tare gave it no
        zero at all (a quad: none on one electrode; its window begins again
        there: baseline.py), and a
        sensor's new description (an INFO, which may swap its calibration
        in: sensor_states.py)."""
        pending: list[tuple[SensorState | Exception, Reading]] = []
        taring: list[int] = []  # readings in their sensor's tare window, the one that completes it aside
        out: list[ForceFrame] = []
        sensors = self._sensors
        for reading in readings:
            try:
                state = sensors.get(reading.sensor.id)
                if state is None or state.info is not reading.sensor:  # the usual reading skips the call
                    if state is not None and pending and any(earlier is state for earlier, _ in pending):
                        # A new description (an INFO) may swap its calibration in: its earlier readings first.
                        out += self._batch_done(pending, taring)
                        pending, taring = [], []
                    state = self._state(reading.sensor, reading.board_restart)
                state.last_t_host = reading.t_host
                if pending and state.baseline.changes_zero(reading.capacitance_pF) and \
                        any(earlier is state for earlier, _ in pending):
                    out += self._batch_done(pending, taring)
                    pending, taring = [], []
                zeroless = state.baseline.zeroless
                ready = state.baseline.update(reading.capacitance_pF)
                if zeroless and not state.baseline.zeroless:  # its first plausible reading began its tare (baseline.py)
                    self._window_begun(state, state.judge_tare)
                if ready:
                    if not state.tare_judged:
                        self._judge_tare(state, reading.t_host)
                else:
                    taring.append(len(pending))
            except Exception as exc:  # noqa: BLE001 — isolated: this reading goes out null and flagged
                state = exc
            pending.append((state, reading))
        out += self._batch_done(pending, taring)
        return out

    def _batch_done(self, pending: list[tuple[SensorState | Exception, Reading]], taring: list[int]) -> list[ForceFrame]:
        """The frames of a batch whose baselines are updated (``taring``: its readings in a tare window)."""
        if not self.hold_until_tared:
            return self._reconstruct(pending) if not taring else self._with_taring(pending, taring)
        self._held.extend(pending)
        release, taring = [], []
        while self._held and (isinstance(self._held[0][0], Exception) or self._held[0][0].baseline.ready
                              or len(self._held) > HOLD_READINGS):
            if not isinstance(self._held[0][0], Exception) and not self._held[0][0].baseline.ready:
                taring.append(len(release))
            release.append(self._held.popleft())
        return self._with_taring(release, taring) if taring else self._reconstruct(release)

    def _with_taring(self, pending: list[tuple[SensorState | Exception, Reading]], taring: list[int]) -> list[ForceFrame]:
        """A batch that holds readings of a tare window: those go out null
        and flagged ``taring`` whatever else the batch holds (so a frame's
        forces do not depend on how reads were batched: the live service
        merges reads that waited, a replay feeds them one at a time); the
        rest as usual, all in arrival order."""
        out: list[ForceFrame | None] = [None] * len(pending)
        for i in taring:
            state, reading = pending[i]
            out[i] = self._null_frames(state.info, [reading], "taring")[0]
        skip = set(taring)
        rest = [i for i in range(len(pending)) if i not in skip]
        for i, frame in zip(rest, self._reconstruct([pending[i] for i in rest])):
            out[i] = frame
        return out

    def flush(self) -> list[ForceFrame]:
        """Release every held reading; those of sensors that never completed a
        tare (a log shorter than the tare window) come out null and flagged."""
        frames = self._reconstruct(list(self._held))
        self._held.clear()
        return frames

    def _reconstruct(self, items: list[tuple[SensorState | Exception, Reading]]) -> list[ForceFrame]:
        """The items' frames; more than SLICE_READINGS (an offline replay's
        megabyte reads, a held backlog) go through in slices of that many
        (long arrays leave the caches; the frames are the same either way)."""
        if len(items) > SLICE_READINGS:
            return [frame for start in range(0, len(items), SLICE_READINGS)
                    for frame in self._reconstruct(items[start:start + SLICE_READINGS])]
        plan = self._quad_plan
        if plan is not None and not self._isolation.failing and plan.fits(items):
            try:
                return plan.frames(items)
            except Exception:  # noqa: BLE001 — nothing was changed (QuadPlan.frames): the general path finds the culprit
                self._quad_plan = None
        groups: dict[int, tuple[SensorState, list[int], list[Reading]]] = {}
        out: list[ForceFrame | None] = [None] * len(items)
        for index, (state, reading) in enumerate(items):
            group = groups.get(id(state))
            if group is None:
                if isinstance(state, Exception):  # its baseline or state failed already
                    out[index] = self._isolation.error_frames(reading.sensor, [reading], state)[0]
                    continue
                group = groups[id(state)] = (state, [], [])
            group[1].append(index)
            group[2].append(reading)

        def place(indices, frames):
            for i, frame in zip(indices, frames):
                out[i] = frame

        # Tared sensors of a kind go through one call per step, all sensors'
        # frames together: at 1 kHz the per-call cost, not the per-frame
        # arithmetic, dominates. Quads are batched by model, grids by level;
        # a sensor that failed last time runs alone until it succeeds.
        quads: dict[tuple, list[tuple[SensorState, list[int], list[Reading]]]] = {}
        grids: list[tuple[SensorState, list[int], list[Reading]]] = []
        failing = self._isolation.failing
        for group in groups.values():
            state = group[0]
            if not state.baseline.ready:
                place(group[1], self._null_frames(state.info, group[2], "taring"))
            elif state.info.kind == "quad":
                key = state.processor.batch_key if state.info.id not in failing else ("alone", state.info.id)
                batch = quads.get(key)
                if batch is None:
                    batch = quads[key] = []
                batch.append(group)
            else:
                grids.append(group)
        if grids:
            for (_, indices, _), frames in zip(grids, self._isolated_grids([(state, rs) for state, _, rs in grids])):
                place(indices, frames)
        for batch in quads.values():
            frames = self._isolation.without_state([(state, rs) for state, _, rs in batch], self._quads.frames)
            place((i for _, indices, _ in batch for i in indices), frames)
        self._plan_quads(items, groups, quads)
        return out

    def _plan_quads(self, items: list, groups: dict, quads: dict) -> None:
        """Keep how a read of tared quads went — k scans of the same sensors,
        scan after scan, none failing — for the next such read
        (quad_batch.QuadPlan). A read without tared quads (a read's grids)
        leaves the plan as it is."""
        if not quads:
            return
        self._quad_plan = None
        n = len(groups)
        if len(items) % n or self._isolation.failing or sum(map(len, quads.values())) != n:
            return
        states = [group[0] for group in groups.values()]  # in the order they came
        if any(items[i][0] is not states[i % n] for i in range(len(items))):
            return
        batches = [([indices[0] for _, indices, _ in batch], [state for state, _, _ in batch]) for batch in quads.values()]
        self._quad_plan = QuadPlan(self.level, states, batches)

    def _isolated_grids(self, members: list[tuple[SensorState, list[Reading]]]) -> list[list[ForceFrame]]:
        """Tared grids' frames per sensor. At ``full`` they go through one
        call, with rollback (Isolation.with_rollback). Below ``full`` each
        sensor is its own call anyway, isolated where it is made."""
        if self.level != "full":
            return self._reconstruct_grids(members, isolated=True)
        return self._isolation.with_rollback(members, self._reconstruct_grids)

    def _null_frames(self, info: SensorInfo, readings: list[Reading], flag: str) -> list[ForceFrame]:
        """Frames without forces, flagged ``flag`` (taring, reconstruction_error)."""
        forces = np.full((len(readings), 3 if info.kind == "quad" else info.channels), np.nan)
        state = self._sensors.get(info.id)
        calibration = state.calibration.id if state is not None else ""
        return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, r.frame_flags() + [flag], self.level, None,
                           calibration, None, r.t_host_scan) for r, f in zip(readings, forces)]

    def _reconstruct_grids(self, members: list[tuple[SensorState, list[Reading]]],
                           isolated: bool = False) -> list[list[ForceFrame]]:
        """Tared grids, each with its readings; frames per sensor. Below
        ``full`` each sensor is processed on its own; ``isolated`` then turns
        a sensor's exception into its null, flagged frames."""
        if self.level == "full":
            return self._grids_frames(members, process_full(self._jobs(members)))
        out = []
        for state, rs in members:
            if not isolated:
                out.append(self._grid_frames(state, rs, self._process_grid(state, rs)))
                continue
            try:
                frames = self._grid_frames(state, rs, self._process_grid(state, rs))
            except Exception as exc:  # noqa: BLE001 — isolated: null frames, counted, logged at most once a minute
                frames = self._isolation.error_frames(state.info, rs, exc)
            else:
                if self._isolation.failing:
                    self._isolation.failing.discard(state.info.id)
            out.append(frames)
        return out

    @staticmethod
    def _jobs(members: list[tuple[SensorState, list[Reading]]]) -> list[GridJob]:
        """Each grid's job, its frames and times rows of arrays made once for
        all (once per sensor where the grids differ in size)."""
        if len({state.info.channels for state, _ in members}) > 1:
            return [job for member in members for job in Reconstructor._jobs([member])]
        readings = [r for _, rs in members for r in rs] if len(members) > 1 else members[0][1]
        capacitance = np.array([r.capacitance_pF for r in readings])
        t_s = np.array([r.t_us for r in readings]) * 1e-6
        # A board flag is rare: one look per reading, the mask only where one says a channel clipped.
        flagged = np.array([r.board_flags & FLAG_SATURATED for r in readings], dtype=bool) \
            if any(r.board_flags for r in readings) else None
        jobs, start = [], 0
        for state, rs in members:
            end = start + len(rs)
            jobs.append(GridJob(state.processor, capacitance[start:end], state.baseline.value, state.baseline.std,
                                t_s[start:end], None if flagged is None else
                                level0.clipped(capacitance[start:end], flagged[start:end], state.baseline.value)))
            start = end
        return jobs

    def _process_grid(self, state: SensorState, readings: list[Reading]):
        job = self._jobs([(state, readings)])[0]
        return job.processor.process(job.capacitance, job.baseline, job.baseline_std, job.t_s, job.clipped)

    def _grid_frames(self, state: SensorState, readings: list[Reading], result) -> list[ForceFrame]:
        return self._grids_frames([(state, readings)], [result])[0]

    def _grids_frames(self, members: list[tuple[SensorState, list[Reading]]], results: list) -> list[list[ForceFrame]]:
        """Each grid's frames from its result; their frame flags and load
        cycles found for all sensors together (one call per step, not per sensor)."""
        for (state, _), result in zip(members, results):
            if state.loaded is not None:
                np.bitwise_or(result.taxel_flags, LOADED_AT_TARE, out=result.taxel_flags, where=state.loaded)
        if len(results) == 1:
            forces, taxel_flags, sigma = results[0].forces_N, results[0].taxel_flags, results[0].sigma_N
        else:
            forces, taxel_flags, sigma = (np.concatenate([getattr(r, name) for r in results])
                                          for name in ("forces_N", "taxel_flags", "sigma_N"))
        update_many([state.cycles for state, _ in members], forces, [len(rs) for _, rs in members])
        union = np.bitwise_or.reduce(taxel_flags, axis=1) & ~np.uint8(NO_READING)
        union = union.tolist() if np.count_nonzero(union) else None
        out, i, level, names = [], 0, self.level, FLAG_NAMES_BY_BITS
        for state, readings in members:
            calibration = state.calibration.id
            frames = []
            for r in readings:
                flags = r.frame_flags()
                if union is not None and union[i]:  # "saturated" may be the board's already (a clipped channel)
                    flags.extend([name for name in names[union[i]] if name not in flags] if flags else names[union[i]])
                frames.append(ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, forces[i], r.capacitance_pF, flags, level,
                                         taxel_flags[i], calibration, sigma[i], r.t_host_scan))
                i += 1
            out.append(frames)
        return out
