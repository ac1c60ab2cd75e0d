"""Property-based fuzzing of the decoder with hypothesis, and a seeded
byte-mutation fuzz of real captures; each on both decoders (protocol_decoder.py's
and protocol_bulk.py's), and the two compared frame for frame and counter
for counter on the mutated captures."""
import random
from binascii import crc_hqx
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimQuad
from service.protocol import FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.protocol_sequence import RESTART_JUMP_US
from service.protocol_bulk import BulkDecoder

DECODERS = pytest.mark.parametrize("decoder_class", [Decoder, BulkDecoder])

frame_specs = st.one_of(
    st.tuples(st.just(FrameType.QUAD), st.integers(0, 255), st.binary(min_size=16, max_size=16)),
    st.tuples(st.just(FrameType.GRID), st.integers(0, 255), st.binary(min_size=4, max_size=64).filter(lambda b: len(b) % 4 == 0)),
    st.tuples(st.just(FrameType.INFO), st.just(255), st.binary(max_size=40)),
    st.tuples(st.just(FrameType.ERROR), st.just(255), st.binary(max_size=40)),
)
frames_st = st.lists(
    st.tuples(frame_specs, st.integers(0, 3), st.integers(0, 65535), st.integers(0, 2**32 - 1)), max_size=12
)


def encode_all(specs):
    return [
        (encode_frame(ftype, sensor, seq, t_us, payload, flags), (ftype, sensor, flags, seq, t_us, payload))
        for (ftype, sensor, payload), flags, seq, t_us in specs
    ]


def decode_in_chunks(data, cuts, decoder_class=Decoder):
    decoder = decoder_class()
    points = sorted({c % (len(data) + 1) for c in cuts}) if data else []
    frames, last = [], 0
    for point in points + [len(data)]:
        frames += decoder.feed(data[last:point])
        last = point
    return frames + decoder.finish(), decoder


def key(frame):
    return (frame.type, frame.sensor, frame.flags, frame.seq, frame.t_us, frame.payload, frame.gap, frame.board_restart)


def passed_on(expected):
    """The frames a decoder passes on, with their gap and restart flag, per
    protocol.md "Restarts and repeats". A data frame from id 255 (the board)
    is dropped. One whose board clock does not run forward from its sensor's
    last one is the first after a restart when an INFO the board sent before
    it came since that last frame; otherwise it is a repeat, dropped, when it
    equals the last frame of its sensor passed on (or dropped as late) with
    its sequence number, however long ago, and a restart when the clock
    went back — unless its sequence is the next one (not 0 after 65 535)
    and it is no such repeat: then it is in order. After an INFO, a clock that fell back by more than
    RESTART_JUMP_US (yet "forward" modulo 2^32) is a restart too, and so,
    after an INFO stamped before the sensor's last scan, is a sequence that
    fell back (by half its period or more) while the clock ran on, and a
    sequence that jumped by twice the scans the clock's step holds at 5 000
    scans/s. A scan
    whose clock went back, no INFO since, that one of the sensor's gaps of at
    most 256 scans missed (and behind by no more than those scans take at
    1 Hz) came late: dropped. Any other frame whose sequence did not advance
    or fell back by at most 256, sooner than a gap of that many scans (mod
    2^16) could take at 5 000 scans/s, is none of the protocol's frames:
    dropped (not a gap of ~65 000 scans)."""
    last, recent, missing, kept = {}, {}, {}, []
    for spec in expected:
        ftype, sensor, flags, seq, t_us, payload = spec
        gap, restart = 0, False
        if ftype in (FrameType.GRID, FrameType.QUAD):
            if sensor == 255:
                continue
            if sensor in last:
                last_seq, last_t_us, info_t_us = last[sensor]
                step = (t_us - last_t_us) % 2**32
                if step > 2**31 and seq == last_seq + 1 and recent[sensor].get(seq) != spec:
                    pass  # the next scan, after a long pause or a clock step back: in order
                elif step == 0 or step > 2**31:
                    restart = info_t_us is not None and 0 < (t_us - info_t_us) % 2**32 < 2**31
                    if not restart and recent[sensor].get(seq) == spec:
                        continue
                    if not restart and step and (last_seq - seq) % 2**16 <= 256 and seq in missing[sensor] \
                            and 2**32 - step <= (last_seq - seq) % 2**16 * 1_000_000:
                        missing[sensor].remove(seq)
                        recent[sensor][seq] = spec
                        continue
                    restart = restart or step != 0
                elif info_t_us is not None and t_us < last_t_us and step > RESTART_JUMP_US:
                    restart = True  # after an INFO the clock fell back: a restart past half the clock's period
                elif info_t_us is not None and (seq - last_seq) % 2**16 >= 2**15 \
                        and 0 < (last_t_us - info_t_us) % 2**32 < 2**31:
                    restart = True  # after a power-up INFO the sequence started again: a board up for a short time
                elif info_t_us is not None and (seq - last_seq - 1) % 2**16 * 200 > 2 * step:
                    restart = True  # after an INFO, twice the scans missed that the clock's step holds at 5 kHz
                if restart:
                    missing[sensor] = []
                else:
                    forward = (seq - last_seq) % 2**16
                    if (forward == 0 or forward > 2**16 - 256) and step < (forward - 1) % 2**16 * 200:
                        continue
                    gap = (seq - last_seq - 1) % 2**16
                    if 0 < gap <= 256:
                        missing[sensor] = (missing[sensor] + [(last_seq + k) % 2**16 for k in range(1, gap + 1)])[-256:]
            missing.setdefault(sensor, [])
            last[sensor] = (seq, t_us, None)
            recent.setdefault(sensor, {})[seq] = spec
        elif ftype == FrameType.INFO:
            last = {sid: (s, t, t_us) for sid, (s, t, _) in last.items()}
        kept.append(spec + (gap, restart))
    return kept


