import struct
from binascii import crc_hqx

import pytest

from service.protocol import FLAG_OVERRUN, FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.protocol_bulk import BulkDecoder


def quad_payload(*af):
    return struct.pack("<4I", *af)


def hand_frame(ftype=0x11, sensor=1, flags=0, seq=5, t_us=1000, payload=None, version=1, crc=None, length=None):
    """Build a frame byte by byte from the protocol table, independently of encode_frame."""
    payload = quad_payload(10, 20, 30, 40) if payload is None else payload
    length = len(payload) if length is None else length
    body = bytes([version, ftype, sensor, flags]) + seq.to_bytes(2, "little") + t_us.to_bytes(4, "little")
    body += length.to_bytes(2, "little") + payload
    if crc is None:
        crc = crc_hqx(body, 0xFFFF)
    return b"\xa5\x5a" + body + crc.to_bytes(2, "little")


def test_crc_is_ccitt_false():
    # The standard check value of CRC-16/CCITT-FALSE.
    assert crc_hqx(b"123456789", 0xFFFF) == 0x29B1


def test_encoder_matches_hand_built_frame():
    assert encode_frame(FrameType.QUAD, 1, 5, 1000, quad_payload(10, 20, 30, 40)) == hand_frame()
    grid = encode_frame(FrameType.GRID, 0, 0, 0, bytes(256))
    assert len(grid) == 272  # the protocol's link budget figure
    assert len(hand_frame()) == 32


def test_decodes_hand_built_frame_fields():
    (frame,) = Decoder().feed(hand_frame(flags=FLAG_OVERRUN, seq=65535, t_us=0xFFFFFFFF))
    assert frame.type == FrameType.QUAD
    assert (frame.sensor, frame.flags, frame.seq, frame.t_us) == (1, FLAG_OVERRUN, 65535, 0xFFFFFFFF)
    assert struct.unpack("<4I", frame.payload) == (10, 20, 30, 40)


def test_bad_crc_is_dropped_and_counted():
    good = hand_frame(seq=1)
    bad = hand_frame(seq=2, crc=0x1234)
    decoder = Decoder()
    frames = decoder.feed(bad + good)
    assert [f.seq for f in frames] == [1]
    assert decoder.counters.crc_errors == 1
    assert decoder.counters.sensor(1).crc_errors == 1
    assert decoder.counters.bytes_discarded == len(bad)


def test_a_damaged_header_names_no_phantom_sensor_in_the_counters():
    """A frame whose sensor byte was damaged (1 → 116) fails its CRC and was
    counted as sensor 116's: summaries listed a sensor that never sent a
    frame. Ids without a valid frame are left out; the stream counts it."""
    good = hand_frame(seq=1)
    damaged = bytearray(hand_frame(seq=2))
    damaged[4] = 116  # the sensor byte, after sync (2), version and type
    decoder = Decoder()
    decoder.feed(good + bytes(damaged))
    counted = decoder.counters.as_dict()
    assert counted["crc_errors"] == 1 and list(counted["sensors"]) == ["1"]


def test_truncated_frame_then_good_frame():
    truncated = hand_frame(seq=1)[:20]
    frames = Decoder().feed(truncated + hand_frame(seq=2) + hand_frame(seq=3))
    assert [f.seq for f in frames] == [2, 3]


def test_garbage_between_frames():
    garbage = b"\x00\xff\xa5\x13\x37\xa5"
    decoder = Decoder()
    frames = decoder.feed(hand_frame(seq=1) + garbage + hand_frame(seq=2))
    assert [f.seq for f in frames] == [1, 2]
    assert decoder.counters.bytes_discarded == len(garbage)


def test_sync_inside_payload_is_not_a_frame_start():
    payload = quad_payload(0x5AA55AA5, 0xA55A0000, 0x5AA5, 7)
    assert b"\xa5\x5a" in payload
    frames = Decoder().feed(hand_frame(payload=payload, seq=1) + hand_frame(seq=2))
    assert [f.seq for f in frames] == [1, 2]
    assert frames[0].payload == payload


