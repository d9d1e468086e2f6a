"""The intake: an IMU's events reach the outbox, and their delivery runs, before the rest of its group."""

from __future__ import annotations

import asyncio

from service_support import batches_of, demo_fleet

from protocols.events import Event
from protocols.frames import SampleBatch
from service.demo import DEMO_VEHICLE, demo_scenario
from service.intake import Intake

V = DEMO_VEHICLE
FRAME = 20


class ListSource:
    """Frames already queued, as a MAVLink source holds them when the service is behind."""

    def __init__(self, batches: list[SampleBatch]):
        self._batches = list(batches)

    async def get(self) -> SampleBatch:
        if not self._batches:
            raise EOFError
        return self._batches.pop(0)

    def get_nowait(self) -> SampleBatch | None:
        return self._batches.pop(0) if self._batches else None

    @property
    def queued(self) -> int:
        return len(self._batches)


def first_raising_frame(frames: list[SampleBatch]) -> int:
    f = demo_fleet()
    return next(k for k, b in enumerate(frames) if f.process(b, arrival_s=0.0))


def test_an_imu_s_event_is_delivered_before_the_other_imus_of_its_group_are_processed():
    faulty = list(batches_of(demo_scenario().session, vehicle=V, imu=0, batch_samples=FRAME))
    calm = demo_scenario(fault_magnitude=0.0).session
    resting = list(batches_of(calm, vehicle=V, imu=1, batch_samples=FRAME))
    k = first_raising_frame(faulty)
    f = demo_fleet()
    for b in faulty[:k]:
        assert not f.process(b, arrival_s=0.0)
    for b in resting[:k]:
        f.process(b, arrival_s=0.0)
    # The group the service takes off its queue: the faulty IMU's raising frame, then ten of the other's.
    group = [faulty[k], *resting[k : k + 10]]
    other = f.pipelines[(V, 1)]
    seq_before = other.last_seq

    async def scenario() -> tuple[list[Event], list[int | None], list[int | None]]:
        stored: list[Event] = []
        at_store: list[int | None] = []
        at_delivery: list[int | None] = []
        wake = asyncio.Event()

        def store(events: list[Event]) -> bool:
            if events:
                stored.extend(events)
                at_store.append(other.last_seq)
                wake.set()
            return True

        async def writable() -> bool:
            return True

        async def deliver() -> None:
            await wake.wait()
            at_delivery.append(other.last_seq)

        intake = Intake(f, store=store, writable=writable, clock=lambda: 0.0, say=print)
        delivery = asyncio.create_task(deliver())
        await intake.mavlink_frames(ListSource(group))  # type: ignore[arg-type]
        await delivery
        return stored, at_store, at_delivery

    stored, at_store, at_delivery = asyncio.run(scenario())
    assert stored[0].imu == 0
    # Stored, and delivered, while the other IMU's ten frames still waited...
    assert at_store[0] == seq_before
    assert at_delivery == [seq_before]
    # ...and those frames were all processed after.
    assert other.last_seq == resting[k + 9].seq
