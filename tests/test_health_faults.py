"""/health names taxels and quad electrodes that stay null or flagged, and a sensor its INFO describes twice."""
import time

import numpy as np

from service.health import health_report
from service.live_service import TactileService
from service.protocol import FrameType, encode_frame
from service.readings import OPEN_SENTINEL, SHORT_SENTINEL

GRID, QUAD = np.full(64, 10_660_000.0), np.full(4, 2_200_000.0)  # aF: table 1's C0 and the quad's, about
SENTINELS = [OPEN_SENTINEL, SHORT_SENTINEL]
DEAD = "a dead channel? Check the sensor's cable and connector"


def feed(service, rng, seq0, count, grid, quad, t_host):
    """``count`` scans of both sensors at ``t_host``: converter noise of 500 aF on every count but a sentinel."""
    out = b""
    for i in range(seq0, seq0 + count):
        g = np.where(np.isin(grid, SENTINELS), grid, grid + rng.normal(0, 500, 64))
        q = np.where(np.isin(quad, SENTINELS), quad, quad + rng.normal(0, 500, 4))
        out += encode_frame(FrameType.GRID, 0, i, i * 1000, g.astype("<u4").tobytes())
        out += encode_frame(FrameType.QUAD, 1, i, i * 1000, q.astype("<u4").tobytes())
    service.pipeline.feed(out, t_host)


def faulty_after(grid, quad, frames=200):
    """/health after a tare on GRID and QUAD (2 s ago), then ``frames`` scans of ``grid`` and ``quad`` now."""
    rng = np.random.default_rng(3)
    service = TactileService("sim://")
    now = time.time()
    feed(service, rng, 0, 150, GRID, QUAD, now - 2.0)
    feed(service, rng, 150, frames, grid, quad, now)
    return health_report(service)


def test_open_and_shorted_channels_are_named_with_what_to_do():
    """The adversary's sentinel case: taxel 27 open, 28 shorted, the quad's
    electrode 0 open, on every frame: /health stayed ok with no problem."""
    grid, quad = GRID.copy(), QUAD.copy()
    grid[27], grid[28], quad[0] = OPEN_SENTINEL, SHORT_SENTINEL, OPEN_SENTINEL
    report = faulty_after(grid, quad)
    assert report["sensors"]["0"]["faulty_channels"] == {"no_reading": [27, 28]}
    assert report["sensors"]["1"]["faulty_channels"] == {"no_reading": [0]}
    assert report["status"] == "degraded"
    assert ("sensor 0: taxels 27 (row 3, col 3), 28 (row 3, col 4) had no reading (an open or shorted channel: "
            f"null) in most of the last 1 s's frames: {DEAD}") in report["problems"]
    assert ("sensor 1: electrodes 0 (row 0, col 0) had no reading (an open or shorted channel: null) in most of "
            f"the last 1 s's frames: {DEAD}") in report["problems"]


def test_a_stuck_channel_is_named_stale():
    """Taxel 45 (row 5, col 5) and the quad's electrode 2 repeat one count
    while the rest of the board shows noise: stale after 50 frames, so in
    150 of the 200 frames /health looks at."""
    grid, quad = GRID.copy(), QUAD.copy()
    grid[45], quad[2] = GRID[45] * 1.02, QUAD[2] * 1.1
    rng = np.random.default_rng(3)
    service = TactileService("sim://")
    now = time.time()
    feed(service, rng, 0, 150, GRID, QUAD, now - 2.0)
    stuck = b"".join(encode_frame(FrameType.GRID, 0, i, i * 1000, np.where(np.arange(64) == 45, grid, grid + rng.normal(
        0, 500, 64)).astype("<u4").tobytes()) + encode_frame(FrameType.QUAD, 1, i, i * 1000, np.where(
            np.arange(4) == 2, quad, quad + rng.normal(0, 500, 4)).astype("<u4").tobytes()) for i in range(150, 350))
    frames = service.pipeline.feed(stuck, now)
    assert sum("stale" in f.flags for f in frames if f.sensor.id == 0) == 150
    report = health_report(service)
    assert report["sensors"]["0"]["faulty_channels"] == {"stale": [45]}
    assert report["sensors"]["1"]["faulty_channels"] == {"stale": [2]}
    assert ("sensor 0: taxels 45 (row 5, col 5) had a stale reading (its converter repeats one count: null) in "
            f"most of the last 1 s's frames: {DEAD}") in report["problems"]
    assert report["status"] == "degraded"


