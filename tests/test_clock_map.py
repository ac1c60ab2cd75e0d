"""Board clock → host clock (service.clock_map) against streams whose true
scan times are known: a reference generator here, and the simulator."""
import numpy as np
import pytest

from firmware_sim.board import BoardConfig
from firmware_sim.delivery import deliveries
from firmware_sim.sensors import SimQuad
from firmware_sim.urlhandler.protocol_sim import config_from_url
from service.clock_map import ClockMap
from service.protocol import DATA_TYPES
from service.protocol_decoder import Decoder

WRAP = 1 << 32
LATENCY = 0.5e-3  # the link's least delay: part of the envelope, the same for every board


def reads(seconds, rate_hz, ppm, offset_us, jitter_ms, seed, start=100.0, board_us0=0):
    """(t_us (k,), t_recv, true host time of each scan (k,)) per read.

    Scans every 1/rate of board time; t_us = board µs + offset (wrapping), the
    scan's true time = start + board seconds / (1 + ppm·1e-6). Frames leave in
    chunks of 1-4 scans, each chunk late by LATENCY + U(0, jitter), never
    before the previous chunk; a read takes what came out together.
    """
    rng = np.random.default_rng(seed)
    board_us = board_us0 + np.rint(np.arange(1, int(seconds * rate_hz) + 1) * 1e6 / rate_hz).astype(np.int64)
    scan = start + (board_us - board_us0) * 1e-6 / (1 + ppm * 1e-6)
    ends = np.unique(np.minimum(np.cumsum(rng.integers(1, 5, scan.size)), scan.size) - 1)
    release = np.maximum.accumulate(scan[ends] + LATENCY + rng.uniform(0, jitter_ms * 1e-3, ends.size))
    raw = (board_us + offset_us) % WRAP
    bounds = np.r_[0, ends + 1]
    return [(raw[a:b], float(t), scan[a:b]) for a, b, t in zip(bounds[:-1], bounds[1:], release)]


def run(clock, stream):
    """Feed every read; (t_recv, host times it returned, truth) per read."""
    return [(t_recv, clock.observe(t_us, t_recv), truth) for t_us, t_recv, truth in stream]


def test_a_noiseless_stream_gives_offset_and_rate_exactly():
    ppm, offset = 123.4, 3_000_000_000
    board_us = np.arange(0, 5_000_000, 1000)
    t_recv = 50.0 + board_us * 1e-6 / (1 + ppm * 1e-6)
    clock = ClockMap()
    for u, t in zip(board_us, t_recv):
        clock.observe(np.array([(u + offset) % WRAP]), t)
    status = clock.status()
    assert status["locked"] and status["samples"] == board_us.size
    # The rate to 1e-9 relative: 1e-3 ppm.
    assert status["rate_error_ppm"] == pytest.approx(ppm, abs=1e-3)
    probe = np.array([0, 1_234_567, 4_999_000])
    np.testing.assert_allclose(clock.to_host((probe + offset) % WRAP), 50.0 + probe * 1e-6 / (1 + ppm * 1e-6), rtol=0, atol=1e-9)
    assert clock.to_host(offset) == pytest.approx(50.0, abs=1e-9)  # a scalar gives a float
    assert status["jitter_ms"] == pytest.approx(0, abs=1e-6)


def test_before_lock_the_map_is_receive_time_minus_the_least_delay():
    clock = ClockMap()
    assert np.isnan(clock.to_host(5))
    assert clock.observe(np.array([1000, 2000]), 10.0).tolist() == pytest.approx([10.0 - 0.001, 10.0])
    # 1 ms of board time later, received 3 ms later: 2 ms late against the first read.
    assert clock.observe(np.array([3000]), 10.003).tolist() == pytest.approx([10.001])
    # Received 0.5 ms early against the first: the least delay is now this one's.
    assert clock.observe(np.array([5000]), 10.0025).tolist() == pytest.approx([10.0025])
    assert clock.to_host(1000) == pytest.approx(10.0025 - 0.004)
    assert clock.status()["locked"] is False


@pytest.mark.parametrize("rate_hz", [1000, 200])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_two_boards_see_one_event_within_0p3_ms_after_10_s(rate_hz, seed):
    """±200 ppm, offsets apart (one about to wrap), 5 ms one-sided jitter, chunked reads."""
    boards = [(200.0, 123_456_789, 0.0), (-200.0, WRAP - 4_000_000, 0.0007)]
    clocks, errors = [], []
    for b, (ppm, offset, phase) in enumerate(boards):
        clock = ClockMap()
        done = run(clock, reads(10.5, rate_hz, ppm, offset, 5.0, 10 * seed + b, start=100.0 + phase))
        late = np.concatenate([out - (truth + LATENCY) for t_recv, out, truth in done if t_recv > 110.0])
        errors.append(np.abs(late).max())
        clocks.append((clock, ppm, offset, phase))
    assert max(errors) < 0.15e-3  # every frame after 10 s, against its true scan time
    events = np.linspace(109.0, 110.5, 301)  # true times of events the two boards both saw
    seen = [clock.to_host((np.rint((events - 100.0 - phase) * (1 + ppm * 1e-6) * 1e6).astype(np.int64) + offset) % WRAP)
            for clock, ppm, offset, phase in clocks]
    assert np.abs(seen[0] - seen[1]).max() < 0.3e-3
    np.testing.assert_allclose(seen[0], events + LATENCY, atol=0.15e-3)


