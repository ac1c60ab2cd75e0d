"""A decimated stream (max_rate) keeps every quality flag: the flags of the
frames it skipped come with the next frame it sends of that sensor."""
import asyncio

import numpy as np
import orjson

from service.fanout import hub as hub_module
from service.fanout.encoding import decode_binary
from service.fanout.hub import Hub, Subscriber
from service.readings import SensorInfo
from service.reconstruct import ForceFrame
from service.reconstruct.taxel_flags import SATURATED, STALE

GRID, QUAD = SensorInfo(0, "grid", 2, 2), SensorInfo(1, "quad", 2, 2)
RATE_HZ, SECONDS = 1000, 2.0


def grid_frame(seq, flags=(), taxel_flags=None, info=GRID):
    bits = np.zeros(info.rows * info.cols, np.uint8) if taxel_flags is None else np.asarray(taxel_flags, np.uint8)
    forces = np.full(info.rows * info.cols, float(seq))  # a frame's forces name it: seq N everywhere
    return ForceFrame(info, seq, seq * 1000, 100.0 + seq / RATE_HZ, forces, np.ones(info.rows * info.cols),
                      list(flags), "full", taxel_flags=bits)


def quad_frame(seq, flags=()):
    return ForceFrame(QUAD, seq, seq * 1000, 100.0 + seq / RATE_HZ, np.full(3, float(seq)), np.ones(4), list(flags), "full")


def stream(frames_by_seq, subscribers):
    """Publish 1 kHz frames (one batch per ms) to the subscribers; every
    message each received, decoded, in order."""
    async def scenario():
        hub, received = Hub(), [[] for _ in subscribers]
        for subscriber in subscribers:
            hub.add(subscriber)
        for batch in frames_by_seq:
            hub.publish(batch)
            for subscriber, out in zip(subscribers, received):
                while subscriber.pending:
                    message, _, _ = await subscriber.next_message()
                    out.extend(decode_binary(message) if subscriber.binary else orjson.loads(message)["frames"])
        return received

    return asyncio.run(scenario())


def test_a_decimated_client_sees_each_short_flag_once_on_the_next_frame_it_is_sent():
    n = int(RATE_HZ * SECONDS)
    sat_bits = np.zeros(4, np.uint8)
    sat_bits[3] = SATURATED
    events = {500: ["saturated"], 1201: ["seq_gap"], 1600: ["board_restart"]}  # one frame each, 1 ms
    batches = [[grid_frame(seq, events.get(seq, ()), sat_bits if seq == 500 else None),
                quad_frame(seq, ["overrun"] if seq == 900 else ())] for seq in range(n)]
    json_client, binary_client = Subscriber(max_rate_hz=30.0), Subscriber(max_rate_hz=30.0, binary=True)
    for frames in stream(batches, [json_client, binary_client]):
        grid = [f for f in frames if f.get("header", f).get("sensor_id") == 0]
        quad = [f for f in frames if f.get("header", f).get("sensor_id") == 1]
        assert abs(len(grid) - SECONDS * 30) <= 1  # 30 Hz of 1 kHz: still decimated
        seqs = [f["header"]["seq"] if "header" in f else f["seq"] for f in grid]
        for seq, flags in events.items():
            carrier = next(i for i, s in enumerate(seqs) if s >= seq)  # the first frame sent at or after it
            assert seqs[carrier] - seq < RATE_HZ / 30 + 1
            assert [s for s, f in zip(seqs, grid) if flags[0] in f["flags"]] == [seqs[carrier]]  # once, not again
        saturated = [(s, f["taxel_flags"]) for s, f in zip(seqs, grid) if f["taxel_flags"]]
        assert saturated == [(next(s for s in seqs if s >= 500), {"saturated": [3]})]
        for s, f in zip(seqs, grid):  # the forces stay the sent frame's own
            assert np.allclose(f["force_N"], s)
        assert [f["flags"] for f in quad if f["flags"]] == [["overrun"]]  # per sensor: not on the grid
        assert all("overrun" not in f["flags"] for f in grid)


def test_carried_flags_join_the_sent_frames_own_without_repeating_them():
    stale, sat = np.array([STALE, 0, 0, 0], np.uint8), np.array([SATURATED, 0, 0, SATURATED], np.uint8)
    batches = [[grid_frame(0)], [grid_frame(1, ["saturated"], sat)], [grid_frame(2, ["stale", "saturated"], stale)],
               [grid_frame(40, ["stale"], stale)]]  # 40 ms on: due again at 30 Hz
    (frames,) = stream(batches, [Subscriber(max_rate_hz=30.0)])
    assert [f["header"]["seq"] for f in frames] == [0, 40]
    assert sorted(frames[1]["flags"]) == ["saturated", "stale"]
    assert frames[1]["taxel_flags"] == {"saturated": [0, 3], "stale": [0]}
    assert frames[1]["force_N"] == [40.0] * 4


def test_a_sensor_that_changed_shape_keeps_the_frame_flags_not_taxel_indices_of_the_old_shape():
    wide = SensorInfo(0, "grid", 2, 4)
    bits = np.array([0, 0, 0, SATURATED], np.uint8)
    batches = [[grid_frame(0)], [grid_frame(1, ["saturated"], bits)], [grid_frame(40, info=wide)]]
    (frames,) = stream(batches, [Subscriber(max_rate_hz=30.0)])
    assert frames[1]["flags"] == ["saturated"] and frames[1]["taxel_flags"] == {}


def test_decimated_clients_share_each_encoding_while_no_skipped_frame_had_a_flag(monkeypatch):
    encoded = []
    real = hub_module.to_json_dict
    monkeypatch.setattr(hub_module, "to_json_dict",
                        lambda frame, fields: encoded.append(frame.seq) or real(frame, fields))
    crosstalk = np.full(4, 8, np.uint8)  # on every frame: nothing a sent frame lacks
    batches = [[grid_frame(seq, ["crosstalk_corrected"], crosstalk)] for seq in range(1000)]
    a, b = stream(batches, [Subscriber(max_rate_hz=30.0), Subscriber(max_rate_hz=30.0)])
    assert a == b and len(a) == 30
    assert sorted(encoded) == [f["header"]["seq"] for f in a]  # once per sent frame, not per client
