"""What /health has counted, it names: a sensor whose frames are dropped
(and why), ERROR frames from the board, corrupt frames above 1 % of the
link's data frames, a link whose bytes are mostly no frame: one line each,
over the last 10 s, gone once the problem stops. They were counters only
(900 frames of a sensor rejected showed as "sensor 2 stale", as if nothing
came; 30 ERROR frames and 19 % of a quad's frames failing their CRC, as
nothing; 1.20 MB of garbage in 1.29 MB, as nothing). ERROR frames are no
data frames: 20 % of the data frames corrupt among 7 times as many ERROR
frames read "2 %"."""
import time

import numpy as np
import orjson

from service.live_service import TactileService
from service.protocol import FrameType, encode_frame

QUAD = np.full(4, 2_200_000, "<u4").tobytes()
GRID_8X8 = np.full(64, 10_000_000, "<u4").tobytes()
INFO = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(
    {"board": "b", "rate_hz": 200, "sensors": [{"id": 0, "kind": "quad"}, {"id": 2, "kind": "grid", "rows": 4, "cols": 6}]}))


def quads(first: int, count: int, sensors=(0,)) -> bytes:
    """``count`` scans of the quads ``sensors`` from scan ``first``, 5 ms apart (200 Hz)."""
    return b"".join(encode_frame(FrameType.QUAD, sid, s, 5000 * (s + 1), QUAD) for s in range(first, first + count)
                    for sid in sensors)


def lines_of(report: dict, sensor: int) -> list[str]:
    return [p for p in report["problems"] if p.startswith(f"sensor {sensor}:") or p.startswith(f"sensor {sensor} ")]


def misshapen(first: int, count: int) -> bytes:
    """Quad 0's scans, with sensor 2 sending 8x8 grids (the INFO says 4x6) and unlisted sensor 7 80-byte grids."""
    return b"".join(encode_frame(FrameType.QUAD, 0, s, 5000 * (s + 1), QUAD)
                    + encode_frame(FrameType.GRID, 2, s, 5000 * (s + 1), GRID_8X8)
                    + encode_frame(FrameType.GRID, 7, s, 5000 * (s + 1), GRID_8X8[:80]) for s in range(first, first + count))


def test_a_sensor_whose_frames_are_all_dropped_is_named_with_why_not_called_stale():
    service = TactileService("sim://")
    service.pipeline.feed(INFO + misshapen(0, 200), time.time())
    report = service.health()
    assert report["rejected"]["shape_mismatch"] == 200 and report["rejected"]["unknown_shape"] == 200
    assert lines_of(report, 2) == ["sensor 2: 200 frames dropped in the last 10 s: 256-byte GRID frames where the "
                                   "board's INFO describes a 4x6 grid (96 bytes)"]
    assert lines_of(report, 7) == ["sensor 7: 200 frames dropped in the last 10 s: 80-byte GRID frames, and the "
                                   "board's INFO does not describe it (without a description only a 256-byte GRID "
                                   "frame is read, as an 8x8 grid)"]
    assert lines_of(report, 0) == []


def test_without_info_a_dropped_frame_is_told_against_what_the_sensor_was_taken_as():
    service = TactileService("sim://")
    service.pipeline.feed(quads(0, 50, sensors=(3,)) + b"".join(
        encode_frame(FrameType.GRID, 3, s, 5000 * (s + 1), GRID_8X8) + encode_frame(FrameType.GRID, 4, s, 5000 * (s + 1),
                                                                                 GRID_8X8[:64]) for s in range(50, 80)),
        time.time())
    report = service.health()
    assert lines_of(report, 3) == ["sensor 3: 30 frames dropped in the last 10 s: 256-byte GRID frames where it was "
                                   "taken as a quad (16 bytes)"]
    assert lines_of(report, 4) == ["sensor 4: 30 frames dropped in the last 10 s: 64-byte GRID frames, and no INFO "
                                   "came (without a description only a 256-byte GRID frame is read, as an 8x8 grid)"]


def test_dropped_frames_are_forgotten_10_s_after_the_last():
    service = TactileService("sim://")
    now = time.time()
    service.pipeline.feed(INFO + misshapen(0, 200), now - 12.0)
    service.pipeline.feed(quads(200, 100), now)
    report = service.health()
    assert lines_of(report, 2) == ["sensor 2 stale"] and lines_of(report, 7) == []  # it sends nothing now
    assert report["rejected"]["shape_mismatch"] == 200  # the count stays


def test_error_frames_from_the_board_are_one_line_with_the_latest_text_until_they_stop():
    service = TactileService("sim://")
    now = time.time()
    errors = b"".join(quads(s, 20) + encode_frame(FrameType.ERROR, 255, 0, 5000 * (s + 20), text)
                      for s, text in ((20 * k, b"mux settle timeout" if k < 29 else b"adc\x1b[2J overrun")
                                      for k in range(30)))
    service.pipeline.feed(INFO + errors, now)
    report = service.health()
    assert [p for p in report["problems"] if "ERROR" in p] == [
        "the board sent 30 ERROR frames in the last 10 s, the latest: \"adc\\x1b[2J overrun\""]
    service = TactileService("sim://")
    service.pipeline.feed(INFO + errors, now - 12.0)
    service.pipeline.feed(quads(600, 100), now)
    report = service.health()
    assert report["boards"]["b"]["board_error_count"] == 30 and not [p for p in report["problems"] if "ERROR" in p]


