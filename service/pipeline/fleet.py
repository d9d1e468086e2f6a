"""All pipelines of a service (:class:`FleetProcessor`): routing, admission limits, cross-IMU checks,
status and checkpoints."""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable, Collection, Iterator, Sequence
from typing import Any

from estimators.conventions import (
    Triad,
)
from estimators.coverage import Check, CheckCoverage
from estimators.cross_imu_norm import MIN_RATE_HZ
from estimators.nominal_passport import SensorClass, nominal_passport
from estimators.passport import Passport, check_references
from estimators.stream_validity import (
    CrossImuMonitor,
    CrossImuReport,
    ValidityLimits,
)
from protocols.events import (
    Event,
    ImuState,
    ImuStatus,
    Predicate,
    Status,
    StreamCause,
    make_event,
)
from protocols.frames import SampleBatch
from protocols.gnss_frames import GnssFrame
from service.pipeline.imu_pipeline import ImuPipeline, join_batches, split_batch
from service.pipeline.norm_check import NormBlockSink, VehicleNorm
from service.pipeline.options import (
    RECOVERED_SEVERITY,
    SEVERITY,
    PipelineOptions,
)
from service.pipeline.thrust_axis import THRUST_CONFIG, ThrustAxisCheck

PassportLookup = Callable[[str, int], Passport | None]
"""``(vehicle, imu) -> Passport``; raises ``ValueError`` (e.g. ``PassportStoreError``) with the reason."""


def _cross_imu_event(
    vehicle: str,
    report: CrossImuReport,
    limits: ValidityLimits,
    scalar_note: str,
    *,
    epoch: int,
    clock_offset_s: float = 0.0,
) -> Event:
    # The bins are on the reference IMU's clock: the event is on its own IMU's, as its others are.
    t_s = report.bin_start_s + limits.cross_imu_window_s + clock_offset_s
    accel_ratio = report.accel_dev_mps2 / limits.cross_imu_accel_mps2
    gyro_ratio = report.gyro_dev_rps / limits.cross_imu_gyro_rps
    if accel_ratio >= gyro_ratio:
        triad, value, limit, unit = (
            Triad.ACCEL,
            report.accel_dev_mps2,
            limits.cross_imu_accel_mps2,
            "m/s^2",
        )
    else:
        triad, value, limit, unit = (
            Triad.GYRO,
            report.gyro_dev_rps,
            limits.cross_imu_gyro_rps,
            "rad/s",
        )
    others = ",".join(f"IMU{i}" for i in report.others)
    if report.consistent:
        text = f"{vehicle} IMU{report.imu}: agrees again with {others} [cross_imu]"
        return make_event(vehicle=vehicle, imu=report.imu, t_s=t_s, predicate=Predicate.CROSS_IMU, cause=StreamCause.RECOVERED,
                          severity=RECOVERED_SEVERITY, triad=triad, estimate=value, tolerance=limit, unit=unit, text=text, epoch=epoch)  # fmt: skip
    word = "accelerometer" if triad is Triad.ACCEL else "gyro"
    text = f"{vehicle} IMU{report.imu} {word}: disagrees with {others} by {value:.3g} {unit} (limit {limit:.3g}) [cross_imu]"
    if scalar_note:
        text += f"; scalar checks: {scalar_note}"
    return make_event(vehicle=vehicle, imu=report.imu, t_s=t_s, predicate=Predicate.CROSS_IMU, cause=StreamCause.DISAGREEMENT,
                      severity=SEVERITY[Predicate.CROSS_IMU], triad=triad, estimate=value, tolerance=limit, unit=unit, text=text, epoch=epoch)  # fmt: skip


def _norm_too_slow(rate0_hz: float, rate1_hz: float) -> str | None:
    """Why the cross-IMU norm check does not apply to a pair of these rates, or None
    (:data:`estimators.cross_imu_norm.MIN_RATE_HZ`)."""
    slowest = min(rate0_hz, rate1_hz)
    if slowest >= MIN_RATE_HZ:
        return None
    return (
        f"IMU samples at {slowest:.3g} Hz: snapshots that far apart cannot be paired through a "
        f"manoeuvre (the check needs {MIN_RATE_HZ:g} Hz or more)"
    )


