"""The live quads' plan (quad_batch.QuadPlan) against the general path, sensor by sensor.

Reads go through the plan once it is made (one scan each, or several that
piled up); the reference is each quad alone, with no plan, its frames of a
read together (a read that piled up takes one fatigue factor for its
frames, as the batched path always has, where frame by frame a cycle
counted mid-read would move it). Bit for bit, through what changes a
plan's basis: different calibrations (two batches), a tare and a new
calibration mid-stream, load cycles that move the fatigue factor, sentinel
and implausible channels (null and flagged, never a number), and quads
that start failing mid-stream (their frames null and flagged, the others
as without them).
"""
import numpy as np
import pytest

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimQuad
from service.protocol_decoder import Decoder
from service.interpreter import Interpreter
from service.readings import Reading
from service.reconstruct import Reconstructor
from service.reconstruct.quad_batch import QuadPlan

QUADS = range(6)
TARE_AT, CALIBRATE_AT, FAIL_AT = 400, 700, 1100  # read numbers
STUCK_SEQS = range(500, 640)  # quad 3's electrode 2 repeats one count: stale from seq 550 (its 50th repeat)
RELEASE_FROM_SEQ = 1300  # quad 0 lets go of the scene's load every other 40 frames from here (load cycles)


def _boom(*_args, **_kwargs):
    raise RuntimeError("boom")


def _with(r: Reading, capacitance: np.ndarray, opened: bool = False) -> Reading:
    return Reading(r.sensor, r.seq, r.t_us, r.t_host, r.board_flags, r.gap, capacitance, opened, r.shorted_channel)


def _faulty(r: Reading) -> Reading:
    """Quad 1 now and then: an open channel (NaN), an implausible one (1 aF) or a top count;
    quad 3's electrode 2 latched for a while (stale)."""
    if r.sensor.id == 3 and r.seq in STUCK_SEQS:
        c = r.capacitance_pF.copy()
        c[2] = 2.31
        return _with(r, c)
    if r.sensor.id != 1 or r.seq % 37 not in (5, 6, 7):
        return r
    c = r.capacitance_pF.copy()
    kind = r.seq % 37
    c[kind % 4] = np.nan if kind == 5 else (1e-6 if kind == 6 else 4294.967294)
    return _with(r, c, opened=kind == 5)


@pytest.fixture(scope="module")
def reads():
    data, _ = capture(BoardConfig(sensors=[SimQuad(i) for i in QUADS], scene="demo", seed=9), 1.8)
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [_faulty(r) for r in (interpreter.interpret(f, 0.0) for f in Decoder().feed(data)) if r is not None]
    unloaded = {r.seq: r.capacitance_pF for r in readings if r.sensor.id == 0 and r.seq < RELEASE_FROM_SEQ}
    readings = [_with(r, unloaded[r.seq - 1000]) if r.sensor.id == 0 and r.seq >= RELEASE_FROM_SEQ and r.seq // 40 % 2
                else r for r in readings]
    scans: dict[int, list[Reading]] = {}
    for r in readings:
        scans.setdefault(r.t_us, []).append(r)
    scans = list(scans.values())
    rng = np.random.default_rng(4)
    out, i = [], 0
    while i < len(scans):
        n = int(rng.choice([1, 2, 3], p=[0.8, 0.1, 0.1]))  # reads that piled up: several scans
        out.append([r for scan in scans[i:i + n] for r in scan])
        i += n
    return out


