"""Front ends that put a simulated board behind a pseudo-terminal or TCP.

Both pace the board by the wall clock and share one loop: send what the
board produced, take commands, sleep until the next scan. When the peer does
not keep up (or, over TCP, no client is connected) the board drops scans and
flags OVERRUN, as a real board would.
"""
from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty
from typing import Callable

from .board import Board, BoardConfig
from .delivery import DelayedLink

PENDING_LIMIT = 1 << 16


class _Link:
    """One connected peer: pending output, non-blocking send and receive."""

    def __init__(self, fileno: int, send: Callable[[bytes], int], recv: Callable[[int], bytes]) -> None:
        self.fileno = fileno
        self._send = send
        self._recv = recv
        self.pending = bytearray()

    def flush(self) -> None:
        if self.pending:
            try:
                sent = self._send(self.pending)
            except BlockingIOError:
                return
            del self.pending[:sent]

    def poll_commands(self, timeout: float) -> bytes | None:
        """Wait up to ``timeout`` for command bytes; None when the peer hung up."""
        wanted_write = [self.fileno] if self.pending else []
        readable, _, _ = select.select([self.fileno], wanted_write, [], max(timeout, 0.0))
        if not readable:
            return b""
        try:
            data = self._recv(4096)
        except BlockingIOError:
            return b""
        return data if data else None


def _run(board: Board, link: _Link, t0: float, stop: threading.Event) -> None:
    """Stream until ``stop`` is set or the peer goes away (OSError)."""
    delayed = DelayedLink(board.config.jitter_ms, board.config.seed) if board.config.jitter_ms > 0 else None
    while not stop.is_set():
        now = time.monotonic() - t0
        data = board.advance(now, room=max(PENDING_LIMIT - len(link.pending) - (delayed.pending if delayed else 0), 0))
        if delayed:
            delayed.put(data, now)
            data = delayed.take(now)
        link.pending += data
        link.flush()
        due = min(board.next_scan_time, delayed.next_release if delayed else board.next_scan_time)
        commands = link.poll_commands(min(due - (time.monotonic() - t0), 0.05))
        if commands is None:
            return
        if commands:
            link.pending += board.receive(commands)


def open_pty() -> tuple[int, int, str]:
    """A raw pseudo-terminal pair: (master fd, slave fd, slave device path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def serve_pty(config: BoardConfig, master: int, stop: threading.Event) -> None:
    """Run a board on the master side of a pty until ``stop`` is set.

    The caller keeps the slave fd open so that writes never fail while no
    program has the device open; the kernel buffer then fills and the board
    reports OVERRUN once a reader arrives.
    """
    board = Board(config)
    link = _Link(master, lambda data: os.write(master, data), lambda n: os.read(master, n))
    link.pending += board.power_up()
    _run(board, link, time.monotonic(), stop)


def serve_tcp(board: Board, server: socket.socket, stop: threading.Event, t0: float | None = None) -> None:
    """Serve one client at a time on a listening socket until ``stop``.

    The board keeps running between clients (its scans are dropped), so a
    client that reconnects sees the sequence gap of the scans it missed.
    ``t0`` is the monotonic time of the board's power-up (default: now); a
    board handed to a new server with its old ``t0`` carries on as if it had
    been scanning all along.
    """
    t0 = time.monotonic() if t0 is None else t0
    server.settimeout(0.05)
    while not stop.is_set():
        board.advance(time.monotonic() - t0, room=0)
        try:
            client, _ = server.accept()
        except TimeoutError:
            continue
        client.setblocking(False)
        # A board streams small frames at 1 kHz: Nagle's algorithm would hold them for ACKs.
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link = _Link(client.fileno(), client.send, client.recv)
        link.pending += board.power_up()
        try:
            _run(board, link, t0, stop)
        except OSError:
            pass
        finally:
            client.close()


def tcp_server(host: str, port: int) -> socket.socket:
    server = socket.create_server((host, port), reuse_port=False)
    server.listen(1)
    return server
