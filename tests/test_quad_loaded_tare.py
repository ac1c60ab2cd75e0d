"""A quad that tares under a load, judged against its calibration's measured C0 (loaded_tare.judge_quad).

A quad's calibration may carry the C0 its session measured (``c0_pF``:
``tactile calibrate``, an upload). A quad that started while gripped took
the grip as its zero: a 3 N press read 0 N, and after the release Fx
-0.83 N (σ 0.06) with Fz 0, flagged only ``normal_out_of_range``. Its tare
is now judged against that C0 as a grid's is: a service on a registry
holding it (board bytes as a board sends them), the quad's electrodes from
the paper's fits written out here (fit 34: ΔC/C0 = −0.0009 F² + 0.0343 F;
fit 35: a F − b F² signed like F, a = 0.0077, b = 0.0004), so the forces
read are checked against the forces put in."""
import io
import json
import sqlite3

import numpy as np
import orjson
import pytest

from service.calibration.book import CalibrationBook, book_from_options
from service.calibration.registry import Registry, sensor_identity
from service.pipeline import Pipeline
from service.protocol import BOARD_SENSOR_ID, FrameType, encode_frame
from service.readings import SensorInfo
from service.reconstruct import Reconstructor
from service.reconstruct.calibration_upload import upload_document

QUAD = SensorInfo(1, "quad", 2, 2)
BOARD = {"board": "hand", "fw": "1.0", "serial": "B-7", "rate_hz": 1000}
C0_PF = np.array([2.21, 2.18, 2.24, 2.20])  # the session's measured C0 (firmware_sim's quad)
C2, C1, A, B = -0.0009, 0.0343, 0.0077, 0.0004  # fits 34 and 35
NOISE_PF = 5e-4
T0 = 1.8e9  # the host clock at the board's time 0 (s)
# A session's fit: standard errors of [c2, c1] and [a, b] (0.15 % and 0.4 % of the slopes), so σ is not
# the built-in's 7 % and "within σ" means something.
UPLOAD = {"normal_fit": [C2, C1], "shear_fit": [A, B], "normal_fit_se": [1e-5, 5e-5],
          "shear_fit_se": [1e-5, 3e-5]}


def electrodes(fx: float, fy: float, fz: float, warmer: float = 0.0, c0: np.ndarray = C0_PF) -> np.ndarray:
    """C11, C12, C21, C22 (pF) under (Fx, Fy, Fz) N, every C0 (4,) pF ``warmer`` (ΔC/C0) above the session's:
    r = n(Fz) + sx t(Fx) + sy t(Fy), sx, sy = ±1 on the +X/+Y side (paper 001, eqs 28-32)."""
    n = C2 * fz * fz + C1 * fz
    tx, ty = (np.sign(f) * (A * abs(f) - B * f * f) for f in (fx, fy))
    return c0 * (1 + warmer) * (1 + n + np.array([-tx - ty, tx - ty, -tx + ty, tx + ty]))


def registry_with(tmp_path, c0: bool = True):
    """A registry whose active calibration of the quad (board B-7, sensor 1) is UPLOAD, with C0_PF if ``c0``."""
    path = tmp_path / "registry.sqlite3"
    upload = UPLOAD | ({"c0_pF": C0_PF.tolist()} if c0 else {})
    document = upload_document(QUAD, upload, "flat", sensor_identity(BOARD, QUAD))
    with Registry(path) as registry:
        registry.add(document, activate=True)
    return path


def scans(rng, first: int, count: int, force, warmer: float, c0: np.ndarray) -> bytes:
    """``count`` QUAD frames from seq ``first``: ``electrodes`` with NOISE_PF, as counts of aF."""
    out = []
    for k in range(first, first + count):
        counts = np.round((electrodes(*force, warmer, c0) + rng.normal(0, NOISE_PF, 4)) * 1e6).astype("<u4")
        out.append(encode_frame(FrameType.QUAD, 1, k, 1000 * k, counts.tobytes()))
    return b"".join(out)


