"""Load test of the live API on loopback (a script, not a unit test).

    python scripts/loadtest.py --seconds 120 --out out/load-run.md

Starts a simulated board with 4 grid and 4 quad sensors at 1 kHz in its own
process (`tactile sim --tcp`, as a real board is outside the service),
`tactile serve` reading it over TCP, then 20 healthy WebSocket clients subscribed to everything (binary, batched
every 5 ms; in 4 processes of 5), from this process 5 clients that subscribe
to everything (JSON, unbatched) and never read, and, in its own process, one
latency-critical client on one quad sensor, unbatched, binary. All clients
connect together; after a warm-up (``--warmup``, 3 s) a window of
``--seconds`` is measured, then all leave together. It reports, per client
kind, the share of frames received (by sequence continuity) and the latency
of every frame the service received in the window, from the host's receive
stamp (taken when the bytes are read, before decoding) to client receipt
(same machine, same clock) — the warm-up's latency apart, as the cost of 25
clients connecting at once — the service's own latency figures (GET /health, polled each second),
how late the OS wakes a process that only sleeps 1 ms at a time (the floor of
every wake-up on the critical path), and the service's CPU and memory from
/proc. A batched frame waits for its batch by design, so the batching
interval (5 ms) is chosen below the 10 ms goal. Every loop is bounded in time and only loopback is used.
``--healthy/--stalled/--batch-ms`` change the clients; ``--level`` and
``--nice`` the service; ``--slice-us`` the scheduler slice the service and
the critical client ask for (service/sched.py); LOADTEST_SENSORS and LOADTEST_CRITICAL the board
(e.g. one quad, sensor 0).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import platform
import struct
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import uvloop
import websockets

from service.sched import request_slice

SENSORS = os.environ.get("LOADTEST_SENSORS", "grid,grid,grid,grid,quad,quad,quad,quad")
CRITICAL_SENSOR = int(os.environ.get("LOADTEST_CRITICAL", "4"))  # the first quad


def proc_sample(pid: int) -> tuple[float, int]:
    """(CPU seconds used, resident bytes) of a process."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks
    rss = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
    return cpu, rss


# A binary record's head (service/fanout/encoding.py, v4): then the calibration id (m bytes), the
# board name (u8 length b, b bytes), n forces, n sigmas (field bit 4) and the raw channels (field bit 2: n for a grid,
# 4 for a quad), f4 each, and a grid's n taxel-flag bytes (field bit 8).
HEADER = np.dtype([("version", "u1"), ("kind", "u1"), ("sid", "u1"), ("field_bits", "u1"), ("seq", "<u2"),
                   ("t_us", "<u4"), ("stamp", "<f8"), ("scan_stamp", "<f8"), ("flag_bits", "<u4"),
                   ("n", "<u2"), ("m", "u1")])
COUNT_AT = struct.Struct("<H").unpack_from
HEADER_BYTES = np.arange(HEADER.itemsize)
SEQ_WRAP = 1 << 16


