"""What /health says of a link and of each sensor: up, stale, finished."""
import asyncio
import time

import numpy as np
import orjson

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimGrid, SimQuad
from service.health import health_report, stale_after_s
from service.live_service import TactileService
from service.protocol import FrameType, encode_frame


def test_the_stale_threshold_follows_the_announced_rate():
    assert stale_after_s({"rate_hz": 1000}) == 0.5
    assert stale_after_s({"rate_hz": 10}) == 2.0  # 20 scan periods
    assert stale_after_s({"rate_hz": "fast"}) == stale_after_s({"rate_hz": True}) == stale_after_s({}) == 0.5


def test_a_sensor_that_stops_while_another_streams_is_stale_on_its_own():
    service = TactileService("sim://")
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="idle"), 0.3)
    now = time.time()
    service.pipeline.feed(data, now - 1.0)  # both sensors, a second ago
    grid_only = b"".join(encode_frame(FrameType.GRID, 0, 1000 + i, 10**6 + i * 1000, bytes(range(256)))
                         for i in range(3))
    service.pipeline.feed(grid_only, now)
    report = health_report(service)
    assert report["sensors"]["0"]["stale"] is False
    assert report["sensors"]["1"]["stale"] is True and report["sensors"]["1"]["rate_hz"] == 0.0
    assert report["sensors"]["1"]["last_frame_age_s"] >= 1.0
    assert report["status"] == "degraded"


def test_the_end_of_a_replay_is_finished_not_ok(tmp_path):
    run = tmp_path / "run.bin"
    run.write_bytes(capture(BoardConfig(scene="press"), 0.3)[0])
    service = TactileService(f"replay://{run}?speed=max")

    async def scenario():
        service.start()
        try:
            deadline = time.monotonic() + 5
            while service.health()["link"]["state"] != "finished" and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            return service.health()
        finally:
            service.stop()

    report = asyncio.run(scenario())
    assert report["link"]["state"] == "finished" and report["replay"] is True
    assert report["status"] == "degraded" and report["link"]["connects"] == 1  # not reopened from the start
    assert orjson.dumps(report)


