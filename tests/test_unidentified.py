"""Frames a board sends without having said what it is are flagged so.

After a link (re)opens or the board restarts with its power-up INFO lost,
frames wait for its INFO (identify.py); a board that does not answer in
time had its frames read under the description and zeros in force — another
board's, when the link now reaches another — with no flag (the tester's
two boards swapped, neither answering: every quad read Fz +1.33 N, σ 0.093,
on no load, for good). Now each frame read before the board's INFO carries
``unidentified``, JSON and binary, and /health names the board until it
answers. A board's restarts without INFO and its unanswered INFO? were
named nowhere, and a restart 0.9 s after the last INFO? was not asked."""
import asyncio
import struct
import time

import numpy as np

from service.fanout.encoding import decode_binary, to_binary
from service.live_service import TactileService
from service.protocol import FrameType, encode_frame
from service.readout import INFO_REPLY_S
from tests.test_reidentify import QUAD_C0, Scans, TcpBoard, count, live_pipeline, serve

B_QUAD_C0 = QUAD_C0 * 1.06  # board B's quad, 6 % above A's: read on A's zero, Fz is far from its 0 N


def quad_frames(frames):
    return [f for f in frames if f.sensor.id == 1]


def waiting_service(timers: list | None = None) -> tuple[TactileService, list]:
    """A simulated service whose frames wait for INFO as a live link's do,
    its waits' timers kept in ``timers`` for the test to fire."""
    timers = [] if timers is None else timers
    service = TactileService("sim://")
    service.pipeline.identify_on_link(INFO_REPLY_S, lambda restart=False: None, lambda delay, fn: timers.append(fn))
    return service, timers


def test_frames_of_another_board_that_never_answers_are_flagged_until_its_info():
    """A's 200 scans tare its quad; the link drops and reopens on B (no INFO):
    its 10 held scans go on at the bound, and the 10 after, all flagged
    unidentified; B's INFO, late, ends it: its next 10 scans are not."""
    pipeline, _, timers, published = live_pipeline()
    a = Scans("A-1", seed=1)
    pipeline.feed(a.info() + a.next(200), 0.0)
    assert [f for f in published if "unidentified" in f.flags] == []  # A answered: nothing flagged
    pipeline.link_lost()
    b = Scans("B-2", quad_c0=B_QUAD_C0, seq=12000, t_us=60_000_000, reply_s=None, seed=2)
    before = len(published)
    pipeline.feed(b.next(10), 1.0)
    assert len(published) == before  # held for B's INFO
    timers[-1][1]()  # the wait passed: no INFO
    pipeline.feed(b.next(10), 1.3)
    unidentified = published[before:]
    assert [f.seq for f in quad_frames(unidentified)] == list(range(12000, 12020))
    assert all("unidentified" in f.flags for f in unidentified) and len(unidentified) == 40
    fz = np.array([f.forces_N[2] for f in quad_frames(unidentified)])
    assert np.all(np.abs(fz) > 3 * np.array([f.sigma_N[2] for f in quad_frames(unidentified)]))  # why: read on A's zero
    answered = len(published)
    pipeline.feed(b.info() + b.next(10), 1.4)
    assert len(published) - answered == 20 and not any("unidentified" in f.flags for f in published[answered:])


def test_a_restart_without_info_left_unanswered_is_flagged_and_the_binary_record_says_so():
    """A restart whose power-up INFO was lost, INFO? unanswered: its frames
    are flagged (bit 17 in a binary record) until the board's INFO comes,
    however late; the run before the restart is not."""
    pipeline, asked, timers, published = live_pipeline()
    board = Scans("E-1", seed=1)
    pipeline.feed(board.info() + board.next(150), 0.0)
    board.seq, board.t_us = 0, 0  # a restart, INFO lost
    pipeline.feed(board.next(10), 1.0)
    assert len(asked) == 1
    timers[-1][1]()
    assert [f.seq for f in quad_frames(published[300:])] == list(range(10))
    assert all("unidentified" in f.flags for f in published[300:])
    assert not any("unidentified" in f.flags for f in published[:300])
    record = to_binary(published[-1])
    assert struct.unpack_from("<I", record, 26)[0] & 1 << 17  # the u32 frame-flag bits, after 26 bytes of head
    assert "unidentified" in decode_binary(struct.pack("<H", 1) + record)[0]["flags"]
    pipeline.feed(board.next(5) + board.info() + board.next(5), 1.1)  # the reply, 0.1 s late, after 5 scans
    late = published[320:]
    assert [("unidentified" in f.flags) for f in quad_frames(late)] == [True] * 5 + [False] * 5


