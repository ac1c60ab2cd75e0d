"""Link faults injected into a clean byte stream, with a record of what survived.

``inject`` walks the frames of a stream the simulator produced and, per
frame, leaves it alone, corrupts one byte, truncates it, or puts garbage in
front of it (garbage that may contain the sync pattern and a plausible
header). It returns the damaged bytes and the (type, sensor, seq) of every
frame left intact, so a test can demand that exactly those come out.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from service.protocol import CRC_SIZE, HEADER_SIZE, SYNC, VERSION, FrameType

FAULTS = ("flip", "truncate", "garbage", "fake_header")


@dataclass(frozen=True)
class Injection:
    data: bytes
    intact: list[tuple[int, int, int]]  # (type, sensor, seq) of untouched frames
    counts: dict[str, int]


def split_frames(data: bytes) -> list[bytes]:
    """Split a *clean* stream into frames by their length fields."""
    frames, pos = [], 0
    while pos < len(data):
        if data[pos : pos + 2] != SYNC:
            raise ValueError(f"stream is not clean: no sync at byte {pos}")
        (length,) = struct.unpack_from("<H", data, pos + 12)
        end = pos + HEADER_SIZE + length + CRC_SIZE
        frames.append(data[pos:end])
        pos = end
    return frames


def _garbage(rng: np.random.Generator, fake_header: bool) -> bytes:
    junk = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
    if not fake_header:
        return junk
    # A sync and a header that passes every check but the CRC.
    header = struct.pack("<BBBBHIH", VERSION, FrameType.QUAD, 1, 0, 7, 1234, 16)
    return junk + SYNC + header + rng.integers(0, 256, 18, dtype=np.uint8).tobytes()


def inject(data: bytes, rate: float = 0.05, seed: int = 0, faults: tuple[str, ...] = FAULTS) -> Injection:
    """Damage about ``rate`` of the frames of a clean stream."""
    unknown = set(faults) - set(FAULTS)
    if unknown:
        raise ValueError(f"unknown faults {sorted(unknown)}; known: {', '.join(FAULTS)}")
    rng = np.random.default_rng(seed)
    out = bytearray()
    intact = []
    counts = dict.fromkeys(faults, 0)
    for frame in split_frames(data):
        fault = faults[int(rng.integers(len(faults)))] if rng.random() < rate else None
        key = (frame[3], frame[4], struct.unpack_from("<H", frame, 6)[0])
        if fault is None:
            out += frame
            intact.append(key)
            continue
        counts[fault] += 1
        if fault == "flip":
            damaged = bytearray(frame)
            damaged[int(rng.integers(len(frame)))] ^= int(rng.integers(1, 256))
            out += damaged
        elif fault == "truncate":
            out += frame[: int(rng.integers(1, len(frame)))]
        else:
            out += _garbage(rng, fake_header=fault == "fake_header") + frame
            intact.append(key)
    return Injection(bytes(out), intact, counts)