def test_resync_starts_one_byte_after_the_bad_frames_sync():
    # A corrupted grid frame whose payload holds a complete quad frame: the
    # search restarts one byte after the bad frame's sync, so it finds the
    # embedded frame (the protocol's rule) and then the next real frame.
    inner = hand_frame(seq=7)
    payload = b"\x01" * 8 + inner + b"\x02" * (256 - 8 - len(inner))
    bad = hand_frame(ftype=0x10, sensor=0, payload=payload, seq=1, crc=0)
    decoder = Decoder()
    frames = decoder.feed(bad + hand_frame(seq=8))
    assert [(f.sensor, f.seq) for f in frames] == [(1, 7), (1, 8)]
    assert decoder.counters.crc_errors == 1


def test_len_over_1024_is_rejected_without_waiting():
    bad = hand_frame(ftype=0x10, payload=b"", length=1025)
    decoder = Decoder()
    frames = decoder.feed(bad + hand_frame(seq=2))
    assert [f.seq for f in frames] == [2]
    assert decoder.counters.header_errors == 1


def test_quad_with_wrong_length_is_rejected():
    frames = Decoder().feed(hand_frame(payload=b"\x01" * 12, seq=1) + hand_frame(seq=2))
    assert [f.seq for f in frames] == [2]


@pytest.mark.parametrize("version, ftype", [(2, 0x11), (0, 0x11), (1, 0x12), (1, 0x00)])
def test_wrong_version_or_type_is_rejected(version, ftype):
    decoder = Decoder()
    frames = decoder.feed(hand_frame(version=version, ftype=ftype, seq=1) + hand_frame(seq=2))
    assert [f.seq for f in frames] == [2]
    assert decoder.counters.header_errors == 1


def test_stream_split_at_every_byte_boundary():
    stream = b"\x13" + hand_frame(seq=1) + b"\xa5" + hand_frame(ftype=0x10, sensor=0, payload=bytes(range(256)), seq=2)
    stream += hand_frame(seq=3, crc=1) + hand_frame(seq=4)
    expected = [1, 2, 4]
    for cut in range(len(stream) + 1):
        decoder = Decoder()
        frames = decoder.feed(stream[:cut]) + decoder.feed(stream[cut:])
        assert [f.seq for f in frames] == expected, cut
    decoder = Decoder()
    frames = [f for b in stream for f in decoder.feed(bytes([b]))]
    assert [f.seq for f in frames] == expected


def test_finish_recovers_frames_behind_a_corrupt_length():
    # A header claiming 1000 bytes holds back the frames behind it until the
    # stream ends; finish() must resync and recover them.
    lying = hand_frame(ftype=0x10, sensor=0, payload=b"", length=1000)[:14]
    decoder = Decoder()
    assert decoder.feed(lying + hand_frame(seq=1) + hand_frame(seq=2)) == []
    frames = decoder.finish()
    assert [f.seq for f in frames] == [1, 2]
    assert decoder.counters.truncated == 1


def test_sequence_gaps_and_wrap():
    decoder = Decoder()
    seqs = [65533, 65534, 65535, 0, 1, 5, 6]
    frames = decoder.feed(b"".join(hand_frame(seq=s) for s in seqs))
    assert [f.gap for f in frames] == [0, 0, 0, 0, 0, 3, 0]
    counters = decoder.counters.sensor(1)
    assert (counters.frames, counters.seq_gaps, counters.missed_frames) == (7, 1, 3)


def test_info_and_error_frames_do_not_count_in_sequence():
    decoder = Decoder()
    info = hand_frame(ftype=0x01, sensor=255, payload=b'{"board": "x"}', seq=0)
    error = hand_frame(ftype=0x7F, sensor=255, payload=b"unknown command", seq=1)
    frames = decoder.feed(info + error + hand_frame(seq=0))
    assert [f.type for f in frames] == [FrameType.INFO, FrameType.ERROR, FrameType.QUAD]
    assert decoder.counters.sensor(1).frames == 1
    assert 255 not in decoder.counters.sensors


