"""The intake: an IMU's events reach the outbox, and their delivery runs, before the rest of its group."""

from __future__ import annotations

import asyncio
import threading

from service_support import batches_of, demo_fleet

from protocols import log_rate
from protocols._schema import Reason
from protocols.events import Event
from protocols.frames import FrameError, SampleBatch
from protocols.zenoh_adapter import frame_key
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


def raising_group():
    """A fleet, and the group the service takes off its queue: the faulty IMU's raising frame, then ten
    of another IMU's; that IMU's pipeline, its last seq before the group and its last in the group."""
    faulty = list(batches_of(demo_scenario().session, vehicle=V, imu=0, batch_samples=FRAME))
    calm = demo_scenario(fault_magnitude=0.0).session
    resting = list(batches_of(calm, vehicle=V, imu=1, batch_samples=FRAME))
    k = first_raising_frame(faulty)
    f = demo_fleet()
    for b in faulty[:k]:
        assert not f.process(b, arrival_s=0.0)
    for b in resting[:k]:
        f.process(b, arrival_s=0.0)
    other = f.pipelines[(V, 1)]
    return f, [faulty[k], *resting[k : k + 10]], other, other.last_seq, resting[k + 9].seq


def test_an_imu_s_event_is_delivered_before_the_other_imus_of_its_group_are_processed():
    f, group, other, seq_before, seq_after = raising_group()

    async def scenario() -> tuple[list[Event], list[int | None], list[int | None]]:
        stored: list[Event] = []
        at_store: list[int | None] = []
        at_delivery: list[int | None] = []
        wake = asyncio.Event()

        def store(events: list[Event]) -> None:
            if events:
                stored.extend(events)
                at_store.append(other.last_seq)
                wake.set()

        async def deliver() -> None:
            await wake.wait()
            at_delivery.append(other.last_seq)

        intake = Intake(f, store=store, clock=lambda: 0.0, say=print)
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
    assert other.last_seq == seq_after


def test_the_rest_of_the_group_waits_until_the_events_are_handed_over():
    """A transport's worker thread says when it holds the events (20 ms later here): the other IMU's
    frames wait for it, so that the thread does not wait for the interpreter behind them."""
    f, group, other, seq_before, seq_after = raising_group()

    async def scenario() -> list[tuple[str, int | None]]:
        seen: list[tuple[str, int | None]] = []
        loop = asyncio.get_running_loop()

        async def handed_over() -> None:
            seen.append(("asked", other.last_seq))
            handed = asyncio.Event()
            threading.Timer(0.02, loop.call_soon_threadsafe, (handed.set,)).start()
            await handed.wait()
            seen.append(("handed", other.last_seq))

        intake = Intake(
            f,
            store=lambda events: None,
            clock=lambda: 0.0,
            say=print,
            handed_over=handed_over,
        )
        await intake.mavlink_frames(ListSource(group))  # type: ignore[arg-type]
        return seen

    seen = asyncio.run(scenario())
    assert seen == [("asked", seq_before), ("handed", seq_before)]
    assert other.last_seq == seq_after


def test_refused_frames_are_logged_a_new_reason_at_once_and_more_at_a_bounded_rate(monkeypatch):
    """Frames the decoder refused, and frames refused at admission (over the vehicle limit), were
    counted only: with no vehicle admitted there was no status either, so a fleet publishing a newer
    frame schema went unseen. The intake now says them: a new reason at once, more of the same at
    most once per LOG_PERIOD_S, with the last refusal's key and reason."""
    said: list[str] = []
    f = demo_fleet(max_vehicles=1)
    intake = Intake(f, store=lambda events: None, clock=lambda: 0.0, say=said.append)
    error = FrameError(
        Reason.UNKNOWN_VERSION, "frame schema version 2 is newer than this service's 1"
    )
    for _ in range(100):
        intake.reject(frame_key("uav-1", 0), error)
    assert len(said) == 1 and said[0].startswith("frames refused: 1 unknown_version (last decoder")
    assert "ins/uav-1/imu/0: unknown_version: frame schema version 2 is newer" in said[0]
    frames = list(batches_of(demo_scenario().session, vehicle="uav-2", imu=0, batch_samples=FRAME))
    intake.process(frames[:1])
    intake.process(
        list(batches_of(demo_scenario().session, vehicle="uav-3", imu=0, batch_samples=FRAME))[:5]
    )
    intake.reject(frame_key("uav-1", 0), error)
    # A new reason (the vehicle limit) is said at once; the 100 more of the old one wait their period.
    assert len(said) == 2 and "5 over_vehicle_limit" in said[1], said
    # The last decoder refusal is named only beside its own reason, not beside admission refusals.
    assert ("unknown_version" in said[1]) == ("last decoder refusal" in said[1])
    assert f.service_counters["frames.rejected.over_vehicle_limit"] == 5
    for _ in range(3):  # more of a reason said within the period: they wait
        intake.reject(frame_key("uav-1", 0), error)
    assert len(said) == 2
    # Then no frame comes any more: the service's status task says them once the period is over.
    now = log_rate.time.monotonic() + log_rate.LOG_PERIOD_S + 1.0
    monkeypatch.setattr(log_rate.time, "monotonic", lambda: now)
    intake.log_refusals()
    assert len(said) == 3 and said[2].startswith("frames refused: 3 unknown_version (last decoder")
