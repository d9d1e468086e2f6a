"""The streaming pipeline: one :class:`ImuPipeline` per (vehicle, IMU), a :class:`FleetProcessor` over them.

Per batch of samples, in this order (docs/architecture.md):

1. **Order.** Frames are taken in ``seq`` order: a repeated ``seq`` is a
   duplicate, a smaller one is out of order (both rejected and counted), a gap
   counts the missing frames; a frame with no sample later than the last
   accepted one is rejected (``no_new_samples``), and so are single samples
   that go back in time or are not finite. Three rejected frames in a row that
   form a consistent new stream (consecutive ``seq``, increasing time) are
   taken as a restart of the source (seq and clock from scratch): the stream
   restarts, the estimates are kept. A step forward of more than
   :data:`TIME_JUMP_PERIODS` sample periods is counted as a ``time_jump``; the
   static detector starts a new segment there by itself.
2. **Stream validity** (:mod:`estimators.stream_validity`): stale axes, error
   density; the timeout is checked by :meth:`FleetProcessor.tick`.
3. **Temperature.** When the frame carries temperature and the passport's
   triad has a temperature model (methods.md M3) the samples are brought to the
   passport's reference temperature
   (:func:`estimators.temperature.to_reference_temperature`) before anything
   else sees them; the status says so. Beyond the range the model was fitted on
   the model is held at the nearer edge (not extrapolated), which leaves an
   unmodelled error: a ``temperature`` event (cause ``temperature_range``) is
   raised when a sample leaves the range and a ``recovered`` one when the
   temperature is back inside by :data:`TEMPERATURE_HYSTERESIS_C`; F0 does not
   test samples taken outside the range (``f0.<triad>.skipped_temperature``) and
   positions whose mean temperature is outside do not enter the diagnosis
   (``positions.skipped_temperature.<triad>``). A schema-1 passport's model has
   no range: it is used at any temperature, and the status says so.
4. **Static detection and positions**
   (:class:`estimators.positions.PositionAccumulator`, per sample), with the
   detector's thresholds raised to the unit's own noise at the stream's rate
   (:func:`detector_config`).
5. **F0 on every static sample** (methods.md M1) with
   :func:`estimators.scalar.f0_batch` over the samples :class:`StaticGate`
   releases (documented to give the per-sample
   :class:`~estimators.scalar.F0Monitor`'s decisions), centred on the
   passport's nominal errors, λ0 from :func:`estimators.scalar.derive_lambda0`
   with the passport's noise and tolerances at the configured false-alarm
   probability. The first run of FAILs lasting ``f0_persistence_s`` without a
   break (:func:`estimators.scalar.persistent_failure`) raises an event dated at
   the run's first sample: a knock on the resting vehicle fails a few samples
   and is only counted (``f0.<triad>.fail``); the measured Xsens session has one
   such knock at 208.1 s. M1's flow "on failure, run the
   diagnosis" is implemented literally: the failed triad's recursive estimate
   restarts from the positions *after* the failure, so F1…F9 describe the
   faulty sensor, not an average of before and after.
6. **Recursive re-estimation** (:class:`estimators.ninepar.RecursiveNineParam`)
   with each new position, and **diagnosis** (:func:`estimators.diagnosis.diagnose`)
   against the unit's passport once ``min_positions`` positions are in.
7. **Events** (:mod:`protocols.events`) on transitions only: a condition that
   stays raised gives one event, its end gives one ``recovered`` event.

Everything here is synchronous and deterministic: the same batches with the
same arrival times give the same events (ids included), which is what makes
``ins-health replay`` reproducible and lets the daemon re-derive, after a crash,
events whose ids the outbox already holds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from estimators.conventions import (
    EARTH_RATE_RPS,
    PARAM_AXIS,
    PARAM_CAUSE,
    STANDARD_GRAVITY_MPS2,
    Triad,
)
from estimators.diagnosis import DEFAULT_FALSE_ALARM_PROB, Outcome, diagnose
from estimators.ninepar import RecursiveNineParam, canonical_triad_matrix
from estimators.passport import Passport, TriadPassport
from estimators.positions import Position, PositionAccumulator, PositionConfig
from estimators.scalar import F0Config, derive_lambda0, f0_batch, persistent_failure
from estimators.static_detector import FinalDecisions, StaticDetectorConfig
from estimators.stream_validity import (
    CrossImuMonitor,
    CrossImuReport,
    StreamValidity,
    ValidityLimits,
    ValidityReport,
    plausible_rate_hz,
)
from estimators.temperature import to_reference_temperature
from protocols.events import (
    Event,
    EventCause,
    ImuState,
    ImuStatus,
    Predicate,
    Severity,
    Status,
    StreamCause,
    event_from_finding,
    make_event,
)
from protocols.frames import SampleBatch

PIPELINE_STATE_VERSION = 1

SEVERITY: dict[Predicate, Severity] = {
    Predicate.F0: Severity.WARNING,
    Predicate.STALE: Severity.CRITICAL,
    Predicate.TIMEOUT: Severity.WARNING,
    Predicate.ERROR_DENSITY: Severity.WARNING,
    Predicate.CROSS_IMU: Severity.WARNING,
    Predicate.TEMPERATURE: Severity.WARNING,
}
"""MAV_SEVERITY of each predicate's event: F0 says *that* a triad failed (warning); F1…F9 name the
sensor and the cause (:data:`FINDING_SEVERITY`); a stuck axis is critical; recoveries are info."""

FINDING_SEVERITY = Severity.ERROR
_TRIAD_WORD = {Triad.ACCEL: "accelerometer", Triad.GYRO: "gyro"}
RECOVERED_SEVERITY = Severity.INFO
RATE_PROBE_SAMPLES = 16
"""Samples collected before the sample rate (which sets the static detector's window) is measured."""
TIME_JUMP_PERIODS = 10
"""Sample periods between two samples beyond which the gap is counted as a time jump."""
CLOCK_RESET_FRAMES = 3
"""Consecutive rejected frames forming a consistent new stream after which the source is taken to have restarted."""
DETECTOR_NOISE_FACTOR = 3.0
"""Static detector thresholds at least this many times the unit's white-noise window spread."""
TEMPERATURE_HYSTERESIS_C = 1.0
"""The temperature must be back this far inside the model's range before the out-of-range event recovers
(at most a quarter of the range): a unit resting at the edge would otherwise flicker in and out with the
sensor's noise and quantization, one event pair each time."""
F0_SHELL_LIMIT = 1.0
"""A triad whose λ0 exceeds this cannot fail F0 meaningfully (the shell is thicker than the unit
sphere: a MEMS gyro against the Earth rate); F0 is then not run for it, and the status says why."""


@dataclass(frozen=True)
class PipelineOptions:
    """What every pipeline of a service shares.

    Attributes
    ----------
    gravity_mps2 : local gravity, the accelerometers' reference, m/s².
    gravity_rel_err : bound of its relative error (enters λ0, M1's reference term).
    false_alarm_probability : per-sample F0 false-alarm probability.
    f0_persistence_s : how long F0 must fail without a break before it is declared, s
        (:func:`estimators.scalar.persistent_failure`; at least one sample). A knock rings
        for a few ms; a sensor fault stays.
    diagnosis_false_alarm_probability : per-diagnosis probability of a false F1…F9 (estimators.diagnosis).
    min_positions : positions before F1…F9 are evaluated.
    validity : stream-validity and cross-IMU limits.
    detector : static detector thresholds.
    positions : position building options.
    """

    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    gravity_rel_err: float = 3.0e-3
    false_alarm_probability: float = 1.0e-9
    f0_persistence_s: float = 0.02
    diagnosis_false_alarm_probability: float = DEFAULT_FALSE_ALARM_PROB
    min_positions: int = 9
    validity: ValidityLimits = ValidityLimits()
    detector: StaticDetectorConfig = StaticDetectorConfig()
    positions: PositionConfig = PositionConfig()

    def reference(self, triad: Triad) -> float:
        return self.gravity_mps2 if Triad(triad) is Triad.ACCEL else EARTH_RATE_RPS


@dataclass
class _TriadCheck:
    """F0 and the diagnosis of one triad against its passport."""

    passport: TriadPassport
    f0: F0Config | None
    lambda0: float
    f0_note: str
    estimator: RecursiveNineParam | None
    since_t_s: float = -math.inf
    f0_failing: bool = False
    f0_fail_t_s: float | None = None
    active: dict[str, float] = field(default_factory=dict)  # predicate -> data time raised
    f0_run: int = 0  # F0 failures in a row at the end of the last batch
    f0_run_onset: tuple[float, float] | None = None  # (t_s, residual) of that run's first sample
    temp_out_edge_c: float | None = (
        None  # range edge crossed while the temperature event is raised, °C
    )
    # [first, last] sample times taken outside the temperature model's range that F0 has not seen yet:
    # the static gate hands samples to F0 up to a window later than the frame that carried them.
    temp_skip_s: list[list[float]] = field(default_factory=list)

    def record_temperature_skip(self, t_s: np.ndarray, outside: np.ndarray) -> None:
        """Note the samples (times ``t_s`` (N,), ascending) taken outside the temperature model's range (``outside`` (N,))."""
        if self.temp_skip_s and t_s.size and t_s[0] <= self.temp_skip_s[-1][1]:
            # Time went back: the source restarted (ImuPipeline._source_restart), the old stream is finished.
            self.temp_skip_s.clear()
        edges = np.diff(np.concatenate([[0], outside.astype(np.int8), [0]]))
        first, last = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
        self.temp_skip_s += [
            [float(t_s[a]), float(t_s[b])] for a, b in zip(first, last, strict=True)
        ]

    def take_temperature_skip(self, t_s: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the samples at ``t_s`` (N,), ascending, F0 must skip; forgets the spans F0 has passed."""
        if not self.temp_skip_s or not t_s.size:
            return np.zeros(t_s.shape, dtype=bool)
        spans = np.array(self.temp_skip_s)
        k = np.searchsorted(spans[:, 0], t_s, side="right") - 1
        skip = (k >= 0) & (t_s <= spans[np.maximum(k, 0), 1])
        # F0 sees the samples in time order, so spans ending by the last of these are done.
        self.temp_skip_s = [s for s in self.temp_skip_s if s[1] > t_s[-1]]
        return skip


def _f0_config(
    tp: TriadPassport, options: PipelineOptions, rate_hz: float
) -> tuple[F0Config | None, float, str]:
    """F0's configuration for one triad (λ0 derived from the passport, module docstring step 5)."""
    ref = options.reference(tp.triad)
    # Per-sample white noise scales with the square root of the rate it is sampled at; the
    # audited bias wander (passport.bias_instability_std, docs/audit-xsens.md) does not.
    white = tp.noise_std * math.sqrt(rate_hz / tp.sample_rate_hz)
    noise_norm = np.maximum(np.hypot(white, tp.bias_instability_std) * tp.reference / ref, 1e-12)
    quant = None if tp.quantization_step is None else tp.quantization_step * tp.reference / ref
    nominal = tp.nominal.copy()
    nominal[:3] *= tp.reference / ref
    tol = tp.tolerance.copy()
    tol[:3] *= tp.reference / ref
    lam = derive_lambda0(
        noise_std_norm=noise_norm,
        false_alarm_prob=options.false_alarm_probability,
        quantization_norm=quant,
        tolerance_norm=tol,
        reference_rel_err=options.gravity_rel_err if tp.triad is Triad.ACCEL else 0.0,
    )
    if lam.lambda0 > F0_SHELL_LIMIT:
        return (
            None,
            lam.lambda0,
            f"F0 {tp.triad.value}: not resolvable (λ0 {lam.lambda0:.3g} > {F0_SHELL_LIMIT:g})",
        )
    cfg = F0Config(
        lambda0=lam.lambda0,
        reference=ref,
        bias_norm=tuple(nominal[:3]),
        matrix=tuple(map(tuple, canonical_triad_matrix(nominal))),
    )
    return cfg, lam.lambda0, f"F0 {tp.triad.value}: λ0 {lam.lambda0:.3g}"


def detector_config(
    base: StaticDetectorConfig, passport: Passport | None, rate_hz: float
) -> StaticDetectorConfig:
    """The static detector's thresholds for this unit at this rate.

    A quiet window's spread is about ``√3·σ`` for per-axis white noise σ, and σ grows with the
    square root of the rate; a threshold below the unit's own noise would call a resting unit
    moving. Each triad's threshold is therefore the larger of the configured one and
    :data:`DETECTOR_NOISE_FACTOR` × the spread of the passport's noise at ``rate_hz``
    (:meth:`estimators.static_detector.StaticDetectorConfig.from_noise`).
    """
    if passport is None:
        return base
    noise = {}
    for triad, tp in passport.triads.items():
        noise[triad] = float(
            tp.noise_std.max() * tp.reference * math.sqrt(rate_hz / tp.sample_rate_hz)
        )
    scaled = StaticDetectorConfig.from_noise(
        accel_noise_mps2=noise.get(Triad.ACCEL),
        gyro_noise_rps=noise.get(Triad.GYRO),
        factor=DETECTOR_NOISE_FACTOR,
        base=base,
    )
    return replace(
        base,
        accel_std_mps2=max(base.accel_std_mps2, scaled.accel_std_mps2),
        gyro_std_rps=max(base.gyro_std_rps, scaled.gyro_std_rps),
    )


def _new_estimator(tp: TriadPassport, options: PipelineOptions) -> RecursiveNineParam | None:
    # A triad whose passport resolves no parameter (a MEMS gyro against Ω) has nothing to diagnose.
    if not np.any(tp.observable):
        return None
    return RecursiveNineParam(tp.triad, reference=options.reference(tp.triad))


class StaticGate:
    """Holds samples until the static detector's decision on them is final, and erodes the static runs.

    F0 (M1) holds only while the unit is static. The detector's causal verdict
    ``static_now`` lags an abrupt start of motion (a take-off) by up to one
    window, so F0 is applied to the detector's *final* decisions instead
    (``W − 1`` samples late; the same decisions as the batch detector), with
    ``margin`` samples removed at both ends of every static run: the slow start
    and end of a turn sit inside a quiet window too (the positions trim the same
    amount for the same reason). The delay is ``W − 1 + margin`` samples.

    Samples are numbered by the detector's accepted-sample count; the caller
    pushes exactly the samples the detector accepted, with the decisions that
    became final while it fed them.
    """

    def __init__(self, margin: int) -> None:
        self.margin = int(margin)
        self._c0 = 0  # number of the first buffered sample
        self._t = np.zeros(0)
        self._x = np.zeros((0, 6))
        self._d0 = 0  # number of the first kept decision
        self._dec = np.zeros(0, dtype=bool)  # final static flag per decided sample
        self._brk = np.zeros(0, dtype=bool)  # a segment ends after this sample
        self._next = 0  # next sample to release

    def push(
        self, t_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray, decisions: FinalDecisions
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Buffer samples and the decisions that became final; returns ``(t, accel, gyro, static)`` released."""
        if t_s.size:
            self._t = np.concatenate([self._t, t_s])
            self._x = np.concatenate([self._x, np.hstack([accel, gyro])])
        end = self._d0 + self._dec.size
        # Decisions already held (a checkpoint taken mid-stream) are skipped; a gap would misplace every flag.
        if decisions.start > end:
            raise ValueError(f"static decisions skip samples {end}…{decisions.start - 1}")
        skip = min(end - decisions.start, decisions.static.size)
        if skip < decisions.static.size:
            self._dec = np.concatenate([self._dec, decisions.static[skip:]])
            self._brk = np.concatenate([self._brk, decisions.brk[skip:]])
        return self._release()

    def _release(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m, d0 = self.margin, self._d0
        end = d0 + self._dec.size
        upto = end - m
        brk_at = np.flatnonzero(self._brk[max(0, self._next - d0) :])
        if brk_at.size:
            upto = max(upto, self._next + int(brk_at[-1]) + 1)
        upto = min(upto, self._c0 + self._t.size)
        if upto <= self._next:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool)
        c = np.arange(self._next, upto)
        bad = np.concatenate([[0], np.cumsum(~self._dec)])
        brk = np.concatenate([[0], np.cumsum(self._brk)])
        lo, hi = c - m - d0, c + m - d0  # decision positions of the window [c − m, c + m]
        inside = (lo >= 0) & (hi < self._dec.size)
        lo_c, hi_c = np.clip(lo, 0, self._dec.size), np.clip(hi, -1, self._dec.size - 1)
        static = inside & (bad[hi_c + 1] - bad[lo_c] == 0) & (brk[hi_c] - brk[lo_c] == 0)
        i0, i1 = self._next - self._c0, upto - self._c0
        t, x = self._t[i0:i1], self._x[i0:i1]
        self._next = upto
        # Keep the samples not released and the decisions the next windows still look back on.
        self._t, self._x, self._c0 = self._t[i1:], self._x[i1:], upto
        keep_from = max(0, upto - m - d0)
        self._dec, self._brk, self._d0 = (
            self._dec[keep_from:],
            self._brk[keep_from:],
            d0 + keep_from,
        )
        return t, x[:, :3], x[:, 3:], static

    def state_dict(self) -> dict[str, Any]:
        return {"margin": self.margin, "c0": self._c0, "t": self._t, "x": self._x, "d0": self._d0,
                "dec": self._dec, "brk": self._brk, "next": self._next}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> StaticGate:
        gate = cls(int(state["margin"]))
        gate._c0, gate._d0, gate._next = int(state["c0"]), int(state["d0"]), int(state["next"])
        gate._t = np.asarray(state["t"], float).reshape(-1)
        gate._x = np.asarray(state["x"], float).reshape(-1, 6)
        gate._dec = np.asarray(state["dec"], bool).reshape(-1)
        gate._brk = np.asarray(state["brk"], bool).reshape(-1)
        if gate._x.shape[0] != gate._t.size or gate._dec.size != gate._brk.size:
            raise ValueError("inconsistent static gate state")
        return gate


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
    passport_note : why there is no passport (shown in the status).
    options : shared options.
    """

    def __init__(
        self,
        vehicle: str,
        imu: int,
        *,
        passport: Passport | None,
        options: PipelineOptions,
        passport_note: str = "",
    ):
        self.vehicle, self.imu = vehicle, imu
        self.passport = passport
        self.passport_note = passport_note
        self.options = options
        self.validity = StreamValidity(limits=options.validity)
        self.detection: _Detection | None = None
        self.f0_persist = 1
        self.checks: dict[Triad, _TriadCheck] = {}
        self._probe: list[SampleBatch] = []
        self.last_seq: int | None = None
        self.accepted: SampleBatch | None = None
        self.last_t_s: float | None = None
        self.last_batch_n = 1
        self._restart_probe: list[tuple[int, float, float]] = []
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
            **kw,
        )

    def _setup(self, rate_hz: float) -> _Detection:
        self.f0_persist = max(1, round(self.options.f0_persistence_s * rate_hz))
        detector = detector_config(self.options.detector, self.passport, rate_hz)
        self.detection = _Detection(
            rate_hz,
            PositionAccumulator(
                rate_hz=rate_hz, detector_config=detector, config=self.options.positions
            ),
            StaticGate(self.options.positions.trim_samples(rate_hz)),
        )
        if self.passport is not None:
            for triad, tp in self.passport.triads.items():
                cfg, lam, note = _f0_config(tp, self.options, rate_hz)
                self.checks[triad] = _TriadCheck(
                    tp, cfg, lam, note, _new_estimator(tp, self.options)
                )
        return self.detection

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
        problem = self._order_problem(batch)
        if problem is not None:
            if not self._restarted(batch):
                self._count(problem)
                return events + self._validity_events(
                    self.validity.record_rejected(batch.n_samples), self.last_t_s or 0.0
                )
            events += self._source_restart()
        self._restart_probe = []
        first_seq = batch.seq - frames + 1
        if self.last_seq is not None and first_seq > self.last_seq + 1:
            self._count("frames.missing", first_seq - self.last_seq - 1)
        self.last_seq = batch.seq
        keep = self._ordered(batch)
        self._count("frames.accepted", frames)
        if self.last_t_s is not None and batch.t_s[keep][0] - self.last_t_s > self._jump_s():
            self._count("time_jumps")
        self._count("samples.rejected.out_of_order_or_non_finite", int((~keep).sum()))
        report = self.validity.update(
            accel_mps2=batch.accel_mps2,
            gyro_rps=batch.gyro_rps,
            bad=~keep,
            arrival_s=arrival_s,
            t_s=batch.t_s,
        )
        t_k = batch.t_s[keep]
        events += self._validity_events(report, float(t_k[-1]))
        good = batch if keep.all() else SampleBatch(
            batch.vehicle, batch.imu, batch.seq, t_k, batch.accel_mps2[keep], batch.gyro_rps[keep],
            None if batch.temp_c is None else batch.temp_c[keep],
        )  # fmt: skip
        self.accepted = good
        self.last_t_s = float(t_k[-1])
        self.last_batch_n = batch.n_samples
        self.n_samples += int(t_k.size)
        self._count("samples.accepted", int(t_k.size))
        if self.detection is None:
            self._probe.append(good)
            if sum(b.n_samples for b in self._probe) < RATE_PROBE_SAMPLES:
                return events
            batches, self._probe = self._probe, []
            rate_hz = plausible_rate_hz(
                np.concatenate([b.t_s for b in batches]), self.options.validity
            )
            if rate_hz is None:
                # Counted, and the next frames probe afresh: a stream at an implausible rate
                # never sizes the detector (ValidityLimits.min_rate_hz/max_rate_hz).
                self._count("samples.rejected.implausible_rate", sum(b.n_samples for b in batches))
                return events
            det = self._setup(rate_hz)
            for b in batches:
                events += self._temperature_range(b) + self._run(det, b)
            return events
        return events + self._temperature_range(good) + self._run(self.detection, good)

    def joins(self, prev: SampleBatch | None, batch: SampleBatch) -> bool:
        """Whether ``batch`` may join one batch with the frames before it (``prev``: the last of them; None: the first).

        Only where joining changes nothing but the cost: the chain is set up and
        in no timeout, error-density or restart episode, and the frame is finite,
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
        t = batch.t_s
        return (
            (last_seq is None or batch.seq == last_seq + 1)
            and (last_t_s is None or last_t_s < t[0] <= last_t_s + self._jump_s())
            and bool(np.all(np.diff(t) > 0))
            and bool(np.isfinite(t).all())
            and bool(np.isfinite(batch.accel_mps2).all())
            and bool(np.isfinite(batch.gyro_rps).all())
            and (batch.temp_c is None or bool(np.isfinite(batch.temp_c).all()))
        )

    def _jump_s(self) -> float:
        """A step forward in sample time larger than this is a time jump (data lost or a clock step)."""
        return TIME_JUMP_PERIODS / self.detection.rate_hz if self.detection else 1.0

    def _ordered(self, batch: SampleBatch) -> np.ndarray:
        """(N,) samples that are finite and later than every sample before them (this frame and the last accepted)."""
        t = batch.t_s
        finite = (
            np.isfinite(t)
            & np.isfinite(batch.accel_mps2).all(axis=1)
            & np.isfinite(batch.gyro_rps).all(axis=1)
        )
        if batch.temp_c is not None:
            finite &= np.isfinite(batch.temp_c)
        start = -math.inf if self.last_t_s is None else self.last_t_s
        prev_max = np.maximum.accumulate(
            np.concatenate([[start], np.where(finite, t, -math.inf)[:-1]])
        )
        return finite & (t > prev_max)

    def _order_problem(self, batch: SampleBatch) -> str | None:
        """Why this frame cannot follow the last accepted one (a counter name), or None."""
        last = self.last_seq
        if last is not None and batch.seq == last:
            return "frames.duplicate"
        if last is not None and batch.seq < last:
            return "frames.out_of_order"
        if not self._ordered(batch).any():
            return "frames.rejected.no_new_samples"
        return None

    def _restarted(self, batch: SampleBatch) -> bool:
        """Whether rejected frames form a consistent new stream: the source rebooted (seq and clock from scratch).

        :data:`CLOCK_RESET_FRAMES` consecutive rejected frames with consecutive ``seq`` and increasing time
        are taken as a restart; the ones before the decision stay rejected.
        """
        probe = self._restart_probe
        t0, t1 = float(batch.t_s[0]), float(batch.t_s[-1])
        if (
            probe
            and batch.seq == probe[-1][0] + 1
            and t0 > probe[-1][2]
            and np.all(np.diff(batch.t_s) > 0)
        ):
            probe.append((batch.seq, t0, t1))
        else:
            self._restart_probe = probe = [(batch.seq, t0, t1)]
        return len(probe) >= CLOCK_RESET_FRAMES

    def _source_restart(self) -> list[Event]:
        self._count("source_restarts")
        self._restart_probe = []
        self.last_seq = None
        self.last_t_s = None
        # The old stream ended: its pending position is complete.
        return self.finish()

    # ------------------------------------------------------------------ the chain

    def _run(self, det: _Detection, b: SampleBatch) -> list[Event]:
        accel, gyro = b.accel_mps2, b.gyro_rps
        temp = b.temp_c
        if temp is not None and self.checks:
            accel, gyro = self._temperature(accel, gyro, temp)
        # Static detector and positions over the batch: the per-sample results, vectorized where the stream is clean.
        positions, decisions = det.accumulator.update_batch(b.t_s, accel, gyro, temp)
        events = self._f0_all(*det.gate.push(b.t_s, accel, gyro, decisions))
        return events + self._positions(positions)

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
                where = f"{self.vehicle} IMU{self.imu} {_TRIAD_WORD[triad]}: temperature {temp_c:.1f} °C"
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
        self, triad: Triad, check: _TriadCheck, t_s: np.ndarray, x: np.ndarray, static: np.ndarray
    ) -> list[Event]:
        if check.f0 is None:
            return []
        # Beyond the temperature model's range compensation is not exact (module docstring step 3): not tested.
        hot = check.take_temperature_skip(t_s)
        self._count(f"f0.{triad.value}.skipped_temperature", int(np.count_nonzero(hot & static)))
        res = f0_batch(x, static & ~hot, check.f0)
        self._count(f"f0.{triad.value}.tests", res.n_tests)
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

    def _restart_diagnosis(self, check: _TriadCheck, t_s: float) -> None:
        # M1 (Fig. 2): F0 failed → diagnose from what the unit does from now on.
        check.estimator = _new_estimator(check.passport, self.options)
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
        self, triad: Triad, check: _TriadCheck, est: RecursiveNineParam, t_s: float
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
                        text=f"{self.vehicle} IMU{self.imu} {_TRIAD_WORD[c.triad]} {c.axis}: stuck at {c.value:.6g} "
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
        if self.passport is None:
            return ImuState.NO_PASSPORT
        if self.timed_out:
            return ImuState.NO_DATA
        if self.stale or any(c.f0_failing or c.active for c in self.checks.values()):
            return ImuState.FAULT
        if self.error_dense or any(c.temp_out_edge_c is not None for c in self.checks.values()):
            return ImuState.WARNING
        if self.detection is None or self.n_positions < self.options.min_positions:
            return ImuState.STARTING
        return ImuState.OK

    def status(self) -> ImuStatus:
        parts = []
        if self.passport is None:
            parts.append(self.passport_note or "no passport")
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
        if self.stale:
            parts.append("stale " + ",".join(f"{t}.{a}" for t, a in sorted(self.stale)))
        return ImuStatus(
            self.imu,
            self.state,
            self.n_samples,
            self.last_t_s,
            self.n_positions,
            "; ".join(parts)[:500],
        )

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume after a restart (positions and estimates included)."""
        det = self.detection
        return {
            "version": PIPELINE_STATE_VERSION,
            "vehicle": self.vehicle,
            "imu": self.imu,
            "rate_hz": None if det is None else det.rate_hz,
            "last_seq": self.last_seq,
            "last_t_s": self.last_t_s,
            "last_batch_n": self.last_batch_n,
            "n_samples": self.n_samples,
            "n_positions": self.n_positions,
            "stale": sorted(list(k) for k in self.stale),
            "error_dense": self.error_dense,
            "temperature_compensated": self.temperature_compensated,
            "validity": self.validity.state_dict(),
            "accumulator": None if det is None else det.accumulator.state_dict(),
            "gate": None if det is None else det.gate.state_dict(),
            "counters": dict(self.counters),
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
                }
                for t, c in self.checks.items()
            },
        }

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
            self.last_seq = state["last_seq"]
            self.last_t_s = state["last_t_s"]
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
                if cs["estimator"] is not None and check.estimator is not None:
                    check.estimator = RecursiveNineParam.from_state_dict(cs["estimator"])
        except (KeyError, TypeError) as exc:
            raise ValueError(
                f"checkpoint of {self.vehicle} IMU{self.imu} is incomplete: {exc}"
            ) from None