def test_reset_keeps_sequence_state_so_reconnect_gaps_count():
    decoder = Decoder()
    decoder.feed(hand_frame(seq=10) + hand_frame(seq=11)[:9])
    decoder.reset()
    (frame,) = decoder.feed(hand_frame(seq=20))
    assert frame.gap == 9  # seq 11..19 never arrived whole
    assert decoder.counters.bytes_discarded == 9


def test_encode_rejects_oversize_payload():
    with pytest.raises(ValueError, match="1025 bytes"):
        encode_frame(FrameType.GRID, 0, 0, 0, bytes(1025))


def test_a_repeated_scan_is_dropped_and_counted_not_taken_for_65535_missed():
    decoder = Decoder()
    scan = encode_frame(FrameType.QUAD, 1, 7, 7000, bytes(16))
    stream = encode_frame(FrameType.QUAD, 1, 6, 6000, bytes(16)) + scan + scan + encode_frame(FrameType.QUAD, 1, 8, 8000, bytes(16))
    frames = decoder.feed(stream)
    assert [f.seq for f in frames] == [6, 7, 8]
    counters = decoder.counters.as_dict()["sensors"]["1"]
    assert counters["duplicates"] == 1 and counters["seq_gaps"] == 0 and counters["missed_frames"] == 0
    assert decoder.counters.bytes_discarded == len(scan)  # every byte is in a frame or discarded


def test_a_board_that_restarts_is_no_gap():
    decoder = Decoder()
    before = b"".join(encode_frame(FrameType.QUAD, 1, seq, 5_000_000 + 1000 * seq, bytes(16)) for seq in range(100, 110))
    after = b"".join(encode_frame(FrameType.QUAD, 1, seq, 900 + 1000 * seq, bytes(16)) for seq in range(5))
    frames = decoder.feed(before + after)
    counters = decoder.counters.as_dict()["sensors"]["1"]
    assert counters["board_restarts"] == 1 and counters["missed_frames"] == 0 and counters["seq_gaps"] == 0
    assert [f.board_restart for f in frames].index(True) == 10 and sum(f.board_restart for f in frames) == 1


def test_the_board_clock_wrapping_is_no_restart():
    decoder = Decoder()
    t0 = (1 << 32) - 2500
    frames = decoder.feed(b"".join(encode_frame(FrameType.QUAD, 1, seq, (t0 + 1000 * seq) % (1 << 32), bytes(16))
                                   for seq in range(6)))
    assert not any(f.board_restart for f in frames)
    assert decoder.counters.as_dict()["sensors"]["1"]["board_restarts"] == 0


def test_a_gap_while_the_clock_runs_on_is_counted():
    decoder = Decoder()
    decoder.feed(encode_frame(FrameType.QUAD, 1, 65530, 1000, bytes(16)) + encode_frame(FrameType.QUAD, 1, 4, 12000, bytes(16)))
    counters = decoder.counters.as_dict()["sensors"]["1"]
    assert counters["seq_gaps"] == 1 and counters["missed_frames"] == 9 and counters["board_restarts"] == 0


def test_an_older_scan_sent_again_is_a_repeat_not_a_restart():
    decoder = Decoder()
    a, b, c = (encode_frame(FrameType.QUAD, 1, seq, 1000 * seq, bytes(16)) for seq in (40, 41, 42))
    frames = decoder.feed(a + b + a + c)
    assert [f.seq for f in frames] == [40, 41, 42] and not any(f.board_restart for f in frames)
    counters = decoder.counters.as_dict()["sensors"]["1"]
    assert counters["duplicates"] == 1 and counters["board_restarts"] == 0 and counters["missed_frames"] == 0


def test_a_data_frame_from_the_boards_own_id_is_dropped_and_counted():
    decoder = Decoder()
    board_data = hand_frame(sensor=255, seq=1)
    frames = decoder.feed(hand_frame(seq=1) + board_data + hand_frame(ftype=0x10, sensor=255, payload=bytes(256)))
    assert [(f.sensor, f.seq) for f in frames] == [(1, 1)]
    assert decoder.counters.board_id_data == 2
    assert decoder.counters.as_dict()["board_id_data"] == 2
    assert 255 not in decoder.counters.sensors
    assert decoder.counters.bytes_discarded == len(board_data) + 272