class FleetProcessor:
    """All pipelines of a service: routing, admission limits, cross-IMU checks, status, checkpoints.

    Parameters
    ----------
    passports : passport lookup per (vehicle, IMU): the unit's own passport, or None (it has none); a
        ``ValueError`` (or a passport whose reference does not fit ``options``' gravity,
        :func:`~estimators.passport.check_references`) refuses it, reported once through
        ``on_passport_error``.
    options : pipeline options.
    on_norm_block : told every block of each vehicle's cross-IMU norm check (:mod:`service.pipeline.norm_check`).
    nominal : sensor class whose nominal passport (:func:`~estimators.nominal_passport.nominal_passport`)
        a unit without a usable passport of its own runs on (None: stream validity checks only). A
        refused entry falls back to it too: a corrupt or altered file must not switch F0 off, and the
        unit stays reported as refused (``on_passport_error``, the status). Only a passport of its own
        counts as one for the vehicle limit.
    on_pipeline_error : told ``(vehicle, imu, error)`` for each frame an IMU's chain raised on: that
        IMU starts afresh (its counters kept, ``pipeline.errors`` counted) and the others go on.
    max_vehicles : vehicles served at once; at the limit a vehicle with a passport takes the place of
        the longest idle vehicle without one (``vehicles.evicted_without_passport``, and
        ``on_evicted(evicted, admitted)`` is told), any other new vehicle is refused
        (``frames.rejected.over_vehicle_limit``).
    vehicles : vehicles served (empty: all).
    max_imus_per_vehicle : IMUs served per vehicle (frames beyond are counted).
    """

    def __init__(
        self,
        *,
        passports: PassportLookup,
        options: PipelineOptions = PipelineOptions(),
        vehicles: tuple[str, ...] = (),
        max_vehicles: int = 256,
        max_imus_per_vehicle: int = 4,
        on_passport_error: Callable[[str, int, str], None] | None = None,
        on_pipeline_error: Callable[[str, int, str], None] | None = None,
        on_evicted: Callable[[str, str], None] | None = None,
        nominal: SensorClass | None = None,
        on_norm_block: NormBlockSink | None = None,
    ):
        self.options = options
        self._on_norm_block = on_norm_block
        self.norms: dict[str, VehicleNorm] = {}
        # A vehicle's checkpointed norm check, resumed when its pair is known again (_new_norm).
        self._saved_norms: dict[str, dict[str, Any]] = {}
        self._passports = passports
        self.nominal = None if nominal is None else SensorClass(nominal)
        self._nominal_passport = (
            None
            if self.nominal is None
            else nominal_passport(self.nominal, gravity_mps2=options.gravity_mps2)
        )
        self._vehicles = frozenset(vehicles)
        self._max_vehicles = int(max_vehicles)
        self._max_imus = int(max_imus_per_vehicle)
        self._on_passport_error = on_passport_error
        self._on_pipeline_error = on_pipeline_error
        self._on_evicted = on_evicted
        # The frames routed so far when each vehicle's last one was (which vehicle idles longest).
        self._seen: dict[str, int] = {}
        self._frames_routed = 0
        self.pipelines: dict[tuple[str, int], ImuPipeline] = {}
        self.cross: dict[str, CrossImuMonitor] = {}
        self._gnss_rate: dict[str, float] = {}
        """Vehicles whose GNSS frames came, and their receivers' rate (the thrust-axis threshold)."""
        self._gnss_recent: dict[str, deque[GnssFrame]] = {}
        """Each vehicle's GNSS frames of the span a new thrust-axis check can still use."""
        self.vehicle_counters: dict[str, dict[str, int]] = {}
        self.service_counters: dict[str, int] = {}
        self._restore: Callable[[str, int], dict[str, Any] | None] | None = None
        self._on_restore_error: Callable[[str, int, str], None] | None = None
        self._restore_cross: Callable[[str], dict[str, Any] | None] | None = None
        self._on_cross_error: Callable[[str, str], None] | None = None
        # (samples, counts, timed out) of each pipeline at the last checkpoint (changed_keys).
        self._saved: dict[tuple[str, int], tuple[int, int, bool]] = {}
        self._by_vehicle: dict[str, dict[int, ImuPipeline]] = {}

    def set_restore(
        self,
        load: Callable[[str, int], dict[str, Any] | None],
        on_error: Callable[[str, int, str], None] | None = None,
        *,
        load_cross: Callable[[str], dict[str, Any] | None] | None = None,
        on_cross_error: Callable[[str, str], None] | None = None,
    ) -> None:
        """Where new pipelines take their checkpointed state from (``None``: start fresh).

        A state the pipeline cannot resume from is discarded (the unit starts fresh) and
        ``on_error(vehicle, imu, why)`` is told, so the caller can move it aside.
        ``load_cross(vehicle)`` gives a vehicle's cross-IMU state (:meth:`checkpoint_states`)
        when its first unit is admitted; one that cannot be resumed is discarded the same
        way (``on_cross_error(vehicle, why)``).
        """
        self._restore = load
        self._on_restore_error = on_error
        self._restore_cross = load_cross
        self._on_cross_error = on_cross_error

    def count_service(self, name: str, n: int = 1) -> None:
        if n:
            self.service_counters[name] = self.service_counters.get(name, 0) + int(n)

    def count_vehicle(self, vehicle: str, name: str, n: int = 1) -> None:
        if n and vehicle in self.vehicle_counters:
            c = self.vehicle_counters[vehicle]
            c[name] = c.get(name, 0) + int(n)

    def admit(self, vehicle: str, imu: int) -> ImuPipeline | None:
        """The pipeline of (vehicle, IMU), created (and restored from its checkpoint) on first use; None if refused."""
        pipe = self.pipelines.get((vehicle, imu))
        if pipe is not None:
            return pipe
        if self._vehicles and vehicle not in self._vehicles:
            self.count_service("frames.rejected.unknown_vehicle")
            return None
        known = vehicle in self.vehicle_counters
        if known and len(self._by_vehicle.get(vehicle, {})) >= self._max_imus:
            self.count_vehicle(vehicle, "frames.rejected.over_imu_limit")
            return None
        at_limit = not known and len(self.vehicle_counters) >= self._max_vehicles
        passport, note = self._passport_of(vehicle, imu)
        if at_limit and (passport is None or not self._make_room_for(vehicle)):
            self.count_service("frames.rejected.over_vehicle_limit")
            return None
        self.vehicle_counters.setdefault(vehicle, {})
        if note and self._on_passport_error is not None:
            self._on_passport_error(vehicle, imu, note)
        pipe = self._pipeline(vehicle, imu, passport, note)
        if self._restore is not None:
            state = self._restore(vehicle, imu)
            if state is not None:
                try:
                    pipe.load_state(state)
                    self.count_vehicle(vehicle, "checkpoints.restored")
                except Exception as exc:
                    pipe = self._pipeline(vehicle, imu, passport, note)
                    self.count_vehicle(vehicle, "checkpoints.discarded")
                    if self._on_restore_error is not None:
                        self._on_restore_error(vehicle, imu, f"{type(exc).__name__}: {exc}")
        self.pipelines[(vehicle, imu)] = pipe
        self._by_vehicle.setdefault(vehicle, {})[imu] = pipe
        if vehicle not in self.cross:
            self.cross[vehicle] = self._cross_monitor(vehicle)
        return pipe

    def _pipeline(
        self, vehicle: str, imu: int, passport: Passport | None, note: str
    ) -> ImuPipeline:
        """A fresh pipeline on the unit's own passport, else on the nominal one (if configured)."""
        if passport is not None or self.nominal is None:
            return ImuPipeline(
                vehicle, imu, passport=passport, options=self.options, passport_note=note
            )
        return ImuPipeline(
            vehicle,
            imu,
            passport=self._nominal_passport,
            options=self.options,
            passport_note=note,
            nominal_class=self.nominal.value,
        )

    def _passport_of(self, vehicle: str, imu: int) -> tuple[Passport | None, str]:
        """The unit's passport, or None and why not (``""`` when the lookup simply has none)."""
        try:
            passport = self._passports(vehicle, imu)
            if passport is not None:
                # A reference in other units (a passport in g) would turn every bias into a fault.
                check_references(passport, gravity_mps2=self.options.gravity_mps2)
        except ValueError as exc:
            return None, str(exc)
        return passport, ""

    def _make_room_for(self, vehicle: str) -> bool:
        """At the vehicle limit, a vehicle with a passport takes the place of the longest idle one
        without any: a flood of made-up vehicle ids (each one frame) would otherwise fill the limit
        for good and lock the fleet's real vehicles out. Whether room was made."""
        idle = [
            v
            for v, pipes in self._by_vehicle.items()
            if all(p.passport is None or p.nominal_class is not None for p in pipes.values())
        ]
        if not idle:
            return False
        victim = min(idle, key=lambda v: self._seen.get(v, -1))
        for imu_of in self._by_vehicle.pop(victim):
            del self.pipelines[(victim, imu_of)]
            self._saved.pop((victim, imu_of), None)
        self.vehicle_counters.pop(victim, None)
        self.cross.pop(victim, None)
        self.norms.pop(victim, None)
        self._seen.pop(victim, None)
        self.count_service("vehicles.evicted_without_passport")
        if self._on_evicted is not None:
            self._on_evicted(victim, vehicle)
        return True

    def _cross_monitor(self, vehicle: str) -> CrossImuMonitor:
        """The cross-IMU monitor of a vehicle's first admitted unit, resumed from its checkpoint if any."""
        limits = self.options.validity
        state = None if self._restore_cross is None else self._restore_cross(vehicle)
        if state is None:
            return CrossImuMonitor(limits=limits)
        if isinstance(state, dict) and isinstance(state.get("norm"), dict):
            self._saved_norms[vehicle] = state["norm"]
        try:
            monitor = CrossImuMonitor.from_state(state, limits=limits)
        except ValueError as exc:
            self.count_vehicle(vehicle, "checkpoints.discarded")
            if self._on_cross_error is not None:
                self._on_cross_error(vehicle, str(exc))
            return CrossImuMonitor(limits=limits)
        self.count_vehicle(vehicle, "checkpoints.restored")
        return monitor

    def process(self, batch: SampleBatch, *, arrival_s: float) -> list[Event]:
        """Route one decoded frame to its pipeline; returns the events raised."""
        events, good = self._through_pipeline(batch, arrival_s)
        return events if good is None else events + self._cross(good)

    def _through_pipeline(
        self, batch: SampleBatch, arrival_s: float
    ) -> tuple[list[Event], SampleBatch | None]:
        """The events of one frame in its pipeline and the samples it accepted (for the cross-IMU check)."""
        pipe = self.admit(batch.vehicle, batch.imu)
        if pipe is None:
            return [], None
        self._seen[batch.vehicle] = self._frames_routed = self._frames_routed + 1
        try:
            events = pipe.process(batch, arrival_s=arrival_s)
        except Exception as exc:
            self._start_afresh(pipe, exc)
            return [], None
        return events + self._thrust_imu(pipe), pipe.accepted

    def gnss(self, frame: GnssFrame) -> list[Event]:
        """A vehicle's GNSS frame into the thrust-axis check of each of its IMUs (the first makes
        them: :mod:`service.pipeline.thrust_axis`); returns the events raised."""
        if self._vehicles and frame.vehicle not in self._vehicles:
            self.count_service("gnss.rejected.unknown_vehicle")
            return []
        self._gnss_rate[frame.vehicle] = frame.rate_hz
        self.count_service("gnss.frames")
        recent = self._gnss_recent.setdefault(frame.vehicle, deque())
        recent.append(frame)
        keep_s = THRUST_CONFIG.span_s + THRUST_CONFIG.gnss_late_s
        while recent[0].t_s[-1] < frame.t_s[-1] - keep_s:
            recent.popleft()
        events: list[Event] = []
        for pipe in self._by_vehicle.get(frame.vehicle, {}).values():
            check = self._thrust_of(pipe)
            try:
                events += check.gnss(frame.t_s, frame.vel_enu_mps)
            except ValueError:
                self._thrust_restart(pipe)
        return events

    def _thrust_of(self, pipe: ImuPipeline) -> ThrustAxisCheck:
        """The pipeline's check; a new one is given the vehicle's recent GNSS frames (an IMU that
        comes after the receiver, or starts afresh, still finds the epochs its windows need)."""
        if pipe.thrust is None:
            pipe.thrust = ThrustAxisCheck(pipe.vehicle, pipe.imu, self._gnss_rate[pipe.vehicle])
            for frame in self._gnss_recent.get(pipe.vehicle, ()):
                pipe.thrust.gnss(frame.t_s, frame.vel_enu_mps)
        return pipe.thrust

    def _thrust_imu(self, pipe: ImuPipeline) -> list[Event]:
        """The samples a pipeline accepted into its thrust-axis check, when its vehicle has GNSS."""
        good = pipe.accepted
        if good is None or pipe.vehicle not in self._gnss_rate:
            return []
        try:
            return self._thrust_of(pipe).imu(good)
        except ValueError:
            self._thrust_restart(pipe)
            return []

    def _thrust_restart(self, pipe: ImuPipeline) -> None:
        """A stream the check refuses (its clock went back: a restarted source) starts it afresh."""
        pipe.thrust = None
        pipe.counters["thrust_axis.restarts"] = pipe.counters.get("thrust_axis.restarts", 0) + 1

    def process_queued(
        self,
        batches: list[SampleBatch],
        *,
        arrival_s: float,
        frames: Sequence[int] | None = None,
    ) -> list[Event]:
        """Frames taken from a queue together: the same events as :meth:`process` frame by frame, at less cost.

        The chain's cost is mostly per batch, so a run of consecutive frames of
        one IMU that :meth:`ImuPipeline.joins` goes through it as one batch
        (the per-frame counters still count frames; the scalar state an event
        of it describes is the one at the end of the run). Every other frame is
        processed alone. The frames of each IMU keep their order; IMUs are
        taken fewest queued samples first, so that an IMU of small frames (a slow
        unit, or one sample per MAVLink message) does not wait for the work of
        the large ones; IMUs without a pipeline yet come after them in the order
        of their first frame, as the admission limits take them. What is raised
        does not depend on that order. The cross-IMU check then takes the
        accepted frames one by one in the order they came, as frame-by-frame
        processing does: the IMUs it compares are the same however the frames
        were queued (an IMU whose frames were all taken first would otherwise
        run ahead of the others by the whole group).

        ``frames``: how many equal frames each batch joins (:func:`~service.pipeline.imu_pipeline.split_batch`;
        default one each), as a log reader joins them: the same events as those frames queued one
        by one. A batch of several that cannot join is taken frame by frame.
        """
        return [
            e
            for step in self.queued_steps(batches, arrival_s=arrival_s, frames=frames)
            for e in step
        ]

    def queued_steps(
        self,
        batches: list[SampleBatch],
        *,
        arrival_s: float,
        frames: Sequence[int] | None = None,
    ) -> Iterator[list[Event]]:
        """:meth:`process_queued` one IMU at a time: the events of each IMU's frames as soon as its
        frames are through, then those of the cross-IMU check (lists that may be empty).

        The events and their order are :meth:`process_queued`'s. A caller that stores each
        step's events can deliver them before the rest of the group is processed. Between
        two steps this processor must not take frames or give states to a checkpoint (the
        group's cross-IMU check comes at its end).
        """
        counts = [1] * len(batches) if frames is None else list(frames)
        groups: dict[tuple[str, int], list[tuple[int, SampleBatch, int]]] = {}
        for n, (b, f) in enumerate(zip(batches, counts, strict=True)):
            groups.setdefault((b.vehicle, b.imu), []).append((n, b, f))
        accepted: list[tuple[int, SampleBatch, int]] = []

        def order(
            item: tuple[tuple[str, int], list[tuple[int, SampleBatch, int]]],
        ) -> tuple[bool, int]:
            key, group = item
            known = key in self.pipelines
            return (not known, sum(b.n_samples for _, b, _ in group) if known else 0)

        for key, group in sorted(groups.items(), key=order):
            events: list[Event] = []
            i = 0
            while i < len(group):
                pipe = self.pipelines.get(key)
                n, first, f = group[i]
                j = i + 1
                if pipe is not None and pipe.joins(None, first, f):
                    while j < len(group) and pipe.joins(group[j - 1][1], group[j][1], group[j][2]):
                        j += 1
                elif f > 1:
                    # Taken frame by frame, as they came.
                    group[i : i + 1] = [(n, b, 1) for b in split_batch(first, f)]
                    continue
                if pipe is None or (j == i + 1 and f == 1):
                    raised, good = self._through_pipeline(first, arrival_s)
                    events += raised
                    if good is not None:
                        accepted.append((n, good, 1))
                else:
                    events += self._process_joined(pipe, group[i:j], arrival_s)
                    # Joined frames are clean: every sample of each was accepted.
                    accepted += group[i:j]
                i = j
            yield events
        cross: list[Event] = []
        for _, good, f in sorted(accepted, key=lambda item: item[0]):
            alone = len(self._by_vehicle.get(good.vehicle, {})) < 2
            for frame in [good] if f == 1 or alone else split_batch(good, f):
                cross += self._cross(frame)
        yield cross

    def _process_joined(
        self, pipe: ImuPipeline, run: list[tuple[int, SampleBatch, int]], arrival_s: float
    ) -> list[Event]:
        """Consecutive frames ``run`` (queue index, batch, frames it joins) through ``pipe`` as one batch."""
        _, last, last_frames = run[-1]
        frames = sum(f for _, _, f in run)
        self._seen[last.vehicle] = self._frames_routed = self._frames_routed + frames
        # joins() keeps a run's frames all with temperature or all without.
        joined = join_batches([b for _, b, _ in run])
        assert joined is not None
        try:
            events = pipe.process(joined, arrival_s=arrival_s, frames=frames)
        except Exception as exc:
            self._start_afresh(pipe, exc, frames=frames)
            return []
        pipe.last_batch_n = last.n_samples // last_frames
        return events + self._thrust_imu(pipe)

    def _start_afresh(self, pipe: ImuPipeline, exc: Exception, *, frames: int = 1) -> None:
        """An IMU whose chain raised on ``frames`` frames (joined ones raise together): a half-updated
        chain would refuse every later frame (a detector ahead of its positions), so the IMU starts
        afresh with its passport, keeping its counters (``pipeline.errors`` added), and
        ``on_pipeline_error`` is told once per frame lost, as frame-by-frame processing tells it.
        The other IMUs go on."""
        fresh = ImuPipeline(
            pipe.vehicle,
            pipe.imu,
            passport=pipe.passport,
            options=self.options,
            passport_note=pipe.passport_note,
            nominal_class=pipe.nominal_class,
        )
        fresh.counters = pipe.counters
        fresh.thrust = pipe.thrust
        fresh.counters["pipeline.errors"] = fresh.counters.get("pipeline.errors", 0) + 1
        self.pipelines[(pipe.vehicle, pipe.imu)] = fresh
        self._by_vehicle[pipe.vehicle][pipe.imu] = fresh
        if self._on_pipeline_error is not None:
            for _ in range(frames):
                self._on_pipeline_error(pipe.vehicle, pipe.imu, f"{type(exc).__name__}: {exc}")

    def _cross(self, good: SampleBatch) -> list[Event]:
        """Cross-IMU consistency of a frame's accepted samples (it needs a second IMU on the vehicle):
        the vector comparison of bin means, then the norm comparison in flight."""
        if len(self._by_vehicle.get(good.vehicle, {})) < 2:
            return []
        reports = self.cross[good.vehicle].add(good.imu, good.t_s, good.accel_mps2, good.gyro_rps)
        events = [
            _cross_imu_event(
                good.vehicle,
                r,
                self.options.validity,
                self._scalar_note(good.vehicle, r.imu),
                epoch=self.pipelines[(good.vehicle, r.imu)].epoch,
                clock_offset_s=self.cross[good.vehicle].clock_offsets_s.get(r.imu, 0.0),
            )
            for r in reports
        ]
        norm = self.norms.get(good.vehicle) or self._new_norm(good.vehicle)
        cross = self.cross[good.vehicle]
        # An IMU on another clock joins the norm check once its offset is taken (not_running says
        # why until then): paired by time on two clocks, its samples would meet none of the other's.
        if norm is None or cross.clock_unaligned(good.imu) is not None:
            return events
        return events + norm.add(good, cross.clock_offsets_s)

    def _new_norm(self, vehicle: str) -> VehicleNorm | None:
        """The vehicle's norm check, once its two lowest-numbered IMUs know their sample rates."""
        pipes = self._by_vehicle[vehicle]
        i0, i1 = sorted(pipes)[:2]
        rates = [pipes[i].detection for i in (i0, i1)]
        if (
            rates[0] is None
            or rates[1] is None
            or _norm_too_slow(rates[0].rate_hz, rates[1].rate_hz)
        ):
            return None
        saved = self._saved_norms.pop(vehicle, None)
        if saved is not None:
            try:
                norm = VehicleNorm.from_state(
                    vehicle,
                    saved,
                    gravity_mps2=self.options.gravity_mps2,
                    on_block=self._on_norm_block,
                )
                if norm.pair == (i0, i1):
                    self.norms[vehicle] = norm
                    return norm
                raise ValueError(
                    f"it compares IMU{norm.pair[0]} and IMU{norm.pair[1]}, not IMU{i0} and IMU{i1}"
                )
            except ValueError as exc:
                self.count_vehicle(vehicle, "checkpoints.discarded")
                if self._on_cross_error is not None:
                    self._on_cross_error(vehicle, f"cross-IMU norm: {exc}")
        norm = self.norms[vehicle] = VehicleNorm(
            vehicle,
            (i0, i1),
            min(rates[0].rate_hz, rates[1].rate_hz),
            gravity_mps2=self.options.gravity_mps2,
            on_block=self._on_norm_block,
        )
        return norm

    def norm_coverage(self, vehicle: str, imu: int) -> tuple[CheckCoverage, ...]:
        """The cross-IMU norm's coverage for ``imu`` of ``vehicle``: both channels for an IMU of the
        compared pair (not run yet, with why, before both rates are known), nothing otherwise."""
        pipes = self._by_vehicle.get(vehicle, {})
        if len(pipes) < 2 or imu not in sorted(pipes)[:2]:
            return ()
        norm = self.norms.get(vehicle)
        if norm is None:
            rates = [pipes[i].detection for i in sorted(pipes)[:2]]
            slow = (
                None
                if rates[0] is None or rates[1] is None
                else _norm_too_slow(rates[0].rate_hz, rates[1].rate_hz)
            )
            return tuple(
                CheckCoverage(
                    Check.CROSS_IMU_NORM,
                    t,
                    ran=False,
                    applies=slow is None,
                    reason=slow or "the sample rates are not measured yet",
                )
                for t in (Triad.ACCEL, Triad.GYRO)
            )
        waiting = [why for i in norm.pair if (why := self.cross[vehicle].clock_unaligned(i))]
        if waiting:
            return tuple(
                CheckCoverage(Check.CROSS_IMU_NORM, t, ran=False, reason=waiting[0])
                for t in (Triad.ACCEL, Triad.GYRO)
            )
        return norm.coverage(imu)

    def _scalar_note(self, vehicle: str, imu: int) -> str:
        pipe = self.pipelines.get((vehicle, imu))
        if pipe is None:
            return ""
        notes = [f"F0 {t.value} failing" for t, c in pipe.checks.items() if c.f0_failing]
        notes += [
            f"{t.value} {','.join(sorted(c.active))}" for t, c in pipe.checks.items() if c.active
        ]
        return "; ".join(notes) if notes else "F0 passing"

    def reject(self, vehicle: str | None, imu: int | None, reason: str) -> list[Event]:
        """A frame the decoder rejected; attributed to its IMU when the key names a served one."""
        if vehicle is None:
            self.count_service(f"frames.rejected.{reason}")
            return []
        pipe = self.pipelines.get((vehicle, imu)) if imu is not None else None
        if pipe is None:
            if vehicle in self.vehicle_counters:
                self.count_vehicle(vehicle, f"frames.rejected.{reason}")
            else:
                self.count_service(f"frames.rejected.{reason}")
            return []
        return pipe.reject_frame(reason)

    def tick(self, now_s: float) -> list[Event]:
        """Timeout checks of every pipeline."""
        events: list[Event] = []
        for key in sorted(self.pipelines):
            events += self.pipelines[key].check_timeout(now_s)
        return events

    def finish(self) -> list[Event]:
        """End of data (replay): every pipeline finalizes its pending position
        (:meth:`ImuPipeline.end_of_data`)."""
        events: list[Event] = []
        for key in sorted(self.pipelines):
            events += self.pipelines[key].end_of_data()
        return events

    def cross_not_running(self, vehicle: str, imu: int) -> str | None:
        """Why the vehicle's cross-IMU check does not compare this IMU now (its clock, its lag), or None."""
        if len(self._by_vehicle.get(vehicle, {})) < 2 or vehicle not in self.cross:
            return None
        return self.cross[vehicle].not_compared(imu)

    def vehicles(self) -> list[str]:
        return sorted(self.vehicle_counters)

    def status(
        self, vehicle: str, *, service: str, now_unix_s: float, extra: dict[str, int] | None = None
    ) -> Status:
        """The status message of one vehicle (its pipelines, its counters, the service-wide counters)."""
        # The vehicle's own pipelines only: a status period costs the fleet's size, not its square.
        pipes = [p for _, p in sorted(self._by_vehicle.get(vehicle, {}).items())]
        counters: dict[str, int] = {}
        for pipe in pipes:
            for name, n in pipe.counters.items():
                counters[f"imu{pipe.imu}.{name}"] = n
        counters.update(self.vehicle_counters.get(vehicle, {}))
        counters.update({f"service.{k}": v for k, v in self.service_counters.items()})
        counters.update(extra or {})
        imus = tuple(
            dataclasses.replace(st, coverage=st.coverage + self.norm_coverage(vehicle, st.imu))
            for st in (self._with_cross(p.status(), vehicle) for p in pipes)
        )
        return Status(
            vehicle=vehicle, service=service, t_s=now_unix_s, counters=counters, imus=imus
        )

    def _with_cross(self, st: ImuStatus, vehicle: str) -> ImuStatus:
        """An IMU's status with the cross-IMU check said when it does not run (it is a vehicle's)."""
        why = self.cross_not_running(vehicle, st.imu)
        if why is None:
            return st
        return dataclasses.replace(
            st,
            # A check that applies did not run: not ok (as the pipeline's own checks).
            state=ImuState.WARNING if st.state is ImuState.OK else st.state,
            detail="; ".join(d for d in (st.detail, f"cross-IMU not running: {why}") if d),
            coverage=(*st.coverage, CheckCoverage(Check.CROSS_IMU, None, ran=False, reason=why)),
        )

    def state_dicts(self, *, changed_only: bool = False) -> dict[str, dict[str, Any]]:
        """Checkpoint states keyed ``"<vehicle>/<imu>"`` (see :meth:`changed_keys` for ``changed_only``)."""
        keys = self.changed_keys() if changed_only else sorted(self.pipelines)
        return {f"{v}/{i}": self.pipelines[(v, i)].state_dict() for v, i in keys}

    def checkpoint_states(
        self, vehicle: str, imus: Collection[int] | None = None
    ) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None]:
        """The checkpoint of one vehicle: its units' states keyed ``"<vehicle>/<imu>"`` and its cross-IMU state.

        Taken together (no frame can come between them), so a restart resumes the units
        and the comparison between them from the same moment; the cross-IMU state is
        None for a vehicle with fewer than two units (there is nothing to compare).
        ``imus``: only these units' states (the others' saved states are still current:
        :meth:`changed_keys`); None: every unit's.
        """
        pipes = self._by_vehicle.get(vehicle, {})
        units = {
            f"{vehicle}/{imu}": pipe.state_dict()
            for imu, pipe in sorted(pipes.items())
            if imus is None or imu in imus
        }
        cross = self.cross.get(vehicle)
        if cross is None or len(pipes) < 2:
            return units, None
        state = cross.state_dict()
        norm = self.norms.get(vehicle)
        if norm is not None:
            state["norm"] = norm.state_dict()
        return units, state

    def mark_unsaved(self, keys: list[tuple[str, int]]) -> None:
        """These units' checkpoint could not be written: :meth:`changed_keys` lists them again."""
        for key in keys:
            self._saved.pop(key, None)

    def changed_keys(self, vehicles: Collection[str] | None = None) -> list[tuple[str, int]]:
        """Pipelines that took or refused a frame since the last call (an idle unit's checkpoint is still current).

        ``vehicles``: only their pipelines are looked at (and marked); None: every vehicle's.
        """
        pipes = (
            self.pipelines.items()
            if vehicles is None
            else [((v, i), p) for v in vehicles for i, p in self._by_vehicle.get(v, {}).items()]
        )
        out = []
        for key, p in sorted(pipes):
            mark = (p.n_samples, sum(p.counters.values()), p.timed_out)
            if self._saved.get(key) != mark:
                self._saved[key] = mark
                out.append(key)
        return out
