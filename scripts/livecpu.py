"""Live CPU per sensor: what `tactile serve` costs with no client, by number of sensors (a script, not a unit test).

    python scripts/livecpu.py --seconds 20 --rounds 3 [--before DIR] [--out docs]
    python scripts/livecpu.py --in-process 1,3 --boards 4+4,32 --seconds 4 --rounds 3 [--before DIR]

For each board — 1 grid; 2 grids + 2 quads; 4 + 4 (the load test's); 8 + 8;
16 + 16, all 8×8 grids and quads at 1 kHz, scene ``demo`` — the simulator's
bytes are computed beforehand, scan by scan, and sent over TCP in their own
process at the board's pace, one write per scan (the live simulator itself
cannot make 16 sensors' physics at 1 kHz on a shared 2-core machine, and
would take the CPU the service is measured on), and `tactile serve --level
full` reads them with no client connected: decode to publish, the whole service. After the tare and a warm-up, the service's
user + sys CPU (/proc/PID/stat, as scripts/loadtest.py) is taken over
``--seconds``, with the frames it decoded (GET /health) to show the board kept
its rate. Each figure is the median of ``--rounds`` runs, the boards (and,
with ``--before DIR``, a second source tree: e.g. ``git archive`` of an older
commit unpacked there) alternating, so a slow phase of a shared host does not
land on one of them. ``--out DIR`` writes DIR/livecpu.png and DIR/livecpu.json (every run:
CPU %, frames/s); the table printed goes into docs/performance.md. Figures are
per frame decoded, scaled to the board's full rate, so that a run that
received less (a service that fell behind, a stalled sender) still counts.

``--in-process`` times the pipeline alone (Pipeline.feed_reads, the
service's reconstruction and publication without its event loop), reads fed
one at a time and as they come when several piled up while the service was
busy (the service feeds whatever waited, so how many go together depends on
how long the previous batch took: a faster pipeline is fed fewer at a time).

A board of more than ~25 sensors cannot describe itself: its INFO would
exceed the protocol's 1024-byte payload (16 grids + 16 quads: 1124 bytes).
The board here announces the sensors that fit; the service takes the others
from their data frames (a 256-byte grid payload is 8×8, a quad is a quad).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import orjson

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from firmware_sim.board import Board, BoardConfig  # noqa: E402 — the tree above, not an installed copy
from firmware_sim.frontends import tcp_server  # noqa: E402
from firmware_sim.urlhandler.protocol_sim import parse_sensors  # noqa: E402
from service.protocol import MAX_PAYLOAD  # noqa: E402

BOARDS = {"1": (1, 0), "4": (2, 2), "4+4": (4, 4), "16": (8, 8), "32": (16, 16)}  # name: (grids, quads)


def spec(grids: int, quads: int) -> str:
    return ",".join(["grid"] * grids + ["quad"] * quads)


class FittingBoard(Board):
    """A board whose INFO lists only the sensors that fit one payload."""

    def info(self) -> dict:
        doc = super().info()
        while len(orjson.dumps(doc)) > MAX_PAYLOAD - 16:  # room for PING's "pong"
            doc["sensors"] = doc["sensors"][:-1]
        return doc


def scans(sensors: str, seconds: float) -> list[bytes]:
    """The board's bytes, one item per 1 ms scan (the first with its power-up INFO)."""
    board = FittingBoard(BoardConfig(sensors=parse_sensors(sensors), scene="demo"))
    out = [board.power_up() + board.advance(0.001)]
    out += [board.advance(i / 1000) for i in range(2, int(seconds * 1000) + 1)]
    return out


def send_scans(port: int, items: list[bytes]) -> None:
    """Serve ``items`` to the first client, item i at 1 ms × i after it connects, until it leaves."""
    server = tcp_server("127.0.0.1", port)
    server.settimeout(None)
    client, _ = server.accept()
    client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    t0 = time.monotonic()
    try:
        for i, data in enumerate(items):
            delay = t0 + i / 1000 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            client.sendall(data)
    except OSError:
        return  # the service was stopped: the run is over
    threading.Event().wait()