def info(t_us, board_seq=0):
    return hand_frame(ftype=0x01, sensor=255, payload=b'{"board": "b"}', seq=board_seq, t_us=t_us)


def test_a_board_in_a_boot_loop_restarts_within_256_scans_and_nothing_is_dropped():
    # Each power-up: INFO at board time 0, then scans from seq 0 and t_us 0
    # again, with fresh readings. The second run's first 40 scans carry the
    # seq and t_us of the first run's, in different bytes.
    def run(first_value):
        return info(0) + b"".join(hand_frame(seq=s, t_us=1000 * (s + 1), payload=quad_payload(first_value + s, 2, 3, 4))
                                  for s in range(40))
    decoder = Decoder()
    frames = decoder.feed(run(100) + run(200) + run(300))
    data = [f for f in frames if f.type == FrameType.QUAD]
    assert len(data) == 120
    assert [i for i, f in enumerate(data) if f.board_restart] == [40, 80]
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.duplicates, counters.seq_gaps, counters.missed_frames) == (2, 0, 0, 0)


@pytest.mark.parametrize("bulk", [False, True])
def test_a_board_up_for_less_time_than_it_was_off_that_restarts_is_no_gap(bulk):
    # Up 50 ms, off, then its power-up INFO and scans from seq 0 whose clock
    # (from 80 ms: the board's boot took that long) stands past the last one
    # before: the clock ran on, the sequence started again. Five times over,
    # as a board in a brown-out loop.
    def run(start_us):
        return info(0) + b"".join(hand_frame(seq=s, t_us=start_us + 1000 * s) for s in range(50))
    decoder = BulkDecoder() if bulk else Decoder()
    frames = [f for f in decoder.feed(b"".join(run(1000 + 80_000 * k) for k in range(5))) if f.type == FrameType.QUAD]
    assert [i for i, f in enumerate(frames) if f.board_restart] == [50, 100, 150, 200]
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.seq_gaps, counters.missed_frames) == (4, 0, 0)


@pytest.mark.parametrize("bulk", [False, True])
def test_the_next_scan_after_a_long_pause_is_in_order(bulk):
    # STOP for 40 min, START: the sequence runs on, the clock jumped 2.4e9 µs,
    # more than half its period, so modulo 2^32 it looks like a step back.
    decoder = BulkDecoder() if bulk else Decoder()
    before = b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(5))
    after = b"".join(hand_frame(seq=s, t_us=2_400_000_000 + 1000 * s) for s in range(5, 10))
    frames = decoder.feed(before + after)
    assert [f.seq for f in frames] == list(range(10)) and not any(f.board_restart or f.gap for f in frames)
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.seq_gaps, counters.duplicates) == (0, 0, 0)


@pytest.mark.parametrize("bulk", [False, True])
def test_a_long_outage_then_the_reply_to_info_is_a_gap_not_a_restart(bulk):
    # A reconnect after 40 s at 1 kHz: the service asks INFO?, the board (still
    # running) replies stamped now, then scans 40 000 on, whose seq mod 2^16
    # looks "fallen back". The scans missed are a gap.
    decoder = BulkDecoder() if bulk else Decoder()
    before = b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(60_000, 60_005))
    after = info(1000 * 100_000) + b"".join(hand_frame(seq=(100_000 + s) % 65536, t_us=1000 * (100_001 + s))
                                            for s in range(3))
    frames = [f for f in decoder.feed(before + after) if f.type == FrameType.QUAD]
    assert not any(f.board_restart for f in frames) and frames[5].gap == 100_000 - 60_004 - 1
    assert decoder.counters.sensor(1).board_restarts == 0


