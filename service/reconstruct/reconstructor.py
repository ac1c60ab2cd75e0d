"""The Reconstructor: readings (capacitance) → ForceFrames (forces + flags), per sensor.

Isolation: a sensor whose reconstruction raises (any exception) gets its
frames of the batch out with null forces and the frame flag
``reconstruction_error``; every other sensor's frames are reconstructed as
if it were absent. Sensors are batched (grids of a level in one call, quads
sharing a model in one call); when a batched call raises, every sensor's
state is rolled back and each is run alone to find the culprit, which then
runs alone until it succeeds again, so a failing sensor costs the others
nothing. ``Reconstructor.errors()`` reports per sensor the last error, how
often and when; the log gets at most one line per sensor per minute.
"""
from __future__ import annotations

import logging
import time
import traceback
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..physics.paper_data import GridCalibration, grid_calibration
from ..physics.quad_model import NOMINAL_C0_PF, QuadModel
from ..physics.mountings import MOUNTINGS
from ..physics.taxel_response import SENSITIVITY_RANGE_PCT_PER_N, table_top, taxel_response
from ..readings import Reading, SensorInfo
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .force_frame import ForceFrame
from .grid import NO_READING, GridJob, GridProcessor, flag_names, process_full
from .level0 import tare_window_pF
from .levels import DEFAULT_LEVEL, LEVELS, SceneConfig, choose_level
from .quad import QuadProcessor

log = logging.getLogger(__name__)

RECONSTRUCTION_ERROR = "reconstruction_error"  # frame flag of a sensor whose reconstruction raised
ERROR_LOG_INTERVAL_S = 60.0  # at most one log line per failing sensor per interval


@dataclass
class _SensorState:
    info: SensorInfo
    baseline: Baseline
    processor: GridProcessor | QuadProcessor