def run(pipeline: Pipeline, phases, seed: int = 1, first: int = 1, info: bool = True, c0: np.ndarray = C0_PF):
    """INFO (``info``), then each phase (scans, (Fx, Fy, Fz), warmer) 20 scans a read, received as the board
    sends them (1 kHz, from Unix time T0), of a quad of C0 ``c0``: its quad frames per phase."""
    rng = np.random.default_rng(seed)
    if info:
        document = BOARD | {"sensors": [{"id": 1, "kind": "quad"}]}
        pipeline.feed(encode_frame(FrameType.INFO, BOARD_SENSOR_ID, 0, 0, json.dumps(document).encode()), T0)
    out, k = [], first
    for count, force, warmer in phases:
        frames = []
        for start in range(k, k + count, 20):
            frames += pipeline.feed(scans(rng, start, 20, force, warmer, c0), T0 + 1e-3 * (start + 20))
        k += count
        out.append([f for f in frames if f.sensor.id == 1])
    return out


def pipeline_on(registry, level: str = "full") -> Pipeline:
    return Pipeline(Reconstructor(level=level), calibrations=CalibrationBook(registry))


def held(frames, last: int = 200) -> tuple[np.ndarray, np.ndarray, set]:
    """(mean forces (3,), mean σ (3,), flags) of the last ``last`` frames."""
    frames = frames[-last:]
    return (np.mean([f.forces_N for f in frames], axis=0), np.mean([f.sigma_N for f in frames], axis=0),
            {flag for f in frames for flag in f.flags})


@pytest.mark.parametrize("level", ["full", "table"])
@pytest.mark.parametrize("force", [(0.0, 0.0, 3.0), (1.0, -0.5, 3.0)])
def test_a_quad_started_under_a_load_reads_it_flagged_and_zero_after_release(tmp_path, force, level):
    pipeline = pipeline_on(registry_with(tmp_path), level)
    loaded, released = run(pipeline, [(600, force, 0.0), (600, (0.0, 0.0, 0.0), 0.0)])
    mean, sigma, flags = held(loaded)
    assert np.all(np.abs(mean - force) <= sigma), (mean, sigma)  # main: Fz 0.000 N, the press its zero
    errors = np.array([f.forces_N for f in loaded[-200:]]) - force
    assert np.mean(np.abs(errors) <= 3.0 * np.array([f.sigma_N for f in loaded[-200:]])) >= 0.99
    assert flags == {"loaded_at_tare"}
    assert pipeline.reconstructor.loaded_at_tare(1) == [0, 1, 2, 3] and pipeline.reconstructor.below_c0(1) == []
    np.testing.assert_array_equal(pipeline.reconstructor.baseline(1), C0_PF)
    mean, sigma, flags = held(released)
    assert np.all(np.abs(mean) < 0.01), mean  # main (1, -0.5, 3): Fx -0.83 N, Fy +0.41 N, Fz 0 normal_out_of_range
    assert flags == {"loaded_at_tare"}  # until the next tare: the zero is the calibration's C0


@pytest.mark.parametrize("warmer", [0.0, 0.003, -0.003, 0.01, -0.01])
def test_a_quad_started_unloaded_is_not_called_loaded_within_a_few_kelvin(tmp_path, warmer):
    """1 % warmer than at its calibration (a 0.29 N Fz's worth) stands within the margin, 4 × 0.1 % of C0
    and the 2 % common-mode allowance (a 0.71 N Fz's worth): the tare's own mean is the zero, so a later
    2 N press reads 2 N, unflagged."""
    pipeline = pipeline_on(registry_with(tmp_path))
    rest, pressed = run(pipeline, [(300, (0.0, 0.0, 0.0), warmer), (600, (0.0, 0.0, 2.0), warmer)])
    assert pipeline.reconstructor.loaded_at_tare(1) == [] and pipeline.reconstructor.below_c0(1) == []
    mean, _, flags = held(rest, 100)
    assert np.all(np.abs(mean) < 0.005) and not flags
    mean, sigma, flags = held(pressed)
    assert np.all(np.abs(mean - [0.0, 0.0, 2.0]) <= sigma) and not flags


