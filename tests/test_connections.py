"""Slow and idle connections against the service's connection bounds
(service/api/connections.py, docs/deploy.md): 1 100 connections sending a
header byte every 5 s held every descriptor of a 1024-file service."""
import contextlib
import os
import json
import select
import socket
import time
import urllib.parse
import urllib.request

import orjson
from websockets.sync.client import connect

from service.live_service import TactileService
from tests.conftest import live_server

REQUEST_TIMEOUT_S = 5.0  # docs/deploy.md
PARTIAL_HEAD = b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-a: "


def _closed(sock: socket.socket, wait_s: float = 0.0) -> bool:
    """Whether the server closed ``sock`` (an end of stream or a reset), waiting up to ``wait_s``."""
    if not select.select([sock], [], [], wait_s)[0]:
        return False
    try:
        return sock.recv(65536) == b""
    except ConnectionResetError:
        return True


def _response(sock: socket.socket) -> bytes:
    """One whole response (its Content-Length'd body) from ``sock``."""
    data = b""
    while b"\r\n\r\n" not in data:
        data += sock.recv(65536)
    head, body = data.split(b"\r\n\r\n", 1)
    lines = head.lower().split(b"\r\n")
    length = next(int(line.split(b":")[1]) for line in lines if line.startswith(b"content-length"))
    while len(body) < length:
        body += sock.recv(65536)
    return head


def _loris(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.sendall(PARTIAL_HEAD)
    return sock


def test_a_request_still_arriving_after_the_timeout_is_closed(served):
    """A head sent a byte every 0.5 s, on a new connection and on one kept
    alive after a response (a byte cancelled uvicorn's keep-alive timer):
    both stayed open for ever; both are closed 5 s after the connection
    opened or the response ended."""
    port = urllib.parse.urlsplit(served[0]).port
    kept = socket.create_connection(("127.0.0.1", port), timeout=5)
    kept.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    assert _response(kept).startswith(b"HTTP/1.1 200")
    started = {kept: time.monotonic()}
    fresh = _loris(port)
    started[fresh] = time.monotonic()
    kept.sendall(b"G")
    lasted = {}
    while len(lasted) < 2 and time.monotonic() - started[kept] < 2 * REQUEST_TIMEOUT_S:
        for sock in set(started) - set(lasted):
            if _closed(sock, 0.25):
                lasted[sock] = time.monotonic() - started[sock]
            else:
                sock.sendall(b"a")
    for sock in started:
        sock.close()
    assert set(lasted) == {kept, fresh}, f"still open after {2 * REQUEST_TIMEOUT_S:g} s"
    for sock, seconds in lasted.items():
        assert REQUEST_TIMEOUT_S - 0.1 < seconds < REQUEST_TIMEOUT_S + 1.0, seconds


def _frames(ws, seconds: float) -> list[int]:
    """The seq of each frame received by the service in the next
    ``seconds`` that ``ws`` delivers within them (not those queued before)."""
    seqs, since, until = [], time.time(), time.monotonic() + seconds
    while time.monotonic() < until:
        frames = orjson.loads(ws.recv(timeout=5))["frames"]
        seqs += [frame["header"]["seq"] for frame in frames if frame["header"]["stamp"] >= since]
    return seqs


def test_connections_past_the_cap_close_those_waiting_never_a_stream():
    """With a cap of 6 and one WebSocket streaming, 20 half-open connections:
    the 15 oldest are closed at once (the stream's and 5 others' are the 6),
    /health answers on a new connection (closing the oldest still waiting)
    and the stream goes on at the simulator's 1 kHz. With 6 streams, a new
    connection is closed at once and the streams go on (at least half
    their rate: 1 kHz, and 20 Hz asked)."""
    from service.api.connections import BoundedH11

    capped = type("Capped", (BoundedH11,), {"max_connections": 6, "request_timeout_s": 60.0})
    with live_server(TactileService("sim://?sensors=quad"), 1, http=capped) as server:
        port, cap = server.config.port, 6
        url = f"ws://127.0.0.1:{port}/ws?sensors=0"
        with connect(url, max_queue=None) as ws:  # unbounded: a full queue stops the client reading, and so its close
            ws.recv(timeout=5)
            lorises = [_loris(port) for _ in range(20)]
            try:
                time.sleep(0.5)
                assert [_closed(sock) for sock in lorises] == [True] * 15 + [False] * 5
                assert len(server.server_state.connections) == cap
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5) as answer:
                    assert answer.status == 200 and json.loads(answer.read())["status"] in ("ok", "degraded")
                assert _closed(lorises[15], 1.0) and not any(_closed(sock) for sock in lorises[16:])
                seqs = _frames(ws, 0.5)
                assert len(seqs) > 0.5 * 1000 * 0.5 and seqs == sorted(seqs)
                with contextlib.ExitStack() as opened:
                    # the first takes /health's place, the others a loris's; at 20 Hz, for the test's CPU
                    slow = url + "&max_rate=20"
                    streams = [opened.enter_context(connect(slow, max_queue=None)) for _ in range(cap - 1)]
                    assert all(_closed(sock, 1.0) for sock in lorises[16:])
                    late = socket.create_connection(("127.0.0.1", port), timeout=5)
                    late.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                    assert _closed(late, 1.0)
                    late.close()
                    seqs = _frames(ws, 0.5)
                    assert len(seqs) > 0.5 * 1000 * 0.5 and seqs == sorted(seqs)
                    for stream in streams:
                        seqs = _frames(stream, 0.5)
                        assert len(seqs) > 0.5 * 20 * 0.5 and seqs == sorted(seqs)
            finally:
                for sock in lorises:
                    sock.close()