@pytest.mark.parametrize("bulk", [False, True])
def test_a_restart_just_before_the_board_clock_wraps_is_no_gap(bulk):
    """The last scan 0.5 s before the u32 µs clock wraps, seq 33 000; the
    board powers up (INFO at 0, scans from seq 0): the clock looks 0.5 s on,
    the sequence 32 536 on — more scans than 0.5 s holds even at 5 000 a
    second. A restart, not 32 536 missed scans."""
    decoder = BulkDecoder() if bulk else Decoder()
    last = 2**32 - 500_000
    before = b"".join(hand_frame(seq=33_000 + s, t_us=last - 1000 * (4 - s)) for s in range(5))
    after = info(0) + b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(3))
    frames = [f for f in decoder.feed(before + after) if f.type == FrameType.QUAD]
    counters = decoder.counters.sensor(1)
    assert frames[5].board_restart and (counters.board_restarts, counters.seq_gaps, counters.missed_frames) == (1, 0, 0)


def test_a_gap_after_an_info_reply_at_the_fastest_rate_is_still_a_gap():
    """5 000 scans/s, 2 s lost, then INFO? answered and the scans go on:
    10 000 scans missed over 2 s of clock is a gap (what a restart after a
    wrap is told from)."""
    decoder = Decoder()
    before = b"".join(hand_frame(seq=s, t_us=200 * (s + 1)) for s in range(5))
    after = info(200 * 10_004) + b"".join(hand_frame(seq=10_005 + s, t_us=200 * (10_006 + s)) for s in range(3))
    frames = [f for f in decoder.feed(before + after) if f.type == FrameType.QUAD]
    assert not any(f.board_restart for f in frames) and frames[5].gap == 10_000


def test_an_info_reply_then_the_next_scan_is_neither_a_restart_nor_a_gap():
    decoder = Decoder()
    before = b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(5))
    after = info(5500) + b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(5, 8))
    frames = [f for f in decoder.feed(before + after) if f.type == FrameType.QUAD]
    assert not any(f.board_restart or f.gap for f in frames)


def test_a_board_up_for_over_half_its_clock_period_that_restarts_is_no_gap():
    # Up 50 min (3e9 µs: past half the 71.6 min period), then a power-up: its
    # INFO, and scans from seq 0 and t_us ~0, which modulo the clock look like
    # a step forward of 21.6 min.
    decoder = Decoder()
    before = b"".join(hand_frame(seq=s, t_us=3_000_000_000 + 1000 * s) for s in range(5))
    after = info(0) + b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(5))
    frames = [f for f in decoder.feed(before + after) if f.type == FrameType.QUAD]
    assert [f.board_restart for f in frames] == [False] * 5 + [True] + [False] * 4
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.seq_gaps, counters.missed_frames) == (1, 0, 0)


def test_a_clock_wrapping_through_an_info_reply_is_no_restart():
    decoder = Decoder()
    top = (1 << 32) - 2500
    # An INFO? reply between the last scan before the wrap and the first after it.
    frames = decoder.feed(hand_frame(seq=7, t_us=top) + hand_frame(seq=8, t_us=top + 1000) + info(top + 1500)
                          + hand_frame(seq=9, t_us=(top + 3000) % (1 << 32)) + hand_frame(seq=10, t_us=(top + 4000) % (1 << 32)))
    data = [f for f in frames if f.type == FrameType.QUAD]
    assert [f.t_us for f in data][2:] == [500, 1500]  # wrapped
    assert [f.board_restart for f in data] == [False] * 4 and decoder.counters.sensor(1).seq_gaps == 0


def test_a_power_up_identical_to_the_last_one_is_a_restart_not_repeats():
    # A deterministic board (the simulator with one seed) that powers up
    # twice sends the same bytes twice; the INFO between makes it a restart.
    run = info(0) + b"".join(hand_frame(seq=s, t_us=1000 * (s + 1)) for s in range(10))
    decoder = Decoder()
    frames = decoder.feed(run + run)
    assert [f.seq for f in frames if f.type == FrameType.QUAD] == list(range(10)) * 2
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.duplicates, counters.missed_frames) == (1, 0, 0)


def test_a_restart_whose_info_was_lost_is_still_a_restart_when_the_bytes_differ():
    before = b"".join(hand_frame(seq=s, t_us=1000 * (s + 1), payload=quad_payload(1, 2, 3, s)) for s in range(50))
    after = b"".join(hand_frame(seq=s, t_us=1000 * (s + 1), payload=quad_payload(9, 9, 9, s)) for s in range(5))
    decoder = Decoder()
    frames = decoder.feed(before + after)
    assert len(frames) == 55 and [i for i, f in enumerate(frames) if f.board_restart] == [50]
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.duplicates, counters.missed_frames) == (1, 0, 0)


