"""Channels that fail a calibration session: a taxel dead all session is
named (refused, or listed as failed with --partial), never left silently at
its previous values; its presses, answered on no live channel, are set aside
rather than credited to a noisy neighbour. A session of 24 taxels at 200 Hz (with
two of six dead, the board's total response no longer matched the reference
well enough to align the clocks)."""
import struct
import warnings

import numpy as np
import pytest

from firmware_sim.calibration_session import probe_schedule, session
from firmware_sim.faults import split_frames
from service.calibration.calibrate import calibrate, document
from service.calibration.dead_taxels import dead_taxels
from service.calibration.segmentation import segment
from service.protocol import HEADER_SIZE, FrameType, encode_frame
from service.readings import OPEN_SENTINEL, SHORT_SENTINEL

RATE_HZ = 200.0


def rewritten(raw: bytes, change) -> bytes:
    """The stream with every grid frame's channels (u4 aF) replaced by ``change(channels)``."""
    out = bytearray()
    for frame in split_frames(raw):
        _, kind, sensor, flags, seq, t_us, length = struct.unpack_from("<BBBBHIH", frame, 2)
        if kind != FrameType.GRID:
            out += frame
            continue
        channels = np.frombuffer(frame[HEADER_SIZE:HEADER_SIZE + length], "<u4").copy()
        out += encode_frame(kind, sensor, seq, t_us, change(channels).astype("<u4").tobytes(), flags)
    return bytes(out)


@pytest.fixture(scope="module")
def dead(tmp_path_factory):
    """Taxels 0–23 each pressed twice, in a shuffled order (a dead taxel's
    presses in a row leave a long stretch the reference shows and the board
    does not) with varied pauses; taxel 2 reads open, taxel 4 shorted all
    session, taxel 3 has 30 fF of noise per frame (the simulator's: 1 fF).
    The session, its frame count, the refusal and the --partial result."""
    order = np.random.default_rng(2).permutation(list(range(24)) * 2)
    sim = session(None, probe_schedule(order, repeats=1, gap_jitter_s=0.8, seed=1), rate_hz=RATE_HZ, seed=5)
    rng = np.random.default_rng(5)

    def change(channels):
        channels[2], channels[4] = OPEN_SENTINEL, SHORT_SENTINEL
        channels[3] = np.rint(channels[3] + rng.normal(0.0, 30000.0))
        return channels

    folder = tmp_path_factory.mktemp("dead")
    (folder / "s.bin").write_bytes(rewritten(sim.raw, change))
    (folder / "r.csv").write_text(sim.reference_csv)
    path, ref = folder / "s.bin", folder / "r.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # numpy's All-NaN warning was all that showed them
        with pytest.raises(ValueError) as refused:
            calibrate(path, ref)
        result = calibrate(path, ref, allow_partial=True)
    return sim, len(result.session.t_s), str(refused.value), result


LIVE = [t for t in range(24) if t not in (2, 4)]


def test_taxels_dead_all_session_are_refused_by_name_and_listed_as_failed_when_partial(dead):
    sim, frames, refused, result = dead
    assert refused == (f"cannot calibrate: taxel row 1, col 3 (index 2): lost channel, dead all session: every one of "
                       f"its {frames} frames reads the open-circuit sentinel; taxel row 1, col 5 (index 4): lost "
                       f"channel, dead all session: every one of its {frames} frames reads the short-circuit sentinel")
    assert sorted(result.fits) == LIVE and sorted(result.problems) == [2, 4]
    failed = document(result)["statistics"]["taxels_failed"]
    assert sorted(failed) == ["2", "4"] and "short-circuit sentinel" in failed["4"]
    gains = np.array([result.fits[t].gain for t in LIVE])
    assert np.abs(gains / sim.gain[LIVE] - 1).max() < 5e-3


def test_a_dead_taxels_press_is_not_credited_to_a_noisy_live_one(dead):
    """The tester's G4: a press on dead taxel 5 went to noisy taxel 9 (its
    chance rise 0.0001) and refused the run as taxel 9's "non-monotone
    response". Here one of taxel 2's presses went to taxel 3 (rise 0.00036,
    0.9 σ of its noise) and into its fit."""
    sim, _, refused, result = dead
    assert "index 3" not in refused
    aside = [p for p in result.presses if p.problem]
    assert len(aside) == 4 and all(p.problem.startswith("no taxel responded") for p in aside)  # two on each dead one
    assert sorted(p.taxel for p in result.presses if p.problem is None) == sorted(LIVE * 2)
    assert abs(result.fits[3].gain / sim.gain[3] - 1) < 5e-3


