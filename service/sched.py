"""Ask the Linux scheduler to wake this process promptly (a latency hint).

Since Linux 6.12 the fair scheduler (EEVDF) lets a normal, unprivileged
task ask for a shorter time slice with ``sched_setattr``: its virtual
deadlines come sooner, so when it wakes it may preempt a task that is in
the middle of a longer slice instead of waiting for that slice to end. The
process still gets only its fair share of the CPU, in smaller, earlier
pieces. Measured under the load test (docs/load.md): a process that sleeps
1 ms at a time is woken up to 0.4–0.65 ms late at p99 with a 100 µs slice,
1.2–2.2 ms with the kernel's default (1.4 ms on the 2-core test VM); for the
service itself no difference could be told from the host's noise.

Python's ``os`` module has no ``sched_setattr``, so the system call is made
through ctypes. Older kernels ignore the field and other systems lack the
call: ``request_slice`` then reports what happened and changes nothing.
"""
from __future__ import annotations

import ctypes
import gc
import os
import platform
import struct
import sys
from dataclasses import dataclass

# struct sched_attr, first version (48 bytes): size, policy, flags, nice,
# priority, runtime (the slice for SCHED_OTHER), deadline, period.
_SCHED_ATTR = struct.Struct("<IIQiIQQQ")
_SYSCALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}  # sched_setattr, sched_getattr
SCHED_OTHER = 0
MIN_SLICE_US, MAX_SLICE_US = 100, 100_000  # the kernel's clamp for a custom slice


@dataclass(frozen=True)
class SliceRequest:
    """What ``request_slice`` asked for (None: nothing) and what the kernel now reports."""

    requested_us: int | None
    granted_us: int | None  # the slice the kernel reports afterwards; None where it could not be read
    error: str | None = None

    @property
    def applied(self) -> bool:
        return self.error is None and self.granted_us == self.requested_us

    def as_dict(self) -> dict:
        return {"requested_us": self.requested_us, "granted_us": self.granted_us,
                "applied": self.applied, "error": self.error}


def _syscall_numbers() -> tuple[int, int] | None:
    """(sched_setattr, sched_getattr) here, or None where there are none."""
    return _SYSCALLS.get(platform.machine()) if platform.system() == "Linux" else None


def _syscall(number: int, *args) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(number, *args) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))


def current_slice_us() -> int | None:
    """The calling thread's time slice in µs (``sched_getattr``), or None
    where the call does not exist or the thread is not SCHED_OTHER."""
    numbers = _syscall_numbers()
    if numbers is None:
        return None
    buffer = ctypes.create_string_buffer(_SCHED_ATTR.size)
    try:
        _syscall(numbers[1], 0, buffer, _SCHED_ATTR.size, 0)
    except OSError:
        return None
    _, policy, _, _, _, runtime_ns, _, _ = _SCHED_ATTR.unpack(buffer.raw)
    return runtime_ns // 1000 if policy == SCHED_OTHER else None


def request_slice(slice_us: int) -> SliceRequest:
    """Ask for a time slice of ``slice_us`` for the calling thread and the
    threads it starts afterwards (they inherit it), at normal priority and
    the thread's current niceness.

    Raises ValueError for a slice outside the kernel's 100–100 000 µs; any
    refusal by the system is returned in ``error``, never raised, since the
    hint is an optimisation and the caller runs correctly without it.
    """
    if not MIN_SLICE_US <= slice_us <= MAX_SLICE_US:
        raise ValueError(f"slice_us={slice_us} is outside {MIN_SLICE_US}..{MAX_SLICE_US}")
    numbers = _syscall_numbers()
    if numbers is None:
        return SliceRequest(slice_us, None, f"sched_setattr is not available on {platform.system()} {platform.machine()}")
    attr = ctypes.create_string_buffer(_SCHED_ATTR.pack(_SCHED_ATTR.size, SCHED_OTHER, 0, os.nice(0), 0,
                                                        slice_us * 1000, 0, 0))
    try:
        _syscall(numbers[0], 0, attr, 0)
    except OSError as exc:
        return SliceRequest(slice_us, current_slice_us(), f"sched_setattr: {exc.strerror}")
    granted = current_slice_us()
    error = None if granted == slice_us else "the kernel does not support a custom slice (Linux < 6.12)"
    return SliceRequest(slice_us, granted, error)


# How long a thread that wants the interpreter waits for one that runs
# Python without pause (a history read, a replay, the built-in simulator)
# before it must hand over: CPython's default is 5 ms, longer than the whole
# 2 ms budget of a frame.
SWITCH_INTERVAL_S = 0.0005


def tune_for_latency(slice_us: int | None) -> SliceRequest:
    """Called once on the event loop's thread before the readout starts
    (threads started after it inherit the slice). What exists now (modules,
    the app) lives as long as the process: keep it out of the collector's
    full passes, which would otherwise stall the loop for tens of ms every
    few seconds at 8 kHz of frames."""
    gc.freeze()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    if slice_us:
        return request_slice(slice_us)
    return SliceRequest(None, current_slice_us())
