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

and prints start + encode against naive: the largest "× naive decoder" any
implementation of the same export could reach here.
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
    print(f"{len(docs)} frames; CPU s, median of {args.rounds} (runs):")
    for name, values in runs.items():
        print(f"  {name:7s} {median[name]:.3f}  ({', '.join(f'{v:.3f}' for v in values)})")
    print(f"floor = start + encode = {floor:.3f} s: at most {median['naive'] / floor:.2f} × the naive decoder, "
          f"{len(docs) / floor:,.0f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