def _run(reads, alone=None, fail=False, monkeypatch=None):
    """Frames by (sensor, seq), the reconstructor, and how many reads the
    plan made. ``alone``: only that quad, no plan."""
    infos = {r.sensor.id: r.sensor for read in reads for r in read}
    rec = Reconstructor(level="full", clock=lambda: 0.0)
    if alone is not None:
        rec._plan_quads = lambda *_: None
    for sid in (2, 3):
        rec.set_calibration(infos[sid], {"normal_fit": [-0.0008, 0.031], "shear_fit": [0.0075, 0.0004]})
    planned = []
    original = QuadPlan.frames
    monkeypatch.setattr(QuadPlan, "frames",
                        lambda plan, items: planned.append(len(items) // len(plan.states)) or original(plan, items))
    frames = {}
    for k, read in enumerate(reads):
        if k == TARE_AT and 5 in rec._sensors:
            rec.tare(5)
        if k == CALIBRATE_AT and 4 in rec._sensors:
            rec.set_calibration(infos[4], {"normal_fit": [-0.0007, 0.033], "shear_fit": [0.0078, 0.0004]})
        if fail and k == FAIL_AT:  # quad 2's processor (its batch's first) and quad 4's tare fail from here on
            rec._sensors[2].processor.sigma = _boom
            rec._sensors[4].baseline.update = _boom
        batches = [read] if alone is None else [[r for r in read if r.sensor.id == alone]]
        for batch in batches:
            for frame in rec.process_many(batch):
                frames[(frame.sensor.id, frame.seq)] = frame
    return frames, rec, planned


def _assert_same(a, b):
    np.testing.assert_array_equal(a.forces_N, b.forces_N)
    np.testing.assert_array_equal(a.sigma_N, b.sigma_N)
    np.testing.assert_array_equal(a.capacitance_pF, b.capacitance_pF)
    assert (a.flags, a.seq, a.t_us, a.level) == (b.flags, b.seq, b.t_us, b.level)


def test_planned_reads_give_each_quad_what_it_gets_alone(reads, monkeypatch):
    together, rec, planned = _run(reads, monkeypatch=monkeypatch)
    assert len(planned) > 0.7 * len(reads) and {2, 3} <= set(planned)  # the usual way, also for several scans
    for sid in QUADS:
        alone, reference, unplanned = _run(reads, alone=sid, monkeypatch=monkeypatch)
        assert not unplanned
        assert len(alone) == len([key for key in together if key[0] == sid])
        for key, frame in alone.items():
            _assert_same(together[key], frame)
        assert rec.cycle_counts()[sid][2] == reference.cycle_counts()[sid][2]
    assert sum(rec.cycle_counts()[0][2]) > 0, "the release counted load cycles (the fatigue factor moved)"
    flagged = [f for (sid, _), f in together.items() if sid == 1 and ("out_of_range" in f.flags or "open_channel" in f.flags)]
    assert flagged and all(np.isnan(f.forces_N).all() for f in flagged)
    stale = sorted(seq for (sid, seq), f in together.items() if "stale" in f.flags)
    assert stale == list(range(STUCK_SEQS.start + 50, STUCK_SEQS.stop))
    assert all(np.isnan(together[(3, seq)].forces_N).all() for seq in stale)
    assert sum("taring" in f.flags for (sid, _), f in together.items() if sid == 5) == 2 * 99  # start-up and the tare (the last reading of each has forces)


def test_quads_failing_mid_stream_leave_the_others_as_alone(reads, monkeypatch):
    together, rec, planned = _run(reads, fail=True, monkeypatch=monkeypatch)
    assert len(planned) > 0.5 * len(reads)  # until the failures
    for sid in (0, 1, 3, 5):
        alone, reference, _ = _run(reads, alone=sid, monkeypatch=monkeypatch)
        for key, frame in alone.items():
            _assert_same(together[key], frame)
        counter, own = rec._sensors[sid].cycles, reference._sensors[sid].cycles  # a failed plan counted nothing twice
        assert counter.counts.tolist() == own.counts.tolist() and counter._armed.tolist() == own._armed.tolist()
    for sid in (2, 4):
        late = [f for (s, _), f in together.items() if s == sid and "reconstruction_error" in f.flags]
        assert late and all(np.isnan(f.forces_N).all() for f in late)
        first = min(f.seq for f in late)
        assert all("reconstruction_error" in f.flags for (s, seq), f in together.items() if s == sid and seq >= first)
    assert set(rec.errors()) == {2, 4}


def test_a_plan_that_raises_has_counted_no_load_cycle(reads, monkeypatch):
    """QuadPlan.frames computes every batch before counting any load cycle:
    when a later batch raises, the general path that takes over counts the
    read once, not the earlier batches twice."""
    rec = Reconstructor(level="full", clock=lambda: 0.0)
    infos = {r.sensor.id: r.sensor for read in reads for r in read}
    for sid in (2, 3):
        rec.set_calibration(infos[sid], {"normal_fit": [-0.0008, 0.031], "shear_fit": [0.0075, 0.0004]})
    for read in reads[:300]:
        rec.process_many(read)
    plan = rec._quad_plan
    assert plan is not None and len(plan.batches) == 2
    items = [(rec._sensors[r.sensor.id], r) for r in reads[300]]
    assert plan.fits(items)
    from service.reconstruct import quad_batch

    counted = []
    monkeypatch.setattr(quad_batch, "update_many", lambda counters, *_: counted.extend(counters))
    monkeypatch.setattr(plan.batches[-1].processor, "process", _boom)
    with pytest.raises(RuntimeError, match="boom"):
        plan.frames(items)
    assert counted == []  # no counter was stepped before the failure


def test_a_quads_forces_do_not_depend_on_how_its_frames_were_batched_through_load_cycles(reads):
    """Load cycles move a quad's fatigue factor; within a call the factor was
    the count's at the call's start, so a read that piled up, a 1 024-frame
    replay slice and frame-by-frame differed after each cycle (a replay could
    not join recorded reads). Now each frame gets the factor of the count
    before it, however the frames are batched: bit for bit."""
    scans = [[r] for read in reads for r in read]  # frame by frame
    everything = [[r for read in reads for r in read]]  # one call (sliced at 1 024 readings)

    def run(batches):
        rec = Reconstructor(level="full", clock=lambda: 0.0)
        return rec, {(f.sensor.id, f.seq): f for batch in batches for f in rec.process_many(batch)}

    one_by_one, alone = run(scans)
    for batches in (reads, everything):
        other, together = run(batches)
        assert together.keys() == alone.keys()
        for key, frame in alone.items():
            _assert_same(together[key], frame)
        assert other.cycle_counts()[0][2] == one_by_one.cycle_counts()[0][2]
    assert sum(one_by_one.cycle_counts()[0][2]) > 5, "load cycles were counted (the factor moved)"


def test_a_quads_sigma_carries_half_its_fatigue_compensation_and_none_for_an_axis_held_at_its_end():
    """A quad that does not fatigue, compensated by the paper's loss after
    2 500 cycles, read 8 N as 11.24 ± 0.79 N (z 4). The compensation is one
    sensor's: half of it is now σ. An axis held at its usable end (a lower
    bound) had a σ (0.85 N), a grid's saturated force none: now none."""
    from service.readings import SensorInfo
    from service.reconstruct.calibration_upload import processor_for
    from service.reconstruct.quad import FATIGUE_SIGMA_SHARE
    from service.reconstruct.sensor_calibration import builtin

    info = SensorInfo(1, "quad", 2, 2)
    processor = processor_for(info, "full", "flat", builtin(info))
    forces = np.array([[1.0, -0.5, 3.0], [0.0, 0.0, 2.0]])
    fresh = processor.sigma(forces, 1e-4)
    worn = processor.sigma(forces, 1e-4, np.array([0.8, 1.0]))
    extra = forces[0] * FATIGUE_SIGMA_SHARE * (1 / 0.8 - 1)
    assert worn[0] ** 2 - fresh[0] ** 2 == pytest.approx(extra ** 2, rel=1e-9)
    assert np.array_equal(worn[1], fresh[1])
    model = processor.model
    held = processor.sigma(np.array([[model.shear_usable_N, 1.0, model.normal_usable_N]]), 1e-4)
    assert np.isnan(held[0, 0]) and np.isnan(held[0, 2]) and np.isfinite(held[0, 1])


def test_a_quad_frame_with_an_electrode_clipped_at_the_converters_top_has_no_forces_and_is_not_stale():
    """One electrode pinned at the converter's top (the frame's SATURATED
    flag) is a lower bound that skews all three forces: they were numbers
    with a σ, then the electrode was called stale. Now the frame has none,
    flagged saturated by the board, and the electrode is never stale."""
    from service.physics.quad_model import NOMINAL_C0_PF
    from service.pipeline import Pipeline
    from service.protocol import FLAG_SATURATED, FrameType, encode_frame
    from service.reconstruct import Reconstructor

    rng = np.random.default_rng(6)
    frames = []
    for k in range(400):
        raw = np.round(NOMINAL_C0_PF * (1 + rng.normal(0, 2e-4, 4)) * 1e6).astype(np.int64)
        clip = 200 <= k < 330
        if clip:
            raw[0] = 4_000_000  # 4 pF: the converter's top here
        frames.append(encode_frame(FrameType.QUAD, 1, k, 1000 * (k + 1), raw.astype("<u4").tobytes(),
                                   FLAG_SATURATED if clip else 0))
    out = Pipeline(Reconstructor(level="full"), map_clock=False).feed(b"".join(frames), 1.0)
    clipped = [f for f in out if 200 <= f.seq < 330]
    assert len(clipped) == 130
    assert all(np.isnan(f.forces_N).all() and np.isnan(f.sigma_N).all() for f in clipped)
    assert all("saturated" in f.flags and "stale" not in f.flags for f in clipped)
    after = [f for f in out if f.seq >= 331]
    assert all(np.isfinite(f.forces_N).all() and not f.flags for f in after)
