"""Bad calibration input: each gets a clear error (naming the taxel, the
file or the line), and a sensor the model cannot follow gets an empirical
curve, flagged. Short sessions of a few taxels, at 200 Hz."""
import json

import numpy as np
import pytest

from firmware_sim.board import BoardConfig, capture
from firmware_sim.calibration_session import (Press, ScheduleScene, probe_schedule, reference_csv, run_presses,
                                              session, user_grid_calibration)
from firmware_sim.sensors import SimGrid
from service.calibration.alignment import align, board_response
from service.calibration.calibrate import calibrate
from service.calibration.reference import parse_reference, read_reference
from service.calibration.segmentation import segment
from service.calibration.session import load_session
from service.physics.paper_data import GridCalibration
from service.protocol import FrameType, encode_frame

RATE_HZ = 200.0


def write(tmp_path, raw: bytes, csv: str):
    (tmp_path / "s.bin").write_bytes(raw)
    (tmp_path / "r.csv").write_text(csv)
    return tmp_path / "s.bin", tmp_path / "r.csv"


def files(tmp_path, presses, calibration=None, **board):
    sim = session(calibration, presses, rate_hz=RATE_HZ, seed=5, **board)
    return write(tmp_path, sim.raw, sim.reference_csv)


def custom_sensor_files(tmp_path, presses, forward):
    """A session of a grid whose taxel response is ``forward`` (forces (64,) → ΔC/C0 (64,))."""
    scene = ScheduleScene(presses)
    grid = SimGrid(0, calibration=user_grid_calibration(4))

    class Response:
        def forward(self, forces):
            return forward(np.asarray(forces, float))

    grid.response = Response()
    raw, _ = capture(BoardConfig(sensors=[grid], rate_hz=RATE_HZ, scene=scene, seed=2), scene.end_s)
    return write(tmp_path, raw, reference_csv(scene, scene.end_s, seed=2)[0])


def test_reference_lines_are_counted_and_errors_name_the_file_and_line(tmp_path):
    ref = parse_reference("t_s,force_N\n0.0,1\n\nERR\n0.01,2\n1e9x,3\n0.02,nan\n0.03,4\n", "r.csv")
    assert ref.skipped == 4 and ref.skipped_lines == (3, 4, 6, 7) and list(ref.force_N) == [1, 2, 4]
    with pytest.raises(ValueError, match=r"r\.csv: the reference has no numeric line \(2 lines skipped\)"):
        parse_reference("t_s,force_N\n\nfoo,bar\n", "r.csv")
    with pytest.raises(ValueError, match=r"r\.csv:1: .*header"):
        parse_reference("time,force\n0,1\n", "r.csv")
    with pytest.raises(ValueError, match=r"r\.csv:4: time 0\.5 s does not follow 1\.0 s"):
        parse_reference("t_s,force_N\n0.0,0\n1.0,0\n0.5,0\n", "r.csv")
    with pytest.raises(FileNotFoundError, match="no such reference"):
        read_reference(tmp_path / "missing.csv")


def test_a_taxel_pressed_once_is_refused_by_name(tmp_path):
    presses = probe_schedule(range(6), seed=1) + probe_schedule([12], repeats=1, start_s=40.0)
    with pytest.raises(ValueError, match=r"taxel row 2, col 5 \(index 12\): 1 press \(need at least 2\)"):
        calibrate(*files(tmp_path, presses))


def test_a_taxel_pressed_to_under_half_of_full_scale_is_refused_by_name(tmp_path):
    presses = probe_schedule(range(6), seed=1) + probe_schedule([7], peak_N=4.0, start_s=40.0)
    with pytest.raises(ValueError, match=r"taxel row 1, col 8 \(index 7\): force range 0–4\.\d\d N is under half"):
        calibrate(*files(tmp_path, presses))


