"""A served replay (``replay://``) stamps each read with its recorded receive
time moved onto the replay's timeline, not with when the replaying host got
round to it: the clock map sees the recorded intervals, so the frames carry
the flags the export gives (a stall of the replaying host is no clock fault
of the board's), and live sources are stamped on arrival as before."""
import time

import numpy as np
import pytest

from firmware_sim.board import BoardConfig
from firmware_sim.delivery import deliveries
from firmware_sim.sensors import SimQuad
from service.board import Board, BoardSpec
from service.handover import ThreadSink
from service.history import Histories
from service.pipeline import Pipeline
from service.readout import Readout
from service.record.mcap_reader import read_raw
from service.record.recorder import Recorder
from service.replay import replay
from service.sources.protocol_replay import Serial

SECONDS = 2.0  # of recording: the clock map locks after 1 s of board time
STALL = (1.3, 0.2, 1.5)  # recorded: nothing delivered for 0.2 s from 1.3 s, then the backlog at 1.5x real time
HOST_STALL_S = 0.25  # the replaying host's reader held up this long, once


def retime(t: float) -> float:
    at, hold, drain = STALL
    return max(t, at + hold + (t - at) / drain) if t >= at else t


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A quad at 500 Hz, 5 ms delivery jitter, recorded with a 0.2 s delivery stall (its
    own, genuine clock_suspect frames)."""
    path = tmp_path_factory.mktemp("timeline") / "stall.mcap"
    config = BoardConfig(sensors=[SimQuad(1)], rate_hz=500, scene="idle", seed=1, clock_ppm=100.0, jitter_ms=5.0)
    pipeline = Pipeline()
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for t_recv, data in deliveries(config, SECONDS):
        pipeline.feed(data, 1000.0 + retime(t_recv))
    recorder.stop()
    return path


def by_frame(frames) -> dict:
    return {(f.sensor.id, f.seq, f.t_us): f for f in frames}


def exported(path) -> dict:
    """The export's frames (`tactile replay --export`: at full speed, stamped as recorded)."""
    frames = []

    class Collect:
        write = frames.extend

    replay(path, writer=Collect())
    return by_frame(frames)


def test_a_served_replay_with_its_host_stalled_carries_the_exports_flags_and_the_recorded_intervals(recording):
    export = exported(recording)
    suspect = {key for key, frame in export.items() if "clock_suspect" in frame.flags}
    assert 0 < len(suspect) < 150  # the recorded stall, as the live clock map flagged it

    url = f"replay://{recording}?speed=1"
    pipeline = Board(BoardSpec(url), None, Histories()).pipeline
    frames, reads = [], []
    pipeline.listeners.append(frames.extend)

    def feed(data: bytes, t_host: float) -> None:
        reads.append(t_host)
        if len(reads) == 150:  # ~0.6 s in, before the clock map locks; a stall after it is as bad
            time.sleep(HOST_STALL_S)
        pipeline.feed(data, t_host)

    readout = Readout(url, ThreadSink(feed, pipeline.link_lost))
    readout.start()
    try:
        deadline = time.monotonic() + SECONDS + HOST_STALL_S + 5.0
        while not readout.link.finished and time.monotonic() < deadline:
            time.sleep(0.05)
        assert readout.link.finished
    finally:
        readout.stop()
    served = by_frame(frames)
    assert served.keys() == export.keys()
    assert {key for key, frame in served.items() if "clock_suspect" in frame.flags} == suspect
    assert all(sorted(frame.flags) == sorted(export[key].flags) for key, frame in served.items())
    # Receive and scan stamps are the recorded ones shifted by one constant (float rounding of ~1e9 s aside):
    # the host's 0.25 s stall moved every later read by 0.25 s.
    shift = np.array([frame.t_host - export[key].t_host for key, frame in served.items()])
    assert np.ptp(shift) < 1e-5
    scan_shift = np.array([frame.t_host_scan - export[key].t_host_scan for key, frame in served.items()])
    assert np.ptp(scan_shift) < 1e-5


@pytest.mark.parametrize("speed", ["4", "max"])
def test_a_replay_port_stamps_each_read_at_its_recorded_time_on_the_replays_timeline(recording, speed):
    """At speed s a read recorded t after the first is stamped t/s after the
    first's stamp (the wall clock when the replay began); at max there is no
    timeline and reads are stamped on arrival."""
    recorded = [t for t, _ in read_raw(recording)]
    port = Serial(f"replay://{recording}?speed={speed}")
    began = time.time()
    stamps = []
    while not (port.finished and not port.in_waiting):
        if port.read(1 << 16):
            stamps.append(port.read_time)
    assert len(stamps) == len(recorded)
    if speed == "max":
        assert set(stamps) == {None}
        return
    assert began <= stamps[0] <= began + 0.1
    expected = stamps[0] + (np.array(recorded) - recorded[0]) / 4.0
    assert np.abs(np.array(stamps) - expected).max() < 1e-6