def test_an_implausible_channel_is_named_out_of_range_and_a_brief_one_is_not():
    """Taxel 9 and the quad's electrode 3 read 3x their zero (ΔC/C0 = 2,
    past the plausible top of about 1): null, out_of_range. In 40 of 100
    frames (under the half the rule wants) they are not named."""
    grid, quad = GRID.copy(), QUAD.copy()
    grid[9], quad[3] = GRID[9] * 3, QUAD[3] * 3
    report = faulty_after(grid, quad)
    assert report["sensors"]["0"]["faulty_channels"] == {"out_of_range": [9]}
    assert report["sensors"]["1"]["faulty_channels"] == {"out_of_range": [3]}
    assert "sensor 1: electrodes 3 (row 1, col 1) had an implausible reading (null) in most of the last 1 s's " \
           f"frames: {DEAD}" in report["problems"]
    rng = np.random.default_rng(4)
    service = TactileService("sim://")
    now = time.time()
    feed(service, rng, 0, 150, GRID, QUAD, now - 2.0)
    feed(service, rng, 150, 60, GRID, QUAD, now - 0.5)
    feed(service, rng, 210, 40, grid, quad, now)
    report = health_report(service)
    assert report["sensors"]["0"]["faulty_channels"] == {} == report["sensors"]["1"]["faulty_channels"]
    assert report["problems"] == ["link down"]  # sim:// is not started here


def test_a_sensor_tared_under_load_on_every_taxel_says_to_lift_it_and_tare_again():
    """A calibration that measured C0 (table 1's, the counts above), a tare
    under 5 % more on all 64 taxels (past the 2 % a common temperature shift
    may move them), then let go: each taxel's zero is the calibration's C0
    and every frame is flagged loaded_at_tare."""
    rng = np.random.default_rng(5)
    service = TactileService("sim://")
    pipeline = service.pipeline
    now = time.time()
    feed(service, rng, 0, 150, GRID, QUAD, now - 3.0)
    pipeline.set_calibration(pipeline.interpreter.sensors[0], {"sensitivity_pct_per_N": [1.25] * 64,
                                                               "c0_pF": (GRID / 1e6).tolist()})
    pipeline.tare(0)  # its last reading is unloaded: taken; the load comes while it tares
    feed(service, rng, 150, 150, GRID * 1.05, QUAD, now - 2.0)
    feed(service, rng, 300, 100, GRID, QUAD, now)
    assert pipeline.reconstructor.loaded_at_tare(0) == list(range(64))
    report = health_report(service)
    assert report["sensors"]["0"]["faulty_channels"] == {"loaded_at_tare": list(range(64))}
    assert "sensor 0: all 64 taxels had been loaded when tared (its zero is the calibration's C0, or the one it had " \
        "before the service restarted or it left its address) in most of the " \
        "last 1 s's frames: lift the load and tare it again " \
        f"(POST /sensors/{report['sensors']['0']['board']}/0/tare)" in report["problems"]
    assert report["status"] == "degraded"


def described(info: bytes) -> TactileService:
    """A service fed the INFO ``info``, then 150 scans of sensors 0 (grid) and 1 (quad)."""
    service = TactileService("sim://")
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, info), time.time())
    feed(service, np.random.default_rng(6), 0, 150, GRID, QUAD, time.time())
    return service


def test_a_sensor_the_info_describes_twice_is_said_so_not_unlisted():
    """An INFO that lists sensor 0 as a grid and as a quad: it is left
    undescribed, its frames flow, and /health said "the board's INFO does
    not list it"; the log says why, and now /health does too."""
    service = described(b'{"board": "tmux", "serial": "TMX-2", "sensors": [{"id": 0, "kind": "grid", "rows": 8, '
                        b'"cols": 8}, {"id": 0, "kind": "quad"}, {"id": 1, "kind": "quad"}, {"id": 2, "kind": "thermo"}]}')
    report = health_report(service)
    assert report["sensors"]["0"]["not_in_info"] is True and report["sensors"]["1"]["not_in_info"] is False
    assert report["sensors"]["0"]["info_problem"] == "describes it twice, differently"
    assert service.pipeline.interpreter.undescribed == {0: "describes it twice, differently",
                                                        2: "gives it a kind this service does not know ('thermo')"}
    assert "sensor 0 sends data but the board's INFO describes it twice, differently (its shape is taken from its " \
           "frames)" in report["problems"]
    assert not any("does not list" in p for p in report["problems"])


def test_a_sensor_described_with_a_shape_no_grid_has_and_a_refused_info_are_said():
    """Sensor 2 described as a 0x4 grid: set aside (the whole INFO was refused
    and every frame of the board rejected as unknown_shape, /health ok); the
    others read. Then an INFO with a field of the wrong type: refused, said."""
    service = described(b'{"board": "tmux", "serial": "TMX-3", "sensors": [{"id": 0, "kind": "grid", "rows": 8, '
                        b'"cols": 8}, {"id": 1, "kind": "quad"}, {"id": 2, "kind": "grid", "rows": 0, "cols": 4}, '
                        b'{"id": 3, "kind": "thermo"}]}')
    report = health_report(service)
    assert sorted(report["sensors"]) == ["0", "1"] and report["rejected"]["unknown_shape"] == 0
    assert report["problems"] == ["link down",  # sim:// is never started here
                                  "sensor 2: the board's INFO gives it a shape no grid frame can have (rows=0, cols=4: "
                                  "each 1 or more, at most 256 channels); its frames are read only where their size "
                                  "tells an 8x8 grid or a quad"]
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, b'{"board": "tmux", "rate_hz": "fast"}'), time.time())
    assert "the board's last INFO was refused (INFO field 'rate_hz' has the wrong type: 'fast'); the description " \
           "before it stays in force" in health_report(service)["problems"]
