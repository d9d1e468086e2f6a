"""Sources to pipelines: Zenoh frames and MAVLink batches (the samples of :data:`COALESCE_WINDOW_S` per IMU)
into the :class:`~service.pipeline.FleetProcessor`; decoder rejections counted for their IMU."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from protocols._schema import SchemaError
from protocols.events import Event
from protocols.frames import FrameError, SampleBatch
from protocols.mavlink_adapter import MavlinkSource
from protocols.zenoh_adapter import (
    FrameSource,
    parse_frame_key,
)
from service.pipeline import FleetProcessor

COALESCE_WINDOW_S = 0.005
"""How long the MAVLink reader gathers samples after the first into one batch per IMU (5 ms: part of the
latency budget of an event, 20 ms at p99; a 1 kHz IMU then costs the pipeline 200 batches/s, not 1000)."""
COALESCE_MAX = 256
"""MAVLink samples queued per ``queue_capacity`` (a frame's worth: the queue holds that many samples)."""
QUEUED_SAMPLES_MAX = 2000
"""Samples of queued Zenoh frames taken together (2 ms of a 1 kHz IMU's chain per 1000 in one batch)."""


class Intake:
    """Frames from the sources into the fleet's pipelines; the events they raise go to ``store`` (the outbox).

    Parameters
    ----------
    fleet : the pipelines.
    store : where the events of each frame go, in one call per frame.
    clock : the monotonic clock that stamps arrivals (timeouts).
    say : where one-line notices go.
    """

    def __init__(
        self,
        fleet: FleetProcessor,
        *,
        store: Callable[[list[Event]], None],
        clock: Callable[[], float],
        say: Callable[[str], None],
    ):
        self.fleet = fleet
        self._store = store
        self._clock = clock
        self._say = say
        self._reported: set[str] = set()
        self._taken: list[SampleBatch] = []

    def reject(self, key: str, error: FrameError) -> None:
        """A frame the decoder rejected (``FrameSource``'s ``on_reject``): counted for its IMU when the key names one."""
        # A rejected frame counts against its IMU's stream after the frames received before it.
        self._process_taken()
        try:
            vehicle, imu = parse_frame_key(key)
        except SchemaError:
            vehicle, imu = None, None
        self._store(self.fleet.reject(vehicle, imu, error.reason.value))

    def process(self, batches: list[SampleBatch]) -> None:
        """Frames through their pipelines; a pipeline error skips them (counted, reported once per kind)."""
        try:
            events = self.fleet.process_queued(batches, arrival_s=self._clock())
        except Exception as exc:
            self.fleet.count_service("pipeline.errors")
            kind = f"{type(exc).__name__}: {exc}"
            if kind not in self._reported:
                self._reported.add(kind)
                first = batches[0]
                self._say(
                    f"{len(batches)} frame(s) from {first.vehicle} IMU{first.imu} seq {first.seq} on "
                    f"failed in the pipeline: {kind} (skipped, counted as pipeline.errors)"
                )
            return
        self._store(events)

    def _process_taken(self) -> None:
        """Process the frames taken off the queue so far (a rejection met while taking them comes after them)."""
        taken, self._taken = self._taken, []
        if taken:
            self.process(taken)

    async def zenoh_frames(self, source: FrameSource) -> None:
        """Every frame of the Zenoh source, until it is closed and drained."""
        await self._frames(source)

    async def mavlink_frames(self, source: MavlinkSource) -> None:
        """Every batch of the MAVLink source, until it is closed and drained."""
        await self._frames(source)

    async def _frames(self, source: FrameSource | MavlinkSource) -> None:
        async for batch in source:
            # Frames already waiting (the service is behind) are taken together, up to a
            # budget of samples that bounds the delay of the last one: consecutive frames
            # of an IMU then cost the chain one batch (FleetProcessor.process_queued).
            self._taken, n = [batch], batch.n_samples
            while n < QUEUED_SAMPLES_MAX and (more := source.get_nowait()) is not None:
                self._taken.append(more)
                n += more.n_samples
            self._process_taken()
            # Let the delivery and status tasks run between groups.
            await asyncio.sleep(0)
