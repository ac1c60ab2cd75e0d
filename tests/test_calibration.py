"""Calibrating a grid that is not table 1 from a simulated reference-load
session: alignment, per-taxel fit, reconstruction before and after, the
registry and the command. Numbers against the simulator's ground truth."""
import argparse
import json
import sqlite3

import numpy as np
import pytest

from firmware_sim.calibration_session import session, validation_capture
from service.calibration import registry as reg
from service.calibration.calibrate import calibrate, document, summary_lines
from service.calibration.cli import add_parsers
from service.physics.taxel_response import TaxelResponse
from service.calibration.fit import unit_response
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor

RATE_HZ = 200.0


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(simulated session, its files, the calibration) — every taxel twice, ~6 min at 200 Hz."""
    sim = session(rate_hz=RATE_HZ, seed=3, sensor_serial="A8-2291", serial="TMX-000123")
    out = tmp_path_factory.mktemp("calibration")
    raw, ref = out / "session.bin", out / "reference.csv"
    raw.write_bytes(sim.raw)
    ref.write_text(sim.reference_csv)
    return sim, raw, ref, calibrate(raw, ref)


def reconstruction_rms(capture, upload: dict | None) -> float:
    """RMS force error (N) on loaded taxels (truth > 0.05 N) of the full-level reconstruction."""
    pipeline = Pipeline(Reconstructor(hold_until_tared=True), clock=lambda: 0.0)
    frames = []
    pipeline.listeners.append(frames.extend)
    pipeline.feed(capture.raw[:4096], 0.0)
    if upload is not None:
        pipeline.set_calibration(pipeline.interpreter.sensors[0], upload)
    pipeline.feed(capture.raw[4096:], 0.0)
    pipeline.finish(0.0)
    truth = dict(zip(capture.truth_t_us.tolist(), capture.truth_N))
    errors = []
    for frame in frames:
        loaded = truth[frame.t_us] > 0.05
        errors.append(np.asarray(frame.forces_N)[loaded] - truth[frame.t_us][loaded])
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


def test_the_clocks_are_aligned_within_a_millisecond_and_a_few_ppm(run):
    sim, _, _, result = run
    a = result.alignment
    assert abs(a.offset_s - sim.offset_s) < 2e-3
    assert abs(a.rate_ppm - sim.rate_ppm) < 10.0
    mid = 180.0  # board time error in the middle of the session, where the presses are
    assert abs((a.offset_s + mid * a.rate_ppm * 1e-6) - (sim.offset_s + mid * sim.rate_ppm * 1e-6)) < 0.5e-3
    assert a.quality > 0.98 and 1 - a.runner_up > 2 * (1 - a.coarse_best)


def test_every_taxel_gets_its_own_gain_sensitivity_and_c0(run):
    sim, _, _, result = run
    assert sorted(result.fits) == list(range(64)) and not result.problems and not result.flagged_presses
    gain = np.array([result.fits[t].gain for t in range(64)])
    se = np.array([result.fits[t].gain_se for t in range(64)])
    assert np.abs(gain / sim.gain - 1).max() < 1e-3  # the truth differs from table 1 by up to 15 %
    assert np.abs(gain - sim.gain).max() < 5 * se.max()  # the standard errors are honest
    sens = np.array([result.fits[t].sensitivity_per_N for t in range(64)])
    assert np.abs(sens / sim.calibration.sensitivity_per_N - 1).max() < 1e-3
    c0 = np.array([result.fits[t].c0_pF for t in range(64)])
    assert np.abs(c0 / sim.calibration.c0_pF - 1).max() < 1e-4
    assert all(f.model == "table" and f.presses == 2 and f.residual_rms_N < 0.02 for f in result.fits.values())


def test_both_sensitivity_readings_are_reported_and_the_ls_one_restores_the_gain(run):
    _, _, _, result = run
    fit = result.fits[21]
    assert 0.015 < 1 - fit.sensitivity_origin_per_N / fit.sensitivity_per_N < 0.04  # the convex curve: ~2.5 %
    unit = unit_response("flat")
    restored = TaxelResponse.from_table(unit.force_N, unit.relative, np.array([fit.sensitivity_per_N])).gain[0]
    assert restored == pytest.approx(fit.gain, rel=1e-9)


def test_reconstruction_of_a_separate_press_sequence_meets_the_noise_budget(run):
    sim, _, _, result = run
    capture = validation_capture(sim.calibration, rate_hz=RATE_HZ)
    before = reconstruction_rms(capture, None)  # table 1
    upload = {"sensitivity_pct_per_N": [100 * result.fits[t].sensitivity_per_N for t in range(64)]}
    after = reconstruction_rms(capture, upload)
    print(f"reconstruction RMS on loaded taxels: table 1 {before:.4f} N, calibrated {after:.4f} N")
    assert before >= 0.15
    assert after <= 0.015


def test_skipped_reference_lines_are_counted(run):
    sim, _, _, result = run
    assert result.reference.skipped == sim.garbage_lines == 4


def test_registry_round_trip_activation_and_the_builtin(run, tmp_path):
    _, _, _, result = run
    with reg.Registry(tmp_path / "a.sqlite3") as first:
        key = "sensor:A8-2291"
        assert first.active(key)["id"] == reg.BUILTIN_ID  # nothing stored yet: table 1
        doc = document(result, first.active(key))
        cid = first.add(doc)
        assert cid == reg.calibration_id(doc) and len(cid) == 16
        assert doc["sensor"]["key"] == key and doc["sensor"]["board_serial"] == "TMX-000123"
        assert first.active(key)["id"] == reg.BUILTIN_ID
        first.activate(cid[:8])
        assert first.active(key)["id"] == cid
        assert [r["id"] for r in first.list() if r["active"]] == [cid]
        first.export(cid, tmp_path / "cal.json")
        with pytest.raises(sqlite3.DatabaseError, match="immutable"):
            first._db.execute("UPDATE calibrations SET created = 'x'")
    with reg.Registry(tmp_path / "b.sqlite3") as second:
        assert second.import_(tmp_path / "cal.json") == cid
        assert second.get(cid)["taxels"] == json.loads((tmp_path / "cal.json").read_text())["taxels"]
        assert second.import_(tmp_path / "cal.json") == cid  # idempotent
        tampered = json.loads((tmp_path / "cal.json").read_text())
        tampered["taxels"]["gain"][0] *= 1.01
        (tmp_path / "bad.json").write_text(json.dumps(tampered))
        with pytest.raises(ValueError, match="does not match its content"):
            second.import_(tmp_path / "bad.json")
        with pytest.raises(ValueError, match="no calibration"):
            second.get("ffff")
        assert "table 1" in second.get(reg.BUILTIN_ID)["note"]


def test_a_failed_write_leaves_nothing_behind(run, tmp_path, monkeypatch):
    _, _, _, result = run
    doc = document(result)
    with reg.Registry(tmp_path / "r.sqlite3") as registry:
        monkeypatch.setattr(registry, "_activate", lambda cid, key: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            registry.add(doc, activate=True)  # the insert ran; the transaction is rolled back
        assert [r["id"] for r in registry.list()] == [reg.BUILTIN_ID]
        with pytest.raises(ValueError):
            registry.add({**doc, "statistics": {"x": float("nan")}})  # not JSON: refused before writing


def test_registry_location_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("TACTILE_REGISTRY", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert reg.default_path() == tmp_path / "xdg" / "tactile" / "registry.sqlite3"
    monkeypatch.setenv("TACTILE_REGISTRY", str(tmp_path / "r.sqlite3"))
    assert reg.default_path() == tmp_path / "r.sqlite3"
    assert reg.Registry(tmp_path / "arg.sqlite3").path == tmp_path / "arg.sqlite3"


def test_partial_session_keeps_the_previous_values_of_taxels_not_pressed(run):
    _, _, _, result = run
    previous = {**reg.builtin_document(), "id": "0123456789abcdef"}
    partial = type(result)(**{**result.__dict__, "fits": {t: result.fits[t] for t in (0, 9)}})
    doc = document(partial, previous)
    assert doc["taxels"]["source"][0] == "this session" and doc["taxels"]["source"][1] == "0123456789abcdef"
    assert doc["taxels"]["sensitivity_pct_per_N"][1] == previous["taxels"]["sensitivity_pct_per_N"][1]
    # Named, not silent: they appeared nowhere (a reference covering part of the session left five so).
    assert doc["statistics"]["taxels_not_pressed"] == [t for t in range(64) if t not in (0, 9)]
    assert f"not pressed, so not calibrated (they keep their previous values): taxels {[t for t in range(64) if t not in (0, 9)]}" \
        in summary_lines(partial)


def test_the_command_calibrates_stores_lists_exports_and_imports(run, tmp_path, capsys):
    _, raw, ref, _ = run
    parser = argparse.ArgumentParser(prog="tactile")
    add_parsers(parser.add_subparsers(dest="command", required=True))

    def call(*argv):
        args = parser.parse_args([str(a) for a in argv])
        assert args.func(args) == 0
        return capsys.readouterr().out

    registry = tmp_path / "r.sqlite3"
    out = call("calibrate", raw, "--reference", ref, "--registry", registry)
    assert "alignment: t_ref" in out and "4 lines skipped" in out
    cid = out.split("stored ")[1].split()[0]
    assert f"* {cid}" in call("calibrations", "list", "--registry", registry)
    call("calibrations", "export", cid, tmp_path / "c.json", "--registry", registry)
    assert f"imported {cid}" in call("calibrations", "import", tmp_path / "c.json", "--registry", tmp_path / "o.sqlite3")
    assert json.loads(call("calibrations", "show", cid, "--registry", registry))["id"] == cid


def test_the_registry_imports_nothing_above_the_physics_the_readings_and_the_calibration_model():
    from pathlib import Path

    from tests.test_layers import imports

    path = Path(reg.__file__)
    ours = [m for _, m in imports(path) if m.startswith("service")]
    allowed = ("service.physics", "service.readings", "service.board_info", "service.reconstruct.sensor_calibration")
    assert ours and all(m.startswith(allowed) for m in ours), ours


def test_an_mcap_recording_calibrates_like_the_raw_capture(run, tmp_path):
    from service.record.mcap_writer import McapLog

    sim, _, ref, result = run
    path = tmp_path / "session.mcap"
    with open(path, "wb") as stream:
        log = McapLog(stream)
        for k in range(0, len(sim.raw), 1 << 16):  # receive times: any increasing clock
            log.raw(sim.raw[k:k + (1 << 16)], 1000.0 + k * 1e-7)
        log.close()
    again = calibrate(path, ref)
    assert again.alignment.offset_s == pytest.approx(result.alignment.offset_s, abs=1e-9)
    assert again.fits[5].gain == pytest.approx(result.fits[5].gain, rel=1e-12)


@pytest.mark.slow
def test_a_six_minute_session_at_1khz_calibrates_in_under_ten_seconds(tmp_path):
    import time

    sim = session(rate_hz=1000.0, seed=11)
    (tmp_path / "s.bin").write_bytes(sim.raw)
    (tmp_path / "r.csv").write_text(sim.reference_csv)
    started = time.perf_counter()
    result = calibrate(tmp_path / "s.bin", tmp_path / "r.csv")
    elapsed = time.perf_counter() - started
    capture = validation_capture(sim.calibration, rate_hz=1000.0)
    upload = {"sensitivity_pct_per_N": [100 * result.fits[t].sensitivity_per_N for t in range(64)]}
    before, after = reconstruction_rms(capture, None), reconstruction_rms(capture, upload)
    a = result.alignment
    print(f"{len(result.session.t_s)} frames calibrated in {elapsed:.2f} s ({result.timings_s}); alignment error "
          f"{1e3 * (a.offset_s - sim.offset_s):+.3f} ms, {a.rate_ppm - sim.rate_ppm:+.2f} ppm; RMS table 1 "
          f"{before:.4f} N, calibrated {after:.4f} N")
    assert elapsed < 10.0 and after <= 0.015 and before >= 0.15


def test_a_table_imports_only_with_its_sensitivity_reading_named(tmp_path, capsys):
    """Table 1 itself, imported in both readings: the intercept reading gives
    the built-in gains; read through the origin, the same numbers need gains
    ~2.3 % higher (the origin slope of this curve is the lower one)."""
    from service.calibration.cli import main
    from service.physics.paper_data import table1

    table = tmp_path / "table.csv"
    base = table1()
    table.write_text("row,col,c0_pF,sensitivity_pct_per_N\n" + "".join(
        f"{t // 8 + 1},{t % 8 + 1},{base.c0_pF[t]},{100 * base.sensitivity_per_N[t]}\n" for t in range(64)))
    registry = str(tmp_path / "r.sqlite3")
    assert main(["calibrations", "import", str(table), "--registry", registry]) == 2
    assert "--sensitivity-fit intercept|origin" in capsys.readouterr().err
    ids = {}
    for reading in ("intercept", "origin"):
        assert main(["calibrations", "import", str(table), "--registry", registry, "--sensitivity-fit", reading,
                     "--sensor-key", "sensor:T1"]) == 0
        ids[reading] = capsys.readouterr().out.split()[1]
    with reg.Registry(registry) as r:
        intercept, origin = (np.array(r.get(ids[k])["taxels"]["gain"]) for k in ("intercept", "origin"))
    np.testing.assert_allclose(intercept, reg.builtin_document()["taxels"]["gain"], rtol=1e-12)
    assert 0.015 < float(np.mean(origin / intercept - 1)) < 0.04
    bad = tmp_path / "bad.csv"
    bad.write_text("row,col,c0_pF,sensitivity_pct_per_N\n1,1,9.7,abc\n")
    assert main(["calibrations", "import", str(bad), "--registry", registry, "--sensitivity-fit", "origin",
                 "--sensor-key", "sensor:T1"]) == 2
    assert "bad.csv, line 2" in capsys.readouterr().err