@pytest.mark.parametrize("again", [{"flags": FLAG_OVERRUN}, {"t_us": 7500}, {"payload": bytes(range(16))},
                                   {"seq": 5, "t_us": 7200}])
@pytest.mark.parametrize("bulk", [False, True])
def test_a_scan_sent_again_with_other_bytes_is_conflicting_not_a_repeat_nor_65535_missed(again, bulk):
    """Same seq (or one shortly before) and other bytes — other flags, a
    later clock, other counts: not a repeat (a repeat is identical), and no
    gap of 65 535 scans either: dropped, counted in ``conflicting``, and the
    scan not passed on twice. The scans after it are in order."""
    decoder = BulkDecoder() if bulk else Decoder()
    frames = decoder.feed(hand_frame(seq=6, t_us=6000) + hand_frame(seq=7, t_us=7000)
                          + hand_frame(**{"seq": 7, "t_us": 7000, **again}) + hand_frame(seq=8, t_us=8000))
    counters = decoder.counters.as_dict()["sensors"]["1"]
    assert [f.seq for f in frames] == [6, 7, 8] and not any(f.gap for f in frames)
    assert (counters["conflicting"], counters["duplicates"], counters["seq_gaps"], counters["missed_frames"]) == (1, 0, 0, 0)


def test_a_real_gap_of_nearly_a_whole_sequence_is_still_a_gap():
    """65 400 scans missed over 65.4 s (a link down that long at 1 kHz):
    the sequence looks 136 behind, but the clock says a gap that long."""
    decoder = Decoder()
    frames = decoder.feed(hand_frame(seq=100, t_us=100_000) + hand_frame(seq=(100 + 65_401) % 65_536, t_us=65_501_000))
    assert len(frames) == 2 and frames[1].gap == 65_400 and decoder.counters.sensor(1).conflicting == 0


def test_a_repeat_after_an_info_reply_is_still_a_repeat():
    # INFO? or PING answered between a scan and its repetition: the reply
    # carries the board's current time, not a power-up's.
    a, b = hand_frame(seq=40, t_us=40_000), hand_frame(seq=41, t_us=41_000)
    decoder = Decoder()
    frames = decoder.feed(a + b + info(41_500, board_seq=3) + a + b + hand_frame(seq=42, t_us=42_000))
    assert [f.seq for f in frames if f.type == FrameType.QUAD] == [40, 41, 42]
    counters = decoder.counters.sensor(1)
    assert (counters.duplicates, counters.board_restarts, counters.missed_frames) == (2, 0, 0)


def test_the_simulator_powering_up_twice_in_a_row_is_one_restart_per_sensor():
    from firmware_sim.board import BoardConfig, capture

    run, board = capture(BoardConfig(), 0.05)  # one seed: both power-ups send the same bytes
    decoder = Decoder()
    frames = decoder.feed(run + run)
    per_run = 1 + 50 * len(board.config.sensors)  # INFO + 50 scans of each sensor at 1 kHz
    assert len(frames) == 2 * per_run
    assert [i for i, f in enumerate(frames) if f.board_restart] == [per_run + 1, per_run + 2]
    for sensor in (0, 1):
        counters = decoder.counters.sensor(sensor)
        assert (counters.board_restarts, counters.duplicates, counters.missed_frames) == (1, 0, 0)


