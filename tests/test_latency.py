import numpy as np
import pytest

from service.latency import LatencyMeter


def test_percentiles_of_known_latencies():
    meter = LatencyMeter(capacity=1000)
    stamps = 10.0 - np.arange(1, 101) * 1e-3  # latencies 1, 2, ..., 100 ms
    meter.add(10.0, list(stamps[:40]))
    meter.add(10.0, list(stamps[40:]))
    summary = meter.summary()
    # Linear interpolation between order statistics: p50 of 1..100 is 50.5, p99 is 99.01.
    assert summary == {"frames": 100, "window": 100, "p50_ms": 50.5, "p99_ms": 99.01, "max_ms": 100.0}


def test_the_window_keeps_only_the_newest_samples():
    meter = LatencyMeter(capacity=10)
    latencies = np.arange(25, dtype=float)
    for start in range(0, 25, 7):  # batches of 7 wrap around the ring
        meter.add(100.0, list(100.0 - latencies[start:start + 7]))
    summary = meter.summary()
    assert summary["frames"] == 25 and summary["window"] == 10
    assert summary["max_ms"] == 24_000.0 and summary["p50_ms"] == pytest.approx(19_500.0)
    meter.add(100.0, list(100.0 - np.arange(30.0)))  # more than the ring holds at once
    assert meter.summary()["max_ms"] == 29_000.0 and meter.summary()["p50_ms"] == pytest.approx(24_500.0)


def test_empty_meter_and_bad_capacity():
    assert LatencyMeter().summary() == {"frames": 0, "window": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    with pytest.raises(ValueError, match="capacity must be at least 1, got 0"):
        LatencyMeter(capacity=0)