def test_health_names_a_board_read_without_its_info_until_it_answers():
    service, timers = waiting_service()
    a = Scans("A-1", seed=1)
    now = time.time()
    service.pipeline.feed(a.info() + a.next(200), now - 1.0)
    assert [p for p in service.health()["problems"] if "INFO" in p] == []
    service.pipeline.link_lost()
    b = Scans("B-2", quad_c0=B_QUAD_C0, seq=12000, t_us=60_000_000, reply_s=None, seed=2)
    service.pipeline.feed(b.next(10), now - 0.5)
    timers[-1]()
    service.pipeline.feed(b.next(100), now)
    assert [p for p in service.health()["problems"] if "did not answer" in p] == [
        "the board did not answer INFO? within 0.25 s after its link opened: its frames are read as the board that "
        "was there before (serial A-1), on its sensors' zeros, flagged unidentified, until its INFO comes"]
    service.pipeline.feed(b.info() + b.next(10), now)
    assert [p for p in service.health()["problems"] if "did not answer" in p] == []


def test_health_names_a_board_that_never_said_what_it_is():
    """No INFO since the first connect: its frames are read by their sizes alone, flagged."""
    service, timers = waiting_service()
    board = Scans("A-1", reply_s=None, seed=1)
    service.pipeline.feed(board.next(10), time.time() - 0.5)
    timers[-1]()
    frames = service.pipeline.feed(board.next(10), time.time())
    assert len(frames) == 20 and all("unidentified" in f.flags for f in frames)
    assert [p for p in service.health()["problems"] if "did not answer" in p] == [
        "the board did not answer INFO? within 0.25 s after its link opened: its frames are read from their sizes "
        "alone (no INFO came), on the zeros its sensors took, flagged unidentified, until its INFO comes"]


def restart_loop(service, timers, restarts: int, start: float) -> float:
    """``restarts`` restarts of the board 1 s apart from ``start``, each with
    its power-up INFO lost and its INFO? unanswered (each wait's timer run);
    returns the time of the last read."""
    board = Scans("E-1", seed=1)
    service.pipeline.feed(board.info() + board.next(150), start)
    t = start
    for _ in range(restarts):
        board.seq, board.t_us = 0, 0
        t += 1.0
        service.pipeline.feed(board.next(10), t)
        timers[-1]()
        service.pipeline.feed(board.next(10), t + 0.3)
    return t + 0.3


def test_health_names_a_board_in_a_restart_loop_that_never_answers_until_the_window_passes():
    """6 restarts in 6 s, 6 INFO? unanswered: /health said ok. Now a line
    with both counts over the last 10 s, gone 10 s after the last."""
    service, timers = waiting_service()
    now = time.time()
    restart_loop(service, timers, 6, now - 6.5)
    assert [p for p in service.health()["problems"] if p.startswith("the board restarted")] == [
        "the board restarted 6 times with its power-up INFO lost and left 6 INFO? unanswered within 0.25 s in the "
        "last 10 s: its frames went on without it, flagged unidentified; a board that restarts by itself: its power "
        "supply, a watchdog, its firmware?"]
    service, timers = waiting_service(timers)
    restart_loop(service, timers, 6, now - 18.5)
    board = Scans("E-1", seq=5000, t_us=100_000_000, seed=3)
    service.pipeline.feed(board.info() + board.next(10), now)
    assert [p for p in service.health()["problems"] if "INFO" in p] == []
    assert service.pipeline.identification.unanswered == 6  # the counts since start stay
    assert service.pipeline.decoder.restarts_without_info == 12  # each sensor's: the line counts the board's