class Reconstructor:
    """Per-sensor tare and force reconstruction at a fidelity level.

    Live use returns each frame at once; until a sensor's baseline is ready
    its forces are null and flagged ``taring``. With ``hold_until_tared``
    (offline replay) readings are held until their sensor's baseline is ready
    and then released with forces, in arrival order, so no frame of a log
    lacks a value and the export keeps the order of the stream.
    """

    def __init__(self, tare_frames: int = DEFAULT_TARE_FRAMES, hold_until_tared: bool = False,
                 level: str = DEFAULT_LEVEL, mounting: str = "flat", scene: SceneConfig | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """``level="auto"`` takes the cheapest level that meets ``scene``'s
        error budget (see levels.py). ``clock`` (seconds) times the errors
        and paces their log lines."""
        if level not in LEVELS:
            raise ValueError(f"unknown fidelity level {level!r}; known: {', '.join(LEVELS)}")
        if mounting not in MOUNTINGS:
            raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
        self.level_reason = "as configured"
        if level == "auto":
            scene = scene or SceneConfig(mounting=mounting)
            level, self.level_reason = choose_level(scene)
            mounting = scene.mounting
        self.level = level
        self.mounting = mounting
        self.tare_frames = tare_frames
        self.hold_until_tared = hold_until_tared
        self._sensors: dict[int, _SensorState] = {}
        self._held: deque[tuple[_SensorState, Reading]] = deque()
        self._uploaded: dict[int, GridCalibration | QuadModel] = {}
        self._clock = clock
        self._errors: dict[int, dict] = {}
        self._failing: set[int] = set()  # sensors whose last attempt raised: they run alone

    def _processor(self, info: SensorInfo) -> GridProcessor | QuadProcessor:
        uploaded = self._uploaded.get(info.id)
        if info.kind == "quad":
            return QuadProcessor(self.level, uploaded) if isinstance(uploaded, QuadModel) else QuadProcessor(self.level)
        calibration = uploaded if isinstance(uploaded, GridCalibration) else grid_calibration(info.rows, info.cols)
        response = None if self.level == "level0" else taxel_response(calibration, self.mounting)
        return GridProcessor(self.level, calibration, response, table_top(self.mounting))

    def _tare_window(self, info: SensorInfo) -> tuple[np.ndarray, np.ndarray]:
        """Readings a tare may take (level0.py): the plausible window around
        the nominal C0 (table 1's; a quad's NOMINAL_C0_PF), widened."""
        if info.kind == "quad":
            uploaded = self._uploaded.get(info.id)
            model = uploaded if isinstance(uploaded, QuadModel) else QuadModel()
            return tare_window_pF(np.full(info.channels, NOMINAL_C0_PF), model.top_relative)
        return tare_window_pF(grid_calibration(info.rows, info.cols).c0_pF, table_top(self.mounting))

    def set_calibration(self, info: SensorInfo, upload: dict) -> dict:
        """Replace a sensor's calibration; ValueError names the bad field and
        why (the API answers 422). The baseline is kept.

        Grid: ``sensitivity_pct_per_N``, one per taxel (rows*cols), each
        finite and within (0.1, 10) %/N (table 1: 1.22–1.27 %/N); the
        per-taxel response built from them must be finite and strictly
        increasing over each taxel's range and its inverse must give the
        forces back within 0.002 N (TaxelResponse.check).

        Quad: ``normal_fit`` [c2, c1] of ΔC/C0 = c2 F² + c1 F and
        ``shear_fit`` [a, b] of ΔC/C0 = a F − b F² (QuadModel.from_fits):
        all finite; c1 and a within (0.001, 1) per N (fits 34/35: 0.0343,
        0.0077); c2 ≤ 0 and b ≥ 0, each small enough that the curve stays
        usable (slope ≥ 10 % of its initial value) to at least 1 N, i.e.
        |c2| ≤ 0.45·c1 and b ≤ 0.45·a; the usable range is 0.9·c1/(2|c2|)
        (0.9·a/(2b)) capped at 50 N, and 50 N for a linear curve (c2 = 0 or
        b = 0, accepted). The model's forward must be finite and strictly
        increasing over the usable ranges and its inverse give the forces
        back (within 1e-6 N + 1e-6 relative).
        """
        if info.kind == "grid":
            try:
                values = np.asarray(upload.get("sensitivity_pct_per_N", []), dtype=float)
            except (TypeError, ValueError):
                raise ValueError("sensitivity_pct_per_N: expected a list of numbers") from None
            if values.shape != (info.channels,):
                raise ValueError(f"sensitivity_pct_per_N: expected {info.channels} values (rows*cols), got {values.size}")
            low, high = SENSITIVITY_RANGE_PCT_PER_N
            bad = np.flatnonzero(~((values > low) & (values < high)))  # NaN fails both
            if bad.size:
                raise ValueError(f"sensitivity_pct_per_N[{bad[0]}] = {values[bad[0]]} is outside ({low:g}, {high:g}) %/N")
            base = grid_calibration(info.rows, info.cols)
            calibration = GridCalibration(info.rows, info.cols, base.c0_pF, values / 100.0)
            try:
                taxel_response(calibration, self.mounting).check()
            except ValueError as exc:
                raise ValueError(f"sensitivity_pct_per_N: {exc}") from None
            uploaded: GridCalibration | QuadModel = calibration
            applied = {"sensitivity_pct_per_N": values.tolist()}
        else:
            if "normal_fit" not in upload or "shear_fit" not in upload:
                raise ValueError("a quad calibration needs normal_fit [c2, c1] and shear_fit [a, b]")
            model = QuadModel.from_fits(upload["normal_fit"], upload["shear_fit"])
            uploaded = model
            c2, c1, _ = model.normal_fit
            applied = {"normal_fit": [c2, c1], "shear_fit": [model.shear_a, model.shear_b],
                       "normal_usable_N": model.normal_usable_N, "shear_usable_N": model.shear_usable_N}
        previous = self._uploaded.get(info.id)
        self._uploaded[info.id] = uploaded
        state = self._sensors.get(info.id)
        if state is not None:
            try:
                processor = self._processor(info)
            except Exception:  # keep the calibration in use
                if previous is None:
                    del self._uploaded[info.id]
                else:
                    self._uploaded[info.id] = previous
                raise
            state.processor = processor
            self._failing.discard(info.id)
        return applied

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or (state.info is not info and state.info != info):
            state = _SensorState(info, Baseline(info.channels, self.tare_frames, self._tare_window(info)), self._processor(info))
            self._sensors[info.id] = state
        return state

    def tare(self, sensor_id: int | None = None) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared."""
        ids = sorted(self._sensors) if sensor_id is None else [sensor_id]
        for sid in ids:
            if sid not in self._sensors:
                raise KeyError(sid)
            self._sensors[sid].baseline.tare()
            if isinstance(self._sensors[sid].processor, GridProcessor):
                self._sensors[sid].processor.reset()
        return ids

    def baseline(self, sensor_id: int) -> np.ndarray | None:
        state = self._sensors.get(sensor_id)
        return None if state is None or not state.baseline.ready else state.baseline.value

    def crosstalk_report(self, sensor_id: int) -> dict | None:
        state = self._sensors.get(sensor_id)
        if state is None or not isinstance(state.processor, GridProcessor) or state.processor.crosstalk is None:
            return None
        processor = state.processor
        return {
            "mechanical_coupling_in_use": processor.crosstalk.mechanical,
            "electrical_leakage_in_use": processor.crosstalk.electrical,
            "isolated_loads_adopted": processor.adopted_events,
            "pending_estimates": processor.estimator.report(),
            "common_mode_drift": processor.drift.drift,
        }

    def errors(self) -> dict[int, dict]:
        """Per sensor that ever failed: ``error`` (the last exception, as
        text), ``where`` (its innermost frame), ``count`` (failed calls),
        ``frames`` (frames sent out null), ``first_s``/``last_s`` (on the
        clock), ``age_s`` (since the last) and ``active`` (its last attempt
        failed)."""
        now = self._clock()
        return {sid: {key: value for key, value in entry.items() if not key.startswith("_")}
                | {"age_s": now - entry["last_s"], "active": sid in self._failing}
                for sid, entry in self._errors.items()}

    def _record_error(self, sensor_id: int, exc: BaseException, frames: int) -> None:
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
        self._failing.add(sensor_id)
        if entry["_logged_s"] is None or now - entry["_logged_s"] >= ERROR_LOG_INTERVAL_S:
            since = entry["count"] - entry["_logged_count"]
            log.warning("sensor %s: reconstruction failed %d time(s) since the last report (%d in all), "
                        "frames sent null: %s (%s)", sensor_id, since, entry["count"], text, where)
            entry["_logged_s"], entry["_logged_count"] = now, entry["count"]

    def _error_frames(self, info: SensorInfo, readings: list[Reading], exc: BaseException) -> list[ForceFrame]:
        self._record_error(info.id, exc, len(readings))
        forces = np.full((len(readings), 3 if info.kind == "quad" else info.channels), np.nan)
        return self._frames(readings, forces, [r.frame_flags() + [RECONSTRUCTION_ERROR] for r in readings], None)

    def process(self, reading: Reading) -> list[ForceFrame]:
        return self.process_many([reading])

    def process_many(self, readings: list[Reading]) -> list[ForceFrame]:
        """Reconstruct a batch of readings (e.g. one read from the port), each
        sensor's frames together; returns ForceFrames in arrival order."""
        pending: list[tuple[_SensorState | Exception, Reading]] = []
        for reading in readings:
            try:
                state = self._state(reading.sensor)
                state.baseline.update(reading.capacitance_pF)
            except Exception as exc:  # noqa: BLE001 — isolated: this reading goes out null and flagged
                state = exc
            pending.append((state, reading))
        if not self.hold_until_tared:
            return self._reconstruct(pending)
        self._held.extend(pending)
        release = []
        while self._held and (isinstance(self._held[0][0], Exception) or self._held[0][0].baseline.ready):
            release.append(self._held.popleft())
        return self._reconstruct(release)

    def flush(self) -> list[ForceFrame]:
        """Release every held reading; those of sensors that never completed a
        tare (a log shorter than the tare window) come out null and flagged."""
        frames = self._reconstruct(list(self._held))
        self._held.clear()
        return frames

    def _reconstruct(self, items: list[tuple[_SensorState | Exception, Reading]]) -> list[ForceFrame]:
        groups: dict[int, tuple[_SensorState, list[int]]] = {}
        out: list[ForceFrame | None] = [None] * len(items)
        for index, (state, reading) in enumerate(items):
            if isinstance(state, Exception):  # its baseline or state failed already
                out[index] = self._error_frames(reading.sensor, [reading], state)[0]
            else:
                groups.setdefault(id(state), (state, []))[1].append(index)

        def place(indices, frames):
            for i, frame in zip(indices, frames):
                out[i] = frame

        # Tared sensors of a kind go through one call per step, all sensors'
        # frames together: at 1 kHz the per-call cost, not the per-frame
        # arithmetic, dominates. Quads are batched by model, grids by level;
        # a sensor that failed last time runs alone until it succeeds.
        quads: dict[tuple, list[tuple[_SensorState, list[int]]]] = {}
        grids: list[tuple[_SensorState, list[int]]] = []
        for state, indices in groups.values():
            if not state.baseline.ready:
                place(indices, self._taring_frames(state, [items[i][1] for i in indices]))
            elif state.info.kind == "quad":
                key = state.processor.batch_key if state.info.id not in self._failing else ("alone", state.info.id)
                quads.setdefault(key, []).append((state, indices))
            else:
                grids.append((state, indices))
        if grids:
            members = [(state, [items[i][1] for i in indices]) for state, indices in grids]
            for (_, indices), frames in zip(grids, self._isolated_grids(members)):
                place(indices, frames)
        for batch in quads.values():
            members = [(state, [items[i][1] for i in indices]) for state, indices in batch]
            place((i for _, indices in batch for i in indices), self._isolated_quads(members))
        return out

    def _isolated_grids(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[list[ForceFrame]]:
        """Tared grids' frames per sensor. At ``full`` they go through one
        call; if it raises, every processor is rolled back and each sensor
        runs alone, so the culprit's frames come out null and flagged and the
        others' exactly as without it. Below ``full`` each sensor is its own
        call anyway, isolated where it is made."""
        if self.level != "full":
            return self._reconstruct_grids(members, isolated=True)
        together = [m for m in members if m[0].info.id not in self._failing] if self._failing else members
        results: dict[int, list[ForceFrame]] = {}
        if len(together) > 1:
            checkpoints = [state.processor.checkpoint() for state, _ in together]
            try:
                frames = self._reconstruct_grids(together)
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
                frames = self._alone(member, lambda m: self._reconstruct_grids([m])[0])
            out.append(frames)
        return out

    def _isolated_quads(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[ForceFrame]:
        """Quads sharing a model, their frames in member order: one call, or
        each alone if it raises (a quad processor keeps no state but caches)."""
        if len(members) > 1:
            try:
                return self._reconstruct_quads(members)
            except Exception:  # noqa: BLE001 — find the culprit below
                pass
        return [frame for member in members for frame in self._alone(member, lambda m: self._reconstruct_quads([m]))]

    def _alone(self, member: tuple[_SensorState, list[Reading]], run) -> list[ForceFrame]:
        state, readings = member
        try:
            frames = run(member)
        except Exception as exc:  # noqa: BLE001 — isolated: null frames, counted, logged at most once a minute
            return self._error_frames(state.info, readings, exc)
        self._failing.discard(state.info.id)
        return frames

    def _taring_frames(self, state: _SensorState, readings: list[Reading]) -> list[ForceFrame]:
        forces = np.full((len(readings), 3 if state.info.kind == "quad" else state.info.channels), np.nan)
        return self._frames(readings, forces, [r.frame_flags() + ["taring"] for r in readings], None)

    def _reconstruct_grids(self, members: list[tuple[_SensorState, list[Reading]]],
                           isolated: bool = False) -> list[list[ForceFrame]]:
        """Tared grids, each with its readings; frames per sensor. Below
        ``full`` each sensor is processed on its own; ``isolated`` then turns
        a sensor's exception into its null, flagged frames."""
        if self.level == "full":
            jobs = [GridJob(state.processor, np.stack([r.capacitance_pF for r in rs]), state.baseline.value,
                            state.baseline.std, np.array([r.t_us * 1e-6 for r in rs])) for state, rs in members]
            return [self._grid_frames(rs, result) for (_, rs), result in zip(members, process_full(jobs))]
        out = []
        for state, rs in members:
            if not isolated:
                out.append(self._grid_frames(rs, self._process_grid(state, rs)))
                continue
            try:
                frames = self._grid_frames(rs, self._process_grid(state, rs))
            except Exception as exc:  # noqa: BLE001 — isolated: null frames, counted, logged at most once a minute
                frames = self._error_frames(state.info, rs, exc)
            else:
                if self._failing:
                    self._failing.discard(state.info.id)
            out.append(frames)
        return out

    @staticmethod
    def _job(state: _SensorState, readings: list[Reading]) -> GridJob:
        return GridJob(state.processor, np.stack([r.capacitance_pF for r in readings]), state.baseline.value,
                       state.baseline.std, np.array([r.t_us * 1e-6 for r in readings]))

    def _process_grid(self, state: _SensorState, readings: list[Reading]):
        job = self._job(state, readings)
        return job.processor.process(job.capacitance, job.baseline, job.baseline_std, job.t_s)

    def _grid_frames(self, readings: list[Reading], result) -> list[ForceFrame]:
        flags = [r.frame_flags() for r in readings]
        union = np.bitwise_or.reduce(result.taxel_flags, axis=1) & ~np.uint8(NO_READING)
        if np.count_nonzero(union):
            for f, bits in zip(flags, union.tolist()):
                f.extend(flag_names(bits))
        return self._frames(readings, result.forces_N, flags, result.taxel_flags)

    def _reconstruct_quads(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[ForceFrame]:
        """Tared quads sharing one model, each with its readings; their
        frames in member order."""
        counts = [len(rs) for _, rs in members]
        readings = [r for _, rs in members for r in rs] if len(members) > 1 else members[0][1]
        capacitance = np.stack([r.capacitance_pF for r in readings])
        baseline = np.repeat(np.stack([state.baseline.value for state, _ in members]), counts, axis=0)
        noise = np.repeat([state.processor.noise(state.baseline.value, state.baseline.std) for state, _ in members], counts)
        forces, quad_flags = members[0][0].processor.process(capacitance, baseline, noise)
        flags = [r.frame_flags() + extra for r, extra in zip(readings, quad_flags)]
        return self._frames(readings, forces, flags, None)

    def _frames(self, readings: list[Reading], forces: np.ndarray, flags: list[list[str]], taxel_flags: np.ndarray | None) -> list[ForceFrame]:
        if taxel_flags is None:
            return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level)
                    for r, f, fl in zip(readings, forces, flags)]
        return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level, tf)
                for r, f, fl, tf in zip(readings, forces, flags, taxel_flags)]
