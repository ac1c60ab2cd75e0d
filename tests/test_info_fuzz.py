"""Structured fuzz of INFO: JSON of every type in every field, against an
oracle written from protocol.md (a field of the wrong JSON type invalidates
the whole INFO; unknown keys are ignored; a sensor described twice in two
ways is left undescribed, the protocol naming no rule for it; so is one
whose values, of the right types, no sensor can have: an id past 0..254, a
grid shape without rows or cols, or past 256 channels)."""
import json

import orjson
from hypothesis import event, given, settings
from hypothesis import strategies as st

from service.protocol import FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.interpreter import Interpreter

text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=8)  # JSON cannot carry lone surrogates
numbers = st.one_of(st.integers(-(2**70), 2**70), st.integers(-3, 300), st.floats(allow_nan=False, allow_infinity=False))
scalars = st.one_of(st.none(), st.booleans(), numbers, text)
any_json = st.recursive(scalars, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(text, inner, max_size=3),
                        max_leaves=6)
sensor_entry = st.one_of(
    st.fixed_dictionaries({"kind": st.just("quad")}, optional={"serial": text}),
    st.fixed_dictionaries({"kind": st.just("grid"), "rows": st.integers(1, 17), "cols": st.integers(1, 17)},
                          optional={"serial": text}),
    st.fixed_dictionaries({"kind": st.just("thermo")}),  # a kind this service does not know
).flatmap(lambda entry: st.fixed_dictionaries(
    {"id": st.one_of(st.integers(0, 5), st.integers(0, 254))},  # 0..5: duplicates happen
    optional={"gain": any_json},  # a key this service does not know
).map(lambda extra: {**entry, **extra}))
plausible_info = st.fixed_dictionaries({"board": text, "sensors": st.lists(sensor_entry, max_size=4)}, optional={
    "fw": text, "serial": text, "rate_hz": st.one_of(st.integers(1, 5000), st.floats(0.5, 5000)),
    "pong": st.booleans(), "future": any_json,
})


@st.composite
def info_docs(draw):
    """A plausible INFO in which up to three values (a top-level field, a
    sensor entry, a sensor's field) are replaced by any JSON value or removed."""
    doc = draw(plausible_info)
    for _ in range(draw(st.sampled_from([0, 0, 1, 2, 3]))):
        sensors = doc.get("sensors")
        containers = [doc]
        if isinstance(sensors, list) and sensors:
            containers += [sensors] + [entry for entry in sensors if isinstance(entry, dict)]
        target = draw(st.sampled_from(containers))
        if isinstance(target, list):
            target[draw(st.integers(0, len(target) - 1))] = draw(any_json)
            continue
        key = draw(st.sampled_from(sorted(set(target) | {"id", "kind", "rows", "serial", "rate_hz"})))
        if key in target and draw(st.booleans()):
            del target[key]
        else:
            target[key] = draw(any_json)
    return doc


def expected_sensors(doc):
    """What a valid INFO announces, {id: (kind, rows, cols, serial)}; None
    when the INFO is invalid. Exact types (``type(x) is int``): JSON has no
    booleans among its numbers."""
    if type(doc) is not dict:
        return None
    for name, kind in (("board", str), ("fw", str), ("serial", str), ("pong", bool), ("sensors", list)):
        if name in doc and type(doc[name]) is not kind:
            return None
    if "rate_hz" in doc and not (type(doc["rate_hz"]) in (int, float) and doc["rate_hz"] > 0):
        return None
    described, conflicting = {}, set()  # id: (kind, rows, cols, serial), None for a kind not known
    for entry in doc.get("sensors", []):
        if type(entry) is not dict or type(entry.get("id")) is not int:
            return None
        if type(entry.get("kind")) is not str or ("serial" in entry and type(entry["serial"]) is not str):
            return None
        rows, cols = entry.get("rows"), entry.get("cols")
        if entry["kind"] == "grid" and any(v is not None and type(v) is not int for v in (rows, cols)):
            return None  # a wrong type: the whole INFO; a value out of range: that sensor alone (below)
        description = None
        if not 0 <= entry["id"] <= 254:
            pass
        elif entry["kind"] == "quad":
            description = ("quad", 2, 2, entry.get("serial"))
        elif entry["kind"] == "grid":
            # At most 256 channels: a payload is at most 1024 bytes of u32.
            if rows is not None and cols is not None and rows >= 1 and cols >= 1 and rows * cols <= 256:
                description = ("grid", rows, cols, entry.get("serial"))
        if entry["id"] in described:  # described again: the same counts once, another leaves it undescribed
            if described[entry["id"]] != description:
                conflicting.add(entry["id"])
            continue
        described[entry["id"]] = description
    return {sid: d for sid, d in described.items() if d is not None and sid not in conflicting}


def table(interpreter):
    return {sid: (s.kind, s.rows, s.cols, s.serial) for sid, s in interpreter.sensors.items()}


FIRST = {"board": "first", "serial": "TMX-1", "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 16},
                                                          {"id": 1, "kind": "quad", "serial": "Q-1"}]}


@settings(max_examples=600, deadline=None)
@given(st.one_of(info_docs(), any_json))
def test_any_info_is_taken_or_rejected_whole_as_the_protocol_says_and_counted(doc):
    payload = json.dumps(doc).encode()
    if len(payload) > 1024:  # not a frame the protocol allows
        event("too long")
        return
    interpreter = Interpreter()
    frames = Decoder().feed(encode_frame(FrameType.INFO, 255, 0, 0, json.dumps(FIRST).encode())
                            + encode_frame(FrameType.INFO, 255, 1, 1000, payload))
    interpreter.interpret(frames[0], 0.0)
    before, board_before = table(interpreter), dict(interpreter.board)
    assert before == {0: ("grid", 4, 16, None), 1: ("quad", 2, 2, "Q-1")}
    interpreter.interpret(frames[1], 0.0)
    announced = expected_sensors(doc)
    event("rejected" if announced is None else f"accepted, {len(announced)} sensors")
    if announced is None:
        assert interpreter.rejected["info_invalid"] == 1
        assert table(interpreter) == before and interpreter.board == board_before
    else:
        assert interpreter.rejected["info_invalid"] == 0
        identity = [d.get("serial") or d.get("board") for d in (FIRST, orjson.loads(payload))]
        # Another board on the link (its serial, else its model, differs): the first board's other sensors are gone.
        assert table(interpreter) == ({**before, **announced} if identity[0] == identity[1] else announced)
        # Compared with orjson's reading of the JSON: it turns integers beyond 64 bits into floats.
        assert interpreter.board == {k: v for k, v in orjson.loads(payload).items() if k != "sensors"}