class Tally:
    """Frames seen per sensor (by seq, unwrapped) and latencies.

    A client on the same two cores as the service takes CPU from it, so a
    message is only cut into its record headers here (numpy, no per-frame
    Python objects); sequences are unwrapped once at the end."""

    def __init__(self) -> None:
        self._sids: list[np.ndarray] = []
        self._seqs: list[np.ndarray] = []
        self._stamps: list[np.ndarray] = []
        self._latency: list[np.ndarray] = []
        self.dropped_notices = 0

    def binary(self, message: bytes, now: float) -> None:
        (count,) = COUNT_AT(message, 0)
        starts, pos = [], 2
        for _ in range(count):
            starts.append(pos)
            kind, field_bits, n, m = message[pos + 1], message[pos + 3], *COUNT_AT(message, pos + 30), message[pos + 32]
            channels = (n if kind == 0 else 4) if field_bits & 2 else 0
            b = message[pos + HEADER.itemsize + m]
            pos += HEADER.itemsize + m + 1 + b + 4 * (n * (1 + (field_bits >> 2 & 1)) + channels) + (n if field_bits & 8 else 0)
        raw = np.frombuffer(message, np.uint8)[np.add.outer(starts, HEADER_BYTES)]
        headers = raw.view(HEADER)[:, 0]
        self._sids.append(headers["sid"])
        self._seqs.append(headers["seq"])
        self._stamps.append(headers["stamp"])
        self._latency.append(now - headers["stamp"])

    def latency(self, start: float, end: float) -> np.ndarray:
        """Seconds from the host's receive stamp to receipt, for every frame
        the service received between ``start`` and ``end`` (epoch s)."""
        if not self._latency:
            return np.empty(0)
        stamps = np.concatenate(self._stamps)
        return np.concatenate(self._latency)[(stamps >= start) & (stamps < end)]

    @property
    def seqs(self) -> dict[int, np.ndarray]:
        """Per sensor, the sequence numbers received, unwrapped (16 bits wrap
        every 65.5 s at 1 kHz; frames of one sensor arrive in order)."""
        if not self._sids:
            return {}
        sids, seqs = np.concatenate(self._sids), np.concatenate(self._seqs).astype(np.int64)
        out = {}
        for sid in np.unique(sids):
            own = seqs[sids == sid]
            out[int(sid)] = own[0] + np.concatenate(([0], np.cumsum(np.diff(own) & (SEQ_WRAP - 1))))
        return out

    @staticmethod
    def share(seqs: dict[int, np.ndarray], window: dict[int, tuple[int, int]]) -> float:
        """Received / expected, counting each sensor's seqs inside the window
        of seqs every client saw."""
        got = expected = 0
        for sid, (first, last) in window.items():
            own = seqs.get(sid, np.empty(0, np.int64))
            got += np.unique(own[(own >= first) & (own <= last)]).size
            expected += last - first + 1
        return got / expected if expected else 0.0


async def listen(url: str, tally: Tally, stop: float) -> None:
    """Receive until ``stop`` (epoch s), tallying binary frames and drop notices."""
    async with websockets.connect(url, max_size=None) as ws:
        while time.time() < stop:
            try:
                message = await asyncio.wait_for(ws.recv(), timeout=max(stop - time.time(), 0.01))
            except TimeoutError:
                break
            if isinstance(message, bytes):
                tally.binary(message, time.time())
            else:
                tally.dropped_notices += 1


async def stalled(url: str, stop: float) -> None:
    # Subscribe and never read: the server's queue for us must fill and drop.
    async with websockets.connect(url + "/ws", max_size=None, max_queue=1, close_timeout=0.5) as ws:
        ws.transport.pause_reading()
        await asyncio.sleep(max(stop - time.time(), 0))


@dataclass(frozen=True)
class Schedule:
    """One clock for every client (epoch s): all connect at ``begin``, the
    figures cover ``measured`` (after ``warmup``, while every client is
    connected), and all leave at ``stop``. Frames stamped during the warm-up
    are reported apart: the cost of 26 clients connecting at once."""

    begin: float
    warmup_s: float
    seconds: float

    @property
    def warmup(self) -> tuple[float, float]:
        return self.begin, self.begin + self.warmup_s

    @property
    def measured(self) -> tuple[float, float]:
        return self.begin + self.warmup_s, self.stop

    @property
    def stop(self) -> float:
        return self.begin + self.warmup_s + self.seconds


async def sleep_until(t: float) -> None:
    await asyncio.sleep(max(t - time.time(), 0))


async def poll_service(base: str, schedule: Schedule, pid: int, windows: list[dict], usage: list) -> None:
    """The service's own latency figures (GET /health, each over its last
    ~1-10 s) once a second, and its CPU time at both ends of the measured window."""
    start, end = schedule.measured
    await sleep_until(start)
    usage.append((time.time(), *proc_sample(pid)))
    while time.time() < end - 1.0:
        await asyncio.sleep(1.0)
        body = await asyncio.to_thread(lambda: urllib.request.urlopen(base + "/health", timeout=2).read())
        windows.append(json.loads(body)["latency"])
    await sleep_until(end)
    usage.append((time.time(), *proc_sample(pid)))


