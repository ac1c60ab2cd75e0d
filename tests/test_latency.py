import numpy as np
import pytest

from service.latency import LatencyMeter


def test_percentiles_of_known_latencies():
    meter = LatencyMeter(capacity=1000)
    for ms in np.random.default_rng(0).permutation(np.arange(1, 101)):
        meter.add(ms * 1e-3)
    # Linear interpolation between order statistics: p50 of 1..100 is 50.5, p99 is 99.01.
    assert meter.summary() == {"samples": 100, "window": 100, "p50_ms": 50.5, "p99_ms": 99.01, "max_ms": 100.0}


def test_the_window_keeps_only_the_newest_samples():
    meter = LatencyMeter(capacity=10)
    for seconds in range(25):
        meter.add(float(seconds))
    summary = meter.summary()
    assert summary["samples"] == 25 and summary["window"] == 10
    assert summary["max_ms"] == 24_000.0 and summary["p50_ms"] == pytest.approx(19_500.0)  # of 15..24 s


def test_empty_meter_and_bad_capacity():
    assert LatencyMeter().summary() == {"samples": 0, "window": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    with pytest.raises(ValueError, match="capacity must be at least 1, got 0"):
        LatencyMeter(capacity=0)
