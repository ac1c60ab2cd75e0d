"""A service restarted while its sensors are loaded (reconstruct/stored_zero.py).

Auto-tare made whatever was on a sensor its zero: a grid's taxel 27 read
4.51 N before a restart under load and 0.000 N after, a quad's Fz 0.90 N and
0.00 N, unflagged; after the release both read 0 flagged out_of_range. The
service now keeps each sensor's zero in the registry and judges its first
tare against it. Two service lifetimes (TactileService on a temporary
registry, bytes fed as a board sends them, ``stop`` saving as at SIGTERM)."""
import json
import sqlite3
import time

import numpy as np
import pytest

from service.board import BoardSpec
from service.calibration.book import CalibrationBook
from service.calibration.registry import Registry
from service.health import health_report
from service.live_service import TactileService
from service.physics.paper_data import FIT34
from service.protocol import BOARD_SENSOR_ID, FrameType, encode_frame
from service.readings import SensorInfo
from tests import test_quad_loaded_tare as quad_tare

GRID_C0_PF = 10.66 * (1 + 0.01 * ((np.arange(64) * 37) % 11 - 5) / 5)  # ±1 %, as the tester's board
QUAD_C0_PF = np.array([2.21, 2.20, 2.22, 2.21])
PRESSED = [27, 28, 35, 36]
GRID_PRESS, QUAD_PRESS = 0.05, 0.03  # ΔC/C0
KEY_GRID = "board:B-7/sensor:0"


def info(serial: str | None = None) -> bytes:
    grid = {"id": 0, "kind": "grid", "rows": 8, "cols": 8} | ({"serial": serial} if serial else {})
    document = {"board": "hand", "fw": "1.0", "serial": "B-7", "rate_hz": 1000, "sensors": [grid, {"id": 1, "kind": "quad"}]}
    return encode_frame(FrameType.INFO, BOARD_SENSOR_ID, 0, 0, json.dumps(document).encode())


def scans(rng, first: int, count: int, press: float, qpress: float, warmer: float = 0.0,
          grid_c0: np.ndarray = GRID_C0_PF) -> bytes:
    """``count`` scans of the grid (taxels PRESSED at ΔC/C0 ``press``) and the quad (all four at ``qpress``),
    every channel ``warmer`` (ΔC/C0) above its C0, noise 2 fF (grid) and 0.5 fF (quad)."""
    out = []
    grid_load = np.where(np.isin(np.arange(64), PRESSED), press, 0.0)
    for k in range(first, first + count):
        grid = grid_c0 * (1 + warmer) * (1 + grid_load) + rng.normal(0, 2e-3, 64)
        quad = QUAD_C0_PF * (1 + warmer) * (1 + qpress) + rng.normal(0, 5e-4, 4)
        out.append(encode_frame(FrameType.GRID, 0, k, 1000 * k, np.round(grid * 1e6).astype("<u4").tobytes()))
        out.append(encode_frame(FrameType.QUAD, 1, k, 1000 * k, np.round(quad * 1e6).astype("<u4").tobytes()))
    return b"".join(out)


def lifetime(registry, phases, serial: str | None = None, seed: int = 1, grid_c0: np.ndarray = GRID_C0_PF,
             level: str = "full", clock: list | None = None):
    """One service lifetime: INFO, then each phase (scans, press, qpress, warmer: ΔC/C0, or its (first, last)
    over the phase) fed 20 scans a read; stopped as at SIGTERM (zeros and counts saved). (the service,
    [(grid frames, quad frames)] per phase). ``clock`` [Unix time]: the wall clock the zeros are dated by,
    moved on as the board's (a read of 20 scans: 20 ms)."""
    rng = np.random.default_rng(seed)
    service = TactileService(boards=[BoardSpec("socket://127.0.0.1:9", level=level)],
                             calibrations=CalibrationBook(registry))
    pipeline, out, k = service.pipeline, [], 1
    pipeline.feed(info(serial), time.time())
    for count, press, qpress, warmer in phases:
        frames = []
        first, last = warmer if isinstance(warmer, tuple) else (warmer, warmer)
        for start in range(k, k + count, 20):
            now = first + (last - first) * (start - k) / count
            frames += pipeline.feed(scans(rng, start, 20, press, qpress, now, grid_c0), time.time())
            if clock is not None:
                clock[0] += 0.02
        k += count
        out.append(([f for f in frames if f.sensor.id == 0], [f for f in frames if f.sensor.id == 1]))
    service.stop()
    return service, out