def test_a_press_no_live_taxel_answers_is_set_aside_and_a_real_one_is_kept():
    """200 Hz, 16 taxels of 10 pF with 2 fF noise, taxel 9 eight times
    noisier, taxel 5 dead: a press on 5 (2–4 s, 9 N) has no taxel's rise above
    5σ of its noise; one on taxel 3 (6–8 s, 1.2 %/N) is credited to it, with
    the rise 1.2 %/N × the top's mean force (~8.6 N) ≈ 0.10."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 10.0, 0.005)

    def bump(a):  # 9 N for 2 s from a
        return np.where((t > a) & (t < a + 2), 9 * np.sin(np.pi * (t - a) / 2) ** 2, 0.0)

    force = bump(2.0) + bump(6.0)
    sigma = np.full(16, 2e-4)
    sigma[9] *= 8
    cap = 10.0 * (1 + rng.normal(0.0, 1.0, (t.size, 16)) * sigma)
    cap[:, 3] *= 1 + 0.012 * bump(6.0)
    cap[:, 5] = np.nan
    first, second = segment(t, cap, t, force)
    assert first.problem.startswith("no taxel responded (largest rise: ΔC/C0 ")
    assert second.problem is None and second.taxel == 3 and second.response == pytest.approx(0.1, rel=0.1)


def test_dead_channels_are_those_without_one_plausible_reading():
    raw = np.full((50, 6), 10_660_000, dtype=np.uint32)  # 10.66 pF
    raw[:, 0] = OPEN_SENTINEL
    raw[:, 1] = SHORT_SENTINEL
    raw[:25, 2], raw[25:, 2] = OPEN_SENTINEL, 2_000_000_000  # 2000 pF: a stuck converter
    raw[:, 3] = OPEN_SENTINEL
    raw[7, 3] = 10_000_000  # one good frame: alive (it may come and go)
    raw[:, 4] = 5  # 5 aF: no unloaded taxel
    assert dead_taxels(raw) == {
        0: "lost channel, dead all session: every one of its 50 frames reads the open-circuit sentinel",
        1: "lost channel, dead all session: every one of its 50 frames reads the short-circuit sentinel",
        2: "lost channel, dead all session: of its 50 frames, 25 read the open-circuit sentinel, "
           "25 read a capacitance outside [0.01, 1000] pF",
        4: "lost channel, dead all session: every one of its 50 frames reads a capacitance outside [0.01, 1000] pF"}


def test_a_refused_alignment_names_the_dead_taxels_the_board_does_not_show(tmp_path):
    """Six taxels, two of them dead: a third of the presses the reference logs
    are on no channel (the match fell to 0.72, under 0.9)."""
    sim = session(None, probe_schedule(range(6), seed=1), rate_hz=RATE_HZ, seed=5)

    def change(channels):
        channels[2], channels[4] = OPEN_SENTINEL, SHORT_SENTINEL
        return channels

    (tmp_path / "s.bin").write_bytes(rewritten(sim.raw, change))
    (tmp_path / "r.csv").write_text(sim.reference_csv)
    with pytest.raises(ValueError, match=r"does not match the board's response.*; note: presses on dead taxels show on "
                                         r"no channel \(taxel row 1, col 3 \(index 2\): lost channel.*\(index 4\)"):
        calibrate(tmp_path / "s.bin", tmp_path / "r.csv")


def test_a_dead_taxel_leaves_the_sessions_crosstalk_measured_from_presses_not_beside_it(dead):
    """Every frame holds the dead channels' NaN, and the estimator set each aside: 'too few isolated presses'
    (a tester: 25 460 isolated frames without the dead channel). Presses with no dead neighbour and no dead
    channel scanned next to them still measure the coupling (the simulator's: the paper's −0.0028)."""
    _, _, _, result = dead
    assert result.crosstalk is not None and result.crosstalk["events"] >= 1000
    assert result.crosstalk["mechanical"] == pytest.approx(-0.0028, rel=0.1)
    assert result.crosstalk["electrical"] < 0.002  # the simulator's multiplexer does not leak