def test_saturated_samples_are_refused_by_name(tmp_path):
    c0 = np.full(64, 10.0)
    calibration = GridCalibration(8, 8, c0, user_grid_calibration(4).sensitivity_per_N)
    presses = probe_schedule(range(5), peak_N=5.5, seed=1) + probe_schedule([9], start_s=40.0)
    path, ref = files(tmp_path, presses, calibration, full_scale_pF=10.9)  # 9 %: taxel 9 reaches ~11 %
    with pytest.raises(ValueError, match=r"taxel row 2, col 2 \(index 9\): \d+ saturated samples") as error:
        calibrate(path, ref)
    assert "index 0" not in str(error.value)
    partial = calibrate(path, ref, allow_partial=True)
    assert sorted(partial.fits) == [0, 1, 2, 3, 4] and list(partial.problems) == [9]


def test_a_non_monotone_response_is_refused_by_name(tmp_path):
    presses = probe_schedule(range(6), seed=1)

    def forward(forces):
        r = 0.0125 * forces
        r[3] = 0.02 * forces[3] - 0.0016 * forces[3] ** 2  # turns over at 6.25 N
        return r

    with pytest.raises(ValueError, match=r"taxel row 1, col 4 \(index 3\): non-monotone response"):
        calibrate(*custom_sensor_files(tmp_path, presses, forward))


def test_a_response_the_model_cannot_follow_gets_a_flagged_empirical_curve(tmp_path):
    presses = probe_schedule(range(6), seed=1)

    def forward(forces):
        return 0.02 * forces - 0.0008 * forces ** 2  # concave where the model is convex; monotone to 12.5 N

    result = calibrate(*custom_sensor_files(tmp_path, presses, forward))
    assert {f.model for f in result.fits.values()} == {"empirical"}
    fit = result.fits[2]
    assert fit.chi2_reduced > 4 and fit.residual_rms_N < 0.03
    # the empirical curve is not extrapolated: its slopes span 0 to the largest force pressed
    assert fit.sensitivity_per_N == pytest.approx(0.02 - 0.0008 * fit.max_force_N, rel=0.02)


def test_a_press_on_two_taxels_at_once_is_flagged_and_set_aside():
    t = np.arange(0.0, 6.0, 0.005)
    force = np.where((t > 2) & (t < 4), 5 * np.sin(np.pi * (t - 2) / 2) ** 2, 0.0)
    cap = np.full((t.size, 64), 10.0)
    cap[:, 3] *= 1 + 0.012 * force
    cap[:, 4] *= 1 + 0.010 * force
    presses = segment(t, cap, t, force)
    assert len(presses) == 1 and presses[0].taxel == 3 and "taxels 3 and 4 responded comparably" in presses[0].problem


def test_a_periodic_schedule_on_alike_taxels_is_refused_as_ambiguous(tmp_path):
    uniform = GridCalibration(8, 8, np.full(64, 10.0), np.full(64, 0.0125))
    presses = probe_schedule(range(12), gap_jitter_s=0.0, peak_jitter=0.0)
    sim = session(uniform, presses, rate_hz=RATE_HZ, reference={"head_s": 12.0, "tail_s": 12.0})
    path, ref = write(tmp_path, sim.raw, sim.reference_csv)
    board, reference = load_session(path), read_reference(ref)
    with pytest.raises(ValueError, match="ambiguous alignment"):
        align(board.t_s, board_response(board.t_s, board.capacitance_pF), reference.t_s, reference.force_N)


def test_a_reference_of_another_session_is_refused(tmp_path):
    mine = session(None, probe_schedule(range(8), seed=1), rate_hz=RATE_HZ)
    other = session(None, probe_schedule(range(8), seed=2, gap_s=2.0), rate_hz=RATE_HZ)
    with pytest.raises(ValueError, match="does not match|ambiguous"):
        calibrate(*write(tmp_path, mine.raw, other.reference_csv))


def test_a_session_without_that_grid_names_the_grids_there(tmp_path):
    raw, _, _ = run_presses(user_grid_calibration(), [Press(0, 1.5, 9.0)], rate_hz=RATE_HZ)
    (tmp_path / "s.bin").write_bytes(raw)
    with pytest.raises(ValueError, match=r"no grid sensor 3 in the session \(grids: \[0\]\)"):
        load_session(tmp_path / "s.bin", 3)