def proc_cpu(pid: int) -> float:
    """CPU seconds (user + sys) a process has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def health(base: str) -> dict:
    return json.loads(urllib.request.urlopen(base + "/health", timeout=5).read())


def wait_for(base: str, seconds: float) -> None:
    deadline = time.time() + seconds
    while True:
        try:
            health(base)
            return
        except OSError:
            if time.time() > deadline:
                raise
            time.sleep(0.2)


def measure(tree: Path, items: list[bytes], seconds: float, port: int, warmup: float,
            serve_options: tuple[str, ...] = ()) -> tuple[float, float]:
    """(service CPU in % of one core, frames decoded per second) over ``seconds``."""
    board = multiprocessing.Process(target=send_scans, args=(port + 1, items), daemon=True)
    board.start()
    time.sleep(0.5)
    service = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--source", f"socket://127.0.0.1:{port + 1}",
                                "--port", str(port), "--level", "full", *serve_options], cwd=tree,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_for(base, 30)
        time.sleep(warmup)  # past the tare and the first allocations
        t0, cpu0, frames0 = time.time(), proc_cpu(service.pid), health(base)["stream"]["frames"]
        time.sleep(seconds)
        t1, cpu1, frames1 = time.time(), proc_cpu(service.pid), health(base)["stream"]["frames"]
    finally:
        service.terminate()
        service.wait(10)
        board.kill()
        board.join(10)
    return 100 * (cpu1 - cpu0) / (t1 - t0), (frames1 - frames0) / (t1 - t0)


# The pipeline alone, in a fresh interpreter on a tree (argv: tree, pickled reads, merge): the
# board's reads fed to Pipeline.feed_reads ``merge`` at a time, grids reconstructed at once;
# prints the CPU µs per read of the cheapest window of 600 reads after the first 1.2 s.
IN_PROCESS = """
import pickle, sys, time
sys.path.insert(0, sys.argv[1])
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
items, merge = pickle.loads(open(sys.argv[2], "rb").read()), int(sys.argv[3])
pipeline = Pipeline(Reconstructor(level="full"))
def feed(k):
    pipeline.feed_reads([(c, 1000.0 + (k + j) / 1000) for j, c in enumerate(items[k:k + merge])], lambda f: f())
for k in range(0, 1200, merge):
    feed(k)
windows = []
for start in range(1200, len(items) - 599, 600):
    t = time.process_time()
    for k in range(start, start + 600, merge):
        feed(k)
    windows.append(time.process_time() - t)
