"""Sources to pipelines: Zenoh frames and MAVLink samples (joined per IMU by :class:`Coalescer`) into the
:class:`~service.pipeline.FleetProcessor`; decoder rejections counted for their IMU."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import numpy as np

from protocols._schema import SchemaError
from protocols.events import Event
from protocols.frames import FrameError, SampleBatch
from protocols.mavlink_adapter import MavlinkSource
from protocols.zenoh_adapter import (
    FrameSource,
    parse_frame_key,
)
from service.pipeline import FleetProcessor


class Coalescer:
    """Joins one-sample MAVLink batches into one batch per IMU (the pipeline's cost is per batch).

    The joined batches are numbered per (vehicle, IMU) by the coalescer itself:
    a MAVLink link has no frame numbers of its own to check.
    """

    def __init__(self) -> None:
        self._seq: dict[tuple[str, int], int] = {}

    def join(self, batches: list[SampleBatch]) -> list[SampleBatch]:
        groups: dict[tuple[str, int], list[SampleBatch]] = {}
        for b in batches:
            groups.setdefault((b.vehicle, b.imu), []).append(b)
        out = []
        for key, group in groups.items():
            seq = self._seq.get(key, 0)
            self._seq[key] = seq + 1
            temps = (
                None
                if any(b.temp_c is None for b in group)
                else np.concatenate([b.temp_c for b in group])
            )
            out.append(
                SampleBatch(
                    key[0], key[1], seq, np.concatenate([b.t_s for b in group]),
                    np.concatenate([b.accel_mps2 for b in group]), np.concatenate([b.gyro_rps for b in group]), temps,
                )
            )  # fmt: skip
        return out


COALESCE_WINDOW_S = 0.02
"""How long the MAVLink task gathers samples before running them through the pipeline (20 ms)."""
COALESCE_MAX = 256
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

    async def mavlink_frames(self, source: MavlinkSource) -> None:
        """MAVLink samples joined per IMU every :data:`COALESCE_WINDOW_S`, until the source is closed and drained."""
        loop = asyncio.get_running_loop()
        coalescer = Coalescer()
        while True:
            try:
                group = [await source.get()]
            except EOFError:
                return
            deadline = loop.time() + COALESCE_WINDOW_S
            while len(group) < COALESCE_MAX and (left := deadline - loop.time()) > 0:
                try:
                    group.append(await asyncio.wait_for(source.get(), left))
                except (TimeoutError, EOFError):
                    break
            self.process(coalescer.join(group))
            await asyncio.sleep(0)
