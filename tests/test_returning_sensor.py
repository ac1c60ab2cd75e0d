"""A sensor back at its address after another sensor was there (reconstruct/identity.py).

Board EMU-A (its sensors have no serial: each is sensor ``id`` of EMU-A) tared
unloaded; board EMU-B came up on the same link (its own sensors, tared
afresh); EMU-A came back holding 2 N on its quad and 1 N on grid taxel 7.
Both read 0.000 N unflagged (re-tared under the load), then 0 flagged
out_of_range after the release. The sensor back is the one that left
seconds before: its tare is judged against the zero it left with, as a
service restart judges one against its stored zero (stored_zero.py).
Readings built here from known capacitances at 200 Hz: a grid taxel's ΔC/C0
is 2 % per N, the quad's electrodes follow paper 001's fits 34 and 35
(ΔC/C0 = 0.0343 Fz − 0.0009 Fz², 0 N of shear)."""
import io
from dataclasses import replace

import numpy as np
import orjson
import pytest

from service.calibration.book import book_from_options
from service.pipeline import Pipeline
from service.protocol import BOARD_SENSOR_ID, FrameType, encode_frame
from service.readings import Reading, SensorInfo
from service.readout import INFO_REPLY_S
from service.reconstruct import Reconstructor
from service.reconstruct.identity import LEFT_ZEROS
from service.reconstruct.stored_zero import MAX_AGE_S
from service.record.mcap_reader import iter_messages
from service.record.recorder import Recorder
from service.replay import replay

T0 = 1.8e9  # host clock (Unix s) of the first scan
PERIOD_S = 0.005  # 200 Hz
TAXEL, GRID_N_PER_DC = 7, 0.02  # the taxel loaded; its ΔC/C0 per N
QUAD_FZ = 2.0  # N
NOISE_PF = 1e-3


def infos(serial: str, restarted: bool) -> tuple[SensorInfo, SensorInfo]:
    """Grid 0 (4x6) and quad 1 of board ``serial``, as the interpreter describes them: the first INFO on the link
    names no board it was swapped to (``restarted`` False), a later one names it."""
    board = {"board": "emu", "serial": serial}
    named = serial if restarted else None
    return (SensorInfo(0, "grid", 4, 6, board="emu", board_identity=named, board_info=board),
            SensorInfo(1, "quad", 2, 2, board="emu", board_identity=named, board_info=board))


class Board:
    """A board's two sensors: their C0 (pF), ±5 %, and its scans under a load, noise NOISE_PF."""

    def __init__(self, serial: str, seed: int) -> None:
        self.serial, self.rng = serial, np.random.default_rng(seed)
        self.grid_c0 = 5.0 * (1 + 0.05 * self.rng.standard_normal(24))
        self.quad_c0 = 3.5 * (1 + 0.05 * self.rng.standard_normal(4))

    def capacitances(self, count: int, grid_n: float, fz: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """``count`` scans' (grid (24,), quad (4,)) pF, taxel TAXEL under ``grid_n`` N, the quad under ``fz`` N."""
        load = np.where(np.arange(24) == TAXEL, GRID_N_PER_DC * grid_n, 0.0)
        normal = 0.0343 * fz - 0.0009 * fz * fz
        return [(self.grid_c0 * (1 + load) + self.rng.normal(0, NOISE_PF, 24),
                 self.quad_c0 * (1 + normal) + self.rng.normal(0, NOISE_PF, 4)) for _ in range(count)]

    def scans(self, infos, count: int, start_s: float, grid_n: float = 0.0, fz: float = 0.0) -> list[Reading]:
        """``count`` scans from host time ``start_s`` (after T0), as ``capacitances``; the first a board's first
        after its power-up."""
        grid_info, quad_info = infos
        out = []
        for k, (grid, quad) in enumerate(self.capacitances(count, grid_n, fz)):
            t = T0 + start_s + k * PERIOD_S
            out += [Reading(grid_info, k, 5000 * k, t, 0, 0, grid, False, False, k == 0),
                    Reading(quad_info, k, 5000 * k + 100, t, 0, 0, quad, False, False, k == 0)]
        return out

    def info_document(self) -> dict:
        return {"board": "emu", "serial": self.serial, "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 6},
                                                                   {"id": 1, "kind": "quad"}]}

    def info(self) -> bytes:
        """The board's INFO frame (its power-up's, or its answer to INFO?)."""
        return encode_frame(FrameType.INFO, BOARD_SENSOR_ID, 0, 0, orjson.dumps(self.info_document()))

    def reads(self, count: int, start_s: float, grid_n: float = 0.0, fz: float = 0.0,
              first: int = 0) -> list[tuple[bytes, float]]:
        """The board's bytes (its INFO first where ``first`` is 0: its power-up), 10 scans a read, each with the
        host time it is received at, as ``scans``."""
        frames = [self.info()] if first == 0 else []
        for k, (grid, quad) in enumerate(self.capacitances(count, grid_n, fz), first):
            frames.append(encode_frame(FrameType.GRID, 0, k, 5000 * k, np.round(grid * 1e6).astype("<u4").tobytes()) +
                          encode_frame(FrameType.QUAD, 1, k, 5000 * k + 100, np.round(quad * 1e6).astype("<u4").tobytes()))
        head = frames.pop(0) if first == 0 else b""
        frames[0] = head + frames[0]
        return [(b"".join(frames[i:i + 10]), T0 + start_s + PERIOD_S * (i + 9)) for i in range(0, count, 10)]


