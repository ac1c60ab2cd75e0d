"""History answers: frames' JSON kept across reads, the answers byte for byte to_json_dict's."""
import asyncio
from itertools import combinations

import numpy as np
import orjson
import pytest

from service.api.routes_sensors import encode_history
from service.fanout import history_json
from service.fanout.encoding import FIELDS, to_json_dict
from service.fanout.history_json import RecentRings, RingTexts
from service.history import History
from service.readings import SensorInfo
from service.reconstruct import ForceFrame

GRID = SensorInfo(0, "grid", 2, 3)
QUAD = SensorInfo(1, "quad", 2, 2)  # four electrodes
EVERY_FIELDS = [frozenset(c) for n in range(len(FIELDS) + 1) for c in combinations(FIELDS, n)]


def varied(info: SensorInfo, seq: int) -> ForceFrame:
    """Frames unlike each other: NaN forces (some all NaN: no contact),
    frame and taxel flags, σ missing or partly NaN, scan stamps unmapped,
    two calibrations, forces over many magnitudes. σ is exact in float32,
    as the ring keeps it."""
    rng = np.random.default_rng(seq)
    n = 3 if info.kind == "quad" else info.rows * info.cols
    forces = rng.standard_normal(n) * 10.0 ** rng.integers(-8, 4)
    forces[rng.random(n) < 0.2] = np.nan
    if seq % 7 == 0:
        forces[:] = np.nan
    sigma = None if seq % 5 == 0 else np.where(rng.random(n) < 0.3, np.nan, rng.integers(1, 4096, n) / 1024.0)
    flags = [["taring"], [], ["seq_gap", "saturated"], []][seq % 4]
    taxel_flags = None
    if info.kind == "grid":
        taxel_flags = (rng.integers(0, 128, n) * (rng.random(n) < 0.3)).astype(np.uint8) if seq % 3 else None
    return ForceFrame(info, seq % 65536, seq * 1000 + 7, 1.7e9 + seq * 1e-3 + rng.random() * 1e-4, forces,
                      rng.random(4 if info.kind == "quad" else n) * 50.0, flags, "full", taxel_flags,
                      f"cal-{seq % 2}", sigma, float("nan") if seq % 6 == 1 else 1.7e9 + seq * 1e-3 - 5e-4)


def reference(frames: list[ForceFrame], fields: frozenset[str]) -> bytes:
    return orjson.dumps([to_json_dict(f, fields) for f in frames], option=orjson.OPT_SERIALIZE_NUMPY)


def ring(info: SensorInfo, count: int, capacity: int = 64) -> tuple[History, list[ForceFrame]]:
    history = History(info, capacity, 3 if info.kind == "quad" else info.rows * info.cols)
    frames = [varied(info, seq) for seq in range(count)]
    for f in frames:
        history.append(f)
    return history, frames[-capacity:]


RINGS = RecentRings(64 << 20)  # one app's: reads of a test reuse each other's texts


def read(history: History, seconds: float, max_points: int, fields: frozenset[str]) -> bytes:
    return asyncio.run(encode_history(history, seconds, max_points, fields, RINGS))


@pytest.mark.parametrize("info", [GRID, QUAD])
def test_every_set_of_fields_is_answered_as_to_json_dict_encodes_it(info):
    history, kept = ring(info, 100)
    for fields in EVERY_FIELDS:
        assert read(history, 10.0, 1000, fields) == reference(kept, fields), sorted(fields)
        assert read(history, 10.0, 1000, fields) == reference(kept, fields)  # from the kept texts


def test_reads_reuse_what_earlier_reads_encoded_and_stay_exact(monkeypatch):
    encoded = []
    monkeypatch.setattr(history_json, "to_json_dict", lambda f, fields: encoded.append(f) or to_json_dict(f, fields))
    fields = frozenset({"force", "contact", "flags"})
    history = History(GRID, 50, 6)
    frames = [varied(GRID, seq) for seq in range(200)]
    for f in frames[:80]:
        history.append(f)
    assert read(history, 10.0, 1000, fields) == reference(frames[30:80], fields)
    assert len(encoded) == 50
    for f in frames[80:90]:  # ten new frames overwrite the ten oldest slots
        history.append(f)
    encoded.clear()
    assert read(history, 10.0, 1000, fields) == reference(frames[40:90], fields)
    assert len(encoded) == 10
    encoded.clear()
    assert read(history, 0.0095, 1000, fields) == reference(frames[80:90], fields)  # a shorter window: all kept
    assert encoded == []
    sparse = history.window_slots(10.0, 7)
    assert read(history, 10.0, 7, fields) == reference(history.frames_at(sparse), fields)
    history.shrink(20)  # a new sensor took part of the budget: slots hold other frames now
    assert read(history, 10.0, 1000, fields) == reference(frames[70:90], fields)
    assert read(History(GRID, 5, 6), 1.0, 10, fields) == b"[]"


def test_a_large_answer_is_joined_alike(monkeypatch):
    """Past the size joined in a worker thread."""
    from service.api import routes_sensors

    monkeypatch.setattr(routes_sensors, "JOIN_IN_THREAD_BYTES", 1)
    history, kept = ring(QUAD, 40, capacity=40)
    fields = frozenset(FIELDS)
    assert read(history, 10.0, 1000, fields) == reference(kept, fields)
    one = history.window_slots(0.0, 1)
    assert read(history, 0.0, 1, fields) == reference(history.frames_at(one), fields)


def test_the_rings_read_last_are_kept_within_a_size():
    fields = frozenset({"force"})
    rings = [ring(GRID, 10, capacity=10)[0] for _ in range(3)]
    one = len(reference(rings[0].window(10.0, 100), fields)) - 2 - 9  # the texts, without brackets and commas
    recent = RecentRings(max_bytes=2 * one)  # room for two rings' texts

    def read(history: History) -> RingTexts:
        texts = recent.get(history, fields)
        texts.encode(history.window_slots(10.0, 100))
        return texts

    first, second = read(rings[0]), read(rings[1])
    assert first.bytes == second.bytes == one
    assert read(rings[0]) is first  # used again: rings[1] is now the oldest
    read(rings[2])  # three rings' texts now, more than the size
    assert read(rings[0]) is first  # this read forgot the oldest
    assert recent.get(rings[1], fields) is not second
