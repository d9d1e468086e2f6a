"""The streaming chain of one IMU (package docstring): frame order, stream validity, temperature,
static detection and positions, F0, re-estimation and diagnosis, events; its status and checkpoint state."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from estimators.conventions import (
    PARAM_AXIS,
    PARAM_CAUSE,
    Cause,
    Triad,
)
from estimators.coverage import ImuCoverage
from estimators.diagnosis import Outcome, diagnose
from estimators.gross import GrossChange, GrossMonitor, gross_config
from estimators.ninepar import RecursiveNineParam
from estimators.passport import Passport
from estimators.positions import Position, PositionAccumulator
from estimators.scalar import f0_batch, persistence_samples, persistent_failure
from estimators.session import all_usable, finite_rows, plausible_rows
from estimators.stream_validity import (
    StreamValidity,
    ValidityReport,
    plausible_rate_hz,
    typical_step_s,
    typical_steps_s,
)
from estimators.temperature import to_reference_temperature
from protocols.events import (
    Event,
    EventCause,
    ImuState,
    ImuStatus,
    Predicate,
    Severity,
    StreamCause,
    event_from_finding,
    make_event,
)
from protocols.frames import SampleBatch
from service.pipeline.coverage import imu_coverage
from service.pipeline.options import (
    CLOCK_RESET_FRAMES,
    FINDING_SEVERITY,
    NOMINAL_MIN_RATE_HZ,
    PIPELINE_STATE_VERSION,
    RATE_CHECK_BLOCKS,
    RATE_CHECK_SAMPLES,
    RATE_CHECK_TOLERANCE,
    RATE_PROBE_SAMPLES,
    RECOVERED_SEVERITY,
    SEVERITY,
    TEMPERATURE_HYSTERESIS_C,
    TIME_JUMP_PERIODS,
    TRIAD_WORD,
    PipelineOptions,
    detector_config,
)
from service.pipeline.static_gate import StaticGate
from service.pipeline.triad_check import TriadCheck, f0_config, new_estimator

if TYPE_CHECKING:
    from service.pipeline.thrust_axis import ThrustAxisCheck


def _rows(batch: SampleBatch, rows: slice | np.ndarray) -> SampleBatch:
    """The samples ``rows`` (a slice or a mask) of ``batch`` as a batch of the same IMU, ``seq`` and run."""
    return SampleBatch(
        batch.vehicle, batch.imu, batch.seq, batch.t_s[rows], batch.accel_mps2[rows],
        batch.gyro_rps[rows], None if batch.temp_c is None else batch.temp_c[rows], batch.run,
    )  # fmt: skip


def split_batch(batch: SampleBatch, frames: int) -> list[SampleBatch]:
    """The ``frames`` equal frames ``batch`` joins (:func:`join_batches` of them gives it back),
    numbered up to its ``seq``."""
    size = batch.n_samples // frames
    return [
        dataclasses.replace(
            _rows(batch, slice(k * size, (k + 1) * size)), seq=batch.seq - frames + 1 + k
        )
        for k in range(frames)
    ]


def join_batches(batches: list[SampleBatch]) -> SampleBatch | None:
    """Consecutive batches of one IMU as one, numbered and of the run of the last (temperature
    only when every batch has it); None for none."""
    if not batches:
        return None
    last = batches[-1]
    temps = [b.temp_c for b in batches if b.temp_c is not None]
    return SampleBatch(
        last.vehicle, last.imu, last.seq, np.concatenate([b.t_s for b in batches]),
        np.concatenate([b.accel_mps2 for b in batches]), np.concatenate([b.gyro_rps for b in batches]),
        np.concatenate(temps) if len(temps) == len(batches) else None, last.run,
    )  # fmt: skip


@dataclass
class _Detection:
    """What an :class:`ImuPipeline` builds once the sample rate is known (it sets the detector's window)."""

    rate_hz: float
    accumulator: PositionAccumulator
    gate: StaticGate


class ImuPipeline:
    """The streaming chain of one IMU (module docstring). Small state: see :meth:`state_dict`.

    Parameters
    ----------
    vehicle, imu : the IMU.
    passport : its passport, or None (then only stream validity runs, and the status says why).
    passport_note : why there is no passport of its own (shown in the status).
    options : shared options.
    nominal_class : the sensor class when ``passport`` is that class's nominal passport
        (:mod:`estimators.nominal_passport`), not the unit's own: the status says so, and it applies
        only from :data:`~service.pipeline.options.NOMINAL_MIN_RATE_HZ` (:meth:`passport_at`).
    """

    def __init__(
        self,
        vehicle: str,
        imu: int,
        *,
        passport: Passport | None,
        options: PipelineOptions,
        passport_note: str = "",
        nominal_class: str | None = None,
    ):
        self.vehicle, self.imu = vehicle, imu
        self.passport = passport
        self.passport_note = passport_note
        self.nominal_class = nominal_class
        self.nominal_too_slow = ""  # why the nominal passport does not apply at the measured rate
        self.options = options
        self.validity = StreamValidity(limits=options.validity)
        self.detection: _Detection | None = None
        self.f0_persist = 1
        self.checks: dict[Triad, TriadCheck] = {}
        self.gross: GrossMonitor | None = None
        self._probe: list[SampleBatch] = []
        # The rate watch (_watch_rate): sample steps of the block being filled, s, and blocks off in a row.
        self._rate_steps_s = np.empty(RATE_CHECK_SAMPLES)
        self._rate_fill = 0
        self._rate_off = 0
        self.rate_changed_from_hz: float | None = None
        self.last_seq: int | None = None
        self.accepted: SampleBatch | None = None
        self.thrust: ThrustAxisCheck | None = None
        """The thrust-axis check against the vehicle's GNSS, once GNSS frames come (not checkpointed:
        after a restart it learns its noise again)."""
        self.last_t_s: float | None = None
        self.last_batch_n = 1
        self.run: int | None = (
            None  # the run id of the last accepted frame (None: its source gives none)
        )
        # Frames that do not follow the stream but may start a new one (_restarted): held, not yet rejected.
        self._restart_probe: list[tuple[SampleBatch, float, str]] = []
        self._jumped_from_t_s: float | None = None  # the stream's time before its last jump forward
        self.timed_out = False
        self.stale: set[tuple[str, str]] = set()
        self.error_dense = False
        self.n_samples = 0
        self.n_positions = 0
        self.temperature_compensated = False
        self.counters: dict[str, int] = {}

    # ------------------------------------------------------------------ helpers

    def _count(self, name: str, n: int = 1) -> None:
        if n:
            self.counters[name] = self.counters.get(name, 0) + int(n)

    @property
    def epoch(self) -> int:
        """The source's run: the new runs seen (checkpointed with the counters). It enters the ids of
        the unit's events, so a fault at the same time since boot after a reboot is a new event."""
        return self.counters.get("new_runs", 0)

    def _event(
        self, t_s: float, predicate: Predicate, cause: EventCause, severity: Severity, **kw: Any
    ) -> Event:
        return make_event(
            vehicle=self.vehicle,
            imu=self.imu,
            t_s=t_s,
            predicate=predicate,
            cause=cause,
            severity=severity,
            epoch=self.epoch,
            **kw,
        )

    def passport_at(self, rate_hz: float) -> Passport | None:
        """The passport the chain runs against at ``rate_hz``: a nominal one only from
        :data:`NOMINAL_MIN_RATE_HZ`. Below it the static detector's window holds too few samples to tell
        rest from a steady turn, whose |a| is not g: F0 against a class's shell would fail in flight;
        the unit's own passport (its noise, its tolerances) is its operator's statement and applies."""
        if self.nominal_class is not None and rate_hz < NOMINAL_MIN_RATE_HZ:
            return None
        return self.passport

    def _new_detection(self, rate_hz: float) -> _Detection:
        detector = detector_config(self.options, self.passport_at(rate_hz), rate_hz)
        return _Detection(
            rate_hz,
            PositionAccumulator(
                rate_hz=rate_hz, detector_config=detector, config=self.options.positions
            ),
            StaticGate(self.options.positions.trim_samples(rate_hz)),
        )

    def _setup(self, rate_hz: float) -> _Detection:
        """Size the detector and F0 for ``rate_hz``; a triad already checked keeps its diagnosis."""
        self.f0_persist = persistence_samples(self.options.f0_persistence_s, rate_hz)
        self.detection = self._new_detection(rate_hz)
        self._rate_fill = self._rate_off = 0
        gross = gross_config(
            self.passport,
            rate_hz=rate_hz,
            gravity_mps2=self.options.gravity_mps2,
            gravity_rel_err=self.options.gravity_rel_err,
            false_alarm_prob=self.options.false_alarm_probability,
        )
        # A new rate keeps the raised failures, runs and counts; the windows start again at its length.
        self.gross = (
            GrossMonitor(gross)
            if self.gross is None
            else GrossMonitor.from_state(gross, self.gross.state_dict())
        )
        passport = self.passport_at(rate_hz)
        self.nominal_too_slow = (
            f"sampled at {rate_hz:.3g} Hz, too slow to tell rest from steady flight "
            f"(nominal passport from {NOMINAL_MIN_RATE_HZ:g} Hz)"
            if passport is None and self.passport is not None
            else ""
        )
        if passport is None:
            self.checks.clear()
        else:
            for triad, tp in passport.triads.items():
                cfg, lam, note = f0_config(tp, self.options, rate_hz)
                check = self.checks.get(triad)
                if check is None:
                    self.checks[triad] = TriadCheck(
                        tp, cfg, lam, note, new_estimator(tp, self.options)
                    )
                else:
                    check.f0, check.lambda0, check.f0_note = cfg, lam, note
                    check.f0_run, check.f0_run_onset = 0, None
        return self.detection

    def _watch_rate(self, prev_t_s: float | None, t_s: np.ndarray) -> tuple[int, float] | None:
        """Measure the rate again over every :data:`RATE_CHECK_SAMPLES` steps of the samples at
        ``t_s`` (s, after ``prev_t_s``); returns where the detector must be re-sized, if anywhere:
        the index of the sample that completes :data:`RATE_CHECK_BLOCKS` blocks in a row off by
        more than :data:`RATE_CHECK_TOLERANCE`, and the rate of the last, Hz. The steps after that
        sample are not taken: the caller re-sizes there and hands the rest over again, so the
        chain is cut at the same sample however the stream is framed.

        The probe sized the detector from the first samples only: a start-up burst at another
        spacing, or a rate changed in flight, left every later window the wrong length and fault
        detection silently off. A block's rate is from its :func:`typical_step_s`; the probe's
        median, within :data:`RATE_CHECK_TOLERANCE` of it, is kept.
        """
        det = self.detection
        if det is None:
            return None
        first = 0 if prev_t_s is not None else 1  # the first sample whose step is known
        if t_s.size <= first:
            return None
        steps = np.empty(t_s.size - first)
        steps[0] = t_s[first] - (t_s[0] if prev_t_s is None else prev_t_s)
        np.subtract(t_s[first + 1 :], t_s[first:-1], out=steps[1:])
        block, fill = self._rate_steps_s, self._rate_fill
        need = RATE_CHECK_SAMPLES - fill
        if steps.size < need:
            block[fill : fill + steps.size] = steps
            self._rate_fill += steps.size
            return None
        block[fill:] = steps[:need]
        n_full = (steps.size - need) // RATE_CHECK_SAMPLES
        full = steps[need : need + n_full * RATE_CHECK_SAMPLES]
        # The blocks this batch completes, all at once (typical_steps_s: each block's typical_step_s).
        rates = (
            1.0
            / np.concatenate(
                [[typical_step_s(block)], typical_steps_s(full.reshape(n_full, RATE_CHECK_SAMPLES))]
            )
        ).tolist()
        limits = self.options.validity
        for k, rate_hz in enumerate(rates):
            if abs(rate_hz / det.rate_hz - 1.0) <= RATE_CHECK_TOLERANCE or not (
                limits.min_rate_hz <= rate_hz <= limits.max_rate_hz
            ):
                self._rate_off = 0
                continue
            self._rate_off += 1
            if self._rate_off >= RATE_CHECK_BLOCKS:
                self._rate_fill = 0
                return first + need - 1 + k * RATE_CHECK_SAMPLES, rate_hz
        rest = steps[need + full.size :]
        block[: rest.size] = rest
        self._rate_fill = rest.size
        return None

    def _resize(self, rate_hz: float) -> list[Event]:
        """Size the detector and F0 for the stream's new rate (:meth:`_watch_rate`)."""
        assert self.detection is not None
        self._count("rate_changes")
        self.rate_changed_from_hz = self.detection.rate_hz
        # The pending position ends with the old sizing; the diagnosis keeps what it has.
        events = self.finish()
        self._setup(rate_hz)
        return events

    def _chain(self, batch: SampleBatch, prev_t_s: float | None) -> list[Event]:
        """The chain over ``batch`` (samples after ``prev_t_s``, s), re-sized where the rate watch says."""
        events: list[Event] = []
        while (cut := self._watch_rate(prev_t_s, batch.t_s)) is not None:
            k, rate_hz = cut
            head = batch if k + 1 == batch.n_samples else _rows(batch, slice(0, k + 1))
            assert self.detection is not None
            events += self._temperature_range(head) + self._run(self.detection, head)
            events += self._resize(rate_hz)
            if head is batch:
                return events
            batch, prev_t_s = _rows(batch, slice(k + 1, None)), float(head.t_s[-1])
        assert self.detection is not None
        return events + self._temperature_range(batch) + self._run(self.detection, batch)

    # ------------------------------------------------------------------ input

    def reject_frame(self, reason: str) -> list[Event]:
        """A frame of this IMU that the decoder rejected: counted, and its samples enter the error density."""
        self._count(f"frames.rejected.{reason}")
        return self._validity_events(
            self.validity.record_rejected(self.last_batch_n), self.last_t_s or 0.0
        )

    def process(self, batch: SampleBatch, *, arrival_s: float, frames: int = 1) -> list[Event]:
        """Run one frame through the chain; returns the events it raised (module docstring).

        ``frames`` > 1: the batch joins that many consecutive clean frames, the
        last one numbered ``batch.seq`` (:meth:`FleetProcessor.process_queued`).
        Afterwards :attr:`accepted` holds the samples that went in (None if none did).
        """
        self.accepted = None
        events: list[Event] = []
        if batch.run is not None and self.run is not None and batch.run != self.run:
            # The publisher says it started again: a new run from this frame on, nothing to probe.
            events += self._reject_probe() + self._source_restart(new_run=True)
        if self.timed_out:
            self.timed_out = False
            events.append(
                self._event(
                    float(batch.t_s[0]),
                    Predicate.TIMEOUT,
                    StreamCause.RECOVERED,
                    RECOVERED_SEVERITY,
                    unit="s",
                )
            )
        # A finite value beyond any sensor (one corrupt sample of 1e300 rad/s) is no sample either:
        # its square overflows the detector's sums and the attitude's sine.
        plausible = plausible_rows(batch.accel_mps2, batch.gyro_rps)
        usable = finite_rows(batch.t_s, batch.accel_mps2, batch.gyro_rps, batch.temp_c) & plausible
        keep = self._ordered(batch, usable)
        problem = self._order_problem(batch, keep)
        if problem is not None:
            if not self._continues_probe(batch):
                events += self._reject_probe()
            self._restart_probe.append((batch, arrival_s, problem))
            if len(self._restart_probe) < CLOCK_RESET_FRAMES:
                return events
            held = self._restart_probe
            new_run = self._new_run(held[0][0])
            events += self._source_restart(new_run=new_run)
            # The held frames are the new stream's first: taken, not counted as rejected; the
            # cross-IMU check sees all they gave.
            taken: list[SampleBatch] = []
            for b, arrival, _ in held:
                events += self.process(b, arrival_s=arrival)
                taken += [] if self.accepted is None else [self.accepted]
            self.accepted = join_batches(taken)
            return events
        events += self._reject_probe()
        first_seq = batch.seq - frames + 1
        if self.last_seq is not None and first_seq > self.last_seq + 1:
            self._count("frames.missing", first_seq - self.last_seq - 1)
        self.last_seq = batch.seq
        if batch.run is not None:
            self.run = batch.run
        self._count("frames.accepted", frames)
        if self.last_t_s is not None and batch.t_s[keep][0] - self.last_t_s > self._jump_s():
            self._count("time_jumps")
            self._jumped_from_t_s = self.last_t_s
        self._count("samples.rejected.implausible_value", int((~plausible).sum()))
        self._count("samples.rejected.out_of_order_or_non_finite", int((~keep & plausible).sum()))
        report = self.validity.update(
            accel_mps2=batch.accel_mps2,
            gyro_rps=batch.gyro_rps,
            bad=~keep,
            arrival_s=arrival_s,
            t_s=batch.t_s,
        )
        t_k = batch.t_s[keep]
        events += self._validity_events(report, float(t_k[-1]))
        good = batch if keep.all() else _rows(batch, keep)
        self.accepted = good
        prev_t_s, self.last_t_s = self.last_t_s, float(t_k[-1])
        self.last_batch_n = batch.n_samples
        self.n_samples += int(t_k.size)
        self._count("samples.accepted", int(t_k.size))
        if self.detection is None:
            self._probe.append(good)
            if sum(b.n_samples for b in self._probe) < RATE_PROBE_SAMPLES:
                return events
            batches, self._probe = self._probe, []
            # Exactly the first RATE_PROBE_SAMPLES, and the rate watch from the next one on: the
            # same sizing and the same cuts however the stream is framed.
            rate_hz = plausible_rate_hz(
                np.concatenate([b.t_s for b in batches])[:RATE_PROBE_SAMPLES],
                self.options.validity,
            )
            if rate_hz is None:
                # Counted, and the next frames probe afresh: a stream at an implausible rate
                # never sizes the detector (ValidityLimits.min_rate_hz/max_rate_hz).
                self._count("samples.rejected.implausible_rate", sum(b.n_samples for b in batches))
                return events
            det = self._setup(rate_hz)
            seen, prev_t_s = 0, None
            for b in batches:
                n_head = min(b.n_samples, max(0, RATE_PROBE_SAMPLES - seen))
                seen += b.n_samples
                if n_head:
                    head = b if n_head == b.n_samples else _rows(b, slice(0, n_head))
                    events += self._temperature_range(head) + self._run(det, head)
                    prev_t_s = float(head.t_s[-1])
                if n_head < b.n_samples:
                    events += self._chain(
                        b if n_head == 0 else _rows(b, slice(n_head, None)), prev_t_s
                    )
                    prev_t_s = float(b.t_s[-1])
            return events
        return events + self._chain(good, prev_t_s)

    def joins(self, prev: SampleBatch | None, batch: SampleBatch, frames: int = 1) -> bool:
        """Whether ``batch`` may join one batch with the frames before it (``prev``: the last of them; None: the first).

        ``frames`` > 1: ``batch`` joins that many equal frames (:func:`split_batch`), each of which must join.

        Only where joining changes nothing but the cost: the chain is set up and
        in no timeout, error-density or restart episode, and the frame is of the same run, finite,
        in order, the next ``seq`` and within a time jump of the previous one, so
        every per-frame check would have passed it. The chain itself (detector,
        positions, F0, diagnosis) gives the same results however the stream is cut.
        """
        if self.detection is None or self.timed_out or self.error_dense or self._restart_probe:
            return False
        last_seq, last_t_s = (
            (self.last_seq, self.last_t_s) if prev is None else (prev.seq, float(prev.t_s[-1]))
        )
        if prev is not None and (prev.temp_c is None) != (batch.temp_c is None):
            return False
        if batch.run != (self.run if prev is None else prev.run):
            return False
        t = batch.t_s
        size = t.size // frames
        # Where one joined frame ends and the next starts: within a time jump, as between frames.
        starts = t[size::size]
        return (
            (last_seq is None or batch.seq - frames + 1 == last_seq + 1)
            and (last_t_s is None or last_t_s < t[0] <= last_t_s + self._jump_s())
            and bool((t[1:] > t[:-1]).all())
            and bool((starts - t[size - 1 : -1 : size] <= self._jump_s()).all())
            and all_usable(batch.t_s, batch.accel_mps2, batch.gyro_rps, batch.temp_c)
        )

    def _jump_s(self) -> float:
        """A step forward in sample time larger than this is a time jump (data lost or a clock step)."""
        return TIME_JUMP_PERIODS / self.detection.rate_hz if self.detection else 1.0

    def _ordered(self, batch: SampleBatch, usable: np.ndarray) -> np.ndarray:
        """(N,) samples that are ``usable`` (finite and plausible) and later than every usable sample
        before them (this frame and the last accepted)."""
        t = batch.t_s
        start = -math.inf if self.last_t_s is None else self.last_t_s
        prev_max = np.maximum.accumulate(
            np.concatenate([[start], np.where(usable, t, -math.inf)[:-1]])
        )
        return usable & (t > prev_max)

    def _order_problem(self, batch: SampleBatch, ordered: np.ndarray) -> str | None:
        """Why this frame cannot follow the last accepted one (a counter name), or None (``ordered``: :meth:`_ordered`)."""
        last = self.last_seq
        if last is not None and batch.seq == last:
            return "frames.duplicate"
        if last is not None and batch.seq < last:
            return "frames.out_of_order"
        if not ordered.any():
            return "frames.rejected.no_new_samples"
        return None

    def _continues_probe(self, batch: SampleBatch) -> bool:
        """Whether ``batch`` continues the held frames as one consistent stream (consecutive ``seq``,
        increasing time): :data:`CLOCK_RESET_FRAMES` such frames that do not follow the stream are taken
        as a restart of its source (seq and clock from scratch, or a clock stepped)."""
        if not self._restart_probe:
            return True
        last = self._restart_probe[-1][0]
        return (
            batch.seq == last.seq + 1
            and float(batch.t_s[0]) > float(last.t_s[-1])
            and bool(np.all(np.diff(batch.t_s) > 0))
        )

    def _reject_probe(self) -> list[Event]:
        """The held frames formed no new stream: rejected as they would have been on arrival."""
        events: list[Event] = []
        held, self._restart_probe = self._restart_probe, []
        for b, _, problem in held:
            self._count(problem)
            events += self._validity_events(
                self.validity.record_rejected(b.n_samples), self.last_t_s or 0.0
            )
        return events

    def _new_run(self, first: SampleBatch) -> bool:
        """Whether a restarted source whose first frame is ``first`` began a new run: its ``seq`` went
        back, or its time went back to before where the stream was ahead of its last jump forward.
        A stream that goes on from there (one frame or a clock stamped ahead, then the clock as
        before) is the same run on a stepped clock."""
        last_seq = self.last_seq if self.last_seq is not None else -1
        resumes_at_s = self._jumped_from_t_s if self._jumped_from_t_s is not None else math.inf
        return first.seq < last_seq or float(first.t_s[0]) <= resumes_at_s

    def _source_restart(self, *, new_run: bool) -> list[Event]:
        """The source started again. ``new_run``: a new run of the vehicle or publisher (its time or
        ``seq`` went back, :meth:`_new_run`, or its frames carry a new run id): positions and diagnosis start from here, as
        for a unit switched on. Otherwise only the clock stepped: the stream is followed on the new
        clock, and the diagnosis keeps the positions it has."""
        self._count("source_restarts")
        self._restart_probe = []
        self._jumped_from_t_s = None
        self.last_seq = None
        self.last_t_s = None
        # The old stream ended: its pending position is complete.
        events = self.finish()
        # Samples of the old stream still waiting to size the detector would size it on the old clock.
        self._probe = []
        if self.detection is not None:
            # The detector and the positions hold the old stream's clock: every sample of the new one
            # would be older than their last and refused inside them (fault detection would stop).
            self.detection = self._new_detection(self.detection.rate_hz)
            for check in self.checks.values():
                check.f0_run, check.f0_run_onset = 0, None
        if self.gross is not None:
            self.gross.restart()
        if new_run:
            self._count("new_runs")
            # A fault raised in the old run stays raised until the new run's diagnosis clears it.
            self.n_positions = 0
            for check in self.checks.values():
                check.estimator = new_estimator(check.passport, self.options)
                check.since_t_s = -math.inf
        return events

    # ------------------------------------------------------------------ the chain

    def _run(self, det: _Detection, b: SampleBatch) -> list[Event]:
        accel, gyro = b.accel_mps2, b.gyro_rps
        temp = b.temp_c
        if temp is not None and self.checks:
            accel, gyro = self._temperature(accel, gyro, temp)
        # Static detector and positions over the batch: the per-sample results, vectorized where the stream is clean.
        positions, decisions = det.accumulator.update_batch(b.t_s, accel, gyro, temp)
        events = self._f0_all(*det.gate.push(b.t_s, accel, gyro, decisions))
        return events + self._gross(b.t_s, accel, gyro, temp) + self._positions(positions)

    def _gross(
        self, t_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray | None
    ) -> list[Event]:
        """The gross test on every accepted sample (:mod:`estimators.gross`): no static detector, no
        gate; as F0, not beyond a temperature model's range, where compensation is not exact."""
        assert self.gross is not None  # made with the detection
        if temp is not None:
            models = [c.passport.temperature for c in self.checks.values()]
            inside = np.ones(t_s.shape, dtype=bool)
            for model in models:
                if model is not None:
                    inside &= model.in_range(temp)
            if not inside.all():
                self._count("gross.skipped_temperature", int(np.count_nonzero(~inside)))
                t_s, accel, gyro = t_s[inside], accel[inside], gyro[inside]
        up = self.gross.update(t_s, accel, gyro)
        for triad in (Triad.ACCEL, Triad.GYRO):
            self._count(f"gross.{triad.value}.windows", up.tested[triad])
            self._count(f"gross.{triad.value}.fail", up.failed[triad])
        return [self._gross_event(c) for c in up.changes]

    def _gross_event(self, c: GrossChange) -> Event:
        assert self.gross is not None
        where = f"{self.vehicle} IMU{self.imu} {TRIAD_WORD[c.triad]}" + (
            f" {c.axis}" if c.axis else ""
        )
        source = self.gross.config.source
        if c.triad is Triad.ACCEL:
            g = self.options.gravity_mps2
            what = (
                f"|a| at rest {g + c.value_si:.4g} m/s^2, {c.value_si:+.3g} from g {g:.5g} "
                f"(allowed {c.bound_si:.3g} with noise, sigma {c.sigma_si:.2g})"
            )
            cause: EventCause = StreamCause.GRAVITY_MAGNITUDE
        else:
            what = (
                f"mean rate at rest {c.value_si:.3g} rad/s ({math.degrees(c.value_si):.3g} deg/s), "
                f"zero signal {c.nominal_si:.3g} ± {c.bound_si:.3g} rad/s (tolerance, Earth rate, noise)"
            )
            cause = Cause.ZERO_SIGNAL
        kw: dict[str, Any] = dict(
            triad=c.triad, axis=c.axis, estimate=c.value_si, nominal=c.nominal_si,
            tolerance=c.bound_si, sigma=c.sigma_si, unit="m/s^2" if c.triad is Triad.ACCEL else "rad/s",
        )  # fmt: skip
        if c.raised:
            text = f"{where}: {what} for {c.duration_s:.1f} s; tolerances: {source} [gross]"
            return self._event(
                c.t_s, Predicate.GROSS, cause, SEVERITY[Predicate.GROSS], text=text, **kw
            )
        text = (
            f"{where}: back within the gross bound at rest for {c.duration_s:.1f} s: {what} [gross]"
        )
        return self._event(
            c.t_s, Predicate.GROSS, StreamCause.RECOVERED, RECOVERED_SEVERITY, text=text, **kw
        )

    def _f0_all(
        self, t_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray, static: np.ndarray
    ) -> list[Event]:
        events: list[Event] = []
        if t_s.size:
            for triad, check in self.checks.items():
                events += self._f0(
                    triad, check, t_s, accel if triad is Triad.ACCEL else gyro, static
                )
        return events

    def _temperature(
        self, accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        out = {Triad.ACCEL: accel, Triad.GYRO: gyro}
        for triad, check in self.checks.items():
            model = check.passport.temperature
            if model is not None:
                out[triad] = to_reference_temperature(
                    out[triad], temp, model, gravity_mps2=check.passport.reference
                )
                self.temperature_compensated = True
        return out[Triad.ACCEL], out[Triad.GYRO]

    def _temperature_range(self, b: SampleBatch) -> list[Event]:
        """Each temperature model's range against the frame's temperatures (module docstring step 3).

        Runs before the frame enters the chain: notes the samples F0 must skip, and raises one event
        when a sample leaves the range, one ``recovered`` event at the first sample back inside by
        :data:`TEMPERATURE_HYSTERESIS_C`. Sample by sample, so the events do not depend on the framing.
        """
        events: list[Event] = []
        if b.temp_c is None:
            return events
        for triad, check in self.checks.items():
            model = check.passport.temperature
            if model is None:
                continue
            lo, hi = model.valid_min_c, model.valid_max_c
            if lo is None or hi is None:  # a schema-1 model: no range to leave
                continue
            outside = ~model.in_range(b.temp_c)
            if check.f0 is not None:
                check.record_temperature_skip(b.t_s, outside)
            margin = min(TEMPERATURE_HYSTERESIS_C, 0.25 * (hi - lo))
            back = (b.temp_c >= lo + margin) & (b.temp_c <= hi - margin)
            i = 0
            while True:
                entering = check.temp_out_edge_c is None
                hits = np.flatnonzero((outside if entering else back)[i:])
                if not hits.size:
                    break
                i += int(hits[0])
                t_s, temp_c = float(b.t_s[i]), float(b.temp_c[i])
                where = (
                    f"{self.vehicle} IMU{self.imu} {TRIAD_WORD[triad]}: temperature {temp_c:.1f} °C"
                )
                kw = dict(triad=triad, estimate=temp_c, nominal=model.reference_temp_c, unit="degC")
                if entering:
                    check.temp_out_edge_c = edge = hi if temp_c > hi else lo
                    text = (
                        f"{where} outside the passport model's {lo:g}…{hi:g} °C; compensation held at its "
                        f"{edge:g} °C value, F0 and the diagnosis skip these samples [temperature]"
                    )
                    events.append(
                        self._event(
                            t_s,
                            Predicate.TEMPERATURE,
                            StreamCause.TEMPERATURE_RANGE,
                            SEVERITY[Predicate.TEMPERATURE],
                            tolerance=edge,
                            text=text,
                            **kw,
                        )
                    )
                else:
                    text = (
                        f"{where} back within the passport model's {lo:g}…{hi:g} °C [temperature]"
                    )
                    events.append(
                        self._event(
                            t_s,
                            Predicate.TEMPERATURE,
                            StreamCause.RECOVERED,
                            RECOVERED_SEVERITY,
                            tolerance=check.temp_out_edge_c,
                            text=text,
                            **kw,
                        )
                    )
                    check.temp_out_edge_c = None
                i += 1
        return events

    def _f0(
        self, triad: Triad, check: TriadCheck, t_s: np.ndarray, x: np.ndarray, static: np.ndarray
    ) -> list[Event]:
        if check.f0 is None:
            return []
        # Beyond the temperature model's range compensation is not exact (module docstring step 3): not tested.
        hot = check.take_temperature_skip(t_s)
        self._count(f"f0.{triad.value}.skipped_temperature", int(np.count_nonzero(hot & static)))
        res = f0_batch(x, static & ~hot, check.f0)
        self._count(f"f0.{triad.value}.tests", res.n_tests)
        if res.n_tests:
            # The gravity directions F0 saw: its coverage's minimum detectable fault rests on them.
            tested = x[res.state >= 0]
            norm = np.linalg.norm(tested, axis=1, keepdims=True)
            # A dead triad reads exactly 0: it shows no direction, and 0/0 would poison the maximum for good.
            u = np.abs(tested[norm[:, 0] > 0.0]) / norm[norm[:, 0] > 0.0]
            if u.size:
                np.maximum(check.f0_max_abs_u, u.max(axis=0), out=check.f0_max_abs_u)
        self._count(f"f0.{triad.value}.fail", res.n_fail)
        k, run = persistent_failure(res.state, check.f0_run, self.f0_persist)
        events: list[Event] = []
        if k >= 0 and not check.f0_failing:
            onset = k - self.f0_persist + 1
            if onset >= 0:
                t_on, r_on = float(t_s[onset]), float(res.residual[onset])
            elif check.f0_run_onset is not None:
                t_on, r_on = check.f0_run_onset
            else:
                raise ValueError(
                    f"{self.vehicle} IMU{self.imu} {triad.value}: an F0 failure run carried over "
                    "from the last batch has no recorded onset"
                )
            check.f0_failing, check.f0_fail_t_s = True, t_on
            events.append(
                self._event(
                    t_on, Predicate.F0, StreamCause.OUT_OF_SHELL, SEVERITY[Predicate.F0],
                    triad=triad, estimate=r_on, nominal=0.0, tolerance=check.lambda0,
                )
            )  # fmt: skip
            self._restart_diagnosis(check, t_on)
        if run and run <= t_s.size:
            start = t_s.size - run
            check.f0_run_onset = (float(t_s[start]), float(res.residual[start]))
        check.f0_run = run
        return events

    def _restart_diagnosis(self, check: TriadCheck, t_s: float) -> None:
        # M1 (Fig. 2): F0 failed → diagnose from what the unit does from now on.
        check.estimator = new_estimator(check.passport, self.options)
        check.since_t_s = t_s

    def _positions(self, positions: list[Position]) -> list[Event]:
        events: list[Event] = []
        for pos in positions:
            self.n_positions += 1
            self._count("positions")
            for triad, check in self.checks.items():
                est = check.estimator
                mean, cov = pos.mean(triad), pos.cov(triad)
                if est is None or pos.t_start_s < check.since_t_s or mean is None or cov is None:
                    continue
                model = check.passport.temperature
                if (
                    model is not None
                    and pos.temp_mean_c is not None
                    and not model.in_range(np.array([pos.temp_mean_c]))[0]
                ):
                    self._count(
                        f"positions.skipped_temperature.{triad.value}"
                    )  # compensation not exact there
                    continue
                ref = self.options.reference(triad)
                try:
                    # The bias wander does not average down within a position (audited model).
                    est.update(mean / ref, (cov + check.passport.position_cov_floor()) / ref**2)
                except ValueError:
                    self._count(f"positions.rejected.{triad.value}")
                    continue
                events += self._diagnose(triad, check, est, pos.t_end_s)
        return events

    def _diagnose(
        self, triad: Triad, check: TriadCheck, est: RecursiveNineParam, t_s: float
    ) -> list[Event]:
        if est.n_positions < self.options.min_positions:
            return []
        diag = diagnose(
            est.estimate(),
            check.passport,
            false_alarm_prob=self.options.diagnosis_false_alarm_probability,
        )
        events: list[Event] = []
        for finding in diag.findings:
            if finding.predicate not in check.active:
                check.active[finding.predicate] = t_s
                events.append(
                    event_from_finding(
                        finding,
                        vehicle=self.vehicle,
                        imu=self.imu,
                        t_s=t_s,
                        severity=FINDING_SEVERITY,
                        epoch=self.epoch,
                    )
                )
        for result in diag.results:
            if result.outcome is Outcome.PASS and result.predicate in check.active:
                del check.active[result.predicate]
                j = int(result.predicate[1:]) - 1
                events.append(
                    self._event(
                        t_s, Predicate.parse(result.predicate), StreamCause.RECOVERED, RECOVERED_SEVERITY, triad=triad,
                        axis=PARAM_AXIS[j], estimate=result.estimate, nominal=result.nominal, tolerance=result.tolerance,
                        sigma=result.sigma, text=f"{self.vehicle} IMU{self.imu} {triad.value} {PARAM_AXIS[j]}: "
                        f"{PARAM_CAUSE[j].value.replace('_', ' ')} back within tolerance [{result.predicate}]",
                    )
                )  # fmt: skip
        if check.f0_failing and diag.n_evaluated and not diag.findings:
            # The failure stays until a full diagnosis after it clears the triad (an orientation-dependent
            # fault passes F0 in some positions, so passing samples alone prove nothing).
            check.f0_failing = False
            events.append(
                self._event(
                    t_s, Predicate.F0, StreamCause.RECOVERED, RECOVERED_SEVERITY, triad=triad, tolerance=check.lambda0,
                    text=f"{self.vehicle} IMU{self.imu} {triad.value}: F0 cleared, {diag.n_evaluated} parameters within "
                    f"tolerance over {est.n_positions} positions since the failure [F0]",
                )
            )  # fmt: skip
        return events

    def _validity_events(self, report: ValidityReport, t_s: float) -> list[Event]:
        events: list[Event] = []
        limits = self.options.validity
        for c in report.changes:
            key = (c.triad.value, c.axis)
            when = t_s if c.t_s is None else c.t_s
            if c.stale and key not in self.stale:
                self.stale.add(key)
                events.append(
                    self._event(
                        when, Predicate.STALE, StreamCause.STUCK_VALUE, SEVERITY[Predicate.STALE], triad=c.triad, axis=c.axis,
                        estimate=float(c.run_samples), tolerance=float(limits.stale_run_samples), unit="count",
                        text=f"{self.vehicle} IMU{self.imu} {TRIAD_WORD[c.triad]} {c.axis}: stuck at {c.value:.6g} "
                        f"for {limits.stale_run_samples} samples [stale]",
                    )
                )  # fmt: skip
            elif not c.stale and key in self.stale:
                self.stale.discard(key)
                events.append(
                    self._event(when, Predicate.STALE, StreamCause.RECOVERED, RECOVERED_SEVERITY, triad=c.triad, axis=c.axis,
                                estimate=float(c.run_samples), unit="count")
                )  # fmt: skip
        if report.error_dense and not self.error_dense:
            self.error_dense = True
            events.append(
                self._event(
                    t_s, Predicate.ERROR_DENSITY, StreamCause.REJECTED_SAMPLES, SEVERITY[Predicate.ERROR_DENSITY],
                    estimate=report.peak_error_density, tolerance=limits.error_density_max,
                )
            )  # fmt: skip
        elif self.error_dense and report.error_density <= 0.5 * limits.error_density_max:
            self.error_dense = False
            events.append(
                self._event(
                    t_s,
                    Predicate.ERROR_DENSITY,
                    StreamCause.RECOVERED,
                    RECOVERED_SEVERITY,
                    estimate=report.error_density,
                )
            )
        return events

    # ------------------------------------------------------------------ time and end of data

    def check_timeout(self, now_s: float) -> list[Event]:
        """The timeout check (``now_s`` on the clock the arrivals were stamped with)."""
        if self.timed_out or not self.validity.timed_out(now_s):
            return []
        self.timed_out = True
        limit = self.options.validity.timeout_s
        t_s = (self.last_t_s or 0.0) + limit
        events = [
            self._event(
                t_s,
                Predicate.TIMEOUT,
                StreamCause.NO_DATA,
                SEVERITY[Predicate.TIMEOUT],
                tolerance=limit,
                unit="s",
            )
        ]
        # The data stopped: the pending position is complete, let it count.
        return events + self.finish()

    def end_of_data(self) -> list[Event]:
        """The data ended (a replayed log): frames still held as a possible restart formed none and
        are counted as rejected, by their reason; then :meth:`finish`. No error density is judged
        on them: no stream follows them."""
        held, self._restart_probe = self._restart_probe, []
        for _, _, problem in held:
            self._count(problem)
        return self.finish()

    def finish(self) -> list[Event]:
        """End of data: finalize the static detector and diagnose the positions still pending."""
        det = self.detection
        if det is None:
            return []
        positions = det.accumulator.flush()
        empty = np.zeros((0, 3))
        return self._f0_all(
            *det.gate.push(np.zeros(0), empty, empty, det.accumulator.detector.last_step())
        ) + self._positions(positions)

    # ------------------------------------------------------------------ status and checkpoints

    @property
    def state(self) -> ImuState:
        return self._state_of(None)

    def _state_of(self, coverage: ImuCoverage | None) -> ImuState:
        """The state; ``coverage``: :func:`imu_coverage`'s, when the caller has it already."""
        if self.gross is not None and self.gross.failing():
            return ImuState.FAULT
        if self.passport is None or self.nominal_too_slow:
            return ImuState.NO_PASSPORT
        if self.timed_out:
            return ImuState.NO_DATA
        if self.stale or any(c.f0_failing or c.active for c in self.checks.values()):
            return ImuState.FAULT
        if self.error_dense or any(c.temp_out_edge_c is not None for c in self.checks.values()):
            return ImuState.WARNING
        if self.detection is None or self.n_positions < self.options.min_positions:
            return ImuState.STARTING
        # "ok" is the daemon's "no fault": only when every check that applies ran. Otherwise it is
        # replay's "no finding within coverage", at warning severity (a navigation unit's passport
        # without its gyro triad left the gyro's F0 and F1…F9 untested, and the status said "ok").
        if (coverage if coverage is not None else imu_coverage(self)).untested:
            return ImuState.WARNING
        return ImuState.OK

    def status(self) -> ImuStatus:
        parts = []
        if self.passport is None:
            parts.append(self.passport_note or "no passport")
        elif self.nominal_class is not None:
            # A refused entry stays said: the unit runs on its class's passport, not on its own.
            parts += [f"passport: nominal {self.nominal_class}", self.passport_note]
            parts.append(self.nominal_too_slow)
        for check in self.checks.values():
            parts.append(check.f0_note + (" FAILING" if check.f0_failing else ""))
            if check.active:
                parts.append(
                    f"{check.passport.triad.value} faults " + ",".join(sorted(check.active))
                )
            model, name = check.passport.temperature, check.passport.triad.value
            if model is not None and not model.bounded:
                parts.append(
                    f"{name} temperature model has no valid range (passport schema 1): used at any temperature"
                )
            elif model is not None and check.temp_out_edge_c is not None:
                parts.append(
                    f"{name} beyond the temperature model's {model.valid_min_c:g}…{model.valid_max_c:g} °C: F0 and diagnosis skip samples there"
                )
        if self.checks:
            with_model = any(c.passport.temperature is not None for c in self.checks.values())
            parts.append(
                "temperature-compensated (M3)" if self.temperature_compensated
                else ("temperature model waiting for temperature" if with_model else "no temperature model")
            )  # fmt: skip
        if self.gross is not None:
            failing = ",".join(t.value + (f".{a}" if a else "") for t, a in self.gross.failing())
            nominal = " (no passport)" if self.passport is None else ""
            parts.append(
                f"gross at rest: {self.gross.config.source}{nominal}"
                + (f" FAILING {failing}" if failing else "")
            )
        if self.stale:
            parts.append("stale " + ",".join(f"{t}.{a}" for t, a in sorted(self.stale)))
        if self.rate_changed_from_hz is not None and self.detection is not None:
            parts.append(
                f"sample rate changed from {self.rate_changed_from_hz:.4g} to "
                f"{self.detection.rate_hz:.4g} Hz: detector re-sized"
            )
        coverage = imu_coverage(self)
        return ImuStatus(
            self.imu,
            self._state_of(coverage),
            self.n_samples,
            self.last_t_s,
            self.n_positions,
            "; ".join(p for p in parts if p)[:500],
            coverage.checks,
        )

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume after a restart (positions and estimates included)."""
        det = self.detection
        return {
            "version": PIPELINE_STATE_VERSION,
            "vehicle": self.vehicle,
            "imu": self.imu,
            "passport": self._passport_identity(),
            "rate_hz": None if det is None else det.rate_hz,
            "last_seq": self.last_seq,
            "last_t_s": self.last_t_s,
            "run": self.run,
            "last_batch_n": self.last_batch_n,
            "n_samples": self.n_samples,
            "n_positions": self.n_positions,
            "stale": sorted(list(k) for k in self.stale),
            "error_dense": self.error_dense,
            "temperature_compensated": self.temperature_compensated,
            "validity": self.validity.state_dict(),
            "accumulator": None if det is None else det.accumulator.state_dict(),
            "gate": None if det is None else det.gate.state_dict(),
            "gross": None if self.gross is None else self.gross.state_dict(),
            "counters": dict(self.counters),
            "rate_watch": {
                "steps_s": self._rate_steps_s[: self._rate_fill].tolist(),
                "off": self._rate_off,
                "changed_from_hz": self.rate_changed_from_hz,
            },
            "checks": {
                t.value: {
                    "since_t_s": None if math.isinf(c.since_t_s) else c.since_t_s,
                    "f0_failing": c.f0_failing,
                    "f0_fail_t_s": c.f0_fail_t_s,
                    "active": dict(c.active),
                    "estimator": None if c.estimator is None else c.estimator.state_dict(),
                    "f0_run": c.f0_run,
                    "f0_run_onset": None if c.f0_run_onset is None else list(c.f0_run_onset),
                    "temp_out_edge_c": c.temp_out_edge_c,
                    "temp_skip_s": [list(span) for span in c.temp_skip_s],
                    "f0_max_abs_u": c.f0_max_abs_u.tolist(),
                }
                for t, c in self.checks.items()
            },
        }

    def _load_rate_watch(self, watch: dict[str, Any]) -> None:
        """The rate watch's progress from a checkpoint; ``ValueError`` for values it never holds (a
        step that is not positive, a count of blocks outside ``0..RATE_CHECK_BLOCKS - 1``, a former
        rate outside the validity limits): they would divide by zero or never re-size."""
        steps_s = np.asarray(watch["steps_s"], dtype=float)
        off, changed = watch["off"], watch["changed_from_hz"]
        limits = self.options.validity
        if (
            steps_s.ndim != 1
            or steps_s.size >= RATE_CHECK_SAMPLES
            or not bool(np.all(np.isfinite(steps_s) & (steps_s > 0)))
        ):
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu}: rate watch steps unusable"
            )
        if type(off) is not int or not 0 <= off < RATE_CHECK_BLOCKS:
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu}: rate watch count {off!r}"
            )
        if changed is not None and not (
            type(changed) in (int, float) and limits.min_rate_hz <= changed <= limits.max_rate_hz
        ):
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu}: former rate {changed!r} Hz"
            )
        self._rate_steps_s[: steps_s.size] = steps_s
        self._rate_fill = int(steps_s.size)
        self._rate_off = off
        self.rate_changed_from_hz = None if changed is None else float(changed)

    def _passport_identity(self) -> str | None:
        """The passport a state was made against: its unit and date (None: stream checks only)."""
        p = self.passport
        return None if p is None else f"{p.unit_id} {p.created}"

    def load_state(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`state_dict` (raises ``ValueError`` for another unit or version; then start fresh)."""
        if (
            state.get("version") != PIPELINE_STATE_VERSION
            or state.get("vehicle") != self.vehicle
            or state.get("imu") != self.imu
        ):
            raise ValueError(
                f"checkpoint is not a version-{PIPELINE_STATE_VERSION} state of {self.vehicle} IMU{self.imu}"
            )
        # A state saved before the passport was recorded in it is the present unit's.
        if "passport" in state and state["passport"] != self._passport_identity():
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu} was made against passport "
                f"{state['passport']!r}, the store now holds {self._passport_identity()!r} (a replaced "
                "unit: its positions and raised faults are not this one's)"
            )
        try:
            if state["rate_hz"] is not None:
                rate_hz = float(state["rate_hz"])
                limits = self.options.validity
                if not limits.min_rate_hz <= rate_hz <= limits.max_rate_hz:
                    raise ValueError(
                        f"checkpoint of {self.vehicle} IMU{self.imu} has rate {rate_hz!r} Hz"
                    )
                det = self._setup(rate_hz)
                det.accumulator = PositionAccumulator.from_state_dict(state["accumulator"])
                det.gate = StaticGate.from_state(state["gate"])
                # Absent from checkpoints written before the gross test: it starts afresh.
                if state.get("gross") is not None and self.gross is not None:
                    self.gross = GrossMonitor.from_state(self.gross.config, state["gross"])
            self.last_seq = state["last_seq"]
            self.last_t_s = state["last_t_s"]
            self.run = state.get("run")  # absent from checkpoints written before run ids
            self.last_batch_n = int(state["last_batch_n"])
            self.n_samples = int(state["n_samples"])
            self.n_positions = int(state["n_positions"])
            self.stale = {tuple(k) for k in state["stale"]}
            self.error_dense = bool(state["error_dense"])
            self.temperature_compensated = bool(
                state.get("temperature_compensated", False)
            )  # absent from older checkpoints
            self.validity = StreamValidity.from_state(
                state["validity"], limits=self.options.validity
            )
            self.counters = {str(k): int(v) for k, v in state["counters"].items()}
            # Absent from checkpoints written before the rate watch: a block starts afresh.
            watch = state.get("rate_watch") or {"steps_s": [], "off": 0, "changed_from_hz": None}
            self._load_rate_watch(watch)
            for name, cs in state["checks"].items():
                check = self.checks.get(Triad(name))
                if check is None:
                    continue
                check.since_t_s = -math.inf if cs["since_t_s"] is None else float(cs["since_t_s"])
                check.f0_failing = bool(cs["f0_failing"])
                check.f0_fail_t_s = cs["f0_fail_t_s"]
                check.active = {str(k): float(v) for k, v in cs["active"].items()}
                # Absent from older checkpoints: no failure run in progress.
                check.f0_run = int(cs.get("f0_run", 0))
                onset = cs.get("f0_run_onset")
                check.f0_run_onset = None if onset is None else (float(onset[0]), float(onset[1]))
                # Absent from checkpoints written before the temperature range existed: in range, nothing to skip.
                edge = cs.get("temp_out_edge_c")
                check.temp_out_edge_c = None if edge is None else float(edge)
                check.temp_skip_s = [[float(a), float(b)] for a, b in cs.get("temp_skip_s", [])]
                # Absent from checkpoints written before the coverage: no direction seen yet.
                max_u = np.asarray(cs.get("f0_max_abs_u", [0.0, 0.0, 0.0]), dtype=float)
                if max_u.shape != (3,) or not np.all((max_u >= 0) & (max_u <= 1)):
                    raise ValueError(
                        f"checkpoint of {self.vehicle} IMU{self.imu}: F0 directions {cs['f0_max_abs_u']!r}"
                    )
                check.f0_max_abs_u = max_u
                if cs["estimator"] is not None and check.estimator is not None:
                    check.estimator = RecursiveNineParam.from_state_dict(cs["estimator"])
        except (KeyError, TypeError) as exc:
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu} is incomplete: {exc}"
            ) from None