def held(frames, sid: int) -> tuple[float, float, list[str]]:
    """(mean force, its frames' mean σ, the flags of the last frame) over the last 50 frames of sensor ``sid``:
    the grid's taxel TAXEL, the quad's Fz."""
    mine = [f for f in frames if f.sensor.id == sid][-50:]
    index = TAXEL if sid == 0 else 2
    force = np.mean([f.forces_N[index] for f in mine])
    sigma = np.mean([f.sigma_N[index] for f in mine])
    flags = list(mine[-1].flags)
    if sid == 0:
        flags += [name for name, taxels in mine[-1].taxel_flag_lists().items() if TAXEL in taxels]
    return float(force), float(sigma), flags


def swap_and_back(back_after_s: float, other: str = "EMU-B") -> tuple[dict, dict, Reconstructor]:
    """EMU-A tared unloaded, then loaded (what the load reads tared unloaded), released; board ``other``;
    EMU-A back ``back_after_s`` after it left, loaded, then released. ({sensor: (force, σ, flags) under the
    load before}, {sensor: ((force, σ, flags) under the load back, (…) released)}, the reconstructor)."""
    a, b = Board("EMU-A", 1), Board(other, 2)
    reconstructor = Reconstructor()
    first = reconstructor.process_many(a.scans(infos("EMU-A", False), 150, 0.0))
    loaded = reconstructor.process_many(a.scans(infos("EMU-A", False), 200, 0.75, 1.0, QUAD_FZ))
    reconstructor.process_many(a.scans(infos("EMU-A", False), 100, 1.75))
    assert all(f.forces_N[TAXEL if f.sensor.id == 0 else 2] == pytest.approx(0, abs=0.05) for f in first[-20:])
    reconstructor.process_many(b.scans(infos(other, True), 150, 3.0))
    t_back = 2.25 + back_after_s
    again = reconstructor.process_many(a.scans(infos("EMU-A", True), 200, t_back, 1.0, QUAD_FZ))
    released = reconstructor.process_many(a.scans(infos("EMU-A", True), 150, t_back + 1.0))
    return ({sid: held(loaded, sid) for sid in (0, 1)},
            {sid: (held(again, sid), held(released, sid)) for sid in (0, 1)}, reconstructor)


def test_a_sensor_back_after_another_board_reads_its_load_flagged_and_zero_after_the_release():
    """Back 2 s after it left (1.5 s of EMU-B): the quad read 0.000 N (a true 2 N) and taxel 7 0.000 N (what
    read 1.66 N before the swap), unflagged; after the release 0 flagged out_of_range / normal_out_of_range.
    Now each reads the load within 3σ of what it read before the swap, flagged loaded_at_tare, and ~0
    after the release, never below its zero (out of range)."""
    before, back, reconstructor = swap_and_back(2.0)
    assert before[1][0] == pytest.approx(QUAD_FZ, abs=3 * before[1][1])  # the fits' 2 N, tared unloaded
    assert before[0][0] > 1.0 and "loaded_at_tare" not in before[0][2]
    for sid in (0, 1):
        (force, sigma, flags), (after, after_sigma, after_flags) = back[sid]
        assert abs(force - before[sid][0]) < 3 * np.hypot(sigma, before[sid][1]), (sid, force, before[sid])
        assert "loaded_at_tare" in flags
        assert abs(after) < 3 * after_sigma + 1e-3, (sid, after, after_sigma)
        assert not {"out_of_range", "normal_out_of_range"} & set(after_flags), (sid, after_flags)
        kept = reconstructor.zero_kept(sid)
        assert kept["not_used"] is None and kept["age_s"] == pytest.approx(2.5, abs=0.01)  # from its last scan to its tare's last
    assert reconstructor.zero_kept(0)["kept"] == [TAXEL] and reconstructor.zero_kept(1)["kept"] == [0, 1, 2, 3]
    assert reconstructor.replaced(1)["count"] == 2


