"""Sources to pipelines: Zenoh frames and MAVLink batches (the samples of :data:`COALESCE_WINDOW_S` per IMU)
into the :class:`~service.pipeline.FleetProcessor`; decoder rejections counted for their IMU. Events the
outbox cannot take are held and delivered from memory (:mod:`service.outbox_writer`): detection goes on."""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Awaitable, Callable, Iterator

import numpy as np

from estimators.thrust_gnss import MAX_SPEED_MPS
from protocols._schema import Reason, SchemaError
from protocols.events import Event
from protocols.frames import FrameError, SampleBatch
from protocols.gnss_frames import GnssFrame
from protocols.log_rate import LogRate
from protocols.mavlink_adapter import MavlinkSource
from protocols.mavlink_gnss import MavlinkGnssSource
from protocols.zenoh_adapter import (
    FrameSource,
    GnssSource,
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
SPEED_REJECTED = f"speed_over_{MAX_SPEED_MPS:g}_mps"
"""The reason a GNSS epoch faster than a receiver reports is left out (replay's name for it too)."""


async def _one_turn() -> None:
    await asyncio.sleep(0)


class Intake:
    """Frames from the sources into the fleet's pipelines; the events they raise go to ``store`` (the outbox).

    Frames beyond what the sources' bounded queues hold are dropped and counted (the
    Zenoh source's new frames of the unit whose queue is full,
    :class:`protocols._handoff.FairQueues`; the MAVLink source's oldest).

    Parameters
    ----------
    fleet : the pipelines.
    store : where the events of each frame go, in one call per frame.
    clock : the monotonic clock that stamps arrivals (timeouts).
    say : where one-line notices go.
    handed_over : awaited after each IMU whose frames raised events, before the rest of the group:
        until their delivery has handed them to the transports (the service bounds the wait;
        by default one turn of the loop).
    """

    def __init__(
        self,
        fleet: FleetProcessor,
        *,
        store: Callable[[list[Event]], None],
        clock: Callable[[], float],
        say: Callable[[str], None],
        handed_over: Callable[[], Awaitable[None]] = _one_turn,
    ):
        self.fleet = fleet
        self._store = store
        self._handed_over = handed_over
        self._clock = clock
        self._say = say
        self._reported: set[str] = set()
        self._refused: dict[str, int] = {}
        self._refused_log = LogRate()
        self._last_refusal: tuple[str, str] | None = None
        self._taken: list[SampleBatch] = []
        self.mavlink_fed: set[str] = set()
        """Vehicles the MAVLink link has fed IMU samples: they own their streams, and the Zenoh source
        refuses their frames from then on (``FrameSource(refused_vehicles=…)``, one owner per stream)."""
        self.group_lock = asyncio.Lock()
        """Held while a group of frames goes through the pipelines, IMU by IMU with the loop turning between
        them (:meth:`_process_group`). Whatever else reads a unit's whole state or adds to it from the loop
        (checkpoints, the timeout checks) takes it: the group's cross-IMU check comes only at its end."""

    def reject(self, key: str, error: FrameError) -> None:
        """A frame the decoder rejected (``FrameSource``'s ``on_reject``): counted for its IMU when the key names one."""
        # A rejected frame counts against its IMU's stream after the frames received before it.
        self._process_taken()
        try:
            vehicle, imu = parse_frame_key(key)
        except SchemaError:
            vehicle, imu = None, None
        # Another input's frames are not the owner's stream: counted for the vehicle, not its IMU
        # (whose error density would see them).
        owned = error.reason is Reason.OTHER_SOURCE
        self._store(self.fleet.reject(vehicle, None if owned else imu, error.reason.value))
        reason = error.reason.value
        self._refused[reason] = self._refused.get(reason, 0) + 1
        self._last_refusal = (reason, f"{key}: {error}")
        self.log_refusals()

    def log_refusals(self) -> None:
        """Frames refused (by the decoder, or at admission: a vehicle unknown or over the limits)
        said in the log, a new reason at once and more at most once per period: the counters alone
        made a fleet-wide schema mismatch silent where no vehicle had a status yet. Called on each
        refusal, after each group, and by the service's status task (refusals that stop coming are
        still said, and the MAVLink path's admission refusals too)."""
        refused = dict(self._refused)
        for name, n in self.fleet.service_counters.items():
            if name.startswith("frames.rejected."):
                reason = name.removeprefix("frames.rejected.")
                refused[reason] = max(refused.get(reason, 0), n)
        if new := self._refused_log.due(refused):
            last = self._last_refusal
            self._say(
                "frames refused: "
                + ", ".join(f"{n} {k}" for k, n in sorted(new.items()))
                + (
                    f" (last decoder refusal {last[1]})"
                    if last is not None and last[0] in new
                    else ""
                )
                + "; counted on the status topic as frames.rejected.<reason>"
            )

    def process(self, batches: list[SampleBatch]) -> None:
        """Frames through their pipelines; a pipeline error skips them (counted, reported once per kind)."""
        for _ in self._steps(batches):
            pass

    def _steps(self, batches: list[SampleBatch]) -> Iterator[None]:
        """:meth:`process`, IMU by IMU: each IMU's events go to the outbox as soon as its frames are
        through (:meth:`FleetProcessor.queued_steps`), and a step ends after each IMU that raised any."""
        try:
            for events in self.fleet.queued_steps(batches, arrival_s=self._clock()):
                self._store(events)
                if events:
                    yield
        except Exception as exc:
            self.fleet.count_service("pipeline.errors")
            kind = f"{type(exc).__name__}: {exc}"
            # Reported once per exception type: a message naming sample numbers differs every frame.
            if type(exc).__name__ not in self._reported:
                self._reported.add(type(exc).__name__)
                first = batches[0]
                self._say(
                    f"{len(batches)} frame(s) from {first.vehicle} IMU{first.imu} seq {first.seq} on "
                    f"failed in the pipeline: {kind} (skipped, counted as pipeline.errors)"
                )

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
        await self._frames(source, owner=True)

    async def gnss_frames(
        self, source: GnssSource | MavlinkGnssSource, *, dropped_as: str = "gnss.dropped"
    ) -> None:
        """Every GNSS frame of the source (Zenoh's, or the MAVLink link's GPS_RAW_INT) into the
        thrust-axis checks, under :attr:`group_lock` (they read the IMUs' pipelines), until it is
        closed and drained; what the source dropped (its queue full) counted as ``dropped_as``;
        epochs faster than a receiver reports left out (:meth:`_receiver_speeds`)."""
        while True:
            try:
                frame = await source.get()
            except EOFError:
                return
            kept = self._receiver_speeds(frame)
            if kept is not None:
                async with self.group_lock:
                    self._store(self.fleet.gnss(kept))
            if source.dropped:
                self.fleet.service_counters[dropped_as] = source.dropped
            await asyncio.sleep(0)

    def _receiver_speeds(self, frame: GnssFrame) -> GnssFrame | None:
        """``frame`` without its epochs with a velocity component above
        :data:`~estimators.thrust_gnss.MAX_SPEED_MPS` (damaged values: the check's velocity integral
        carried one of 1e17 m/s into a false alarm), counted as ``gnss.rejected.speed_over_515_mps``
        and said once, as the decoder's refusals; None when no epoch is left. Here both sources are
        protected: a Zenoh frame's float64 carries any value, GPS_RAW_INT's speed up to 655 m/s."""
        fast = np.any(np.abs(frame.vel_enu_mps) > MAX_SPEED_MPS, axis=1)
        if not fast.any():
            return frame
        self.fleet.count_service(f"gnss.rejected.{SPEED_REJECTED}", int(fast.sum()))
        if f"gnss:{SPEED_REJECTED}" not in self._reported:
            self._reported.add(f"gnss:{SPEED_REJECTED}")
            self._say(
                f"GNSS epoch(s) left out: {frame.vehicle} seq {frame.seq}: {int(fast.sum())} with a "
                f"velocity above {MAX_SPEED_MPS:g} m/s (counted as gnss.rejected.{SPEED_REJECTED})"
            )
        if fast.all():
            return None
        return dataclasses.replace(
            frame, t_s=frame.t_s[~fast], vel_enu_mps=frame.vel_enu_mps[~fast]
        )

    def gnss_reject(self, key: str, error: FrameError) -> None:
        """A GNSS frame the decoder refused: counted as ``gnss.rejected.<reason>``, a new reason said."""
        reason = error.reason.value
        self.fleet.count_service(f"gnss.rejected.{reason}")
        if f"gnss:{reason}" not in self._reported:
            self._reported.add(f"gnss:{reason}")
            self._say(f"GNSS frame refused: {key}: {error} (counted as gnss.rejected.{reason})")

    async def _frames(self, source: FrameSource | MavlinkSource, *, owner: bool = False) -> None:
        while True:
            try:
                batch = await source.get()
            except EOFError:
                return
            if owner:
                self.mavlink_fed.add(batch.vehicle)
            # Frames already waiting (the service is behind) are taken together, up to a
            # budget of samples that bounds the delay of the last one: consecutive frames
            # of an IMU then cost the chain one batch (FleetProcessor.process_queued).
            self._taken, n = [batch], batch.n_samples
            while n < QUEUED_SAMPLES_MAX and (more := source.get_nowait()) is not None:
                self._taken.append(more)
                n += more.n_samples
            await self._process_group()
            self.log_refusals()
            # Let the delivery and status tasks run between groups.
            await asyncio.sleep(0)

    async def _process_group(self) -> None:
        """The frames taken, under :attr:`group_lock`; after each IMU that raised events the intake awaits
        ``handed_over``, so that their delivery (woken when the outbox took them) goes out before the rest
        of the group.

        Under 25 k MAVLink messages/s of four other IMUs a group is about 3 ms of the pipeline's work,
        which an event waited for in full before it was stored. A cancelled wait still finishes the
        group: frames taken off the queue are never left half processed.
        """
        taken, self._taken = self._taken, []
        async with self.group_lock:
            steps = self._steps(taken)
            try:
                for _ in steps:
                    await self._handed_over()
            finally:
                for _ in steps:
                    pass