print(min(windows) / 600 * 1e6)
"""


def in_process(tree: Path, items: list[bytes], merge: int) -> float:
    """CPU µs per read of the pipeline alone on ``tree``, reads fed ``merge`` at a time (IN_PROCESS)."""
    import pickle
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".pickle") as file:
        file.write(pickle.dumps(items))
        file.flush()
        out = subprocess.run([sys.executable, "-c", IN_PROCESS, str(tree), file.name, str(merge)], cwd=tree,
                             capture_output=True, text=True, check=True)
    return float(out.stdout)


def full_rate(name: str, run: tuple[float, float]) -> float:
    """A run's CPU (% of a core) per frame decoded, times the board's rate: what
    its whole stream costs, also where a run received less (a service that
    fell behind, a host that stalled the sender)."""
    cpu, rate = run
    return cpu * 1000 * sum(BOARDS[name]) / rate


def plot(results: dict[str, dict[str, list[tuple[float, float]]]], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for tree, by_board in results.items():
        names = [n for n in BOARDS if n in by_board and "+" not in n]
        counts = [sum(BOARDS[n]) for n in names]
        ax.plot(counts, [statistics.median(full_rate(n, r) for r in by_board[n]) for n in names], "o-", label=tree)
    ax.axhline(50, color="grey", linestyle="--", linewidth=1, label="goal at 32 sensors")
    ax.set_xscale("log", base=2)
    ax.set_xticks([1, 4, 16, 32], ["1", "4", "16", "32"])
    ax.set_xlabel("sensors at 1 kHz (half 8×8 grids, half quads; 1: one grid)")
    ax.set_ylabel("service CPU, % of one core")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def table(results: dict[str, dict[str, list[tuple[float, float]]]]) -> str:
    """Per board and tree: CPU at the board's full rate (median, and each run),
    frames decoded per second (median) and CPU µs per frame (median)."""
    trees = list(results)
    head = "| sensors (grids + quads) | " + " | ".join(
        f"{t}: CPU % of a core at 1 kHz (runs) | {t}: frames/s | {t}: µs per frame" for t in trees) + " |"
    lines = [head, "|" + "---|" * (3 * len(trees) + 1)]
    for name, (grids, quads) in BOARDS.items():
        if not all(name in results[t] for t in trees):
            continue
        cells = []
        for t in trees:
            runs = results[t][name]
            at_rate = [full_rate(name, r) for r in runs]
            cells += [f"**{statistics.median(at_rate):.0f}** ({', '.join(f'{v:.0f}' for v in at_rate)})",
                      f"{statistics.median(r[1] for r in runs):,.0f}",
                      f"{statistics.median(1e4 * r[0] / r[1] for r in runs):.1f}"]
        lines.append(f"| {grids + quads} ({grids} + {quads}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="measured window per run (default 20)")
    parser.add_argument("--warmup", type=float, default=4.0, help="seconds after start-up before the window (default 4)")
    parser.add_argument("--rounds", type=int, default=3, help="runs per board and tree (default 3); the median is shown")
    parser.add_argument("--boards", default=",".join(BOARDS), help=f"which boards (default {','.join(BOARDS)})")
    parser.add_argument("--before", type=Path, help="a second source tree to measure alternately (its service/ is run)")
    parser.add_argument("--port", type=int, default=8775)
    parser.add_argument("--grid-batch-ms", type=float, metavar="MS",
                        help="run this tree's service with --grid-batch-ms MS (not --before's: give --before this tree for an A/B)")
    parser.add_argument("--before-grid-batch-ms", type=float, metavar="MS",
                        help="run --before's service with --grid-batch-ms MS (to compare two trees both batching grids)")
    parser.add_argument("--out", type=Path, help="write livecpu.png into this directory")
    parser.add_argument("--in-process", metavar="MERGES",
                        help="instead, the pipeline alone (no service), reads fed 1, 2, … at a time, e.g. 1,3: "
                             "µs per read (the cheapest window of each run; the median of runs)")
    args = parser.parse_args()
    trees = ({"before": args.before.resolve()} if args.before else {}) | {"after" if args.before else "this tree": ROOT}
    boards = [b for b in args.boards.split(",") if b]
    if args.in_process:
        return in_process_table(trees, boards, [int(m) for m in args.in_process.split(",")], args)
    results: dict[str, dict[str, list[tuple[float, float]]]] = {t: {} for t in trees}
    streams = {name: scans(spec(*BOARDS[name]), args.warmup + args.seconds + 15) for name in boards}  # 15: start-up
    for round_ in range(args.rounds):
        for name in boards:
            for label, tree in trees.items():
                batch_ms = args.before_grid_batch_ms if label == "before" else args.grid_batch_ms
                options = ("--grid-batch-ms", str(batch_ms)) if batch_ms else ()
                run = measure(tree, streams[name], args.seconds, args.port, args.warmup, options)
                results[label].setdefault(name, []).append(run)
                print(f"round {round_ + 1}, {name} sensors, {label}: {run[0]:.1f} % of a core, {run[1]:,.0f} frames/s",
                      flush=True)
    print(table(results))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        plot(results, args.out / "livecpu.png")
        (args.out / "livecpu.json").write_text(json.dumps(results, indent=1))
    return 0


def in_process_table(trees: dict[str, Path], boards: list[str], merges: list[int], args) -> int:
    """``--in-process``: each board, merge and tree alternating for ``--rounds``; prints the medians."""
    streams = {name: scans(spec(*BOARDS[name]), 1.2 + args.seconds) for name in boards}
    results: dict[tuple[str, int, str], list[float]] = {}
    for round_ in range(args.rounds):
        for name in boards:
            for merge in merges:
                for label, tree in trees.items():
                    us = in_process(tree, streams[name], merge)
                    results.setdefault((name, merge, label), []).append(us)
                    print(f"round {round_ + 1}, {name} sensors, reads by {merge}, {label}: {us:.0f} µs per read", flush=True)
    print("| sensors (grids + quads) | reads fed together | " + " | ".join(f"{t}: µs per read (runs)" for t in trees) + " |")
    print("|" + "---|" * (len(trees) + 2))
    for name in boards:
        for merge in merges:
            cells = [f"**{statistics.median(results[name, merge, t]):.0f}** "
                     f"({', '.join(f'{v:.0f}' for v in results[name, merge, t])})" for t in trees]
            print(f"| {sum(BOARDS[name])} ({' + '.join(map(str, BOARDS[name]))}) | {merge} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