def test_an_equal_info_during_the_tare_back_keeps_the_zero_it_left_with():
    """The same INFO again while EMU-A tares back (its answer to INFO? 50 ms after its power-up INFO) looked its
    stored zero up again, found the one it left with already handed over, and tared on the load: the quad read
    0.001 ± 0.004 N (a true 2 N) unflagged, zero_kept None. Now it is judged against the zero it left with as
    with one INFO: the quad's Fz within 3σ of the fits' 2 N, taxel 7 kept, both flagged loaded_at_tare."""
    a, b = Board("EMU-A", 1), Board("EMU-B", 2)
    reconstructor = Reconstructor()
    reconstructor.process_many(a.scans(infos("EMU-A", False), 150, 0.0))
    reconstructor.process_many(b.scans(infos("EMU-B", True), 150, 3.0))
    scans, again = a.scans(infos("EMU-A", True), 200, 4.25, 1.0, QUAD_FZ), infos("EMU-A", True)
    # From its 41st scan, in the tare window, readings carry the equal INFO (new objects, as the interpreter makes)
    frames = reconstructor.process_many(scans[:80] + [replace(s, sensor=again[s.sensor.id]) for s in scans[80:]])
    force, sigma, flags = held(frames, 1)
    assert abs(force - QUAD_FZ) < 3 * sigma and sigma < 0.5, (force, sigma)
    assert "loaded_at_tare" in flags and "loaded_at_tare" in held(frames, 0)[2]
    assert reconstructor.zero_kept(1)["kept"] == [0, 1, 2, 3] and reconstructor.zero_kept(0)["kept"] == [TAXEL]
    assert reconstructor.zero_kept(1)["not_used"] is None


def test_a_board_back_that_answers_info_again_keeps_the_zero_it_left_with_live():
    """The same on the live path: EMU-A back holding 2 N sends its power-up INFO, then its answer to the
    readout's INFO? one read (50 ms) later. Its quad read 0.001 ± 0.004 N unflagged; now the fits' 2 N within
    3σ, flagged loaded_at_tare, all four electrodes keeping the zero it left with."""
    pipeline, published = Pipeline(Reconstructor(), map_clock=False), []
    pipeline.listeners.append(published.extend)
    pipeline.identify_on_link(INFO_REPLY_S, lambda: None, lambda delay, fn: None)
    a, b = Board("EMU-A", 1), Board("EMU-B", 2)
    for board, start_s in ((a, 0.0), (b, 3.0)):
        for data, t_host in board.reads(300, start_s):
            pipeline.feed(data, t_host)
        pipeline.link_lost()
    start = len(published)
    for k, (data, t_host) in enumerate(a.reads(300, 5.0, 1.0, QUAD_FZ)):
        pipeline.feed(data + (a.info() if k == 1 else b""), t_host)
    force, sigma, flags = held(published[start:], 1)
    assert abs(force - QUAD_FZ) < 3 * sigma and sigma < 0.5, (force, sigma)
    assert "loaded_at_tare" in flags and pipeline.reconstructor.zero_kept(1)["kept"] == [0, 1, 2, 3]


def test_a_sensor_back_after_max_age_tares_afresh():
    """Back more than MAX_AGE_S after it left: drift at the bound could explain more than a load, so the zero it
    left with is not used (said in zero_kept) and the load is tared away, as a service restart does with an
    old stored zero."""
    _, back, reconstructor = swap_and_back(MAX_AGE_S + 5.0)
    for sid in (0, 1):
        (force, _, flags), _ = back[sid]
        assert force == pytest.approx(0.0, abs=0.05) and "loaded_at_tare" not in flags
        assert reconstructor.zero_kept(sid)["not_used"].startswith("saved 1")


def test_another_sensor_at_the_address_still_tares_afresh():
    """EMU-C, never here before, comes up loaded where EMU-B was: no zero of its own was kept, so it tares afresh
    (nothing judged against EMU-A's or EMU-B's zero)."""
    a, b, c = Board("EMU-A", 1), Board("EMU-B", 2), Board("EMU-C", 3)
    reconstructor = Reconstructor()
    reconstructor.process_many(a.scans(infos("EMU-A", False), 150, 0.0))
    reconstructor.process_many(b.scans(infos("EMU-B", True), 150, 1.0))
    frames = reconstructor.process_many(c.scans(infos("EMU-C", True), 200, 2.0, 1.0, QUAD_FZ))
    for sid in (0, 1):
        force, _, flags = held(frames, sid)
        assert force == pytest.approx(0.0, abs=0.05) and "loaded_at_tare" not in flags
        assert reconstructor.zero_kept(sid) is None


