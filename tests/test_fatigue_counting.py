"""Load cycles (reconstruct/fatigue.py) counted the same however a stream is
cut into batches — one frame at a time as live, a few, or thousands as a
replay — against a per-taxel state machine written from the definition."""
import numpy as np
import pytest

from service.reconstruct.fatigue import FEW_FRAMES, HIGH_N, JUDGE_EVERY, LOW_N, CycleCounter


def reference(forces: np.ndarray) -> np.ndarray:
    """Cycles per taxel: rise above HIGH_N, then fall below LOW_N; NaN and
    the band between change nothing."""
    counts = [0] * forces.shape[1]
    for taxel in range(forces.shape[1]):
        armed = False
        for value in forces[:, taxel]:
            if value > HIGH_N:
                armed = True
            elif value < LOW_N and armed:
                armed = False
                counts[taxel] += 1
    return np.array(counts)


def stream(frames: int, taxels: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    forces = rng.choice([0.0, 0.2, 0.5, 0.9, 1.1, 3.0, np.nan], size=(frames, taxels))
    forces[rng.random(forces.shape) < 0.3] = 0.0  # long unloaded stretches, as a real stream
    return forces


@pytest.mark.parametrize("cuts", [[1], [2], [FEW_FRAMES], [FEW_FRAMES + 1], [1, 5, 2, 40, 3, 1, 700]])
@pytest.mark.parametrize("taxels", [1, 64])
def test_counts_do_not_depend_on_how_the_stream_is_cut(cuts, taxels):
    forces = stream(3000, taxels, seed=taxels + len(cuts))
    counter = CycleCounter(taxels)
    start, i = 0, 0
    while start < len(forces):
        size = cuts[i % len(cuts)]
        counter.update(forces[start:start + size])
        start, i = start + size, i + 1
    expected = reference(forces[::JUDGE_EVERY])  # every JUDGE_EVERY-th frame of the stream is judged
    assert expected.sum() > 100  # the stream does cycle
    np.testing.assert_array_equal(counter.counts, expected)


def test_a_cycle_spanning_batches_of_both_paths_is_counted_once():
    counter = CycleCounter(1)
    counter.update(np.array([[2.0]] * (FEW_FRAMES + 2)))  # armed in a whole-batch scan
    counter.update(np.array([[0.5]]))  # in the band (and not a judged frame)
    counter.update(np.array([[0.1]]))  # falls, frame by frame (judged from the next judged frame)
    counter.update(np.array([[0.1]] * (FEW_FRAMES + 2)))
    assert counter.counts.tolist() == [1]