@pytest.mark.parametrize("level", ["full", "table"])
def test_a_quad_3_percent_warmer_than_its_calibration_is_loaded_and_its_sigma_covers_the_zero_it_kept(tmp_path, level):
    """3 % warmer than at its calibration, past the 2.4 % margin: loaded at the tare, C0 kept as the zero, so
    at rest it reads fit 34's Fz at ΔC/C0 = 0.03 (0.896 N). That zero is only as good as the ±2 % common-mode
    allowance the judgement gave it (loaded_tare.COMMON_MAX_DRIFT): σ_Fz holds 0.02 through the slope
    (0.583 N at rest), so the phantom stands within 3σ (it had σ 0.062 N: 14σ), flagged."""
    pipeline = pipeline_on(registry_with(tmp_path), level)
    rest, = run(pipeline, [(600, (0.0, 0.0, 0.0), 0.03)])
    assert pipeline.reconstructor.loaded_at_tare(1) == [0, 1, 2, 3]
    phantom = (C1 - np.sqrt(C1 * C1 + 4.0 * C2 * 0.03)) / (-2.0 * C2)
    mean, sigma, flags = held(rest)
    assert phantom == pytest.approx(0.896, abs=1e-3) and mean[2] == pytest.approx(phantom, abs=0.01)
    assert flags == {"loaded_at_tare"}
    fz, sigma_z = (np.array([f.forces_N[2] for f in rest[-200:]]), np.array([f.sigma_N[2] for f in rest[-200:]]))
    assert np.all(np.abs(fz) <= 3.0 * sigma_z), (fz.max(), sigma_z.min())
    assert np.all(sigma_z >= 0.02 / C1)  # at least the allowance through fit 34's slope at 0 N (0.583 N)
    np.testing.assert_allclose(sigma[:2], 0.02135, rtol=0.01)  # a common shift moves no shear: X, Y σ as before


@pytest.mark.parametrize("level, before", [("full", [0.03832, 0.03832, 0.14010]),
                                           ("table", [0.03833, 0.03832, 0.14009])])
def test_a_normally_tared_quads_sigma_is_unchanged(tmp_path, level, before):
    """1 % warmer, within the margin: tared on its own means, its mean σ under a 2 N press what it was before a
    kept zero had a σ (``before``, measured on the code then), within 1 %."""
    pipeline = pipeline_on(registry_with(tmp_path), level)
    _, pressed = run(pipeline, [(300, (0.0, 0.0, 0.0), 0.01), (600, (0.0, 0.0, 2.0), 0.01)])
    assert pipeline.reconstructor.loaded_at_tare(1) == []
    _, sigma, _ = held(pressed)
    np.testing.assert_allclose(sigma, before, rtol=0.01)


def test_the_threshold_is_an_fz_of_0713_N_and_the_quad_is_judged_as_a_whole():
    """4 × hypot(0.05 fF, 0.1 % of C0) + 2 % of C0 = 2.400 % of C0: fit 34 reaches ΔC/C0 0.024 at 0.7130 N
    (−0.0009 F² + 0.0343 F), so 0.70 N at the tare passes as unloaded and 0.73 N is a load. One electrode
    above it makes all four loaded (each force combines all four); one below C0 by as much is no mismatch."""
    from service.reconstruct.loaded_tare import judge_quad

    std = np.full(4, NOISE_PF)
    threshold = (C1 - np.sqrt(C1 * C1 + 4.0 * C2 * 0.024)) / (-2.0 * C2)
    assert threshold == pytest.approx(0.7130, abs=1e-4)
    for fz, loaded in ((0.70, []), (0.73, [0, 1, 2, 3])):
        found, mismatch, c0 = judge_quad(C0_PF, electrodes(0.0, 0.0, fz), std, 100)
        assert np.flatnonzero(found).tolist() == loaded and not mismatch.any()
        np.testing.assert_array_equal(c0, C0_PF)
    one = C0_PF * np.array([0.975, 1.0, 1.0, 1.025])
    found, mismatch, _ = judge_quad(C0_PF, one, std, 100)
    assert found.all() and not mismatch.any()


