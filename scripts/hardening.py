"""Figures of the hardening measures (a script, not a unit test). Loopback only, bounded loops.

    python scripts/hardening.py reconnect   # 10 unplug/replug cycles of a TCP board: time to frames again
    python scripts/hardening.py stale       # a board that goes mute: time from its last byte to 'stale'
    python scripts/hardening.py sensors     # data frames of 255 sensors without INFO: sensors kept, RSS (pipeline)
    python scripts/hardening.py body        # a 50 MB request body: time to the refusal, the service's RSS
    python scripts/hardening.py loris       # 1 100 slow-header connections to a 1024-file service: its fds, /health
"""
from __future__ import annotations

import http.client
import json
import os
import resource
import socket
import statistics
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

from firmware_sim import frontends
from firmware_sim.board import Board, BoardConfig
from service.handover import ThreadSink
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.readout import Readout


def wait_for(predicate, timeout: float = 10.0, step: float = 0.001) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return False


class TcpBoard:
    def __init__(self) -> None:
        self.board, self.t0, self.port = Board(BoardConfig(scene="idle")), time.monotonic(), None
        self.plug()

    def plug(self) -> None:
        server = frontends.tcp_server("127.0.0.1", self.port or 0)
        self.port = server.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, args=(server,), daemon=True)
        self.thread.start()

    def _serve(self, server) -> None:
        with server:
            frontends.serve_tcp(self.board, server, self.stop, self.t0)

    def unplug(self) -> None:
        self.stop.set()
        self.thread.join()


def reconnect(cycles: int = 10) -> dict:
    device, pipeline = TcpBoard(), Pipeline()
    readout = Readout(f"socket://127.0.0.1:{device.port}", ThreadSink(pipeline.feed, pipeline.link_lost))
    readout.start()
    took, rng = [], np.random.default_rng(1)
    try:
        for _ in range(cycles):
            assert wait_for(lambda: readout.link.up)
            device.unplug()
            assert wait_for(lambda: not readout.link.up)
            time.sleep(rng.uniform(0.5, 3.0))  # away for a while, at any point of the backoff
            frames = pipeline.decoder.counters.frames
            device.plug()
            plugged = time.monotonic()
            assert wait_for(lambda: pipeline.decoder.counters.frames > frames)
            took.append(time.monotonic() - plugged)
    finally:
        readout.stop()
        device.unplug()
    return {"cycles": cycles, "frames_again_s": {"min": round(min(took), 3), "median": round(statistics.median(took), 3),
                                                  "max": round(max(took), 3)}}


def stale() -> dict:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    sent_at = []

    def mute_after_one_frame() -> None:
        conn, _ = server.accept()
        time.sleep(0.2)  # pyserial's socket:// drops what is waiting when it opens
        conn.sendall(encode_frame(FrameType.QUAD, 0, 0, 0, bytes(16)))
        sent_at.append(time.time())
        time.sleep(5)
        conn.close()

    threading.Thread(target=mute_after_one_frame, daemon=True).start()
    pipeline = Pipeline()
    readout = Readout(f"socket://127.0.0.1:{port}", ThreadSink(pipeline.feed, pipeline.link_lost))
    readout.start()
    try:
        assert wait_for(lambda: bool(sent_at) and readout.link.last_data_time is not None)
        assert wait_for(lambda: readout.link.state(time.time()) == "stale")
        return {"stale_after_last_byte_s": round(time.time() - readout.link.last_data_time, 3)}
    finally:
        readout.stop()
        server.close()


def sensors() -> dict:
    pipeline = Pipeline()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    payload = np.arange(64, dtype="<u4").tobytes()
    for seq in range(0, 4000, 4):  # reads of 4 scans (as live), every ring filled to its share of the budget
        chunk = b"".join(encode_frame(FrameType.GRID, sid, s, s * 1000, payload)
                         for s in range(seq, seq + 4) for sid in range(255))
        pipeline.feed(chunk, time.time())
    return {"sensors_kept": len(pipeline.interpreter.sensors), "dropped": pipeline.interpreter.rejected,
            "history_MB": round(pipeline.history.bytes / 2**20, 1),
            "peak_rss_MB": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "rss_after_MB": round(rss_MB(os.getpid()), 1),
            "rss_before_MB": round(before / 1024, 1)}


def rss_MB(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS")) / 1024


def body(megabytes: int = 50) -> dict:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--token", "t"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out = {}
    try:
        assert wait_for(lambda: _up(port), 20, 0.1)
        time.sleep(2)
        for name, headers in (("with_token", {"Authorization": "Bearer t"}), ("without_token", {})):
            before = rss_MB(server.pid)
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            started = time.monotonic()
            conn.putrequest("PUT", "/sensors/0/calibration")
            for key, value in {**headers, "Content-Type": "application/json",
                               "Content-Length": str(megabytes << 20)}.items():
                conn.putheader(key, value)
            conn.endheaders()
            try:
                conn.send(b"[" + b"1," * ((megabytes << 20) // 2 - 1))
            except OSError:
                pass  # the service answered and closed before taking it all
            response = conn.getresponse()
            out[name] = {"status": response.status, "answered_s": round(time.monotonic() - started, 3),
                         "rss_delta_MB": round(rss_MB(server.pid) - before, 1)}
            conn.close()
    finally:
        server.terminate()
        server.wait(10)
    return out


def loris(connections: int = 1100, seconds: int = 12, port: int | None = None) -> dict:
    """``connections`` sockets each sending a header byte a second to a
    service whose soft open-file limit is 1024 (the usual default): each
    second, the service's descriptors, how many of the sockets it has
    closed, and what /health answered on a new connection."""
    if port is None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4 * connections), hard))  # ours, for the sockets
    server = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard)))
    seconds_out, socks = [], []
    try:
        assert wait_for(lambda: _up(port), 20, 0.1)
        for _ in range(connections):
            sock = socket.create_connection(("127.0.0.1", port), timeout=2)
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-a: ")
            socks.append(sock)
        closed: set = set()
        for second in range(1, seconds + 1):
            time.sleep(1)
            for sock in set(socks) - closed:
                try:
                    sock.sendall(b"a")
                except OSError:
                    closed.add(sock)
            try:
                health = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=3))["status"]
            except OSError as exc:
                health = repr(exc)[:60]
            seconds_out.append({"s": second, "service_fds": len(os.listdir(f"/proc/{server.pid}/fd")),
                                "closed_by_service": len(closed), "health": health})
    finally:
        for sock in socks:
            sock.close()
        server.terminate()
        server.wait(10)
    return {"connections": connections, "soft_limit": 1024, "each_second": seconds_out}


def _up(port: int) -> bool:
    try:
        return urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=1).status == 200
    except OSError:
        return False


if __name__ == "__main__":
    figures = {"reconnect": reconnect, "stale": stale, "sensors": sensors, "body": body, "loris": loris}
    if len(sys.argv) != 2 or sys.argv[1] not in figures:
        sys.exit(__doc__)
    print(json.dumps(figures[sys.argv[1]](), indent=1))