async def run_clients(base: str, schedule: Schedule, n_stalled: int, service_pid: int,
                      service_latency: list[dict], usage: list) -> None:
    """This process's clients: the stalled ones, and the poll of the service's figures."""
    url = base.replace("http", "ws", 1)
    await sleep_until(schedule.begin)
    tasks = [asyncio.create_task(stalled(url, schedule.stop)) for _ in range(n_stalled)]
    tasks.append(asyncio.create_task(poll_service(base, schedule, service_pid, service_latency, usage)))
    await asyncio.gather(*tasks, return_exceptions=True)


def healthy_clients(base: str, schedule: Schedule, n: int, batch_ms: float, results) -> None:
    """``n`` healthy clients on one event loop, in a process of their own:
    twenty clients are twenty programs, and one process parsing all their
    messages would delay the receipt of the last by the parsing of the others."""
    url = base.replace("http", "ws", 1) + f"/ws?encoding=binary&batch_ms={batch_ms:g}&fields=force,flags"
    tallies = [Tally() for _ in range(n)]

    async def run() -> None:
        await sleep_until(schedule.begin)
        await asyncio.gather(*(listen(url, t, schedule.stop) for t in tallies), return_exceptions=True)

    uvloop.run(run())
    results.put([(t.seqs, t.latency(*schedule.measured), t.latency(*schedule.warmup), t.dropped_notices)
                 for t in tallies])


def align_wraps(clients: list[dict[int, np.ndarray]]) -> None:
    """Put every client's unwrapped seqs on one count: each client unwraps
    from its own first frame, so one that joined just before a wrap (seq
    65535) and one just after it (seq 0) would be 65536 apart. Clients join
    within seconds of each other, far less than a wrap."""
    first_seen: dict[int, int] = {}
    for seqs_by_sensor in clients:
        for sid, seqs in seqs_by_sensor.items():
            reference = first_seen.setdefault(sid, int(seqs[0]))
            seqs_by_sensor[sid] = seqs + SEQ_WRAP * round((reference - int(seqs[0])) / SEQ_WRAP)


def shared_window(clients: list[dict[int, np.ndarray]]) -> dict[int, tuple[int, int]]:
    """Per sensor, the span of seqs that every client receiving it was
    connected for: shares are counted inside it (clients connect and leave
    a few frames apart)."""
    align_wraps(clients)
    window: dict[int, tuple[int, int]] = {}
    for seqs_by_sensor in clients:
        for sid, seqs in seqs_by_sensor.items():
            first, last = int(seqs.min()), int(seqs.max())
            lo, hi = window.get(sid, (first, last))
            window[sid] = (max(lo, first), min(hi, last))
    return {sid: span for sid, span in window.items() if span[1] > span[0]}


def window_p99s(windows: list[dict], stage: str) -> str:
    """Median and worst of the service's per-window p99 for one stage."""
    p99s = [w[stage]["p99_ms"] for w in windows if w[stage]["p99_ms"] is not None]
    return f"{np.median(p99s):.3g} / {max(p99s):.3g}" if p99s else "-"


def request_slice_or_say(slice_us: int) -> None:
    if slice_us:
        request = request_slice(slice_us)
        if not request.applied:
            print(f"loadtest: slice of {slice_us} us not applied: {request.error}", file=sys.stderr)


def latency_client(base: str, schedule: Schedule, sensor: int, results, slice_us: int, fifo_priority: int) -> None:
    """In its own process, so the other clients' work does not delay it;
    at real-time priority if asked, as 1 kHz control loops usually run
    (ros2_control's at SCHED_FIFO 50)."""
    if fifo_priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
    else:
        request_slice_or_say(slice_us)
    tally = Tally()
    url = f"{base.replace('http', 'ws', 1)}/ws?encoding=binary&fields=force&sensors={sensor}"
    uvloop.run(listen(url, tally, schedule.stop))
    results.put((tally.seqs, tally.latency(*schedule.measured), tally.latency(*schedule.warmup)))


