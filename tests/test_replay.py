"""Raw-capture replay: corrupt frames dropped, good frames exported."""
import io

import numpy as np
import orjson
import pytest

from firmware_sim.board import Board, BoardConfig, capture
from firmware_sim.faults import inject
from service.cli import main
from service.protocol import FrameType
from service.replay import replay

DATA_TYPES = (FrameType.GRID, FrameType.QUAD)


def export(path):
    out = io.BytesIO()
    pipeline = replay(path, out)
    return [orjson.loads(line) for line in out.getvalue().splitlines()], pipeline


@pytest.fixture(scope="module")
def press_capture(tmp_path_factory):
    data, board = capture(BoardConfig(scene="press", seed=11), 3.0, keep_truth=True)
    path = tmp_path_factory.mktemp("cap") / "press.bin"
    path.write_bytes(data)
    return path, data, board


def test_clean_capture_exports_every_frame_with_forces_near_truth(press_capture):
    path, _, board = press_capture
    lines, pipeline = export(path)
    assert len(lines) == 6000
    truth = {(t.sensor, t.seq): t.values for t in board.truth}
    grid = [l for l in lines if l["kind"] == "grid"]
    expected = np.array([truth[(0, l["seq"])] for l in grid])
    errors = np.array([l["taxels_N"] for l in grid]) - expected
    loaded = expected > 0.05
    # 1 fF noise on ~10 pF at ~1.25 %/N is σ ≈ 0.008 N per taxel; unloaded
    # taxels are clamped at zero force, which leaves σ/√2.
    assert np.sqrt((errors[~loaded] ** 2).mean()) == pytest.approx(0.008 / np.sqrt(2), rel=0.25)
    assert np.sqrt((errors[loaded] ** 2).mean()) < 2 * 0.008
    assert np.abs(errors).max() < 0.06
    assert all(l["flags"] == [] for l in lines)
    assert grid[1500]["contact"]["contacts"] in (0, 1)
    quad = [l for l in lines if l["kind"] == "quad"]
    assert set(quad[0]) == {"board", "sensor", "seq", "t_us", "kind", "fxyz_N", "sigma_N", "calibration", "flags"}
    # Neither sensor has a calibration of its own: the papers' built-ins, named in every line.
    assert {l["calibration"] for l in grid} == {"builtin-table1"}
    assert {l["calibration"] for l in quad} == {"builtin-fits34-35"}
    # Unloaded, σ is the reading's noise alone (1 fF at ~1.25 %/N: ~0.008 N), never zero.
    unloaded_sigma = np.array([l["sigma_N"] for l in grid])[~loaded]
    assert np.median(unloaded_sigma) == pytest.approx(0.008, rel=0.3)


def test_corrupt_capture_drops_every_bad_frame_and_exports_every_good_one(press_capture, tmp_path):
    _, data, _ = press_capture
    damaged = inject(data, rate=0.05, seed=5)
    assert min(damaged.counts.values()) > 30
    path = tmp_path / "damaged.bin"
    path.write_bytes(damaged.data)
    lines, pipeline = export(path)
    expected = [(sensor, seq) for ftype, sensor, seq in damaged.intact if ftype in DATA_TYPES]
    assert [(l["sensor"], l["seq"]) for l in lines] == expected
    counters = pipeline.decoder.counters
    assert counters.crc_errors + counters.header_errors >= damaged.counts["flip"]
    assert counters.sensor(0).missed_frames + counters.sensor(1).missed_frames == 6000 - len(expected)
    gap_lines = [l for l in lines if "seq_gap" in l["flags"]]
    assert len(gap_lines) == counters.sensor(0).seq_gaps + counters.sensor(1).seq_gaps


def test_sentinel_channels_export_as_null(tmp_path):
    data, _ = capture(BoardConfig(scene="idle"), 0.2)
    frames = bytearray(data)
    # Rewrite one grid frame with an open channel, through the encoder.
    from service.protocol import encode_frame
    from service.protocol_decoder import Decoder

    out = bytearray()
    for frame in Decoder().feed(bytes(frames)):
        payload = frame.payload
        if frame.type == FrameType.GRID and frame.seq == 150:
            counts = np.frombuffer(payload, "<u4").copy()
            counts[9] = 0xFFFFFFFF
            payload = counts.tobytes()
        out += encode_frame(frame.type, frame.sensor, frame.seq, frame.t_us, payload, frame.flags)
    path = tmp_path / "open.bin"
    path.write_bytes(bytes(out))
    lines, _ = export(path)
    (line,) = [l for l in lines if l["kind"] == "grid" and l["seq"] == 150]
    assert line["taxels_N"][9] is None and line["flags"] == ["open_channel"]
    assert all(v is not None for i, v in enumerate(line["taxels_N"]) if i != 9)