PassportLookup = Callable[[str, int], Passport]
"""``(vehicle, imu) -> Passport``; raises ``ValueError`` (e.g. ``PassportStoreError``) with the reason."""


def _cross_imu_event(
    vehicle: str, report: CrossImuReport, limits: ValidityLimits, scalar_note: str
) -> Event:
    t_s = report.bin_start_s + limits.cross_imu_window_s
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
                          severity=RECOVERED_SEVERITY, triad=triad, estimate=value, tolerance=limit, unit=unit, text=text)  # fmt: skip
    word = "accelerometer" if triad is Triad.ACCEL else "gyro"
    text = f"{vehicle} IMU{report.imu} {word}: disagrees with {others} by {value:.3g} {unit} (limit {limit:.3g}) [cross_imu]"
    if scalar_note:
        text += f"; scalar checks: {scalar_note}"
    return make_event(vehicle=vehicle, imu=report.imu, t_s=t_s, predicate=Predicate.CROSS_IMU, cause=StreamCause.DISAGREEMENT,
                      severity=SEVERITY[Predicate.CROSS_IMU], triad=triad, estimate=value, tolerance=limit, unit=unit, text=text)  # fmt: skip


class FleetProcessor:
    """All pipelines of a service: routing, admission limits, cross-IMU checks, status, checkpoints.

    Parameters
    ----------
    passports : passport lookup per (vehicle, IMU); a ``ValueError`` leaves that unit without a
        passport (validity checks only) and is reported once through ``on_passport_error``.
    options : pipeline options.
    vehicles : vehicles served (empty: all).
    max_vehicles, max_imus_per_vehicle : admission limits (frames beyond them are counted).
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
    ):
        self.options = options
        self._passports = passports
        self._vehicles = frozenset(vehicles)
        self._max_vehicles = int(max_vehicles)
        self._max_imus = int(max_imus_per_vehicle)
        self._on_passport_error = on_passport_error
        self.pipelines: dict[tuple[str, int], ImuPipeline] = {}
        self.cross: dict[str, CrossImuMonitor] = {}
        self.vehicle_counters: dict[str, dict[str, int]] = {}
        self.service_counters: dict[str, int] = {}
        self._restore: Callable[[str, int], dict[str, Any] | None] | None = None
        self._on_restore_error: Callable[[str, int, str], None] | None = None
        # (samples, counts, timed out) of each pipeline at the last checkpoint (changed_keys).
        self._saved: dict[tuple[str, int], tuple[int, int, bool]] = {}
        self._by_vehicle: dict[str, dict[int, ImuPipeline]] = {}

    def set_restore(
        self,
        load: Callable[[str, int], dict[str, Any] | None],
        on_error: Callable[[str, int, str], None] | None = None,
    ) -> None:
        """Where new pipelines take their checkpointed state from (``None``: start fresh).

        A state the pipeline cannot resume from is discarded (the unit starts fresh) and
        ``on_error(vehicle, imu, why)`` is told, so the caller can move it aside.
        """
        self._restore = load
        self._on_restore_error = on_error

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
            self.count_service("frames.unknown_vehicle")
            return None
        known = vehicle in self.vehicle_counters
        if not known and len(self.vehicle_counters) >= self._max_vehicles:
            self.count_service("frames.over_vehicle_limit")
            return None
        if known and len(self._by_vehicle.get(vehicle, {})) >= self._max_imus:
            self.count_vehicle(vehicle, "frames.over_imu_limit")
            return None
        self.vehicle_counters.setdefault(vehicle, {})
        try:
            passport, note = self._passports(vehicle, imu), ""
        except ValueError as exc:
            passport, note = None, str(exc)
            if self._on_passport_error is not None:
                self._on_passport_error(vehicle, imu, note)
        pipe = ImuPipeline(
            vehicle, imu, passport=passport, options=self.options, passport_note=note
        )
        if self._restore is not None:
            state = self._restore(vehicle, imu)
            if state is not None:
                try:
                    pipe.load_state(state)
                    self.count_vehicle(vehicle, "checkpoints.restored")
                except Exception as exc:
                    pipe = ImuPipeline(
                        vehicle, imu, passport=passport, options=self.options, passport_note=note
                    )
                    self.count_vehicle(vehicle, "checkpoints.discarded")
                    if self._on_restore_error is not None:
                        self._on_restore_error(vehicle, imu, f"{type(exc).__name__}: {exc}")
        self.pipelines[(vehicle, imu)] = pipe
        self._by_vehicle.setdefault(vehicle, {})[imu] = pipe
        self.cross.setdefault(vehicle, CrossImuMonitor(limits=self.options.validity))
        return pipe

    def process(self, batch: SampleBatch, *, arrival_s: float) -> list[Event]:
        """Route one decoded frame to its pipeline; returns the events raised."""
        pipe = self.admit(batch.vehicle, batch.imu)
        if pipe is None:
            return []
        events = pipe.process(batch, arrival_s=arrival_s)
        if pipe.accepted is not None:
            events += self._cross(pipe.accepted)
        return events

    def process_queued(self, batches: list[SampleBatch], *, arrival_s: float) -> list[Event]:
        """Frames taken from a queue together: the same events as :meth:`process` frame by frame, at less cost.

        The chain's cost is mostly per batch, so a run of consecutive frames of
        one IMU that :meth:`ImuPipeline.joins` goes through it as one batch
        (the per-frame counters still count frames; the cross-IMU check still
        takes them frame by frame; the scalar state an event of it describes
        is the one at the end of the run). Every other frame is processed
        alone. The frames of each IMU keep their order; IMUs are taken in order
        of their first frame.
        """
        groups: dict[tuple[str, int], list[SampleBatch]] = {}
        for b in batches:
            groups.setdefault((b.vehicle, b.imu), []).append(b)
        events: list[Event] = []
        for key, group in groups.items():
            i = 0
            while i < len(group):
                pipe = self.pipelines.get(key)
                j = i + 1
                if pipe is not None and pipe.joins(None, group[i]):
                    while j < len(group) and pipe.joins(group[j - 1], group[j]):
                        j += 1
                if pipe is None or j == i + 1:
                    events += self.process(group[i], arrival_s=arrival_s)
                else:
                    events += self._process_joined(pipe, group[i:j], arrival_s)
                i = j
        return events

    def _process_joined(
        self, pipe: ImuPipeline, run: list[SampleBatch], arrival_s: float
    ) -> list[Event]:
        last = run[-1]
        joined = SampleBatch(
            last.vehicle,
            last.imu,
            last.seq,
            np.concatenate([b.t_s for b in run]),
            np.concatenate([b.accel_mps2 for b in run]),
            np.concatenate([b.gyro_rps for b in run]),
            None if last.temp_c is None else np.concatenate([b.temp_c for b in run]),
        )
        events = pipe.process(joined, arrival_s=arrival_s, frames=len(run))
        pipe.last_batch_n = last.n_samples
        for b in run:
            events += self._cross(b)
        return events

    def _cross(self, good: SampleBatch) -> list[Event]:
        """Cross-IMU consistency of a frame's accepted samples (it needs a second IMU on the vehicle)."""
        if len(self._by_vehicle.get(good.vehicle, {})) < 2:
            return []
        reports = self.cross[good.vehicle].add(good.imu, good.t_s, good.accel_mps2, good.gyro_rps)
        return [
            _cross_imu_event(
                good.vehicle, r, self.options.validity, self._scalar_note(good.vehicle, r.imu)
            )
            for r in reports
        ]

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
        """End of data (replay): every pipeline finalizes its pending position."""
        events: list[Event] = []
        for key in sorted(self.pipelines):
            events += self.pipelines[key].finish()
        return events

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
        imus = tuple(p.status() for p in pipes)
        return Status(
            vehicle=vehicle, service=service, t_s=now_unix_s, counters=counters, imus=imus
        )

    def state_dicts(self, *, changed_only: bool = False) -> dict[str, dict[str, Any]]:
        """Checkpoint states keyed ``"<vehicle>/<imu>"`` (see :meth:`changed_keys` for ``changed_only``)."""
        keys = self.changed_keys() if changed_only else sorted(self.pipelines)
        return {f"{v}/{i}": self.pipelines[(v, i)].state_dict() for v, i in keys}

    def changed_keys(self) -> list[tuple[str, int]]:
        """Pipelines that took or refused a frame since the last call (an idle unit's checkpoint is still current)."""
        out = []
        for key, p in sorted(self.pipelines.items()):
            mark = (p.n_samples, sum(p.counters.values()), p.timed_out)
            if self._saved.get(key) != mark:
                self._saved[key] = mark
                out.append(key)
        return out