def test_a_quad_without_a_measured_c0_tares_on_the_load_as_before(tmp_path):
    """Nothing to judge against: the grip is the zero (its tared mean), unflagged, as it always was."""
    pipeline = pipeline_on(registry_with(tmp_path, c0=False))
    rng = np.random.default_rng(3)
    loaded, = run(pipeline, [(600, (1.0, -0.5, 3.0), 0.0)], seed=3)
    pressed = np.array([electrodes(1.0, -0.5, 3.0) + rng.normal(0, NOISE_PF, 4) for _ in range(100)])
    np.testing.assert_allclose(pipeline.reconstructor.baseline(1), np.round(pressed * 1e6).mean(axis=0) * 1e-6,
                               rtol=1e-12)
    mean, _, flags = held(loaded)
    assert np.all(np.abs(mean) < 0.01) and not flags and pipeline.reconstructor.loaded_at_tare(1) == []


def test_another_quads_c0_is_a_mismatch_not_a_load(tmp_path):
    """The calibration's C0 3 % above this quad's on every electrode (another quad's, or C0 drifted past
    the common-mode allowance):
    all four read below it by more than the margin; none is judged loaded, the tare's mean is the zero
    and the calibration says which electrodes (loaded_tare.judge's mismatch, as a grid's)."""
    pipeline = pipeline_on(registry_with(tmp_path))
    loaded, = run(pipeline, [(600, (0.0, 0.0, 0.0), -0.03)])
    assert pipeline.reconstructor.below_c0(1) == [0, 1, 2, 3] and pipeline.reconstructor.loaded_at_tare(1) == []
    mean, _, flags = held(loaded)
    assert np.all(np.abs(mean) < 0.005) and not flags


def test_a_calibration_uploaded_mid_press_judges_the_tare_it_makes(tmp_path):
    """A quad of 17 pF electrodes has no zero on the built-in calibration (its window: 0.37-13.5 pF); its
    calibration, with its C0, uploaded while it is pressed makes it tare at its next reading, under the
    press: judged, the press reads 3 N."""
    c0 = np.array([17.0, 17.4, 16.8, 17.2])
    pipeline = Pipeline(Reconstructor(), calibrations=CalibrationBook(tmp_path / "empty.sqlite3"))
    before, = run(pipeline, [(200, (0.0, 0.0, 3.0), 0.0)], c0=c0)
    assert np.isnan(before[-1].forces_N).all()
    pipeline.set_calibration(pipeline.interpreter.sensors[1], UPLOAD | {"c0_pF": c0.tolist()})
    after, = run(pipeline, [(600, (0.0, 0.0, 3.0), 0.0)], first=201, info=False, c0=c0)
    mean, sigma, flags = held(after)
    assert np.all(np.abs(mean - [0.0, 0.0, 3.0]) <= sigma) and flags == {"loaded_at_tare"}
    assert pipeline.reconstructor.loaded_at_tare(1) == [0, 1, 2, 3]


