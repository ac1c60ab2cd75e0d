"""Ctrl-C, as every ``tactile`` command takes it: the command ends within
about a second and exits 130 saying it was interrupted (cli.main), even in
a long computation (the InterruptWatchdog), and even when uvicorn, which
catches Ctrl-C itself, is the one serving (noting_sigint).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

# Commands that stop on Ctrl-C by design and need longer than the usual second to
# finish what they wrote (the MCAP's summary), or that uvicorn stops itself.
_INTERRUPT_GRACE_S = {"record": 10.0}
_UVICORN_HANDLES_SIGINT = ("serve",)
INTERRUPT_GRACE_S = 0.8


def interrupted(command: str) -> str:
    return f"tactile {command}: interrupted"


class InterruptWatchdog:
    """Ctrl-C ends the command within about a second even while the main thread
    is inside a long computation (a sparse factorisation does not look at
    signals): the C-level signal handler writes to a wake-up pipe, this thread
    reads it and, if the main thread has not finished within the grace period,
    says so and exits 130 without unwinding."""

    def __init__(self, command: str, grace_s: float) -> None:
        self._command, self._grace_s = command, grace_s
        self._done = threading.Event()
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        try:
            self._previous = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        except ValueError:  # not the main thread (called from a test's thread): no watchdog
            self._previous = None
            os.close(self._read), os.close(self._write)
            self._read = None
            return
        threading.Thread(target=self._run, name="tactile-interrupt", daemon=True).start()

    def _run(self) -> None:
        while True:
            try:
                data = os.read(self._read, 64)
            except OSError:
                return
            if not data:
                return
            if signal.SIGINT in data and not self._done.wait(self._grace_s):
                print(interrupted(self._command), file=sys.stderr, flush=True)
                os._exit(130)

    def close(self) -> None:
        self._done.set()
        if self._read is None:
            return
        try:
            signal.set_wakeup_fd(self._previous if self._previous is not None else -1)
        except ValueError:
            pass
        os.close(self._write)


def watchdog_for(args, name: str) -> InterruptWatchdog | None:
    """The watchdog of command ``name``; none where uvicorn stops the command itself."""
    if args.command in _UVICORN_HANDLES_SIGINT or getattr(args, "serve", False):
        return None
    return InterruptWatchdog(name, _INTERRUPT_GRACE_S.get(args.command, INTERRUPT_GRACE_S))


@contextlib.contextmanager
def noting_sigint(noted: list):
    """uvicorn catches Ctrl-C, shuts down, re-raises it to the handler it found and
    then swallows the KeyboardInterrupt: a handler of ours notes that it came.
    (A SIGINT that is ignored, as in a background job, stays ignored.)"""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def note(signum, frame):
        noted.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, note)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
