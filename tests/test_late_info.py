"""A board already streaming when the service connected (its reply to INFO?
lost): its first INFO comes later, while its sensors carry a load. It names
the board (protocol.md: the sensors are the same), so each keeps its zero; a
sensor the INFO gives another shape is another sensor, tared afresh."""
import numpy as np
import orjson
import pytest

from service.calibration.registry import builtin_document
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.reconstruct import Reconstructor

GRID_C0 = np.array(builtin_document()["taxels"]["c0_pF"])  # pF (64,): table 1's unloaded taxels
QUAD_C0 = np.array([5.0, 5.1, 4.9, 5.05])  # pF (4,): a quad's electrodes unloaded (it has no stored C0)
LOADED = range(300, 600)  # scans with taxel 9 at +5 % ΔC/C0 and the quad's four electrodes at +2 %
INFO_AT = 450  # the board's first INFO, mid-load
SCANS = 800


def scans(info: dict) -> list[bytes]:
    """The board's byte stream, a scan (grid 0, quad 1) at a time, ``info`` before scan INFO_AT."""
    rng = np.random.default_rng(7)
    out = []
    for k in range(SCANS):
        grid, quad = GRID_C0.copy(), QUAD_C0.copy()
        if k in LOADED:
            grid[9] *= 1.05
            quad *= 1.02
        grid_aF = np.round((grid + rng.normal(0, 0.002, 64)) * 1e6).astype("<u4")
        quad_aF = np.round((quad + rng.normal(0, 0.002, 4)) * 1e6).astype("<u4")
        chunk = encode_frame(FrameType.GRID, 0, k, 1000 * (k + 1), grid_aF.tobytes()) + \
            encode_frame(FrameType.QUAD, 1, k, 1000 * (k + 1) + 500, quad_aF.tobytes())
        if k == INFO_AT:
            chunk = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(info)) + chunk
        out.append(chunk)
    return out


def run(info: dict) -> dict[int, list]:
    """{sensor: its frames in scan order}, read live 10 scans at a time (no --board-name); a replay,
    joining the reads, reads the same."""
    stream = scans(info)
    chunks = [b"".join(stream[k:k + 10]) for k in range(0, SCANS, 10)]
    pipeline = Pipeline(Reconstructor(level="table"), map_clock=False)
    frames = [f for chunk in chunks for f in pipeline.feed(chunk, 1.0)]
    joined = Pipeline(Reconstructor(level="table"), map_clock=False).feed_many([(chunk, 1.0) for chunk in chunks])
    assert [(f.sensor.id, f.seq, f.flags) for f in joined] == [(f.sensor.id, f.seq, f.flags) for f in frames]
    assert all(np.array_equal(a.forces_N, b.forces_N, equal_nan=True) for a, b in zip(joined, frames))
    return {sid: [f for f in frames if f.sensor.id == sid] for sid in (0, 1)}


@pytest.mark.parametrize("serial", [None, "G8-777"])
def test_a_late_first_info_naming_the_board_keeps_each_sensors_zero_under_load(serial):
    """Taxel 9 held ~4 N when the INFO came: it read 0.014 N unflagged after it
    (tared afresh on the load), and after the release out_of_range; the quad's
    Fz read 0 for the rest of the press. The same bytes must read the same
    force either side of the INFO — also when it gives the grid a serial of
    its own: the sensor read so far is named by it, not replaced (identity.named)."""
    grid_info = {"id": 0, "kind": "grid", "rows": 8, "cols": 8} | ({"serial": serial} if serial else {})
    board = {"board": "emu-late", "fw": "1.0.0", "rate_hz": 500, "sensors": [grid_info, {"id": 1, "kind": "quad"}]}
    by = run(board)
    grid, quad = by[0], by[1]
    assert [f.seq for f in grid] == list(range(SCANS)) and grid[INFO_AT].sensor.board == "emu-late"
    assert not any("taring" in f.flags for f in grid[INFO_AT:] + quad[INFO_AT:])  # no new tare at the INFO
    held = np.array([f.forces_N[9] for f in grid[400:INFO_AT]])  # the load before the INFO, the reference
    after = np.array([f.forces_N[9] for f in grid[INFO_AT:600]])
    sigma = np.array([f.sigma_N[9] for f in grid[INFO_AT:600]])
    assert held.mean() > 1.0  # a real load, read as one
    assert np.all(np.abs(after - held.mean()) <= 3 * sigma)
    released = grid[650:]
    assert not any(f.taxel_flags.any() for f in released)  # not out_of_range, not loaded_at_tare
    assert np.mean([abs(f.forces_N[9]) <= 3 * f.sigma_N[9] for f in released]) >= 0.98  # noise alone
    fz_held = np.array([f.forces_N[2] for f in quad[400:INFO_AT]])
    fz_after = np.array([f.forces_N[2] for f in quad[INFO_AT:600]])
    assert fz_held.mean() > 0.5 and np.abs(fz_after.mean() - fz_held.mean()) <= 0.02 * fz_held.mean()
    assert not any(f.flags for f in quad[650:])
    assert np.mean([np.abs(f.forces_N) <= 3 * f.sigma_N for f in quad[650:]]) >= 0.98