def test_cli_capture_then_replay_export(tmp_path, capsys):
    raw, jsonl = tmp_path / "c.bin", tmp_path / "c.jsonl"
    assert main(["sim", "--capture", str(raw), "--seconds", "0.5", "--scene", "shear"]) == 0
    assert main(["replay", "--raw", str(raw), "--export", str(jsonl)]) == 0
    lines = [orjson.loads(l) for l in jsonl.read_bytes().splitlines()]
    assert len(lines) == 1000
    summary = orjson.loads(capsys.readouterr().err)
    assert summary["stream"]["frames"] == 1001


def test_cli_replay_of_missing_file_is_a_clear_error(tmp_path, capsys):
    assert main(["replay", "--raw", str(tmp_path / "nope.bin")]) == 2
    assert "nope.bin" in capsys.readouterr().err


def test_bench_scenario_reports_every_level_against_truth():
    from service.reports.bench import SCENARIOS, run_scenario

    rows = run_scenario(SCENARIOS[0], seconds=2.0)
    assert [r["level"] for r in rows] == ["level0", "table", "full"]
    by_level = {r["level"]: r for r in rows}
    # The linear level misses the gap nonlinearity on the pressed taxel; the table does not.
    assert by_level["level0"]["rms_loaded_N"] > 5 * by_level["table"]["rms_loaded_N"]
    assert by_level["full"]["rms_loaded_N"] < 0.02