def test_health_names_restarts_answered_in_time_and_a_late_answer():
    """A restart whose INFO? is answered within the wait: named, its frames
    not flagged. An INFO 0.4 s late: the wait's frames were flagged, said so."""
    service, timers = waiting_service()
    board = Scans("E-1", seed=1)
    now = time.time()
    service.pipeline.feed(board.info() + board.next(150), now - 1.0)
    board.seq, board.t_us = 0, 0
    service.pipeline.feed(board.next(10), now - 0.9)
    frames = service.pipeline.feed(board.next(10) + board.info() + board.next(10), now - 0.8)
    assert len(frames) == 60 and not any("unidentified" in f.flags for f in frames)
    assert [p for p in service.health()["problems"] if "INFO" in p] == [
        "the board restarted once with its power-up INFO lost in the last 10 s: its frames waited up to 0.25 s for "
        "its INFO each time; a board that restarts by itself: its power supply, a watchdog, its firmware?"]
    service, timers = waiting_service(timers)
    board = Scans("E-1", seed=1)
    service.pipeline.feed(board.next(10), now - 0.5)
    timers[-1]()
    service.pipeline.feed(board.next(10) + board.info() + board.next(10), now - 0.1)
    assert [p for p in service.health()["problems"] if "INFO" in p] == [
        "the board left 1 INFO? unanswered within 0.25 s in the last 10 s: its frames went on without it, flagged "
        "unidentified"]


def test_a_live_board_restarting_0_9_s_apart_is_asked_info_at_each_restart():
    """Over TCP, as ``tactile serve`` reads it: two restarts 0.9 s apart, each
    power-up INFO lost. The second was not asked (INFO? once a second), its
    frames went on unidentified; now each is asked, and answered."""
    device = TcpBoard(Scans("E-1", seed=1))
    marks = []

    async def scenario(published, until):
        await until(lambda: count(published, 0)() >= 300)
        marks.append(len(device.asked))
        device.restart(Scans("E-1", seed=2))
        await until(lambda: len(device.asked) > marks[0])
        await asyncio.sleep(0.9 - (time.monotonic() - device.asked[-1]))
        device.restart(Scans("E-1", seed=3))
        await asyncio.sleep(0.5)

    published = serve(device, scenario)
    assert len(device.asked) - marks[0] == 2 and device.asked[-1] - device.asked[-2] < 1.0
    assert not any("unidentified" in f.flags for f, _ in published)


def test_frames_released_by_an_info_refused_as_invalid_are_flagged_until_a_valid_info():
    """B's INFO comes in time but is refused whole (payload not JSON): the
    board has not said what it is, yet the 10 scans held for it and the 10
    after went on unflagged, read on A's zero (|Fz| > 3σ). Now all 40 frames
    carry ``unidentified``; B's valid INFO ends it for its next 10 scans."""
    pipeline, _, timers, published = live_pipeline()
    a = Scans("A-1", seed=1)
    pipeline.feed(a.info() + a.next(200), 0.0)
    pipeline.link_lost()
    b = Scans("B-2", quad_c0=B_QUAD_C0, seq=12000, t_us=60_000_000, reply_s=None, seed=2)
    before = len(published)
    pipeline.feed(b.next(10), 1.0)
    assert len(published) == before  # held for B's INFO
    pipeline.feed(encode_frame(FrameType.INFO, 255, 0, b.t_us, b"{not json") + b.next(5), 1.1)
    pipeline.feed(b.next(5), 1.2)
    assert pipeline.interpreter.rejected["info_invalid"] == 1
    refused = published[before:]
    assert [f.seq for f in quad_frames(refused)] == list(range(12000, 12020)) and len(refused) == 40
    assert [f.seq for f in quad_frames(refused) if "unidentified" not in f.flags] == []
    answered = len(published)
    pipeline.feed(b.info() + b.next(10), 1.3)
    assert len(published) - answered == 20 and not any("unidentified" in f.flags for f in published[answered:])