def test_a_late_first_info_that_gives_a_sensor_another_shape_tares_it_afresh():
    """The frames said 8x8 (the protocol's default for 256 bytes); the INFO
    says 4x16: another sensor as far as the reconstruction knows, tared anew."""
    board = {"board": "emu-late", "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 16},
                                              {"id": 1, "kind": "quad"}]}
    grid = run(board)[0]
    assert (grid[INFO_AT - 1].sensor.rows, grid[INFO_AT].sensor.rows) == (8, 4)
    assert ["taring" in f.flags for f in grid[INFO_AT - 1:INFO_AT + 101]] == [False] + [True] * 99 + [False] * 2


def test_another_board_booting_on_the_port_tares_its_sensors_afresh():
    """The service joined board A mid-stream (no INFO, seq from 5000); board
    B then boots on the same port (protocol.md: INFO, then seq from 0, its
    first frames flagged board_restart) with sensors of the same kind and
    shape whose channels stand 2-6 % above A's. They are other sensors, not
    A's named: B's unloaded quad read (-2.20, -0.67, +1.20) N unflagged (σ
    0.16, 0.06, 0.09) on A's zero. Tared afresh, B reads 0 N within noise."""
    rng = np.random.default_rng(3)
    grid_b = GRID_C0 * rng.uniform(1.02, 1.06, 64)  # pF (64,): B's grid, unloaded
    quad_b = QUAD_C0 * np.array([1.06, 1.03, 1.05, 1.02])  # pF (4,): B's quad, unloaded
    board = {"board": "right", "fw": "1.0", "serial": "B-2", "rate_hz": 1000,
             "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}, {"id": 1, "kind": "quad"}]}

    def scan(seq: int, grid: np.ndarray, quad: np.ndarray) -> bytes:
        grid_aF = np.round((grid + rng.normal(0, 0.002, 64)) * 1e6).astype("<u4")
        quad_aF = np.round((quad + rng.normal(0, 0.002, 4)) * 1e6).astype("<u4")
        return encode_frame(FrameType.GRID, 0, seq, 1000 * (seq + 1), grid_aF.tobytes()) + \
            encode_frame(FrameType.QUAD, 1, seq, 1000 * (seq + 1) + 500, quad_aF.tobytes())

    pipeline = Pipeline(Reconstructor(level="table"), map_clock=False)
    frames = []
    for k in range(5000, 5400, 10):  # board A, joined mid-stream
        frames += pipeline.feed(b"".join(scan(j, GRID_C0, QUAD_C0) for j in range(k, k + 10)), 1.0)
    boot = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(board))
    for k in range(0, 600, 10):  # board B, from its power-up
        frames += pipeline.feed(boot + b"".join(scan(j, grid_b, quad_b) for j in range(k, k + 10)), 1.0)
        boot = b""
    for sid in (0, 1):
        b = [f for f in frames if f.sensor.id == sid][400:]
        assert b[0].seq == 0 and "board_restart" in b[0].flags
        assert ["taring" in f.flags for f in b[:101]] == [True] * 99 + [False] * 2  # B's own zero
        unloaded = b[200:]
        assert not any(f.flags or (f.taxel_flags is not None and f.taxel_flags.any()) for f in unloaded)
        forces, sigma = np.array([f.forces_N for f in unloaded]), np.array([f.sigma_N for f in unloaded])
        assert np.mean(np.abs(forces) <= 3 * sigma) >= 0.98, (sid, forces.mean(axis=0))
