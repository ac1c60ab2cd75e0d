"""Replayed-log regression: committed captures with faults against goldens.

Regenerate with ``python -m tests.regenerate_goldens`` when a model change
is meant to move the forces (see that module)."""
import gzip

import numpy as np
import orjson
import pytest

from tests.regenerate_goldens import CAPTURES, DATA, OPEN_SEQS, OPEN_TAXEL, export

FORCE_TOLERANCE_N = 2e-6


def forces(doc):
    return np.array(doc.get("taxels_N", doc.get("fxyz_N")), dtype=float)


@pytest.mark.parametrize("name", sorted(CAPTURES))
def test_replay_matches_golden(name):
    golden = [orjson.loads(line) for line in gzip.decompress((DATA / f"{name}.golden.jsonl.gz").read_bytes()).splitlines()]
    replayed = export(DATA / f"{name}.bin")
    assert [(d["sensor"], d["seq"]) for d in replayed] == [(d["sensor"], d["seq"]) for d in golden]
    for now, then in zip(replayed, golden):
        assert now["flags"] == then["flags"], (now["sensor"], now["seq"])
        assert now.get("taxel_flags") == then.get("taxel_flags"), (now["sensor"], now["seq"])
        a, b = forces(now), forces(then)
        assert np.array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a[~np.isnan(a)], b[~np.isnan(b)], atol=FORCE_TOLERANCE_N, rtol=0)


def test_goldens_carry_the_faults_they_were_made_for():
    golden = [orjson.loads(line) for line in gzip.decompress((DATA / "press_faults.golden.jsonl.gz").read_bytes()).splitlines()]
    grid = [d for d in golden if d["kind"] == "grid"]
    open_frames = [d for d in grid if d["seq"] in OPEN_SEQS]
    assert open_frames and all(d["taxels_N"][OPEN_TAXEL] is None and "open_channel" in d["flags"] for d in open_frames)
    assert any("seq_gap" in d["flags"] for d in golden)  # frames lost to link faults
    assert len(grid) < 360  # 150 Hz × 2.4 s, minus the corrupt frames