def test_a_dash_exports_to_stdout(tmp_path, capsysbinary, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run.bin"
    run.write_bytes(capture(BoardConfig(scene="press"), 0.3)[0])
    assert main(["replay", str(run), "--export", "-"]) == 0
    lines = capsysbinary.readouterr().out.splitlines()
    assert len(lines) == 600 and orjson.loads(lines[0])["seq"] == 0  # 0.3 s of a grid and a quad
    assert not (tmp_path / "-").exists()


@pytest.mark.parametrize("uptime_us", [3_000_000_000, 100_000_000])
def test_a_paced_raw_capture_goes_on_across_a_board_restart_without_a_wait(tmp_path, uptime_us):
    """A board up past 2**31 µs (~36 min) restarts: its clock falls back to 0, no wrap (a replay waited
    21 min for one); up 100 s, the run after the restart was not paced at all (timed 100 s back). The
    time the board was off is unknown: the run after goes on from the run before without a wait."""
    from service.record.pacing import Pacer
    from service.record.readers import raw_chunks

    before, _ = capture(BoardConfig(rate_hz=200, clock_offset_us=uptime_us), 2.0)
    after, _ = capture(BoardConfig(rate_hz=200, seed=1), 2.0)  # power-up: INFO, every seq and t_us from 0
    path = tmp_path / "restart.bin"
    path.write_bytes(before + after)
    times = [t for t, _ in raw_chunks(path)]
    now, slept = [0.0], []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    fast, paced = io.BytesIO(), io.BytesIO()
    replay(path, fast)
    replay(path, paced, pacer=Pacer(1.0, clock=lambda: now[0], sleep=sleep))
    assert times == sorted(times) and times[-1] - times[0] == pytest.approx(4.0, abs=0.1)  # 4 s of scans
    assert sum(slept) == pytest.approx(times[-1] - times[0]) and max(slept) < 0.1
    assert len(slept) > 0.9 * (len(times) - 1)  # every chunk after the restart paced too
    assert paced.getvalue() == fast.getvalue() and fast.getvalue().count(b"\n") > 1000


def test_a_paced_raw_capture_emits_each_chunk_at_its_own_board_time(tmp_path):
    """Paced, a raw capture is read 4 KiB at a time, each chunk timed by the
    newest scan it completes: its frames go out then, at most one chunk's
    span after their own scan, never before it. They went out a chunk late,
    after the wait for the next chunk (up to twice that span)."""
    from service.protocol_decoder import Decoder
    from service.record.pacing import Pacer

    data, _ = capture(BoardConfig(scene="press", rate_hz=100, seed=3), 4.0)
    path = tmp_path / "press.bin"
    path.write_bytes(data)
    span = 4096 / (len(data) / 4.0)  # s of scans in 4 KiB: ~0.13 s
    first = max(f.t_us for f in Decoder().feed(data[:4096]) if f.type in DATA_TYPES) * 1e-6  # the pacing's anchor
    now = [0.0]
    emitted = []

    class Times:
        def write(self, frames):
            emitted.extend((now[0], frame.t_us * 1e-6) for frame in frames)

    pacer = Pacer(1.0, clock=lambda: now[0], sleep=lambda dt: now.__setitem__(0, now[0] + dt))
    replay(path, pacer=pacer, writer=Times())
    late = [w - (t - first) for w, t in emitted if t > 2.0]  # after the tare (held frames go out with it)
    assert len(late) == 2 * 200 and 0.1 < span < 0.2  # two sensors, 2 s at 100 Hz
    assert min(late) >= -1e-9 and max(late) <= span


def pause_capture(tmp_path):
    """A 100 Hz board, silent for 1.5 s (STOP at 2.5 s, START at 4.0 s,
    seq going on), 6 s in all: its path and {scan t_us: the byte offset
    where that scan's frames end}, built scan by scan."""
    board = Board(BoardConfig(scene="press", rate_hz=100, seed=3))
    data, ends = bytearray(board.power_up()), {}
    for k in range(1, 601):
        board.streaming = not 250 < k <= 400
        scan = board.advance(k / 100)
        data += scan
        if scan:
            ends[k * 10_000] = len(data)
    path = tmp_path / "pause.bin"
    path.write_bytes(data)
    return path, ends


def test_a_paced_raw_capture_emits_each_frame_at_its_own_board_time_across_a_pause(tmp_path):
    """A board silent for 1.5 s (STOP at 2.5 s, START at 4.0 s, seq going
    on): paced at speed 1 on a virtual clock, every frame after the tare
    goes out no earlier than its own scan (t_us against the pacing's
    anchor) and at most 25 ms after it. The 4 KiB chunk straddling the
    pause went out whole at its newest scan's time: its frames from before
    the pause up to 1.62 s late. The forces equal an unpaced replay's, bit for bit."""
    from service.record.export import export_line
    from service.record.pacing import Pacer

    path, _ = pause_capture(tmp_path)
    now, anchor = [0.0], []

    class Anchored(Pacer):
        def wait(self, t_recorded, *args):
            anchor.append(t_recorded)  # the first is the board time the clock's 0 stands for
            super().wait(t_recorded, *args)

    class Lines:
        def __init__(self, clock=None):
            self.lines, self.times, self._clock = [], [], clock

        def write(self, frames):
            self.lines += [export_line(frame) for frame in frames]
            self.times += [(self._clock[0], frame.t_us * 1e-6) for frame in frames] if self._clock else []

    paced, fast = Lines(now), Lines()
    replay(path, pacer=Anchored(1.0, clock=lambda: now[0], sleep=lambda dt: now.__setitem__(0, now[0] + dt)),
           writer=paced)
    replay(path, writer=fast)
    late = [w - (t - anchor[0]) for w, t in paced.times if t > 2.0]  # after the tare (held frames go out with it)
    assert len(late) == 2 * (50 + 200)  # two sensors at 100 Hz: 2.01-2.5 s, 4.01-6.0 s
    assert min(late) >= -1e-9 and max(late) <= 0.025, (min(late), max(late))
    assert 0.01 <= anchor[0] <= 0.035  # the first scan at 10 ms
    assert paced.lines == fast.lines and len(fast.lines) == 2 * 450


def test_a_paced_raw_replays_progress_bar_stands_at_the_bytes_released(tmp_path):
    """The progress bar of a paced raw replay moves by the bytes each wait
    releases: after the wait for board time t it stands past t's grid
    frame (272 bytes; its 32-byte quad may end in the next 4 KiB read) and
    short of the next scan's grid, and at the file's size at the end. It
    moved 4 KiB a wait, running ahead of chunks cut shorter (by 109 kB)."""
    from service.cli_recordings import _ProgressPacer
    from service.record.pacing import Pacer

    path, ends = pause_capture(tmp_path)
    now, positions = [0.0], []

    class Bar:
        n = 0

        def update(self, k):
            self.n += k

    class Watched(_ProgressPacer):
        def wait(self, t_recorded, *args):
            super().wait(t_recorded, *args)
            positions.append((round(t_recorded * 1e6), bar.n))

    bar = Bar()
    replay(path, pacer=Watched(Pacer(1.0, clock=lambda: now[0], sleep=lambda dt: now.__setitem__(0, now[0] + dt)),
                               bar, path))
    ahead = [n - ends[t_us] for t_us, n in positions if t_us in ends]
    assert len(positions) > 2 * path.stat().st_size / 4096 and bar.n == path.stat().st_size == ends[6_000_000]
    assert min(ahead) >= -32 and max(ahead) < 272, (min(ahead), max(ahead))  # against the end of t's scan


def test_a_raw_capture_cut_inside_a_frame_is_said_with_the_bytes_left_over(tmp_path, caplog):
    """A capture cut short (head -c) replays every whole frame; the cut was
    only a 'truncated': 1 in the summary, where a cut MCAP gets a warning.
    The first 100 of a 272-byte grid frame after a whole capture: 100 bytes
    left over, said in a warning; a whole capture says nothing."""
    import logging

    from service.protocol import encode_frame

    data, _ = capture(BoardConfig(scene="press", seed=2), 0.3)
    grid = encode_frame(FrameType.GRID, 0, 300, 3_000_000, bytes(256))
    assert len(grid) == 14 + 256 + 2
    (tmp_path / "whole.bin").write_bytes(data)
    (tmp_path / "cut.bin").write_bytes(data + grid[:100])
    with caplog.at_level(logging.WARNING, logger="service.replay"):
        whole, _ = export(tmp_path / "whole.bin")
        assert caplog.text == ""
        cut, pipeline = export(tmp_path / "cut.bin")
    assert cut == whole and len(whole) == 600 and pipeline.decoder.counters.truncated == 1
    assert f"{tmp_path / 'cut.bin'} ends inside a frame: its last 100 bytes" in caplog.text