def grid_frames(count: int, channels: int, info_shape: tuple[int, int] | None) -> bytes:
    out = bytearray()
    if info_shape is not None:
        info = {"board": "b", "fw": "1", "rate_hz": 200,
                "sensors": [{"id": 0, "kind": "grid", "rows": info_shape[0], "cols": info_shape[1]}]}
        out += encode_frame(FrameType.INFO, 255, 0, 0, json.dumps(info).encode())
    payload = np.full(channels, 10_000_000, "<u4").tobytes()
    for k in range(count):
        out += encode_frame(FrameType.GRID, 0, k, 5000 * k, payload)
    return bytes(out)


def test_frames_of_another_shape_than_the_sensor_are_named_not_counted_as_missing(tmp_path):
    path = tmp_path / "s.bin"
    path.write_bytes(grid_frames(150, 16, None))
    with pytest.raises(ValueError, match=r"150 frames of grid sensor 0 carry 64-byte payloads \(16 channels\), but no "
                                         r"INFO announces it, and a grid without one is read as the protocol's 8x8"):
        load_session(path)
    path.write_bytes(grid_frames(150, 16, (8, 8)))
    with pytest.raises(ValueError, match=r"150 frames of grid sensor 0 carry 64-byte payloads \(16 channels\), but "
                                         r"its INFO announces 8x8 \(256 bytes\)"):
        load_session(path)
    path.write_bytes(grid_frames(150, 16, (4, 4)))
    assert load_session(path).capacitance_pF.shape == (150, 16)


@pytest.mark.parametrize("rate_hz, offset_s, rate_ppm", [(10.0, -3600.5, -200.0), (1000.0, 0.75, 200.0)])
def test_references_at_10_hz_and_1_khz_with_any_offset_and_200_ppm_align(tmp_path, rate_hz, offset_s, rate_ppm):
    reference = {"rate_hz": rate_hz, "offset_s": offset_s, "rate_ppm": rate_ppm}
    sim = session(None, probe_schedule(range(12), seed=4), rate_hz=RATE_HZ, seed=4, reference=reference)
    result = calibrate(*write(tmp_path, sim.raw, sim.reference_csv))
    a = result.alignment
    assert abs(a.offset_s - offset_s) < 3e-3 and abs(a.rate_ppm - rate_ppm) < 40  # a 40 s session: ppm is loose
    mid = 20.0
    assert abs(a.offset_s + mid * a.rate_ppm * 1e-6 - offset_s - mid * rate_ppm * 1e-6) < 1e-3
    gain = np.array([result.fits[t].gain for t in range(12)])
    assert np.abs(gain / sim.gain[:12] - 1).max() < 2e-3


def test_sensor_identity_follows_the_protocol():
    from service.calibration.registry import sensor_identity
    from service.readings import SensorInfo

    grid = SensorInfo(2, "grid", 8, 8)
    assert sensor_identity({"board": "b", "serial": "TMX-1"}, SensorInfo(2, "grid", 8, 8, "A8-9"))["key"] == "sensor:A8-9"
    assert sensor_identity({"board": "b", "serial": "TMX-1"}, grid)["key"] == "board:TMX-1/sensor:2"
    assert sensor_identity({"board": "b"}, grid)["key"] == "board:b/sensor:2"


def test_the_report_lists_the_taxels_not_pressed(tmp_path):
    from service.calibration.calibrate import document
    from service.calibration.registry import builtin_document
    from service.calibration.report import write_report

    sim = session(None, probe_schedule(range(6), seed=1), rate_hz=RATE_HZ, seed=5)
    result = calibrate(*write(tmp_path, sim.raw, sim.reference_csv))
    doc = document(result, builtin_document())
    text = write_report(result, doc, "0123abcd", tmp_path / "report").read_text()
    assert "| r1c6 |" in text and "keep their previous calibration (builtin-table1): r1c7, r1c8, r2c1" in text
    assert (tmp_path / "report" / "response.png").stat().st_size > 10_000
    assert (tmp_path / "report" / "residuals.png").stat().st_size > 5_000