def held(phase, taxel: int | None = None) -> float:
    """The mean of the phase's last 200 frames: grid ``taxel``'s force, else the quad's Fz."""
    frames = phase[0][-200:] if taxel is not None else phase[1][-200:]
    return float(np.mean([f.forces_N[taxel if taxel is not None else 2] for f in frames]))


def flags(phase, kind: int) -> set:
    return {flag for f in phase[kind][-200:] for flag in f.flags}


def paper_fz(relative: float) -> float:
    """Fz (N) of fit (34) without its offset (ΔC/C0 = c2 F² + c1 F), its rising branch: the quad's reference."""
    c2, c1, _ = FIT34
    return (c1 - np.sqrt(c1 * c1 + 4.0 * c2 * relative)) / (-2.0 * c2)


def age_stored_zeros(registry, seconds: float) -> None:
    """The zeros the last lifetime kept, as if saved ``seconds`` earlier."""
    with sqlite3.connect(registry) as db:
        db.execute("UPDATE zeros SET saved = saved - ?", (seconds,))


@pytest.fixture
def loaded_before(tmp_path):
    """A first lifetime tared unloaded, then pressed (the tester's case): (registry, its pressed phase)."""
    registry = tmp_path / "registry.sqlite3"
    _, phases = lifetime(registry, [(300, 0.0, 0.0, 0.0), (500, GRID_PRESS, QUAD_PRESS, 0.0)])
    return registry, phases[1]


def test_a_restart_under_load_keeps_the_zero_and_reads_the_load_flagged(loaded_before):
    registry, before = loaded_before
    assert held(before, 27) > 4.0 and held(before) == pytest.approx(paper_fz(QUAD_PRESS), rel=0.03)
    service, (loaded, released) = lifetime(registry, [(500, GRID_PRESS, QUAD_PRESS, 0.0), (500, 0.0, 0.0, 0.0)], seed=2)
    for taxel in PRESSED:  # main read 0.000 N here
        assert held(loaded, taxel) == pytest.approx(held(before, taxel), abs=0.02)
    assert held(loaded) == pytest.approx(held(before), abs=0.01)  # main: 0.00 N
    assert "loaded_at_tare" in flags(loaded, 0) and "loaded_at_tare" in flags(loaded, 1)
    assert {int(t) for t in np.flatnonzero(loaded[0][-1].taxel_flags & 64)} == set(PRESSED)
    after = [held(released, t) for t in PRESSED] + [held(released)]
    assert np.max(np.abs(after)) < 0.03  # main: 0 N flagged out_of_range, the tare's load gone below it
    assert "out_of_range" not in flags(released, 0) | flags(released, 1)
    kept = service.primary.calibration(0)["stored_zero"]
    assert kept["kept"] == PRESSED and kept["not_used"] is None and 0 <= kept["age_s"] < 30
    assert service.primary.calibration(1)["stored_zero"]["kept"] == [0, 1, 2, 3]
    sensors = health_report(service)["sensors"]  # the quad's kept zero said too: only the grid's was
    assert sensors["0"]["faulty_channels"] == {"loaded_at_tare": PRESSED}
    assert sensors["1"]["faulty_channels"] == {"loaded_at_tare": [0, 1, 2, 3]}