@DECODERS
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 4000), max_size=10))
def test_arbitrary_bytes_never_raise_and_only_yield_valid_frames(decoder_class, data, cuts):
    frames, decoder = decode_in_chunks(data, cuts, decoder_class)
    for frame in frames:
        assert encode_frame(frame.type, frame.sensor, frame.seq, frame.t_us, frame.payload, frame.flags) in data
    assert decoder.counters.bytes_discarded + sum(len(f.payload) + 16 for f in frames) == len(data)


@DECODERS
@settings(max_examples=300, deadline=None)
@given(frames_st, st.lists(st.binary(max_size=30), min_size=13, max_size=13), st.lists(st.integers(0, 5000), max_size=10))
def test_frames_survive_any_garbage_and_any_chunking(decoder_class, specs, garbage, cuts):
    encoded = encode_all(specs)
    stream = b"".join(junk + data for junk, (data, _) in zip(garbage, encoded + [(b"", None)]))
    frames, _ = decode_in_chunks(stream, cuts, decoder_class)
    assert [key(f) for f in frames] == passed_on([expected for _, expected in encoded])


@DECODERS
@settings(max_examples=200, deadline=None)
@given(frames_st, st.data())
def test_a_damaged_frame_never_becomes_a_different_frame(decoder_class, specs, data):
    encoded = encode_all(specs)
    if not encoded:
        return
    victim = data.draw(st.integers(0, len(encoded) - 1))
    raw = bytearray(encoded[victim][0])
    position = data.draw(st.integers(0, len(raw) - 1))
    raw[position] ^= data.draw(st.integers(1, 255))
    stream = b"".join(bytes(raw) if i == victim else d for i, (d, _) in enumerate(encoded))
    frames, _ = decode_in_chunks(stream, [], decoder_class)
    expected = [k for i, (_, k) in enumerate(encoded) if i != victim]
    assert [key(f) for f in frames] == passed_on(expected)