def test_a_reference_in_grams_is_not_stored_and_the_error_says_grams(tmp_path, capsys):
    """Paper 000 weighed with a 0.01 g balance: a reference logged in grams
    under the force_N header fitted sensitivities ~100× too small, was
    stored and activated, and then refused by serve and replay (built-in
    forces, a log line). Nothing is stored now, and the error names it."""
    from service.calibration.registry import Registry
    from service.cli import main

    presses = probe_schedule(range(6), seed=1)
    session_path, reference = files(tmp_path, presses)
    def in_grams(line: str) -> str:
        t, _, force = line.partition(",")
        try:
            return f"{t},{float(force) / 9.80665e-3!r}"
        except ValueError:  # the header and comments stay as they are
            return line

    reference.write_text("\n".join(map(in_grams, reference.read_text().splitlines())) + "\n")
    registry = tmp_path / "reg.sqlite3"
    code = main(["calibrate", str(session_path), "--reference", str(reference), "--partial", "--full-scale", "1000",
                 "--registry", str(registry)])
    error = capsys.readouterr().err
    assert code != 0 and "calibration not stored" in error and "grams" in error, error
    with Registry(registry) as stored:
        assert [d["id"] for d in stored.list() if not d["id"].startswith("builtin")] == []


def test_a_reference_saved_by_a_spreadsheet_with_a_byte_order_mark_is_read(tmp_path):
    (tmp_path / "r.csv").write_bytes("\ufefft_s,force_N\n0.0,1.5\n0.01,2.5\n".encode())
    reference = read_reference(tmp_path / "r.csv")
    assert reference.force_N.tolist() == [1.5, 2.5] and reference.skipped == 0


@pytest.mark.parametrize("level", ["table", "full"])
def test_a_force_past_an_empirical_curves_end_is_flagged_saturated_without_sigma(level):
    """An empirical curve ends at the largest force pressed in the session;
    past it the force was held at that end, unflagged, with the curve's
    small σ (a true 8.5 N read 7.89 ± 0.025 N). Now it is held there and
    flagged saturated with no σ, as a model taxel past the table's top."""
    from dataclasses import replace

    from service.readings import SensorInfo
    from service.reconstruct.calibration_upload import processor_for
    from service.reconstruct.taxel_flags import SATURATED
    from service.reconstruct.sensor_calibration import builtin

    info = SensorInfo(0, "grid", 8, 8)
    relative, force = np.array([0.0, 0.05, 0.1]), np.array([0.0, 4.0, 7.9])
    calibration = replace(builtin(info), curves={2: (relative, force)})
    processor = processor_for(info, level, "flat", calibration)
    c0 = calibration.grid.c0_pF
    frames = np.tile(c0, (3, 1))
    frames[:, 2] *= 1 + np.array([0.05, 0.099, 0.11])  # on the curve, just inside its end, past it
    result = processor.process(frames, c0, np.full(64, 0.002), np.arange(3) * 1e-3)
    assert result.forces_N[:, 2] == pytest.approx([4.0, 4.0 + 0.049 / 0.05 * 3.9, 7.9], abs=2e-3)  # (full: unmixed)
    assert (result.taxel_flags[:, 2] & SATURATED).tolist() == [0, 0, SATURATED]
    assert np.isfinite(result.sigma_N[:2, 2]).all() and np.isnan(result.sigma_N[2, 2])


def test_a_reference_flat_at_its_top_is_said_to_have_saturated():
    """A tester's instrument clipped at 8.00 N: 46 taxels calibrated to 8 N without a word (presses past it read
    as it). Flat in several stretches at exactly its largest value is an instrument at its limit; a held press's
    noise, or one press's quantized top, is not."""
    from service.calibration.reference import flat_top

    rng = np.random.default_rng(1)
    t = np.arange(0, 60, 0.01)
    pressed = 12.0 * np.clip(np.sin(2 * np.pi * t / 6), 0, None) + rng.normal(0, 0.01, len(t))
    assert flat_top(np.minimum(pressed, 8.0)) == (8.0, 10)  # ten presses past 8 N
    assert flat_top(pressed) is None
    quantized = np.round(pressed, 2)
    assert flat_top(quantized) is None  # its largest value once, however coarse the steps
    one_hold = np.r_[np.zeros(100), np.full(200, 5.0), np.zeros(100)]
    assert flat_top(one_hold) is None