def test_a_stored_zero_comes_first_and_one_too_old_leaves_the_quad_to_its_c0(tmp_path):
    """Stopped unloaded, started again under 3 N: the zero stored 20 s before keeps the load (stored_zero.py,
    as before); stored 200 s before it is not used, and the calibration's C0 judges the tare. The zero kept
    at the next stop is C0, not the pressed means."""
    from service.board import BoardSpec
    from service.live_service import TactileService

    registry = registry_with(tmp_path)

    def lifetime(force, seed):
        service = TactileService(boards=[BoardSpec("socket://127.0.0.1:9", level="full")],
                                 calibrations=CalibrationBook(registry))
        frames, = run(service.pipeline, [(600, force, 0.0)], seed=seed)
        service.stop()
        return service, frames

    key = sensor_identity(BOARD, QUAD)["key"]
    for age_s, not_used in ((20.0, None), (200.0, "saved 200 s ago")):
        lifetime((0.0, 0.0, 0.0), 1)
        with sqlite3.connect(registry) as db:
            db.execute("UPDATE zeros SET saved = saved - ?", (age_s,))
        service, frames = lifetime((0.0, 0.0, 3.0), 2)
        stored = service.primary.calibration(1)["stored_zero"]
        assert stored["kept"] == ([] if not_used else [0, 1, 2, 3])
        assert (stored["not_used"] or "").startswith(not_used or "")
        assert service.pipeline.reconstructor.loaded_at_tare(1) == [0, 1, 2, 3]
        mean, sigma, flags = held(frames)
        assert np.all(np.abs(mean - [0.0, 0.0, 3.0]) <= sigma) and flags == {"loaded_at_tare"}
        with Registry(registry) as store:
            cid = service.pipeline.reconstructor.calibration(1).id
            kept = np.array(store.zero(key, cid)["zero_pF"])
        np.testing.assert_allclose(kept, C0_PF, rtol=2e-4)  # the pressed means stood 10 % above


def test_a_recording_begun_after_a_loaded_tare_replays_it(tmp_path):
    """The zero a recording begins with (baselines: C0, loaded [0..3], its σ) is the replay's: equal frames and
    σ, flagged."""
    from service.record.recorder import Recorder
    from service.replay import replay

    registry = registry_with(tmp_path)
    pipeline = pipeline_on(registry)
    run(pipeline, [(400, (1.0, -0.5, 3.0), 0.0)])
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    live = run(pipeline, [(400, (1.0, -0.5, 3.0), 0.0), (400, (0.0, 0.0, 0.0), 0.0)], first=401, seed=2, info=False)
    recorder.stop()
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, calibrations=book_from_options(str(registry), None,
                                                                      recording=tmp_path / "run.mcap"))
    again = [orjson.loads(line) for line in out.getvalue().splitlines()]
    live = [f for phase in live for f in phase]
    assert [d["seq"] for d in again] == [f.seq for f in live]
    np.testing.assert_array_equal([d["fxyz_N"] for d in again], [f.forces_N for f in live])
    np.testing.assert_array_equal([d["sigma_N"] for d in again], [f.sigma_N for f in live])  # the kept zero's σ too
    assert all(d["flags"] == ["loaded_at_tare"] for d in again)


@pytest.mark.parametrize("c0", [True, False])
def test_a_tare_asked_while_the_quad_is_pressed_is_refused_naming_its_electrodes_unless_forced(tmp_path, c0):
    """POST /tare's check (pipeline_changes.LoadedAtTare, a 409), as a grid's: a quad tared unloaded then
    pressed with 3 N reads 9.5 % above its measured C0 on every electrode. Without a measured C0 nothing is
    judged and the tare is made, as before."""
    from service.pipeline_changes import LoadedAtTare

    pipeline = pipeline_on(registry_with(tmp_path, c0=c0))
    run(pipeline, [(200, (0.0, 0.0, 0.0), 0.0), (100, (0.0, 0.0, 3.0), 0.0)])
    if not c0:
        assert pipeline.tare(1) == [1]
        return
    with pytest.raises(LoadedAtTare) as refused:  # main: tared, the press its zero
        pipeline.tare(1)
    assert refused.value.taxels == {1: [0, 1, 2, 3]}
    assert pipeline.tare(1, force=True) == [1]