def test_the_cap_leaves_the_service_its_files_below_select_s_limit():
    """Under the usual soft limit of 1024 (and any higher: pyserial's
    select() fails on a descriptor past 1023), connections (each with a
    file it may be answered from), one accept burst (128) and the service's
    own files (128) fit below 1024; macOS's 256 leaves the floor of 16."""
    import resource

    from service.api.connections import connection_cap

    for limit in (1024, 4096, 1 << 20, resource.RLIM_INFINITY):
        assert connection_cap(limit) == (1024 - 128 - 128) // 2
    assert connection_cap(256) == 16


OWN_MEANWHILE = 4  # descriptors the service itself may open while the test counts (seen: 1)


def _open_descriptors() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_a_connection_answered_from_a_file_holds_two_descriptors_which_the_cap_counts():
    """Each connection answered from a file (the API docs' 1.5 MB bundle, to
    a client that does not read) holds its socket and the file: 760 of them
    under a cap of 768 held all 1024 descriptors of a service, and its own
    files failed. With a cap of 20, 30 such clients add 40 descriptors to
    the process (the 30 client sockets, in this same process, set aside),
    not 20: the cap counts two each."""
    from service.api.connections import DESCRIPTORS_PER_CONNECTION, BoundedH11

    cap, clients = 20, 30
    capped = type("Capped", (BoundedH11,), {"max_connections": cap, "request_timeout_s": 60.0})
    with live_server(TactileService("sim://?sensors=quad"), 1, http=capped) as server:
        port = server.config.port
        request = f"GET /static-offline-docs/swagger-ui-bundle.js HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()
        before = _open_descriptors()
        socks = []
        try:
            for _ in range(clients):
                sock = socket.socket()
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a reader that does not read
                sock.connect(("127.0.0.1", port))
                sock.sendall(request)
                socks.append(sock)
            peak, deadline = 0, time.monotonic() + 2.0
            while time.monotonic() < deadline:
                peak = max(peak, _open_descriptors() - before - clients)
                time.sleep(0.05)
        finally:
            for sock in socks:
                sock.close()
    assert 1.5 * cap < peak <= cap * DESCRIPTORS_PER_CONNECTION + OWN_MEANWHILE
