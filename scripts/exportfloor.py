"""What no replay → JSON lines export can go below on this machine (a script, not a unit test).

    python scripts/exportfloor.py CAPTURE.bin [--rounds 3]

The export's lines are fixed by its format (tactile replay --export X.jsonl:
64 forces and 64 σ per grid frame, as float64 shortest repr). Whatever the
decoder and the reconstruction cost, a run cannot spend less CPU than the
interpreter's start with numpy and orjson, plus encoding those lines. This
takes the replay's own frames (decoded and reconstructed first, not timed),
builds each line's dict, and times, in a fresh process each:

  start      python -c "import numpy, orjson"
  encode     orjson.dumps of every frame's export dict (the arrays as numpy
             rows, the way service/record/export.py encodes them), written
             to /dev/null
  naive      the naive decoder (service/reports/naive_decoder.py) on the capture
  arithmetic the full level's numpy arithmetic for every grid frame: each
             sensor's frames (once it is tared) through process_full in blocks
             of 64 frames (the fastest block size here: longer arrays
             leave the caches), the estimator's adoptions switched off,
             min of the rounds, in this process

and prints start + encode against naive: the largest "× naive decoder" any
implementation of the same export could reach here; with the arithmetic
added, the largest at the full level short of new arithmetic.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.reports.bench_process import cpu_seconds  # noqa: E402 — the tree above, not an installed copy

BLOCK = 64

ENCODE = """
import pickle, sys, time, orjson
docs = pickle.loads(open(sys.argv[1], "rb").read())
t = time.process_time()
with open("/dev/null", "wb") as out:
    for doc in docs:
        out.write(orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY) + b"\\n")
print(time.process_time() - t)
"""


def export_docs(capture: Path) -> list[dict]:
    """Every frame's export dict, contacts included, as the replay makes them."""
    from service.fanout.encoding import to_export_dict
    from service.record.export import keep_contacts
    from service.replay import replay

    frames = []

    class Collect:
        def write(self, batch):
            keep_contacts(batch)
            frames.extend(batch)

    replay(capture, writer=Collect())
    return [to_export_dict(frame) for frame in frames]


def full_level_arithmetic(capture: Path, rounds: int) -> float:
    """CPU s of the full level's steps over every tared grid frame of the
    capture, 64 frames a call, adoption points off."""
    import copy
    import time

    import numpy as np

    from service.pipeline import Pipeline
    from service.reconstruct import Reconstructor
    from service.reconstruct.grid_full import GridJob, process_full

    pipeline = Pipeline(Reconstructor(hold_until_tared=True), clock=lambda: 0.0, keep_history=False, map_clock=False)
    readings = pipeline.interpreter.interpret_many(pipeline.decoder.feed(capture.read_bytes()), 0.0)
    reconstructor = pipeline.reconstructor
    reconstructor.process_many(readings)  # every sensor tared, its processor as the replay leaves it
    jobs = []
    for state in reconstructor._sensors.values():
        if state.info.kind != "grid" or not state.baseline.ready:
            continue
        own = [r for r in readings if r.sensor.id == state.info.id]
        jobs.append((state, np.array([r.capacitance_pF for r in own]), np.array([r.t_us for r in own]) * 1e-6))
    best = float("inf")
    for _ in range(rounds):
        took = 0.0
        for state, capacitance, t_s in jobs:
            processor = copy.deepcopy(state.processor)
            processor.frames_to_adoption = lambda: len(capacitance)  # no block split at an adoption point
            processor._advance = lambda frames: None  # and no estimator observing or adopting
            t = time.process_time()
            for start in range(0, len(capacitance), BLOCK):
                block = slice(start, start + BLOCK)
                process_full([GridJob(processor, capacitance[block], state.baseline.value, state.baseline.std,
                                      t_s[block])])
            took += time.process_time() - t
        best = min(best, took)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    import pickle

    docs = export_docs(args.capture)
    with tempfile.TemporaryDirectory() as tmp:
        pickled = Path(tmp) / "docs.pickle"
        pickled.write_bytes(pickle.dumps(docs))
        runs: dict[str, list[float]] = {"start": [], "encode": [], "naive": []}
        for _ in range(args.rounds):
            runs["start"].append(cpu_seconds([sys.executable, "-c", "import numpy, orjson"]))
            encode = subprocess.run([sys.executable, "-c", ENCODE, str(pickled)], capture_output=True, text=True,
                                    check=True)
            runs["encode"].append(float(encode.stdout))
            runs["naive"].append(cpu_seconds([sys.executable, "-m", "service.reports.naive_decoder", str(args.capture),
                                              str(Path(tmp) / "naive.jsonl")]))
    median = {name: statistics.median(values) for name, values in runs.items()}
    floor = median["start"] + median["encode"]
    arithmetic = full_level_arithmetic(args.capture, args.rounds)
    print(f"{len(docs)} frames; CPU s, median of {args.rounds} (runs):")
    for name, values in runs.items():
        print(f"  {name:7s} {median[name]:.3f}  ({', '.join(f'{v:.3f}' for v in values)})")
    print(f"  arithmetic {arithmetic:.3f} (min of {args.rounds})")
    print(f"floor = start + encode = {floor:.3f} s: at most {median['naive'] / floor:.2f} × the naive decoder, "
          f"{len(docs) / floor:,.0f} frames/s")
    floor += arithmetic
    print(f"at the full level, + arithmetic = {floor:.3f} s: at most {median['naive'] / floor:.2f} × the naive "
          f"decoder, {len(docs) / floor:,.0f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
