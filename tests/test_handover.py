"""The live order of work: reads handed from the reading thread to the event
loop, cheap sensors published before the grids of the same reads."""
import asyncio
import threading
import time

import numpy as np

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimGrid, SimQuad
from service.fanout.hub import Outgoing, Subscriber
from service.handover import LoopHandover
from service.live_service import TactileService
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.readings import SensorInfo
from service.reconstruct import ForceFrame


def published_batches(pipeline: Pipeline) -> list[list[tuple[int, int]]]:
    batches = []
    pipeline.listeners.append(lambda frames: batches.append([(f.sensor.id, f.seq) for f in frames]))
    return batches


def test_cheap_sensors_are_published_first_and_every_sensor_stays_in_order():
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1), SimGrid(2)], scene="press"), 0.4)
    pipeline = Pipeline()
    batches = published_batches(pipeline)
    loop = asyncio.new_event_loop()
    handover = LoopHandover(pipeline.feed_reads, pipeline.link_lost, loop)
    half = len(data) // 2
    for part in (data[:half], data[half:]):  # two reads, each drained on its own
        handover.from_thread(part, time.time())
        loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    kinds = [{"grid" if sid != 1 else "quad" for sid, _ in batch} for batch in batches]
    assert kinds == [{"quad"}, {"grid"}, {"quad"}, {"grid"}]  # per read: the quad, then the grids
    published = [key for batch in batches for key in batch]
    assert len(published) == 3 * 400
    for sid in (0, 1, 2):
        seqs = [seq for s, seq in published if s == sid]
        assert seqs == list(range(seqs[0], seqs[0] + 400))


def test_a_quad_read_later_goes_out_before_grids_still_waiting():
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="press"), 0.4)
    pipeline = Pipeline()
    batches = published_batches(pipeline)
    loop = asyncio.new_event_loop()
    half = len(data) // 2
    for part in (data[:half], data[half:]):  # the second read comes before the loop turns
        pipeline.feed_reads([(part, time.time())], loop.call_soon)
    loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    assert [{sid for sid, _ in batch} for batch in batches] == [{1}, {1}, {0}]  # both quads, then all grids at once
    grid_seqs = [seq for sid, seq in batches[2]]
    assert grid_seqs == list(range(grid_seqs[0], grid_seqs[0] + 400))


def test_without_deferral_a_read_is_published_in_arrival_order_as_one_batch():
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="press"), 0.1)
    pipeline = Pipeline()
    batches = published_batches(pipeline)
    frames = pipeline.feed(data, 0.0)
    assert len(batches) == 1 and batches[0] == [(f.sensor.id, f.seq) for f in frames]
    assert [sid for sid, _ in batches[0][:4]] == [0, 1, 0, 1]  # the board's scan order, grids not held back


def test_a_batched_send_lets_a_read_waiting_and_its_unbatched_frames_go_first():
    # Received long ago: its batch is due at once.
    earlier = ForceFrame(SensorInfo(1, "quad", 2, 2), 0, 0, time.time() - 1.0, np.zeros(3), np.ones(4), [], "full")
    data, _ = capture(BoardConfig(sensors=[SimQuad(1)], scene="press"), 0.2)
    service = TactileService("sim://")
    order = []

    async def scenario():
        loop = asyncio.get_running_loop()
        service.primary.handover = LoopHandover(service.pipeline.feed_reads, service.pipeline.link_lost, loop)
        service.pipeline.listeners.append(service.hub.publish)
        controller, dashboard = Subscriber(), Subscriber(batch_ms=1.0)
        service.hub.add(controller)
        service.hub.add(dashboard)

        async def send_unbatched():
            await controller.next_message()
            order.append("unbatched")

        async def send_batched():
            await dashboard.next_message()
            await service.let_urgent_go_first()
            order.append("batched")

        tasks = [asyncio.create_task(send_batched()), asyncio.create_task(send_unbatched())]
        await asyncio.sleep(0)  # both senders wait
        dashboard.take([Outgoing(earlier)])
        await asyncio.sleep(0)  # the batch flushes: the batched sender is due first ...
        service.primary.handover.from_thread(data, time.time())  # ... when a read comes in
        await asyncio.wait_for(asyncio.gather(*tasks), 1.0)

    asyncio.run(scenario())
    assert order == ["unbatched", "batched"]
    assert service.pipeline.decoder.counters.sensor(1).frames == 200 and not service.primary.handover.pending


