"""Regenerate the replayed-log regression goldens (and, on request, the captures).

    python -m tests.regenerate_goldens              # goldens from the committed captures
    python -m tests.regenerate_goldens --captures   # also re-record the captures

Run it when a model change is meant to change the forces; review the diff of
the goldens (gzip -dc tests/data/NAME.golden.jsonl.gz) before committing.
"""
from __future__ import annotations

import gzip
import io
import sys
from pathlib import Path

import numpy as np
import orjson

from firmware_sim.board import BoardConfig, capture
from firmware_sim.faults import inject
from firmware_sim.sensors import Drift, SimGrid, SimQuad
from service.protocol import FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.replay import replay

DATA = Path(__file__).parent / "data"
OPEN_TAXEL = 9
OPEN_SEQS = range(150, 171)

CAPTURES = {
    "press_faults": dict(scene="press", grid={}, seed=7, fault_rate=0.03),
    "demo_leak_drift": dict(scene="demo", grid={"electrical_leakage": 0.01, "drift": Drift(0.002, 10.0)}, seed=8, fault_rate=0.02),
}
RATE_HZ = 150
SECONDS = 2.4


def make_capture(scene: str, grid: dict, seed: int, fault_rate: float) -> bytes:
    """150 Hz for 2.4 s, an open channel for 21 scans, then link faults."""
    config = BoardConfig(sensors=[SimGrid(0, **grid), SimQuad(1)], scene=scene, rate_hz=RATE_HZ, seed=seed)
    data, _ = capture(config, SECONDS)
    out = bytearray()
    for frame in Decoder().feed(data):
        payload = frame.payload
        if frame.type == FrameType.GRID and frame.seq in OPEN_SEQS:
            counts = np.frombuffer(payload, "<u4").copy()
            counts[OPEN_TAXEL] = 0xFFFFFFFF
            payload = counts.tobytes()
        out += encode_frame(frame.type, frame.sensor, frame.seq, frame.t_us, payload, frame.flags)
    return inject(bytes(out), rate=fault_rate, seed=seed).data


GOLDEN_DECIMALS = 6  # forces kept to 1 µN; the test's tolerance is 2 µN


def _rounded(value):
    if isinstance(value, float):
        return round(value, GOLDEN_DECIMALS)
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return value


def export(capture_path: Path) -> list[dict]:
    """The replay export of a capture, one dict per data frame."""
    out = io.BytesIO()
    replay(capture_path, out)
    return [orjson.loads(line) for line in out.getvalue().splitlines()]


def main(argv: list[str]) -> int:
    for name, spec in CAPTURES.items():
        capture_path = DATA / f"{name}.bin"
        if "--captures" in argv or not capture_path.exists():
            capture_path.write_bytes(make_capture(**spec))
        golden = DATA / f"{name}.golden.jsonl.gz"
        lines = b"".join(orjson.dumps(_rounded(doc)) + b"\n" for doc in export(capture_path))
        golden.write_bytes(gzip.compress(lines, mtime=0))
        print(f"{capture_path} ({capture_path.stat().st_size} B) → {golden} ({golden.stat().st_size} B)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
