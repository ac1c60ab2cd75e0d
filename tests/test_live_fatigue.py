"""Load cycles of several sensors counted together (fatigue.update_many)
against each counter alone, when batches hold many frames per sensor (grids
that waited for a batch, reads that piled up): the same counts and the same
pending state, batch after batch."""
import numpy as np
import pytest

from service.reconstruct.fatigue import HIGH_N, LOW_N, CycleCounter, update_many


@pytest.mark.parametrize("taxels", [1, 64])
def test_counters_of_long_batches_count_what_each_counts_alone(taxels):
    rng = np.random.default_rng(taxels)
    sensors, frames = 6, 3000
    levels = np.array([0.0, LOW_N - 0.1, (LOW_N + HIGH_N) / 2, HIGH_N + 0.5, np.nan])
    # Slow loads (a level held for tens of frames) so that cycles span batches and judged frames.
    forces = [np.repeat(levels[rng.integers(0, len(levels), (frames // 30 + 1, taxels))], 30, axis=0)[:frames]
              for _ in range(sensors)]
    alone = [CycleCounter(taxels) for _ in range(sensors)]
    together = [CycleCounter(taxels) for _ in range(sensors)]
    done = [0] * sensors
    while any(d < frames for d in done):
        counts = [min(int(rng.choice([0, 1, 2, 5, 9, 14, 40])), frames - d) for d in done]
        for counter, f, d, c in zip(alone, forces, done, counts):
            counter.update(f[d:d + c])
        update_many(together, np.concatenate([f[d:d + c] for f, d, c in zip(forces, done, counts)]), counts)
        done = [d + c for d, c in zip(done, counts)]
        for a, b in zip(alone, together):
            np.testing.assert_array_equal(a.counts, b.counts)
            np.testing.assert_array_equal(a._armed, b._armed)
            assert a._any_armed == b._any_armed
    assert sum(int(a.counts.sum()) for a in alone) > 20