def corrupt(scans: bytes, every: int, sensor: int) -> tuple[bytes, int]:
    """``scans`` with every ``every``-th frame of ``sensor`` spoiled in its payload, and how many were."""
    frames, spoiled, out, n = scans.split(b"\xa5\x5a")[1:], 0, b"", 0
    for body in frames:
        frame = bytearray(b"\xa5\x5a" + body)
        if frame[4] == sensor:
            n += 1
            if n % every == 0:
                frame[20] ^= 0x40
                spoiled += 1
        out += bytes(frame)
    return out, spoiled


def test_a_burst_of_corrupt_frames_is_one_line_naming_the_sensor_a_rare_one_none():
    service = TactileService("sim://")
    data, spoiled = corrupt(quads(0, 1000, sensors=(0, 1)), 5, sensor=1)
    assert spoiled == 200
    service.pipeline.feed(data, time.time())
    report = service.health()
    assert report["stream"]["crc_errors"] == 200
    assert [p for p in report["problems"] if "CRC" in p] == [
        "200 of 2000 data frames (10 %) in the last 10 s failed their CRC check and were dropped, by their headers "
        "from sensor 1 (200): a loose cable or connector, electrical noise, or a wrong baud rate?"]
    service = TactileService("sim://")
    data, spoiled = corrupt(quads(0, 1000, sensors=(0, 1)), 500, sensor=1)  # 2 of 2000: 0.1 %
    service.pipeline.feed(data, time.time())
    report = service.health()
    assert report["stream"]["crc_errors"] == spoiled == 2 and not [p for p in report["problems"] if "CRC" in p]


def test_corrupt_frames_are_forgotten_10_s_after_the_burst():
    service = TactileService("sim://")
    now = time.time()
    data, _ = corrupt(quads(0, 1000, sensors=(0, 1)), 5, sensor=1)
    service.pipeline.feed(data, now - 12.0)
    service.pipeline.feed(quads(1000, 200, sensors=(0, 1)), now)
    report = service.health()
    assert report["stream"]["crc_errors"] == 200 and not [p for p in report["problems"] if "CRC" in p]


def test_the_crc_share_is_of_the_data_frames_not_the_board_s_error_frames():
    """The tester's board: ERROR frames 7x its data frames, 20 % of these
    corrupt, read "310 of 15211 frames (2 %)". ERROR and INFO frames are no
    data frames: 200 of 1000 (20 %) here, among 7000 ERROR frames."""
    service = TactileService("sim://")
    error = encode_frame(FrameType.ERROR, 255, 0, 0, b"mux settle timeout")
    scans = b"".join(quads(s, 1, sensors=(0, 1)) + error * 14 for s in range(500))
    data, spoiled = corrupt(scans, 2, sensor=1)
    assert spoiled == 250
    service.pipeline.feed(INFO + data, time.time())
    report = service.health()
    assert report["stream"]["frames"] == 1 + 750 + 7000 and report["stream"]["crc_errors"] == 250
    assert [p for p in report["problems"] if "CRC" in p] == [
        "250 of 1000 data frames (25 %) in the last 10 s failed their CRC check and were dropped, by their headers "
        "from sensor 1 (250): a loose cable or connector, electrical noise, or a wrong baud rate?"]


GARBAGE = bytes(b for b in range(256) if b != 0xA5)  # no sync byte: every one skipped, none taken for a frame


def test_a_link_that_is_mostly_garbage_is_named_with_its_share_until_it_stops():
    """300 bytes of garbage after each 32-byte scan (the tester's: 1.20 MB
    of 1.29 MB skipped in 4 s, status ok): one line with the bytes skipped
    and received, every frame still read; gone 10 s after."""
    service = TactileService("sim://")
    data = INFO + b"".join(quads(s, 1) + GARBAGE + GARBAGE[:45] for s in range(200))
    service.pipeline.feed(data, time.time())
    report = service.health()
    assert report["boards"]["b"]["sensors"]["0"]["frames"] == 200 and report["stream"]["bytes_discarded"] == 60000
    assert [p for p in report["problems"] if "bytes" in p] == [
        f"60000 of {len(data)} bytes ({100 * 60000 / len(data):.0f} %) received in the last 10 s were no part of a "
        "good frame and were skipped: a wrong baud rate, another device's output on this port, or electrical noise?"]
    service = TactileService("sim://")
    now = time.time()
    service.pipeline.feed(data, now - 12.0)
    service.pipeline.feed(quads(200, 100), now)
    assert [p for p in service.health()["problems"] if "bytes" in p] == []


def test_a_link_that_skips_a_partial_frame_or_a_few_bytes_is_not_named():
    """A frame cut at the start, a boot banner: no pattern (at least 4096 bytes and 10 % of the window's)."""
    service = TactileService("sim://")
    service.pipeline.feed(quads(0, 10)[5:] + b"boot v1.1.0\r\n" * 20 + quads(10, 10), time.time())
    assert service.pipeline.decoder.counters.bytes_discarded == 27 + 13 * 20
    assert [p for p in service.health()["problems"] if "bytes" in p] == []
    service = TactileService("sim://")
    service.pipeline.feed(quads(0, 1000) + GARBAGE * 14, time.time())  # 3570 bytes: 10.04 % of 35570, < 4096
    assert [p for p in service.health()["problems"] if "bytes" in p] == []