def test_a_restart_unloaded_tares_as_without_a_stored_zero(loaded_before, tmp_path):
    registry, _ = loaded_before
    _, (with_zero,) = lifetime(registry, [(400, 0.0, 0.0, 0.0)], seed=3)
    _, (without,) = lifetime(tmp_path / "empty.sqlite3", [(400, 0.0, 0.0, 0.0)], seed=3)
    for kind in (0, 1):
        np.testing.assert_array_equal([f.forces_N for f in with_zero[kind]], [f.forces_N for f in without[kind]])
        assert not flags(with_zero, kind)


def test_a_restart_warmer_within_the_drift_bound_keeps_the_zero_moved_by_the_free_taxels(loaded_before):
    """A minute since the save lets drift explain 1 % ΔC/C0: 0.5 % warmer on every channel is temperature. The
    grid's stored zero moves by its free taxels' level (its pressed taxels then read the load alone, and 0 after
    release); the quad, unloaded, tares as usual."""
    registry, before = loaded_before
    age_stored_zeros(registry, 60)
    service, (loaded, released) = lifetime(registry, [(500, GRID_PRESS, 0.0, 0.005), (500, 0.0, 0.0, 0.005)], seed=4)
    for taxel in PRESSED:
        assert held(loaded, taxel) == pytest.approx(held(before, taxel), rel=0.02)
        assert abs(held(released, taxel)) < 0.05
    assert service.primary.calibration(0)["stored_zero"]["kept"] == PRESSED
    assert service.primary.calibration(1)["stored_zero"]["kept"] == []
    assert abs(held(loaded)) < 0.01 and not flags(loaded, 1)


def test_a_zero_saved_after_a_warming_carries_the_drift_tracked_on_it(tmp_path):
    """Warmed by 0.35 % at 1 %/min over 21 s, the trackers (drift.py, quad_drift.py) follow it: the zero kept is
    the tare's moved by it. Restarted still warm and unloaded, nothing reads above it and both tare as usual;
    kept without the drift, the quad's four electrodes stood 0.35 % (0.10 N) above it 0.1 s after the save,
    past the 0.002 % drift could explain, and kept the old zero as a load."""
    registry = tmp_path / "registry.sqlite3"
    lifetime(registry, [(2000, 0.0, 0.0, 0.0), (21000, 0.0, 0.0, (0.0, 0.0035))])
    with Registry(registry) as store:
        grid = np.array(store.zero(KEY_GRID, "builtin-table1")["zero_pF"])
        quad = np.array(store.zero("board:B-7/sensor:1", "builtin-fits34-35")["zero_pF"])
    stored = (np.median(grid / GRID_C0_PF) - 1, np.median(quad / QUAD_C0_PF) - 1)
    service, (warm,) = lifetime(registry, [(400, 0.0, 0.0, 0.0035)], seed=8)
    kept = [service.primary.calibration(sid)["stored_zero"]["kept"] for sid in (0, 1)]
    assert (kept, not flags(warm, 0) | flags(warm, 1), abs(held(warm)) < 0.01) == ([[], []], True, True)
    assert stored == pytest.approx((0.0035, 0.0035), abs=0.0003)


def test_a_zero_on_which_no_drift_is_tracked_is_as_old_as_its_tare(tmp_path, monkeypatch):
    """At the table level nothing follows drift: 0.3 % of warming over 21 s (0.86 %/min, within the bound)
    stands on the zero in force. Dated by its tare, 21 s before the restart, that is drift (0.35 % allowed):
    the sensors, still warm, tare as usual. Dated by the save, every channel was kept as loaded."""
    import types

    clock = [1.8e9]
    fake = types.SimpleNamespace(time=lambda: clock[0])
    monkeypatch.setattr("service.reconstruct.stored_zero.time", fake)
    monkeypatch.setattr("service.reconstruct.sensor_states.time", fake)
    registry = tmp_path / "registry.sqlite3"
    lifetime(registry, [(200, 0.0, 0.0, 0.0), (21000, 0.0, 0.0, (0.0, 0.003))], level="table", clock=clock)
    service, (warm,) = lifetime(registry, [(400, 0.0, 0.0, 0.003)], seed=8, level="table", clock=clock)
    states = [service.primary.calibration(sid)["stored_zero"] for sid in (0, 1)]
    assert [state["kept"] for state in states] == [[], []] and 21 <= states[0]["age_s"] <= 22
    assert not flags(warm, 0) | flags(warm, 1) and abs(held(warm)) < 0.01 and abs(held(warm, 27)) < 0.05