def test_a_board_flapping_between_many_identities_keeps_at_most_left_zeros():
    """A board whose INFO names another serial at every power-up (3 × LEFT_ZEROS of them, a quad each): the
    zeros of the sensors that left are kept LEFT_ZEROS at most, the newest; one older than MAX_AGE_S is dropped
    when a newer one is kept, being of no use."""
    reconstructor = Reconstructor(tare_frames=10)

    def flap(serial: str, start_s: float) -> None:
        quad = SensorInfo(1, "quad", 2, 2, board="emu", board_identity=serial, board_info={"serial": serial})
        reconstructor.process_many([Reading(quad, k, 5000 * k, T0 + start_s + PERIOD_S * k, 0, 0, np.full(4, 3.5),
                                            False, False, k == 0) for k in range(12)])

    for n in range(3 * LEFT_ZEROS + 1):
        flap(f"F-{n}", n)
    left = [z["identity"][1] for z in reconstructor.replacements.left_zeros()]
    assert left == [f"F-{n}" for n in range(2 * LEFT_ZEROS, 3 * LEFT_ZEROS)]
    flap("G", 3 * LEFT_ZEROS + MAX_AGE_S + 60)  # 3 min later: F-192's zero kept, the oldest past LEFT_ZEROS dropped
    assert len(reconstructor.replacements.left_zeros()) == LEFT_ZEROS
    flap("H", 3 * LEFT_ZEROS + MAX_AGE_S + 61)  # G's zero is 3 min newer than every F's: theirs are of no use
    assert [z["identity"][1] for z in reconstructor.replacements.left_zeros()] == ["G"]


ROW = {"zero_pF": [3.5, 3.6, None, 3.4], "std_pF": [0.001] * 4, "frames": 100, "saved": T0}
BAD_LEFT = [({"identity": ["serial", "X"], "calibration": "c", "zero": {**ROW, "saved": "yesterday"}}, "saved"),
            ({"identity": 5, "calibration": "c", "zero": ROW}, "identity"),
            ({"calibration": "c"}, "identity"),
            ({"identity": ["serial", "X"], "calibration": 7, "zero": ROW}, "calibration"),
            ({"identity": ["serial", ["X"]], "calibration": "c", "zero": ROW}, "identity"),
            ({"identity": ["serial", "X"], "calibration": "c", "zero": {**ROW, "zero_pF": "3.5"}}, "zero_pF"),
            ({"identity": ["serial", "X"], "calibration": "c", "zero": {**ROW, "std_pF": [0.001]}}, "std_pF"),
            ({"identity": ["serial", "X"], "calibration": "c", "zero": {**ROW, "frames": True}}, "frames"),
            ({"identity": ["serial", "X"], "calibration": "c", "zero": {**ROW, "saved": float("nan")}}, "saved"),
            ("left", "not an object")]


def test_a_recorded_left_zero_that_is_malformed_is_skipped_naming_it(caplog):
    """A recording's /baselines ``left`` entries were taken unchecked: saved "yesterday" or an identity 5 raised
    TypeError, one without an identity KeyError, stopping the replay (or the replay:// board) before its first
    frame; a zero_pF that is no list would have at the sensor's return. Each bad one is now skipped with a
    warning naming it and what is wrong, the good ones kept."""
    good = [{"identity": ["board", "EMU-A", 1], "calibration": "builtin-quad", "zero": ROW},
            {"identity": ["serial", "Q-9"], "calibration": "c", "zero": {**ROW, "saved": T0 + 1}}]
    reconstructor = Reconstructor()
    reconstructor.preset_left_zeros([good[0]] + [entry for entry, _ in BAD_LEFT] + [good[1]])
    assert reconstructor.replacements.left_zeros() == good
    warnings = [r.getMessage() for r in caplog.records if "left" in r.getMessage()]
    assert len(warnings) == len(BAD_LEFT)
    for message, (entry, field) in zip(warnings, BAD_LEFT):
        assert field in message and repr(entry)[:40] in message, (message, entry)