def test_a_sensor_whose_reconstruction_fails_degrades_health_by_name_while_the_others_flow(monkeypatch):
    from service.reconstruct import quad

    def broken(self, capacitance, baseline, noise, sensitivity=1.0, stale=None):
        raise FloatingPointError("model out of its domain")

    service = TactileService("sim://")
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="press"), 0.4)
    now = time.time()
    service.pipeline.feed(data[: len(data) // 2], now)
    monkeypatch.setattr(quad.QuadProcessor, "process", broken)
    frames = service.pipeline.feed(data[len(data) // 2:], now)
    report = health_report(service)
    quads = [f for f in frames if f.sensor.id == 1 and "taring" not in f.flags]
    grids = [f for f in frames if f.sensor.id == 0]
    assert quads and all("reconstruction_error" in f.flags and np.isnan(f.forces_N).all() for f in quads)
    assert grids and not any("reconstruction_error" in f.flags for f in grids)
    assert not np.isnan(grids[-1].forces_N).all()
    assert report["status"] == "degraded"
    assert any(p.startswith("sensor 1 reconstruction fails: FloatingPointError") for p in report["problems"])
    assert report["reconstruction"]["errors"]["1"]["active"] is True and "0" not in report["reconstruction"]["errors"]


def test_the_binary_encoding_carries_the_reconstruction_error_flag():
    from service.fanout.encoding import FRAME_FLAG_BITS, decode_binary, to_binary
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    frame = ForceFrame(SensorInfo(1, "quad", 2, 2), 7, 7000, 1.0, np.full(3, np.nan), np.ones(4),
                       ["reconstruction_error"], "full")
    assert "reconstruction_error" in FRAME_FLAG_BITS
    import struct
    decoded = decode_binary(struct.pack("<H", 1) + to_binary(frame, frozenset({"force", "flags"})))
    assert decoded[0]["flags"] == ["reconstruction_error"]


def test_a_channel_without_a_zero_and_a_sensor_the_info_does_not_list_are_problems_by_name():
    """A grid channel stuck at the converter's top since power-up gets no
    zero from the tare; a sensor streams that the INFO does not describe.
    Both are said in /health, not only in the frames' flags."""
    service = TactileService("sim://")
    info = orjson.dumps({"board": "b", "serial": "B-1", "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]})
    counts = np.full(64, 10_000_000, "<u4")
    counts[5] = 0xFFFFFFFE  # the converter's top count: not a sentinel, not a capacitance either
    scans = b"".join(encode_frame(FrameType.GRID, 0, s, 1000 * (s + 1), counts.tobytes())
                     + encode_frame(FrameType.QUAD, 3, s, 1000 * (s + 1), np.full(4, 2_200_000, "<u4").tobytes())
                     for s in range(150))
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, info) + scans, time.time())
    report = health_report(service)
    assert report["sensors"]["0"]["unzeroed_channels"] == [5] and report["sensors"]["0"]["not_in_info"] is False
    assert report["sensors"]["3"]["not_in_info"] is True and report["sensors"]["3"]["unzeroed_channels"] == []
    assert report["status"] == "degraded"
    assert any("sensor 0: channels [5] have no zero" in p for p in report["problems"])
    assert any("sensor 3 sends data but the board's INFO does not list it" in p for p in report["problems"])
    latest = service.pipeline.latest[0]
    assert np.isnan(latest.forces_N[5]) and "out_of_range" in latest.flags


def test_readings_left_out_of_a_tare_as_glitches_are_told():
    """A glitch in the tare window is left out of the zero (baseline.py);
    /health says which channels lost readings so, since a load let go in
    the middle of the window is left out the same way."""
    service = TactileService("sim://")
    info = orjson.dumps({"board": "b", "serial": "B-2", "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]})
    rng = np.random.default_rng(3)
    scans = []
    for s in range(150):
        counts = (10_000_000 + rng.normal(0, 1500, 64)).astype("<u4")
        if s == 40:
            counts[20] *= 3
        scans.append(encode_frame(FrameType.GRID, 0, s, 1000 * (s + 1), counts.tobytes()))
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, info) + b"".join(scans), time.time())
    assert health_report(service)["sensors"]["0"]["tare_glitches"] == {"20": 1}


def test_a_sensor_tared_under_a_load_since_removed_reads_below_zero_and_says_so():
    """A grid's two taxels and a quad pressed while the service tared, then
    let go: they read below their zero (grid: out of range at 0 N; quad: Fz 0,
    normal_out_of_range), and /health names them with what to do."""
    rng = np.random.default_rng(8)
    service = TactileService("sim://")
    grid, quad = np.full(64, 10_660_000.0), np.full(4, 2_200_000.0)
    pressed_grid, pressed_quad = grid.copy(), quad * 1.05
    pressed_grid[[9, 10]] *= 1.05

    def frames(seq0, count, grid_counts, quad_counts):
        out = b""
        for i in range(seq0, seq0 + count):
            out += encode_frame(FrameType.GRID, 0, i, i * 1000, (grid_counts + rng.normal(0, 500, 64)).astype("<u4").tobytes())
            out += encode_frame(FrameType.QUAD, 1, i, i * 1000, (quad_counts + rng.normal(0, 500, 4)).astype("<u4").tobytes())
        return out

    now = time.time()
    service.pipeline.feed(frames(0, 150, pressed_grid, pressed_quad), now - 2.0)
    report = health_report(service)
    assert report["sensors"]["0"]["below_zero"] == [] and report["sensors"]["1"]["below_zero"] == []
    released = service.pipeline.feed(frames(150, 200, grid, quad), now)
    last_grid = [f for f in released if f.sensor.id == 0][-1]
    last_quad = [f for f in released if f.sensor.id == 1][-1]
    # The full level's unmixing takes the pressed taxels' neighbours' share back out of them, now and then
    # below −5σ too: /health names the taxels below their zero in 90 % of the last second's frames.
    below = last_grid.taxel_flag_lists()["out_of_range"]
    assert {9, 10} <= set(below) and not last_grid.forces_N[below].any()
    below = [9, 10]
    assert "normal_out_of_range" in last_quad.flags and last_quad.forces_N[2] == 0.0
    report = health_report(service)
    assert report["sensors"]["0"]["below_zero"] == below and report["sensors"]["1"]["below_zero"] == [2]
    board = report["sensors"]["0"]["board"]  # the address's path: a bare id is ambiguous with several boards
    assert f"sensor 0: taxels {below} read below their tared zero for 1 s: tared under a load since removed? " \
           f"Tare it again unloaded (POST /sensors/{board}/0/tare)" in report["problems"]
    assert any(p.startswith("sensor 1: its normal force reads below its tared zero") for p in report["problems"])
    assert orjson.dumps(report)


def test_a_sensor_the_board_no_longer_lists_and_that_sends_nothing_is_retired_not_a_problem():
    """A board's new INFO drops sensor 1, which stops: /health said "sensor 1
    stale" and "sends data but the board's INFO does not list it" for ever,
    the second false. Now it is retired (listed as such), not a problem; a
    sensor dropped from INFO that goes on sending is still one."""
    service = TactileService("sim://")
    both = orjson.dumps({"board": "b", "sensors": [{"id": 0, "kind": "quad"}, {"id": 1, "kind": "quad"}]})
    only0 = orjson.dumps({"board": "b", "sensors": [{"id": 0, "kind": "quad"}]})
    quad = np.full(4, 2_200_000, "<u4").tobytes()
    now = time.time()
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, both) + b"".join(
        encode_frame(FrameType.QUAD, sid, s, 1000 * (s + 1), quad) for s in range(150) for sid in (0, 1)), now - 2.0)
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 151_000, only0) + b"".join(
        encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(151, 300)), now)
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is True and report["sensors"]["0"]["retired"] is False
    assert not any("sensor 1" in p for p in report["problems"])  # (the link itself is down: never started)
    service.pipeline.feed(encode_frame(FrameType.QUAD, 1, 150, 300_000, quad), now)  # it sends again, unlisted
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is False
    assert any("sensor 1 sends data but the board's INFO does not list it" in p for p in report["problems"])