def test_calibrate_says_its_reference_saturated(tmp_path):
    presses = probe_schedule(range(6), seed=1)
    raw, ref = files(tmp_path, presses)
    lines = ref.read_text().splitlines()
    forces = [float(line.split(",")[1]) for line in lines[1:] if line and line[0].isdigit()]
    top = round(0.8 * max(forces), 3)
    ref.write_text("\n".join([lines[0]] + [f"{line.split(',')[0]},{min(float(line.split(',')[1]), top)}"
                                           if line and line[0].isdigit() else line for line in lines[1:]]) + "\n")
    from service.calibration.calibrate import document, summary_lines

    result = calibrate(raw, ref, allow_partial=True)
    said = [line for line in summary_lines(result) if "WARNING" in line]
    assert said and f"holds its largest force, {top:.3f} N, flat in" in said[0]
    assert document(result, {})["statistics"]["reference_flat_top_warning"] == said[0]


def test_presses_far_past_the_full_scale_are_named_where_the_alignment_fails(tmp_path, monkeypatch):
    """Three taxels pressed to 25 N made a session 'not the same session' (correlation 0.877): the note says
    what the reference's force may do to the match."""
    import service.calibration.calibrate as calibrate_module

    def refused(*args, **kwargs):
        raise ValueError("the reference does not match the board's response: correlation 0.877")

    monkeypatch.setattr(calibrate_module, "align", refused)
    presses = probe_schedule(range(6), seed=1)
    with pytest.raises(ValueError, match=r"correlation 0\.877; note: the reference reaches \d+\.\d N, past 1\.5× the "
                                         r"full scale \(5 N\)"):
        calibrate(*files(tmp_path, presses), full_scale_N=5.0)


def lbf(ref, newtons=4.448222):
    """The reference rewritten as an instrument logging lbf (or another unit of ``newtons``) under a force_N header would."""
    lines = ref.read_text().splitlines()
    ref.write_text("\n".join([lines[0]] + [f"{line.split(',')[0]},{float(line.split(',')[1]) / newtons}"
                                           if line and line[0].isdigit() else line for line in lines[1:]]) + "\n")


def test_a_reference_in_lbf_is_named_as_a_possible_unit_mistake(tmp_path, capsys):
    """lbf under a force_N header was refused as 'force range under half of full scale', without a word of units;
    with --full-scale 2.2 it was stored, 4.4× the paper's sensitivities, without a word. Then a note after every
    taxel's refusal said lbf or kgf might be why; now the refusal starts with the unit the reference's forces stand
    at against the board's response (table 1's taxels within ±15 % of the model curve at gain 1)."""
    from service.cli import main

    raw, ref = files(tmp_path, probe_schedule(range(6), seed=1))
    lbf(ref)
    with pytest.raises(ValueError, match=r"^cannot calibrate: the reference logs 0\.2\d+× the force the board's response "
                                         r"gives .*, as one in lbf would \(4\.44822 N each\): convert it to N; taxel"):
        calibrate(raw, ref)
    lbf(ref, 9.80665 / 4.448222)  # now in kgf
    with pytest.raises(ValueError, match=r"^cannot calibrate: the reference logs 0\.1\d+× .*, as one in kgf would"):
        calibrate(raw, ref)
    lbf(ref, 4.448222 / 9.80665)  # back in lbf
    registry = tmp_path / "r.sqlite3"
    assert main(["calibrate", str(raw), "--reference", str(ref), "--full-scale", "2.2", "--partial",
                 "--registry", str(registry)]) == 0
    err = capsys.readouterr().err
    assert "WARNING: the fitted slopes" in err and "above the paper's 1.24 %/N: is the reference's force in lbf" in err