def test_a_stored_zero_older_than_drift_can_be_judged_by_is_not_used(loaded_before):
    """Saved 5 min before: drift at 1 %/min could explain 5 % ΔC/C0, the whole press: the load is the zero, as
    without one, and /health says how old it was."""
    registry, _ = loaded_before
    age_stored_zeros(registry, 300)
    service, (loaded,) = lifetime(registry, [(500, GRID_PRESS, QUAD_PRESS, 0.0)], seed=5)
    assert abs(held(loaded, 27)) < 0.05 and abs(held(loaded)) < 0.01
    state = service.primary.calibration(0)["stored_zero"]
    assert state["kept"] == [] and state["not_used"].startswith("saved 30") and "120 s" in state["not_used"]


def test_another_sensor_at_the_address_never_uses_the_first_ones_zero(tmp_path):
    """By serial: another serial has no zero of its own stored. Without one (keyed by board and id), another
    sensor's C0 pattern reads below the stored zero on many taxels: not used either."""
    registry = tmp_path / "registry.sqlite3"
    lifetime(registry, [(300, 0.0, 0.0, 0.0)], serial="S-1")
    service, (loaded,) = lifetime(registry, [(300, GRID_PRESS, 0.0, 0.0)], serial="S-2", seed=6)
    assert service.primary.calibration(0)["stored_zero"] is None and abs(held(loaded, 27)) < 0.05
    with Registry(registry) as store:
        assert store.zero("sensor:S-2", "builtin-table1") is not None and store.zero(KEY_GRID, "builtin-table1") is None

    lifetime(registry, [(300, 0.0, 0.0, 0.0)])
    other = GRID_C0_PF * (1 + np.random.default_rng(9).normal(0, 0.03, 64))
    service, (loaded,) = lifetime(registry, [(300, GRID_PRESS, 0.0, 0.0)], seed=7, grid_c0=other)
    state = service.primary.calibration(0)["stored_zero"]
    assert state["kept"] == [] and "read below it" in state["not_used"] and abs(held(loaded, 27)) < 0.05


def test_a_replay_and_a_simulated_board_never_read_a_stored_zero(loaded_before):
    """A replay's zeros are its recording's (the goldens: tests/test_regression.py); a simulated board is new
    every run. Neither reads the registry's zero, though one is kept for the sensor."""
    registry, _ = loaded_before
    board = {"board": "hand", "serial": "B-7"}
    assert CalibrationBook(registry).load_zero(board, SensorInfo(0, "grid", 8, 8), "builtin-table1") is not None
    assert CalibrationBook(registry, replaying=True).load_zero(board, SensorInfo(0, "grid", 8, 8), "builtin-table1") is None
    assert TactileService("sim://", calibrations=CalibrationBook(registry)).pipeline.reconstructor.load_zero is None


@pytest.mark.parametrize("age_s, kept", [(20.0, [0, 1, 2, 3]), (40.0, []), (119.0, []), (121.0, None)])
def test_a_quad_05_percent_above_its_stored_zero_is_loaded_only_while_drift_cannot_explain_it(age_s, kept):
    """Quad electrodes 0.5 % above the stored zero, both means of 100 readings at 0.5 fF: the noise margin is
    4·hypot(0.05, 0.05) fF = 0.28 fF (0.013 % of 2.2 pF), drift at 1 %/min adds age/6000, so the 0.5 % excess
    is a load up to 29.2 s after the save and drift since; at 121 s the zero is not used at all."""
    from service.reconstruct.stored_zero import StoredZero, judged

    now = 1.8e9
    stored = StoredZero(QUAD_C0_PF, np.full(4, 5e-4), 100, now - age_s)
    report = judged(stored, QUAD_C0_PF * 1.005, np.full(4, 5e-4), 100, now)
    assert report["age_s"] == age_s
    if kept is None:
        assert report["not_used"].startswith("saved 121 s ago") and not report["kept"].any()
    else:
        assert report["not_used"] is None and np.flatnonzero(report["kept"]).tolist() == kept


