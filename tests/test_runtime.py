"""The running service's hand-off from the reading thread to the event loop."""
import asyncio
import threading
import time

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimGrid, SimQuad
from service import runtime
from service.runtime import TactileService


def test_cheap_sensors_are_published_first_and_every_sensor_stays_in_order():
    data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1), SimGrid(2)], scene="press"), 0.4)
    service = TactileService("sim://")
    service._loop = loop = asyncio.new_event_loop()
    batches = []
    service.pipeline.listeners.append(lambda frames: batches.append([(f.sensor.id, f.seq) for f in frames]))
    half = len(data) // 2
    for part in (data[:half], data[half:]):  # two reads, each drained on its own
        service._received(part, time.time())
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
    service = TactileService("sim://")
    service._loop = loop = asyncio.new_event_loop()
    batches = []
    service.pipeline.listeners.append(lambda frames: batches.append([(f.sensor.id, f.seq) for f in frames]))
    half = len(data) // 2
    for part in (data[:half], data[half:]):  # the second read is drained before the loop turns
        service._received(part, time.time())
        service._drain()
    loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    assert [{sid for sid, _ in batch} for batch in batches] == [{1}, {1}, {0}]  # both quads, then all grids at once
    grid_seqs = [seq for sid, seq in batches[2]]
    assert grid_seqs == list(range(grid_seqs[0], grid_seqs[0] + 400))


def test_a_batched_send_lets_a_read_waiting_and_its_unbatched_frames_go_first():
    import numpy as np

    from service.fanout.hub import Outgoing, Subscriber
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    earlier = ForceFrame(SensorInfo(1, "quad", 2, 2), 0, 0, time.time(), np.zeros(3), np.ones(4), [], "full")
    data, _ = capture(BoardConfig(sensors=[SimQuad(1)], scene="press"), 0.2)
    service = TactileService("sim://")
    order = []

    async def scenario():
        service._loop = asyncio.get_running_loop()
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
        dashboard._offer([Outgoing(earlier)])  # the batched sender is due first ...
        service._received(data, time.time())  # ... when a read comes in
        await asyncio.wait_for(asyncio.gather(*tasks), 1.0)

    asyncio.run(scenario())
    assert order == ["unbatched", "batched"]
    assert service.pipeline.decoder.counters.frames > 0 and not service._inbox


def test_reads_wait_when_the_loop_falls_behind_instead_of_piling_up():
    service = TactileService("sim://?scene=idle")
    service._loop = asyncio.new_event_loop()  # not running yet: nothing drains
    chunk = bytes(1 << 16)
    posted = []

    def reader():
        for _ in range(2 * runtime.INBOX_LIMIT_BYTES // len(chunk)):
            service._received(chunk, time.time())
            posted.append(1)

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    time.sleep(0.3)
    assert thread.is_alive() and service._inbox_bytes <= runtime.INBOX_LIMIT_BYTES + len(chunk)
    held = len(posted)
    service._loop.run_until_complete(asyncio.sleep(0.05))  # the loop drains: the reader goes on
    thread.join(5)
    assert not thread.is_alive() and len(posted) > held
    service._loop.run_until_complete(asyncio.sleep(0.05))  # and the rest
    service._loop.close()
    assert service._inbox_bytes == 0  # nothing lost on the way: every byte reached the decoder
    assert service.pipeline.decoder.counters.bytes_discarded == 2 * runtime.INBOX_LIMIT_BYTES  # zeros are no frames