def wakeup_probe(schedule: Schedule, results, slice_us: int) -> None:
    """A process that only sleeps 1 ms at a time, at normal priority and
    with the critical client's slice: how late the OS wakes it over the
    measured window is the floor of any wake-up on this host under this
    load (the critical path has two: the service's event loop, the client)."""
    request_slice_or_say(slice_us)
    start, stop = schedule.measured
    time.sleep(max(start - time.time(), 0))
    late = []
    while time.time() < stop:
        t0 = time.perf_counter()
        time.sleep(0.001)
        late.append(time.perf_counter() - t0 - 0.001)
    results.put(np.percentile(np.array(late) * 1000, [50, 99]).tolist())


def percentiles_ms(latency: np.ndarray, qs=(50, 99)) -> list[float]:
    return np.percentile(latency * 1000, qs).tolist() if latency.size else [float("nan")] * len(qs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--port", type=int, default=8765)
    parser.add_argument("--out", help="also write this run's figures here as a markdown table")
    parser.add_argument("--healthy", type=int, default=20, help="healthy clients (default 20)")
    parser.add_argument("--client-processes", type=int, default=4,
                        help="processes the healthy clients are spread over (default 4)")
    parser.add_argument("--stalled", type=int, default=5, help="stalled clients (default 5)")
    parser.add_argument("--batch-ms", type=float, default=5.0, help="healthy clients' batching interval (default 5)")
    parser.add_argument("--level", default="full", help="the service's reconstruction level (default full)")
    parser.add_argument("--nice", type=int, default=0,
                        help="run the service at this niceness (negative: higher priority, needs root; default 0)")
    parser.add_argument("--slice-us", type=int, default=0,
                        help="the scheduler time slice the service and the critical client ask for "
                             "(`tactile serve --sched-slice-us`; 0: the kernel's default)")
    parser.add_argument("--critical-fifo", type=int, default=0, metavar="PRIORITY",
                        help="run the critical client at this SCHED_FIFO priority (needs root or CAP_SYS_NICE; "
                             "default 0: normal priority)")
    parser.add_argument("--warmup", type=float, default=3.0,
                        help="seconds after the clients connect before the measured window (default 3); "
                             "frames of the warm-up are reported apart")
    args = parser.parse_args()
    board = subprocess.Popen([sys.executable, "-m", "service.cli", "sim", "--tcp", str(args.port + 1), "--sensors", SENSORS,
                              "--scene", "demo"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.0)
    source = f"socket://127.0.0.1:{args.port + 1}"
    service = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--source", source, "--port", str(args.port),
                                "--level", args.level, "--sched-slice-us", str(args.slice_us)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=lambda: os.nice(args.nice))
    base = f"http://127.0.0.1:{args.port}"
    try:
        deadline = time.time() + 20
        while time.time() < deadline:
            try:
                urllib.request.urlopen(base + "/health", timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        time.sleep(2.0)  # past the auto-tare
        schedule = Schedule(time.time() + 1.0, args.warmup, args.seconds)  # 1 s to start the client processes
        results = multiprocessing.Queue()
        critical_process = multiprocessing.Process(target=latency_client,
                                                   args=(base, schedule, CRITICAL_SENSOR, results, args.slice_us,
                                                         args.critical_fifo))
        critical_process.start()
        probe_results = multiprocessing.Queue()
        probe_process = multiprocessing.Process(target=wakeup_probe, args=(schedule, probe_results, args.slice_us))
        probe_process.start()
        healthy_results = multiprocessing.Queue()
        processes = max(min(args.client_processes, args.healthy), 1)
        sizes = [len(part) for part in np.array_split(np.arange(args.healthy), processes)]
        healthy_processes = [multiprocessing.Process(target=healthy_clients,
                                                     args=(base, schedule, size, args.batch_ms, healthy_results))
                             for size in sizes if size]
        for process in healthy_processes:
            process.start()
        service_latency: list[dict] = []
        usage: list[tuple[float, float, int]] = []
        uvloop.run(run_clients(base, schedule, args.stalled, service.pid, service_latency, usage))
        (t0, cpu0, _), (t1, cpu1, rss) = usage
        healthy = [client for _ in healthy_processes for client in healthy_results.get(timeout=60)]
        for process in healthy_processes:
            process.join(10)
        critical_seqs, critical_latency, critical_warmup = results.get(timeout=30)
        critical_process.join(10)
        wakeup_p50, wakeup_p99 = probe_results.get(timeout=30)
        probe_process.join(10)
        time.sleep(0.5)  # for the service to see the last clients leave
        health = json.loads(urllib.request.urlopen(base + "/health", timeout=5).read())
    finally:
        service.terminate()
        service.wait(10)
        board.terminate()
        board.wait(10)

    healthy_seqs = [seqs for seqs, _, _, _ in healthy]
    window = shared_window(healthy_seqs + [critical_seqs])
    shares = [Tally.share(seqs, window) for seqs in healthy_seqs] or [float("nan")]
    healthy_latency = np.concatenate([latency for _, latency, _, _ in healthy] + [np.empty(0)])
    healthy_warmup = np.concatenate([warmup for _, _, warmup, _ in healthy] + [np.empty(0)])
    healthy_p50, healthy_p99 = percentiles_ms(healthy_latency)
    critical_p50, critical_p99 = percentiles_ms(critical_latency)
    report = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}",
        "measured_seconds": round(t1 - t0, 1),
        "warmup_seconds": args.warmup,
        "sensors": SENSORS,
        "level": args.level,
        "healthy_clients": f"{args.healthy} binary, batched {args.batch_ms:g} ms, in {len(healthy_processes)} processes",
        "service_niceness": args.nice,
        "slice_us (service, critical client)": health["scheduling"]["granted_us"],
        "critical_client_fifo_priority": args.critical_fifo,
        "frames_published_per_s": health["stream"]["frames"] / max(health["uptime_s"], 1e-9),
        "healthy_min_share": min(shares),
        "healthy_mean_share": float(np.mean(shares)),
        "healthy_dropped_notices": sum(notices for _, _, _, notices in healthy),
        "healthy_latency_ms_p50": healthy_p50,
        "healthy_latency_ms_p99": healthy_p99,
        "critical_share": (Tally.share(critical_seqs, {CRITICAL_SENSOR: window[CRITICAL_SENSOR]})
                           if CRITICAL_SENSOR in window else 0.0),
        "critical_latency_ms_p50": critical_p50,
        "critical_latency_ms_p99": critical_p99,
        "warmup_healthy_latency_ms_p99 / max": "{:.3g} / {:.3g}".format(*percentiles_ms(healthy_warmup, (99, 100))),
        "warmup_critical_latency_ms_p99 / max": "{:.3g} / {:.3g}".format(*percentiles_ms(critical_warmup, (99, 100))),
        "service_p99_ms_received_to_published (median / worst window)": window_p99s(service_latency, "published"),
        "service_p99_ms_received_to_sent_unbatched (median / worst window)": window_p99s(service_latency, "sent_unbatched"),
        "service_p99_ms_received_to_sent_batched (median / worst window)": window_p99s(service_latency, "sent_batched"),
        "os_wakeup_late_ms_p50": wakeup_p50,
        "os_wakeup_late_ms_p99": wakeup_p99,
        "service_cpu_percent_of_one_core": 100 * (cpu1 - cpu0) / (t1 - t0),
        "service_rss_MB": rss / 1e6,
        "websocket_clients_at_end": health["websocket_clients"],
    }
    text = "\n".join(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in report.items())
    print(json.dumps(report, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(
            "# Load test\n\nProduced by `python scripts/loadtest.py "
            f"{' '.join(sys.argv[1:])}` (see the script's docstring for the set-up).\n\n"
            "| figure | value |\n|---|---|\n" + text + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