def quads_0_and_1_with_an_info_of_0(ago_s: float):
    """(service, the INFO listing quad 0 only, a quad payload, now): 150 scans of quads 0 and 1 fed ``ago_s``
    before now."""
    service = TactileService("sim://")
    only0 = orjson.dumps({"board": "b", "sensors": [{"id": 0, "kind": "quad"}]})
    quad = np.full(4, 2_200_000, "<u4").tobytes()
    now = time.time()
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(
        encode_frame(FrameType.QUAD, sid, s, 1000 * (s + 1), quad) for s in range(150) for sid in (0, 1)), now - ago_s)
    return service, only0, quad, now


def test_a_sensor_no_info_ever_listed_that_stops_is_stale_not_retired():
    """Sensors an INFO never described (a board whose INFO cannot list them
    all) are not retired when they stop: that is a failure, said as one."""
    service, only0, quad, now = quads_0_and_1_with_an_info_of_0(2.0)
    service.pipeline.feed(b"".join(encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(150, 300)),
                          now)
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is False and report["sensors"]["1"]["stale"] is True
    assert "sensor 1 stale" in report["problems"]


def test_a_sensor_no_info_listed_that_stopped_before_the_board_restarted_without_it_is_retired():
    """An unlisted sensor that stopped, then a board restart whose INFO
    again does not list it: /health said "stale" and "sends data but the
    board's INFO does not list it" for good (43 s after its last frame). It
    is retired; "sends data" is said only of a sensor that does."""
    service, only0, quad, now = quads_0_and_1_with_an_info_of_0(3.0)
    report = health_report(service)
    assert report["sensors"]["1"]["stale"] and not report["sensors"]["1"]["retired"]
    assert "sensor 1 stale" in report["problems"]
    assert not any("sends data" in p for p in report["problems"])  # it sends nothing now
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(  # restarted: 0 from 0 again
        encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(150)), now)
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is True
    assert not any("sensor 1" in p for p in report["problems"])
    # The restart's INFO in the very read that held sensor 1's last frames (one receive time for both).
    service = TactileService("sim://")
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(
        encode_frame(FrameType.QUAD, sid, s, 1000 * (s + 1), quad) for s in range(150) for sid in (0, 1))
        + encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(
        encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(150)), now - 3.0)
    service.pipeline.feed(b"".join(encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(150, 300)), now)
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is True and not any("sensor 1" in p for p in report["problems"])
    # An INFO alone (the reply to INFO? on a reconnect or a silence) is no restart: sensor 1 failed, and says so.
    service = TactileService("sim://")
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(
        encode_frame(FrameType.QUAD, sid, s, 1000 * (s + 1), quad) for s in range(150) for sid in (0, 1)), now - 3.0)
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, only0) + b"".join(
        encode_frame(FrameType.QUAD, 0, s, 1000 * (s + 1), quad) for s in range(150, 300)), now)
    report = health_report(service)
    assert report["sensors"]["1"]["retired"] is False and "sensor 1 stale" in report["problems"]


