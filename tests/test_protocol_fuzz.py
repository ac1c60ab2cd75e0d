"""Property-based fuzzing of the decoder with hypothesis."""
from hypothesis import given, settings
from hypothesis import strategies as st

from service.protocol import Decoder, FrameType, encode_frame

frame_specs = st.one_of(
    st.tuples(st.just(FrameType.QUAD), st.integers(0, 254), st.binary(min_size=16, max_size=16)),
    st.tuples(st.just(FrameType.GRID), st.integers(0, 254), st.binary(min_size=4, max_size=64).filter(lambda b: len(b) % 4 == 0)),
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


def decode_in_chunks(data, cuts):
    decoder = Decoder()
    points = sorted({c % (len(data) + 1) for c in cuts}) if data else []
    frames, last = [], 0
    for point in points + [len(data)]:
        frames += decoder.feed(data[last:point])
        last = point
    return frames + decoder.finish(), decoder


def key(frame):
    return (frame.type, frame.sensor, frame.flags, frame.seq, frame.t_us, frame.payload)


def without_repeats(expected):
    """The frames a decoder passes on: a data frame whose board clock does
    not advance past its sensor's last one and that repeats one of the
    sensor's recent scans (same seq and board time) is dropped."""
    recent, kept = {}, []
    for ftype, sensor, flags, seq, t_us, payload in expected:
        if ftype in (FrameType.GRID, FrameType.QUAD):
            scans = recent.setdefault(sensor, [])
            if scans:
                step = (t_us - scans[-1][1]) % 2**32
                if (step == 0 or step > 2**31) and (seq, t_us) in scans[-256:]:
                    continue
            scans.append((seq, t_us))
        kept.append((ftype, sensor, flags, seq, t_us, payload))
    return kept


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 4000), max_size=10))
def test_arbitrary_bytes_never_raise_and_only_yield_valid_frames(data, cuts):
    frames, decoder = decode_in_chunks(data, cuts)
    for frame in frames:
        assert encode_frame(frame.type, frame.sensor, frame.seq, frame.t_us, frame.payload, frame.flags) in data
    assert decoder.counters.bytes_discarded + sum(len(f.payload) + 16 for f in frames) == len(data)


@settings(max_examples=300, deadline=None)
@given(frames_st, st.lists(st.binary(max_size=30), min_size=13, max_size=13), st.lists(st.integers(0, 5000), max_size=10))
def test_frames_survive_any_garbage_and_any_chunking(specs, garbage, cuts):
    encoded = encode_all(specs)
    stream = b"".join(junk + data for junk, (data, _) in zip(garbage, encoded + [(b"", None)]))
    frames, _ = decode_in_chunks(stream, cuts)
    assert [key(f) for f in frames] == without_repeats([expected for _, expected in encoded])


@settings(max_examples=200, deadline=None)
@given(frames_st, st.data())
def test_a_damaged_frame_never_becomes_a_different_frame(specs, data):
    encoded = encode_all(specs)
    if not encoded:
        return
    victim = data.draw(st.integers(0, len(encoded) - 1))
    raw = bytearray(encoded[victim][0])
    position = data.draw(st.integers(0, len(raw) - 1))
    raw[position] ^= data.draw(st.integers(1, 255))
    stream = b"".join(bytes(raw) if i == victim else d for i, (d, _) in enumerate(encoded))
    frames, _ = decode_in_chunks(stream, [])
    expected = [k for i, (_, k) in enumerate(encoded) if i != victim]
    assert [key(f) for f in frames] == without_repeats(expected)