def test_reads_wait_when_the_loop_falls_behind_instead_of_piling_up():
    pipeline = Pipeline()
    loop = asyncio.new_event_loop()  # not running yet: nothing drains
    limit = 1 << 20
    handover = LoopHandover(pipeline.feed_reads, pipeline.link_lost, loop, limit_bytes=limit)
    chunk = bytes(1 << 16)
    posted = []

    def reader():
        for _ in range(2 * limit // len(chunk)):
            handover.from_thread(chunk, time.time())
            posted.append(1)

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    time.sleep(0.3)
    assert thread.is_alive() and handover.queued_bytes <= limit + len(chunk)
    held = len(posted)
    loop.run_until_complete(asyncio.sleep(0.05))  # the loop drains: the reader goes on
    thread.join(5)
    assert not thread.is_alive() and len(posted) > held
    loop.run_until_complete(asyncio.sleep(0.05))  # and the rest
    loop.close()
    assert handover.queued_bytes == 0  # nothing lost on the way: every byte reached the decoder
    assert pipeline.decoder.counters.bytes_discarded == 2 * limit  # zeros are no frames


def test_a_link_lost_between_reads_resets_the_decoder_at_that_point():
    data, _ = capture(BoardConfig(sensors=[SimQuad(0)], scene="idle"), 0.05)
    pipeline = Pipeline()
    loop = asyncio.new_event_loop()
    handover = LoopHandover(pipeline.feed_reads, pipeline.link_lost, loop)
    handover.from_thread(data[:-10], time.time())  # the last frame is cut by the unplug ...
    handover.link_lost()
    handover.from_thread(data[-10:], time.time())  # ... and its tail, alone, is no frame
    loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    assert pipeline.decoder.counters.sensor(0).frames == 49


def test_grids_wait_for_their_window_and_go_through_together_quads_never_wait():
    """``grid_batch_s``: the grids of reads that come within the window are
    reconstructed in one batch, the same frames as one read at a time, bit
    for bit (the tare window's frames are null whatever the batch holds);
    the quads of every read are published at once."""
    data, _ = capture(BoardConfig(scene="press", seed=6), 0.6)
    chunk = len(data) // 600  # ~1 ms of scans a read

    def run(window: float) -> tuple[list, list]:
        pipeline = Pipeline(Reconstructor(), grid_batch_s=window)
        batches: list = []
        pipeline.listeners.append(lambda frames: batches.append([(f.sensor.kind, f.seq, f.forces_N) for f in frames]))

        async def feed() -> None:
            loop = asyncio.get_running_loop()
            for start in range(0, len(data), chunk):
                pipeline.feed_reads([(data[start:start + chunk], time.time())], loop.call_soon)
                await asyncio.sleep(0.0005)
            await asyncio.sleep(window + 0.05)  # the last window closes

        asyncio.run(feed())
        grids = [b for b in batches if b[0][0] == "grid"]
        quads = [b for b in batches if b[0][0] == "quad"]
        return grids, quads

    grids_now, quads_now = run(0.0)
    grids_batched, quads_batched = run(0.010)
    assert len(grids_batched) < len(grids_now) / 3  # ~0.4 s of reads: a batch per 10 ms, not one per read
    assert len(quads_batched) >= len(quads_now) * 0.8  # quads keep going out read by read
    frames_now = [f for batch in grids_now for f in batch]
    frames_batched = [f for batch in grids_batched for f in batch]
    assert [f[1] for f in frames_batched] == [f[1] for f in frames_now]
    assert sum(not np.isnan(f[2]).all() for f in frames_now) > 0.7 * len(frames_now)
    assert all(np.array_equal(a[2], b[2], equal_nan=True) for a, b in zip(frames_now, frames_batched))