def test_a_pipeline_takes_what_a_recording_began_with_in_one_call():
    """Pipeline.preset_began (a replay's and a replay:// board's one sequence): the INFO then in force, the
    sensors' zeros and the zeros of sensors that had left, before the first frame. EMU-A's quad, its recorded
    zero its C0, reads 2 N at once from a stream without INFO (the fits' 2 N within 3σ, no tare on the load)."""
    a = Board("EMU-A", 1)
    left = [{"identity": ["board", "EMU-B", 1], "calibration": "builtin-quad", "zero": ROW}]
    pipeline, published = Pipeline(Reconstructor(), map_clock=False), []
    pipeline.listeners.append(published.extend)
    pipeline.preset_began({"board": "emu", "info": a.info_document(), "left": left,
                           "sensors": [{"sensor": 1, "baseline_pF": a.quad_c0.tolist(), "std_pF": [NOISE_PF] * 4}]})
    for data, t_host in a.reads(60, 0.0, 1.0, QUAD_FZ, first=100):
        pipeline.feed(data, t_host)
    quad = [f for f in published if f.sensor.id == 1]
    assert len(quad) == 60 and quad[0].sensor.board_info["serial"] == "EMU-A"
    assert not any("taring" in f.flags for f in quad)
    force, sigma, _ = held(published, 1)
    assert abs(force - QUAD_FZ) < 3 * sigma, (force, sigma)
    assert pipeline.reconstructor.replacements.left_zeros() == left


def swap_bytes() -> list[tuple[bytes, float]]:
    """The swap and return of ``swap_and_back(2.0)`` as a board sends it (reads, host times)."""
    a, b = Board("EMU-A", 1), Board("EMU-B", 2)
    return (a.reads(150, 0.0) + a.reads(200, 0.75, 1.0, QUAD_FZ, first=150) + a.reads(100, 1.75, first=350) +
            b.reads(150, 3.0) + a.reads(200, 4.25, 1.0, QUAD_FZ) + a.reads(150, 5.25, first=200))


@pytest.mark.parametrize("begun_at", [0, 50])
def test_a_recording_of_the_swap_replays_the_return_as_live(tmp_path, begun_at):
    """Recorded from the start (``begun_at`` 0), or begun while EMU-B streamed (read 50): live and the replay
    judge EMU-A's return against the zero it left with on the readings' clock (its recorded host times), so
    every frame replays bit for bit, the loaded ones back too. A recording begun while EMU-A was away holds
    that zero in its /baselines (``left``), where live kept it in memory: without it, EMU-A's return tared
    afresh on the 2 N in the replay. There, the load-cycle counter EMU-A comes back with is the recorded
    count, not the phase of its every-4th-frame judgement: the release completes its cycle a frame or two
    apart, 3 quad frames 5 µN off (fatigue factor 0.99956 for 2 cycles), flags equal."""
    reads = swap_bytes()
    pipeline, recorder, live = Pipeline(Reconstructor(level="table")), None, []
    for i, (data, t_host) in enumerate(reads):
        if i == begun_at:
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        frames = pipeline.feed(data, t_host)
        live += frames if recorder is not None else []
    assert recorder.stop()["error"] is None
    back = [f for f in live if f.sensor.id == 1 and f.t_host > T0 + 5.0 and "taring" not in f.flags]
    assert back and all("loaded_at_tare" in f.flags for f in back)
    assert np.mean([f.forces_N[2] for f in back[:50]]) == pytest.approx(QUAD_FZ, abs=0.1)
    recorded = [orjson.loads(m.data) for topic, m in iter_messages(tmp_path / "run.mcap") if topic.endswith("/forces")]
    out = io.BytesIO()  # as `tactile replay` does: with the calibrations and load cycles the recording holds
    replay(tmp_path / "run.mcap", out, calibrations=book_from_options(str(tmp_path / "registry.sqlite3"), None,
                                                                      recording=tmp_path / "run.mcap"))
    again = [orjson.loads(line) for line in out.getvalue().splitlines()]  # in the order received, as recorded
    assert len(again) == len(recorded) > 800
    if begun_at == 0:
        assert [(i, d) for i, d in enumerate(recorded) if again[i] != d] == []
        return
    assert [(i, d) for i, d in enumerate(recorded) if again[i]["flags"] != d["flags"]] == []
    for d, r in zip(recorded, again):  # its load-cycle counter's phase: a release counted a frame or two apart
        np.testing.assert_allclose(values(r), values(d), rtol=0, atol=1e-5)


def values(doc: dict) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in doc.get("taxels_N") or doc["fxyz_N"]], dtype=float)