# Few distinct values, so that clocks collide, step back and repeat often.
clashing_specs = st.lists(
    st.tuples(
        st.one_of(
            st.tuples(st.just(FrameType.QUAD), st.sampled_from([1, 2, 255]), st.sampled_from([bytes(16), b"\x01" * 16])),
            st.tuples(st.just(FrameType.INFO), st.just(255), st.just(b"{}")),
        ),
        st.integers(0, 1), st.integers(0, 3), st.sampled_from([0, 1000, 2000, 3000, 2**32 - 1000]),
    ),
    max_size=30,
)


@DECODERS
@settings(max_examples=300, deadline=None)
@given(clashing_specs, st.lists(st.tuples(st.integers(0, 29), st.integers(0, 30)), max_size=10))
def test_repeats_and_restarts_follow_the_protocols_rule(decoder_class, specs, copies):
    # Copies of earlier frames put later in the stream are the link's repeats.
    specs = list(specs)
    for source, target in copies:
        if source < len(specs):
            specs.insert(max(target, source + 1), specs[source])
    encoded = encode_all(specs)
    frames, _ = decode_in_chunks(b"".join(data for data, _ in encoded), [], decoder_class)
    assert [key(f) for f in frames] == passed_on([expected for _, expected in encoded])


DATA = Path(__file__).parent / "data"
MUTATIONS = 50_000


def hand_encoded(frame):
    """The frame's bytes rebuilt from protocol.md's table, CRC by binascii."""
    body = bytes([1, frame.type, frame.sensor, frame.flags]) + frame.seq.to_bytes(2, "little")
    body += frame.t_us.to_bytes(4, "little") + len(frame.payload).to_bytes(2, "little") + frame.payload
    return b"\xa5\x5a" + body + crc_hqx(body, 0xFFFF).to_bytes(2, "little")


def mutate(rng, data):
    data = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        at = rng.randrange(len(data) + 1)
        span = rng.randint(1, 40)
        match rng.randrange(6):
            case 0:  # bit flip
                if at < len(data):
                    data[at] ^= 1 << rng.randrange(8)
            case 1:  # random bytes inserted
                data[at:at] = rng.randbytes(span)
            case 2:  # bytes lost
                del data[at : at + span]
            case 3:  # a stretch delivered twice
                data[at:at] = data[at : at + span * 8]
            case 4:  # a sync pattern and a plausible header start out of nowhere
                data[at:at] = b"\xa5\x5a\x01" + bytes([rng.choice([0x01, 0x10, 0x11, 0x7F])]) + rng.randbytes(rng.randint(0, 12))
            case 5:  # a length field (or whatever is there) overwritten
                data[at : at + 2] = rng.randbytes(2)
    return bytes(data)


def test_fifty_thousand_mutations_of_real_captures_never_raise_or_pass_a_bad_crc():
    # Valid captures: the simulator's (grid + quad, several quads) and windows
    # of the committed fault captures, each a few frames long to keep it fast.
    bases = [capture(BoardConfig(scene="press"), 0.004)[0],
             capture(BoardConfig(sensors=[SimQuad(i) for i in range(6)], rate_hz=2000), 0.002)[0]]
    bases += [raw[i : i + 1500] for raw in (p.read_bytes() for p in sorted(DATA.glob("*.bin"))) for i in (0, 20_000, 60_000)]
    rng = random.Random(20261123)
    emitted = 0
    for _ in range(MUTATIONS):
        data = mutate(rng, rng.choice(bases))
        cut = rng.randrange(len(data) + 1)
        decoder, bulk = Decoder(), BulkDecoder()
        frames = decoder.feed(data[:cut]) + decoder.feed(data[cut:]) + decoder.finish()
        encoded = [hand_encoded(f) for f in frames]
        assert all(e in data for e in encoded)  # each frame is in the input whole, its CRC good
        assert decoder.counters.bytes_discarded + sum(map(len, encoded)) == len(data)
        assert bulk.feed(data[:cut]) + bulk.feed(data[cut:]) + bulk.finish() == frames
        assert bulk.counters.as_dict() == decoder.counters.as_dict()
        emitted += len(frames)
    assert emitted > 5 * MUTATIONS  # most frames survive: the check above ran on real frames