def test_below_zero_is_told_on_a_slow_board_too():
    """At 10 scans/s a second holds 10 frames, fewer than the 20 the rule
    wants: the last 20 frames are looked at, however long they took."""
    from service.history import History
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    info = SensorInfo(1, "quad", 2, 2)
    history = History(info, 100, 3)
    for k in range(30):
        history.append(ForceFrame(info, k, k * 100_000, 1000.0 + 0.1 * k, np.array([0.0, 0.0, 0.0]), np.ones(4),
                                  ["normal_out_of_range"], "full"))
    assert history.below_zero() == [2]


def test_a_silent_link_is_not_blamed_on_an_error_from_before_it_connected():
    """A board connected and silent was "link stale: cannot open …
    Connection refused", an error of an earlier attempt."""
    from service.health import _problems
    from service.readout import LinkState

    link = LinkState("socket://127.0.0.1:1")
    link.last_error = "cannot open 'socket://127.0.0.1:1': Connection refused"
    link.up, link.connected_at = True, 100.0
    problems = _problems(link.as_dict(102.0, 0.5), {}, {})
    assert problems == ["link stale: connected, no bytes for 2 s"]
    link.up = False
    assert _problems(link.as_dict(103.0, 0.5), {}, {}) == ["link down: " + link.last_error]


def test_a_link_reopened_on_a_silent_board_is_stale_until_a_byte_comes():
    """A board paused (TCP open): the readout reopened the link every ~2.5 s
    and /health said "up" after each reopen while the last byte was 2.6 s,
    then 5.2 s old. Silence counts from the last byte, across a reopen."""
    from service.health import _problems
    from service.readout import LinkState

    link = LinkState("socket://127.0.0.1:1")
    link.up, link.connected_at, link.last_data_time = True, 97.0, 100.0  # bytes until 100 s
    link.connected_at, link.last_error = 102.5, "no bytes for 2.0 s, not even after INFO?"  # reopened at 102.5 s
    report = link.as_dict(102.6, 0.5)
    assert (report["state"], report["silent_s"], report["last_data_age_s"]) == ("stale", 2.6, 2.6)
    assert _problems(report, {}, {}) == ["link stale: connected, no bytes for 2.6 s"]
    link.last_data_time = 102.7  # the board speaks again
    assert link.as_dict(102.8, 0.5)["state"] == "up"
    fresh = LinkState("socket://127.0.0.1:1")  # first open, no byte yet: up within the threshold, as before
    fresh.up, fresh.connected_at = True, 100.0
    assert [fresh.state(t, 0.5) for t in (100.3, 100.6)] == ["up", "stale"]
