"""Load cycles of several sensors counted together (fatigue.update_many)
against each counter alone, in batches of a frame or two per sensor (a live
read) and of many (grids that waited for a batch, reads that piled up): the
same counts and the same pending state, batch after batch."""
import numpy as np
import pytest

from service.reconstruct.fatigue import HIGH_N, LOW_N, CycleCounter, update_many

LEVELS = np.array([0.0, LOW_N - 0.1, (LOW_N + HIGH_N) / 2, HIGH_N + 0.5, np.nan])


def held(rng, frames: int, taxels: int, hold: int) -> np.ndarray:
    """(frames, taxels) forces, each level held ``hold`` frames (slow loads:
    cycles span batches and judged frames)."""
    return np.repeat(LEVELS[rng.integers(0, len(LEVELS), (frames // hold + 1, taxels))], hold, axis=0)[:frames]


@pytest.mark.parametrize("taxels, hold, sizes, cycles", [
    (3, 1, [0, 1, 2, 3], 10),  # a live read: a frame or two per sensor, levels changing every frame
    (1, 30, [0, 1, 2, 5, 9, 14, 40], 20),  # long batches of a quad's Fz
    (64, 30, [0, 1, 2, 5, 9, 14, 40], 20),  # long batches of a grid
])
def test_counters_counted_together_count_what_each_counts_alone(taxels, hold, sizes, cycles):
    rng = np.random.default_rng(taxels + hold)
    sensors, frames = 6, 3000
    forces = [held(rng, frames, taxels, hold) for _ in range(sensors)]
    alone = [CycleCounter(taxels) for _ in range(sensors)]
    together = [CycleCounter(taxels) for _ in range(sensors)]
    done = [0] * sensors
    while any(d < frames for d in done):
        counts = [min(int(rng.choice(sizes)), frames - d) for d in done]
        for counter, f, d, c in zip(alone, forces, done, counts):
            counter.update(f[d:d + c])
        update_many(together, np.concatenate([f[d:d + c] for f, d, c in zip(forces, done, counts)]), counts)
        done = [d + c for d, c in zip(done, counts)]
        for a, b in zip(alone, together):
            np.testing.assert_array_equal(a.counts, b.counts)
            np.testing.assert_array_equal(a._armed, b._armed)
            assert a._any_armed == b._any_armed
    assert sum(int(a.counts.sum()) for a in alone) > cycles