@pytest.mark.parametrize("bulk", [False, True])
@pytest.mark.parametrize("order", [[249, 251, 250, 252], [249, 251, 252, 253, 250, 254], [249, 252, 250, 251, 253]])
def test_a_scan_the_link_delivered_late_is_dropped_not_taken_for_a_restart(bulk, order):
    """Scans reordered on the link: the gap is counted when it opens, the
    late scan dropped and counted, and the scans after it are in order — no
    restart (which would also restart the board's clock map)."""
    decoder = BulkDecoder() if bulk else Decoder()
    decoder.feed(b"".join(hand_frame(seq=s, t_us=1000 * s, payload=quad_payload(s, 2, 3, 4)) for s in range(200, 249)))
    frames = decoder.feed(b"".join(hand_frame(seq=s, t_us=1000 * s, payload=quad_payload(s, 2, 3, 4)) for s in order))
    expected = [s for s in order if s == 249 or s > max(order[: order.index(s)], default=0)]
    assert [f.seq for f in frames] == expected and not any(f.board_restart for f in frames)
    counters = decoder.counters.sensor(1)
    late = len(order) - len(expected)
    assert (counters.board_restarts, counters.late_frames, counters.duplicates) == (0, late, 0)
    assert counters.missed_frames == late and decoder.counters.as_dict()["sensors"]["1"]["late_frames"] == late


def run_of(seqs, value=0):
    """Scans of quad 1 at 1 kHz, each with its own counts (a repeat is then told by its bytes)."""
    return [hand_frame(seq=s % 65536, t_us=1000 * (s + 1), payload=quad_payload(value + s % 65536, 2, 3, 4))
            for s in seqs]


@pytest.mark.parametrize("bulk", [False, True])
@pytest.mark.parametrize("late_by", [1, 256, 257, 5_000, 65_535])
def test_a_repeat_however_late_is_a_duplicate_not_a_restart(bulk, late_by):
    """The link delivers scan 100 again ``late_by`` scans after it (past the
    256 scans a repeat used to be looked for in, it was passed on again as a
    restart, and the next scan then as a gap of ``late_by`` scans): dropped
    and counted, the scans after it in order."""
    scans = run_of(range(100, 100 + late_by + 1))
    after = run_of(range(101 + late_by, 104 + late_by))
    decoder = BulkDecoder() if bulk else Decoder()
    frames = decoder.feed(b"".join(scans) + scans[0] + b"".join(after))
    assert [f.seq for f in frames] == [s % 65536 for s in range(100, 104 + late_by)]
    assert not any(f.board_restart or f.gap for f in frames)
    counters = decoder.counters.sensor(1)
    assert (counters.duplicates, counters.board_restarts, counters.seq_gaps, counters.missed_frames) == (1, 0, 0, 0)


@pytest.mark.parametrize("bulk", [False, True])
def test_a_late_scan_delivered_again_is_a_duplicate(bulk):
    """Scan 250 comes late (after 251), then the link delivers it once more:
    the second copy is a repeat of a scan already seen, not a restart."""
    decoder = BulkDecoder() if bulk else Decoder()
    scans = dict(zip(range(200, 253), run_of(range(200, 253))))
    order = [*range(200, 250), 251, 250, 250, 252]
    frames = decoder.feed(b"".join(scans[s] for s in order))
    assert [f.seq for f in frames] == [*range(200, 250), 251, 252] and not any(f.board_restart for f in frames)
    counters = decoder.counters.sensor(1)
    assert (counters.late_frames, counters.duplicates, counters.board_restarts) == (1, 1, 0)


@pytest.mark.parametrize("bulk", [False, True])
@pytest.mark.parametrize("with_info", [False, True])
def test_a_restart_long_after_its_first_run_began_is_a_restart_not_a_late_repeat(bulk, with_info):
    """A board up for 1 000 scans powers up again: seq and clock from 0, the
    same (seq, t_us) as its first run's first scans, 1 000 scans later. With
    its INFO it is a restart even when the bytes are the first run's (a
    deterministic board); with the INFO lost, new counts tell it."""
    first = run_of(range(1000))
    again = run_of(range(5), value=0 if with_info else 7)
    decoder = BulkDecoder() if bulk else Decoder()
    frames = [f for f in decoder.feed(b"".join(first) + (info(0) if with_info else b"") + b"".join(again))
              if f.type == FrameType.QUAD]
    assert [f.seq for f in frames] == [*range(1000), *range(5)]
    assert [i for i, f in enumerate(frames) if f.board_restart] == [1000]
    counters = decoder.counters.sensor(1)
    assert (counters.board_restarts, counters.duplicates, counters.missed_frames) == (1, 0, 0)