def test_status_against_the_truth_after_10_s():
    ppm = -173.0
    stream = reads(10.0, 1000, ppm, 7, 5.0, seed=5)
    clock = ClockMap()
    done = run(clock, stream)
    status = clock.status()
    assert status["locked"] and status["restarts"] == 0
    assert status["rate_error_ppm"] == pytest.approx(ppm, abs=5.0)
    assert status["samples"] == len(stream)
    assert status["window_s"] == pytest.approx(10.0, abs=0.01)
    assert 4.0 < status["jitter_ms"] < 5.5  # U(0, 5 ms), and the FIFO's extra delay
    t_recv, out, truth = done[-1]
    actual_ms = abs(out[-1] - (truth[-1] + LATENCY)) * 1e3
    assert actual_ms <= status["offset_uncertainty_ms"] < 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_uncertainty_covers_the_error_as_it_runs(seed):
    clock = ClockMap()
    for t_us, t_recv, truth in reads(8.0, 500, 150.0, 0, 5.0, seed):
        out = clock.observe(t_us, t_recv)
        status = clock.status()
        if status["locked"]:
            assert abs(out[-1] - (truth[-1] + LATENCY)) * 1e3 <= status["offset_uncertainty_ms"]


def test_a_wrap_of_the_board_clock_is_no_step():
    stream = reads(6.0, 1000, 90.0, WRAP - 3_000_000, 5.0, seed=7)
    assert any(t_us[0] > t_us[-1] for t_us, _, _ in stream)  # a wrap inside a read too
    clock = ClockMap()
    done = run(clock, stream)
    assert clock.status()["restarts"] == 0
    after = np.concatenate([out - (truth + LATENCY) for t_recv, out, truth in done if t_recv > 102.0])
    assert np.abs(after).max() < 0.3e-3


def test_a_restart_relocks_and_never_strays_beyond_the_naive_map():
    before = reads(5.0, 1000, 180.0, 2_000_000_000, 5.0, seed=3)
    # Powered up again 0.4 s later: t_us back to a value 2 000 s lower (the protocol: "from 0").
    after = reads(4.0, 1000, 180.0, 0, 5.0, seed=4, start=105.4)
    clock = ClockMap()
    run(clock, before)
    prior = clock.status()["rate_error_ppm"]
    done = run(clock, after)
    status = clock.status()
    assert status["restarts"] == 1 and status["locked"]
    assert status["rate_error_ppm"] == pytest.approx(180.0, abs=5.0)
    for t_recv, out, truth in done:
        assert np.all(out <= t_recv)
        error = np.abs(out - (truth + LATENCY)).max()
        assert error < 5.5e-3  # at worst the naive map: one jitter late
        if t_recv > 105.4 + 2.0:
            assert error < 0.3e-3
    assert prior == pytest.approx(180.0, abs=5.0)


def test_restart_keeps_the_rate_as_prior():
    clock = ClockMap()
    run(clock, reads(5.0, 1000, 250.0, 0, 1.0, seed=1))
    locked_rate = clock.status()["rate_error_ppm"]
    clock.restart()
    status = clock.status()
    assert status == {**status, "locked": False, "samples": 0, "restarts": 1}
    assert status["rate_error_ppm"] == locked_rate
    # A restart whose clock went forward (so no step back to see): told by the caller.
    out = run(clock, reads(0.5, 1000, 250.0, 1_000_000_000, 1.0, seed=2, start=106.0))
    errors = np.concatenate([o - (truth + LATENCY) for _, o, truth in out])
    assert np.abs(errors).max() < 1.5e-3


def test_a_simulated_board_end_to_end():
    """Two simulated boards, skewed ±, offset, 5 ms jitter, decoded by the service's decoder."""
    url = "sim://?sensors=quad&scene=idle&rate=500&seed=4&clock_ppm=190&clock_offset_us=4294000000&jitter_ms=5"
    configs = [config_from_url(url), BoardConfig(sensors=[SimQuad(0)], scene="idle", rate_hz=500, seed=5,
                                                  clock_ppm=-160, clock_offset_us=77, jitter_ms=5)]
    assert (configs[0].clock_ppm, configs[0].clock_offset_us, configs[0].jitter_ms) == (190.0, 4294000000, 5.0)
    errors = []
    for config in configs:
        clock, decoder = ClockMap(), Decoder()
        for t_recv, data in deliveries(config, 10.5):
            t_us = np.array([f.t_us for f in decoder.feed(data) if f.type in DATA_TYPES])
            if t_us.size and t_recv > 10.0:
                board_s = ((t_us - config.clock_offset_us) % WRAP) * 1e-6
                errors.append(clock.observe(t_us, t_recv) - board_s / (1 + config.clock_ppm * 1e-6))
            elif t_us.size:
                clock.observe(t_us, t_recv)
        assert clock.status()["rate_error_ppm"] == pytest.approx(config.clock_ppm, abs=5.0)
    assert np.abs(np.concatenate(errors)).max() < 0.15e-3
