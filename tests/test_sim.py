"""The board simulator: protocol, commands, pacing, noise and its transports."""
import os
import threading
import time

import numpy as np
import orjson
import pytest
import serial

from firmware_sim import frontends
from firmware_sim.board import Board, BoardConfig, capture
from firmware_sim.sensors import Drift, SimGrid, SimQuad
from service.physics.paper_data import table1
from service.protocol import FLAG_OVERRUN, FrameType
from service.protocol_decoder import Decoder
from service.sources import open_source


def decode(data):
    decoder = Decoder()
    frames = decoder.feed(data) + decoder.finish()
    assert decoder.counters.bytes_discarded == 0
    return frames


def test_capture_is_paced_and_starts_with_info():
    data, _ = capture(BoardConfig(rate_hz=500), 2.0)
    frames = decode(data)
    assert frames[0].type == FrameType.INFO
    info = orjson.loads(frames[0].payload)
    assert info["sensors"] == [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}, {"id": 1, "kind": "quad"}]
    grid = [f for f in frames if f.type == FrameType.GRID]
    assert len(grid) == 1000
    assert [f.seq for f in grid] == list(range(1000))
    assert np.diff([f.t_us for f in grid]).tolist() == [2000] * 999


def test_idle_grid_reads_table1_with_1fF_noise():
    data, _ = capture(BoardConfig(scene="idle", noise_fF=1.0, seed=3), 2.0)
    counts = np.array([np.frombuffer(f.payload, "<u4") for f in decode(data) if f.type == FrameType.GRID], float)
    c0_aF = table1().c0_pF * 1e6
    np.testing.assert_allclose(counts.mean(axis=0), c0_aF, atol=150)  # 4 sigma of a 2000-sample mean of 1 fF
    assert counts.std(axis=0).mean() == pytest.approx(1000, rel=0.03)


def test_press_truth_matches_capacitance():
    data, board = capture(BoardConfig(scene="press", noise_fF=0.0), 2.0, keep_truth=True)
    grid_truth = {t.seq: t.values for t in board.truth if t.sensor == 0}
    peak = max(grid_truth.values(), key=lambda v: v.max())
    assert peak.argmax() == 27 and peak.max() == pytest.approx(5.0, abs=1e-3)
    sensor = SimGrid(0)
    for frame in decode(data):
        if frame.type == FrameType.GRID:
            expected = np.rint(sensor.capacitance(grid_truth[frame.seq], frame.t_us * 1e-6) * 1e6)
            np.testing.assert_array_equal(np.frombuffer(frame.payload, "<u4"), expected)


def test_quad_follows_the_paper_fits():
    quad = SimQuad(1)
    c = quad.capacitance(np.array([0.0, 0.0, 10.0]))
    np.testing.assert_allclose(c / np.array(quad.c0_pF) - 1, 0.0343 * 10 - 0.0009 * 100)
    r = quad.capacitance(np.array([4.0, 0.0, 0.0])) / np.array(quad.c0_pF) - 1
    shear = 0.0077 * 4 - 0.0004 * 16
    np.testing.assert_allclose(r, [-shear, shear, -shear, shear])
    # Past the usable range the response is held, never falling.
    held = quad.capacitance(np.array([0.0, 0.0, 25.0]))
    assert np.all(held == quad.capacitance(np.array([0.0, 0.0, 0.9 * 0.0343 / 0.0018])))


def test_grid_effects_crosstalk_leakage_drift():
    plain = SimGrid(0, mechanical_coupling=0.0)
    forces = np.zeros(64)
    forces[27] = 5.0
    base = plain.capacitance(forces)
    coupled = SimGrid(0).capacitance(forces)
    r_peak = base[27] / plain.c0_pF[27] - 1
    neighbours = [18, 19, 20, 26, 28, 34, 35, 36]
    np.testing.assert_allclose(coupled[neighbours] / plain.c0_pF[neighbours] - 1, -0.0028 * r_peak, rtol=1e-9)
    leaky = SimGrid(0, mechanical_coupling=0.0, electrical_leakage=0.01).capacitance(forces)
    assert leaky[28] - base[28] == pytest.approx(0.01 * (base[27] - base[28]))
    drifting = SimGrid(0, mechanical_coupling=0.0, drift=Drift(0.002, 40.0)).capacitance(np.zeros(64), t=10.0)
    np.testing.assert_allclose(drifting / plain.c0_pF - 1, 0.002)


def test_commands():
    board = Board(BoardConfig())
    board.advance(0.01)
    assert board.receive(b"STOP\n") == b""
    assert board.advance(0.02) == b""
    board.receive(b"START\nRATE 100\n")
    frames = decode(board.advance(0.0705))
    assert len([f for f in frames if f.type == FrameType.GRID]) == 5
    (info,) = decode(board.receive(b"INFO?\n"))
    assert orjson.loads(info.payload)["rate_hz"] == 100
    (pong,) = decode(board.receive(b"PING\r\n"))
    assert orjson.loads(pong.payload)["pong"] is True
    errors = decode(board.receive(b"start\nRATE 0\nRATE fast\nRATE 5001\n"))
    assert [f.type for f in errors] == [FrameType.ERROR] * 4
    assert errors[0].payload == b"unknown command"
    assert b"RATE takes an integer" in errors[1].payload


def test_scans_that_do_not_fit_are_dropped_with_overrun():
    board = Board(BoardConfig())
    assert board.advance(0.1, room=0) == b""
    frames = decode(board.advance(0.101))
    grid = [f for f in frames if f.type == FrameType.GRID]
    assert grid[0].seq == 100 and grid[0].flags & FLAG_OVERRUN


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="unknown scene 'nope'"):
        BoardConfig(scene="nope")
    with pytest.raises(ValueError, match="rate_hz=0"):
        BoardConfig(rate_hz=0)


def test_sim_url_through_pyserial():
    port = open_source("sim://?scene=press&rate=2000&sensors=grid4x4,quad")
    try:
        deadline = time.monotonic() + 0.3
        data = b""
        while time.monotonic() < deadline:
            data += port.read(0.05)
    finally:
        port.close()
    frames = decode(data)
    info = orjson.loads(frames[0].payload)
    assert info["sensors"][0] == {"id": 0, "kind": "grid", "rows": 4, "cols": 4}
    grid = [f for f in frames if f.type == FrameType.GRID]
    assert 400 <= len(grid) <= 700  # ~0.3 s at 2 kHz, allowing for scheduling
    assert all(len(f.payload) == 64 for f in grid)


def test_bad_sim_url_is_named():
    with pytest.raises(OSError, match="unknown option 'bogus'"):
        open_source("sim://?bogus=1")


def test_simulator_through_a_real_pty():
    master, slave, path = frontends.open_pty()
    stop = threading.Event()
    worker = threading.Thread(target=frontends.serve_pty, args=(BoardConfig(scene="idle"), master, stop))
    worker.start()
    try:
        with serial.Serial(path, 2_000_000, timeout=0.05) as port:
            port.write(b"INFO?\n")
            data = b""
            deadline = time.monotonic() + 0.5
            while time.monotonic() < deadline:
                data += port.read(4096)
    finally:
        stop.set()
        worker.join()
        os.close(master)
        os.close(slave)
    decoder = Decoder()
    frames = decoder.feed(data)
    infos = [f for f in frames if f.type == FrameType.INFO]
    assert len(infos) >= 1
    grid = [f for f in frames if f.type == FrameType.GRID]
    assert len(grid) >= 200
    assert decoder.counters.crc_errors == 0
