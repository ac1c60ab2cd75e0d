"""The load test's own counting (scripts/loadtest.py): a wrong count there
is a wrong figure in docs/load.md."""
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

from service.fanout.encoding import to_binary
from service.readings import SensorInfo
from service.reconstruct import ForceFrame

_SPEC = importlib.util.spec_from_file_location("loadtest", Path(__file__).parents[1] / "scripts" / "loadtest.py")
loadtest = importlib.util.module_from_spec(_SPEC)
sys.modules["loadtest"] = loadtest  # its dataclasses look their module up there
_SPEC.loader.exec_module(loadtest)

QUAD = SensorInfo(4, "quad", 2, 2)


def message(seqs) -> bytes:
    frames = [ForceFrame(QUAD, seq % 65536, 0, time.time(), np.zeros(3), np.ones(4), [], "full") for seq in seqs]
    return len(frames).to_bytes(2, "little") + b"".join(to_binary(frame) for frame in frames)


def test_records_of_grids_and_quads_with_every_field_are_cut_where_they_end():
    """Each record's length follows its fields (forces, σ, raw, a grid's
    taxel flags): a miscut would count garbage as sequence numbers."""
    from service.fanout.encoding import DEFAULT_FIELDS

    grid = SensorInfo(0, "grid", 3, 5, board="left")
    flags = np.zeros(15, np.uint8)
    flags[2] = 2
    frames = [ForceFrame(grid if k % 2 else QUAD, 100 + k, 0, time.time(), np.zeros(15 if k % 2 else 3),
                         np.ones(15 if k % 2 else 4), [], "full", flags if k % 2 else None, "cal", np.ones(15 if k % 2 else 3))
              for k in range(10)]
    for fields in (DEFAULT_FIELDS, DEFAULT_FIELDS | {"raw"}, frozenset({"force"})):
        tally = loadtest.Tally()
        tally.binary(len(frames).to_bytes(2, "little") + b"".join(to_binary(f, fields) for f in frames), time.time())
        assert {sid: seqs.tolist() for sid, seqs in tally.seqs.items()} == {0: [101, 103, 105, 107, 109],
                                                                            4: [100, 102, 104, 106, 108]}


def tally_of(batches) -> "loadtest.Tally":
    tally = loadtest.Tally()
    for seqs in batches:
        tally.binary(message(seqs), time.time())
    return tally


def test_clients_that_join_on_either_side_of_a_wrap_share_one_window():
    early = tally_of([range(65530, 65536), range(65536, 65600)]).seqs  # joined before the wrap
    late = tally_of([range(65537, 65590)]).seqs  # first frame seq 1
    assert early[4][0] == 65530 and late[4][0] == 1  # each unwrapped from its own first frame
    window = loadtest.shared_window([early, late])
    assert window == {4: (65537, 65589)}
    assert loadtest.Tally.share(early, window) == 1.0
    assert loadtest.Tally.share(late, window) == 1.0


def test_a_frame_missing_inside_the_window_lowers_the_share():
    full = tally_of([range(100, 200)]).seqs
    gappy = tally_of([range(100, 150), range(151, 200)]).seqs
    window = loadtest.shared_window([full, gappy])
    assert window == {4: (100, 199)}
    assert loadtest.Tally.share(gappy, window) == 99 / 100