def test_a_save_while_the_first_tare_is_judged_never_stores_the_loaded_means(loaded_before, monkeypatch):
    """The zeros' saver runs on its own thread every 10 s: one that ran
    between a tare marked judged and its loaded channels given the stored
    zero kept the pressed means (taxel 27 at 11.28 pF, not 10.75), so a
    restart after a crash read the grip as 0 N (a reviewer's interleaving,
    made here at the judgement's first step)."""
    import service.reconstruct.stored_zero as stored_zero

    registry, _ = loaded_before
    before = json.loads(sqlite3.connect(registry).execute(
        "SELECT zero_pF FROM zeros WHERE sensor_key LIKE '%sensor:0'").fetchone()[0])
    service = TactileService(boards=[BoardSpec("socket://127.0.0.1:9", level="full")],
                             calibrations=CalibrationBook(registry))
    judged, saved = stored_zero.judged, []
    monkeypatch.setattr(stored_zero, "judged", lambda *a, **k: saved or saved.append(service.save_cycles()) or
                        judged(*a, **k))
    rng = np.random.default_rng(2)
    service.pipeline.feed(info(), time.time())
    for start in range(1, 601, 20):
        service.pipeline.feed(scans(rng, start, 20, GRID_PRESS, QUAD_PRESS), time.time())
    after = json.loads(sqlite3.connect(registry).execute(
        "SELECT zero_pF FROM zeros WHERE sensor_key LIKE '%sensor:0'").fetchone()[0])
    assert saved and after[27] == pytest.approx(before[27], rel=1e-4)  # not GRID_C0_PF[27] * 1.05


def test_a_quad_restarted_under_normal_and_shear_load_keeps_the_stored_zero_on_all_four(tmp_path):
    """Restarted under (Fx, Fy, Fz) = (2.5, 2.5, 0.5) N, 20 s after its zero
    was saved: the load lowers electrode 0 (ΔC/C0 −1.66 %) and raises 1-3
    (+1.69, +1.69, +5.04 %), so only 1-3 stood above the stored zero and kept
    it; electrode 0 took the load into its tared zero, which read the held
    load as (1.81, 1.81, 0.62) N (σ 0.13) and, after the release,
    (−0.565, −0.562, +0.12) N (σ 0.04, ~13σ). Every force combines all four
    (loaded_tare.py): all four keep the stored zero, and read the forces put
    in (quad_tare.electrodes: the paper's fits 34 and 35)."""
    registry = quad_tare.registry_with(tmp_path)

    def quad_lifetime(phases, seed: int):
        service = TactileService(boards=[BoardSpec("socket://127.0.0.1:9", level="full")],
                                 calibrations=CalibrationBook(registry))
        out = quad_tare.run(service.pipeline, phases, seed=seed)
        service.stop()
        return service, out

    quad_lifetime([(600, (0.0, 0.0, 0.0), 0.0)], 1)
    age_stored_zeros(registry, 20.0)
    load = (2.5, 2.5, 0.5)
    assert np.flatnonzero(quad_tare.electrodes(*load) < quad_tare.C0_PF).tolist() == [0]
    service, (loaded, released) = quad_lifetime([(600, load, 0.0), (600, (0.0, 0.0, 0.0), 0.0)], 2)
    assert service.primary.calibration(1)["stored_zero"]["kept"] == [0, 1, 2, 3]
    for frames, truth in ((loaded, load), (released, (0.0, 0.0, 0.0))):
        mean, sigma, seen = quad_tare.held(frames)
        assert np.all(np.abs(mean - truth) <= 3 * sigma), (truth, mean, sigma)
        assert seen == {"loaded_at_tare"}
