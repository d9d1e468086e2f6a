"""Static positions: the averaged outputs of one static interval (methods.md M1).

M1 averages the outputs of each fixed position so the noise mean vanishes, and
stacks one scalar equation per position. A :class:`Position` carries that
average together with what the estimators and the audit need to weigh it.

From static intervals to positions
----------------------------------
The static intervals come from :mod:`estimators.static_detector`. For each one:

1. **Trim.** ``trim_s`` (default 0.25 s) is dropped at each end: the moving
   window marks a sample static as soon as *some* quiet window holds it, so the
   first and last samples of an interval can still carry the slow start or end
   of a turn (transition leakage). A quarter second is half the detector's
   window.
2. **Reject.** A static run shorter than the detector's ``min_static_s`` is
   rejected as ``SHORT_INTERVAL``; an interval with fewer than ``min_samples``
   samples left after trimming as ``TOO_FEW_SAMPLES``.
3. **Average.** Per triad: the mean (SI), the sample covariance ``Σ`` and the
   covariance of the mean (below); the sample count, time span and the mean of
   the finite temperature samples.
4. **Merge.** An interval that is not a new orientation relative to the
   current position (:func:`estimators.static_detector.is_new_orientation`:
   specific-force direction of the position's mean and the gyro rotation since
   the position's last interval, both below ``orientation_change_deg``) is
   merged into it (pooled moments) and recorded as ``MERGED``. Merging two
   directions ``θ`` apart shortens the mean vector by up to ``1 − cos(θ/2)``:
   an offset of ``−θ²/8`` in M1's ``½(|ã|²−1)`` (3.8e-5 at the default 1°),
   while the pooled scatter enters ``Σ``.

Covariance of the mean (:class:`CovarianceMethod`)
--------------------------------------------------
``SAMPLE``: ``Σ / n``, exact for white noise. ``BATCH_MEANS`` (default): the
samples are cut into consecutive batches of ``batch_s`` (default 0.5 s) and the
integrated autocorrelation time is estimated from the scatter of the batch
means, pooled over the three axes,
``τ̂ = m·tr(C_batch means) / tr(Σ)`` (``m`` samples per batch); the covariance
of the mean is ``Σ / n · max(1, τ̂)`` and ``n_eff = n / max(1, τ̂)``. Correlated
noise (filtered sensors, bias wander, tremor) makes ``τ̂ > 1`` and the plain
``Σ/n`` too optimistic; the floor at 1 keeps the white-noise answer when the
few batch means scatter low by chance (conservative: it never shrinks the
covariance). With fewer than two complete batches ``τ̂`` is 1. A flat-lined
output has ``Σ = 0`` and so a zero covariance: stale outputs are the stream
validity checks' to flag (:mod:`estimators.stream_validity`).

Batch and streaming
-------------------
:func:`build_positions` works on a whole session; :class:`PositionAccumulator`
consumes samples one at a time (O(1) each, plain floats), owns a
:class:`~estimators.static_detector.StreamingStaticDetector`, and emits the
same positions and rejections. A position is emitted when the next accepted
interval turns out to be a new orientation (or at :meth:`PositionAccumulator.flush`),
since until then a following interval may still be merged into it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from enum import Enum

import numpy as np

from estimators.conventions import Triad
from estimators.session import ImuSession
from estimators.static_detector import (
    RotationIntegrator,
    StaticDetection,
    StaticDetectorConfig,
    StaticInterval,
    StreamingStaticDetector,
    direction_change_deg,
    is_new_orientation,
)


@dataclass(frozen=True)
class Position:
    """One static position of the unit.

    Attributes
    ----------
    t_start_s, t_end_s : time span of the averaged samples, s.
    n_samples : number of samples averaged.
    accel_mean_mps2 : (3,) mean specific force, m/s², sensor axes (None without that triad).
    accel_cov_mps2 : (3, 3) covariance of that *mean*, (m/s²)².
    gyro_mean_rps : (3,) mean angular rate, rad/s (None without that triad).
    gyro_cov_rps : (3, 3) covariance of that mean, (rad/s)².
    temp_mean_c : mean temperature, °C, or None.
    index_start, index_stop : input sample indices ``[start, stop)`` of the averaged span, or None.
    n_intervals : static intervals merged into this position.
    accel_n_eff, gyro_n_eff : effective numbers of independent samples behind each mean
        (``n`` for white noise), or None.
    """

    t_start_s: float
    t_end_s: float
    n_samples: int
    accel_mean_mps2: np.ndarray | None
    accel_cov_mps2: np.ndarray | None
    gyro_mean_rps: np.ndarray | None
    gyro_cov_rps: np.ndarray | None
    temp_mean_c: float | None = None
    index_start: int | None = None
    index_stop: int | None = None
    n_intervals: int = 1
    accel_n_eff: float | None = None
    gyro_n_eff: float | None = None

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def mean(self, triad: Triad) -> np.ndarray | None:
        """(3,) mean output of ``triad`` in its SI unit, or None."""
        return self.accel_mean_mps2 if Triad(triad) is Triad.ACCEL else self.gyro_mean_rps

    def cov(self, triad: Triad) -> np.ndarray | None:
        """(3, 3) covariance of that mean, or None."""
        return self.accel_cov_mps2 if Triad(triad) is Triad.ACCEL else self.gyro_cov_rps

    def to_dict(self) -> dict:
        """Plain JSON-able dict (arrays as nested lists)."""
        out = {}
        for key, value in asdict(self).items():
            out[key] = value.tolist() if isinstance(value, np.ndarray) else value
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Position":
        arrays = {"accel_mean_mps2": (3,), "accel_cov_mps2": (3, 3), "gyro_mean_rps": (3,), "gyro_cov_rps": (3, 3)}
        kwargs = dict(data)
        try:
            for key, shape in arrays.items():
                if kwargs.get(key) is not None:
                    a = np.asarray(kwargs[key], dtype=float)
                    if a.shape != shape:
                        raise ValueError(f"{key} must have shape {shape}, got {a.shape}")
                    kwargs[key] = a
            return cls(**kwargs)
        except TypeError as exc:
            raise ValueError(f"invalid Position dict: {exc}") from None


class CovarianceMethod(str, Enum):
    """How the covariance of a position's mean is estimated (module docstring)."""

    SAMPLE = "sample"
    BATCH_MEANS = "batch_means"


class RejectReason(str, Enum):
    """Why a static interval did not become a position of its own."""

    SHORT_INTERVAL = "short_interval"
    TOO_FEW_SAMPLES = "too_few_samples"
    MERGED = "merged"


@dataclass(frozen=True)
class PositionRejection:
    """A static interval that was rejected or merged, with the reason.

    Attributes
    ----------
    reason : why.
    start, stop : input sample indices ``[start, stop)`` of the interval.
    t_start_s, t_end_s : its time span, s.
    detail : one line with the numbers behind the decision.
    """

    reason: RejectReason
    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    detail: str

    def to_dict(self) -> dict:
        return {**asdict(self), "reason": self.reason.value}

    @classmethod
    def from_dict(cls, data: dict) -> "PositionRejection":
        try:
            return cls(RejectReason(data["reason"]), int(data["start"]), int(data["stop"]),
                       float(data["t_start_s"]), float(data["t_end_s"]), str(data["detail"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid PositionRejection dict: {exc}") from None


@dataclass(frozen=True)
class PositionConfig:
    """How static intervals become positions (module docstring).

    Attributes
    ----------
    trim_s : dropped at each end of an interval, s (default 0.25).
    min_samples : fewest samples left after trimming (default 20, at least 2).
    batch_s : batch length for the batch-means covariance, s (default 0.5).
    covariance : :class:`CovarianceMethod` (default BATCH_MEANS).
    """

    trim_s: float = 0.25
    min_samples: int = 20
    batch_s: float = 0.5
    covariance: CovarianceMethod = CovarianceMethod.BATCH_MEANS

    def __post_init__(self) -> None:
        if not (math.isfinite(self.trim_s) and self.trim_s >= 0):
            raise ValueError(f"trim_s must be finite and >= 0, got {self.trim_s!r}")
        if not (math.isfinite(self.batch_s) and self.batch_s > 0):
            raise ValueError(f"batch_s must be finite and > 0, got {self.batch_s!r}")
        if isinstance(self.min_samples, bool) or not isinstance(self.min_samples, (int, np.integer)) or self.min_samples < 2:
            raise ValueError(f"min_samples must be an integer >= 2, got {self.min_samples!r}")
        object.__setattr__(self, "covariance", CovarianceMethod(self.covariance))

    def trim_samples(self, rate_hz: float) -> int:
        return int(round(self.trim_s * rate_hz))

    def batch_samples(self, rate_hz: float) -> int:
        return max(1, int(round(self.batch_s * rate_hz)))


@dataclass(frozen=True)
class PositionsResult:
    """Positions of a session and the intervals that did not become positions of their own."""

    positions: tuple[Position, ...]
    rejections: tuple[PositionRejection, ...]


# ---------------------------------------------------------------------------
# Moments shared by the batch and streaming paths


@dataclass(frozen=True)
class _Moments:
    """Moments of one triad over a set of samples: count, mean, scatter; the same of the batch means."""

    n: int
    mean: np.ndarray
    m2: np.ndarray
    nb: int
    bmean: np.ndarray
    bm2: np.ndarray

    @staticmethod
    def _pool(na, ma, sa, nb, mb, sb):
        # Chan et al.'s pairwise update: exact, no subtraction of large sums.
        if na == 0:
            return nb, mb, sb
        if nb == 0:
            return na, ma, sa
        n = na + nb
        d = mb - ma
        return n, ma + d * (nb / n), sa + sb + np.outer(d, d) * (na * nb / n)

    def combine(self, other: "_Moments") -> "_Moments":
        n, mean, m2 = self._pool(self.n, self.mean, self.m2, other.n, other.mean, other.m2)
        nb, bmean, bm2 = self._pool(self.nb, self.bmean, self.bm2, other.nb, other.bmean, other.bm2)
        return _Moments(n, mean, m2, nb, bmean, bm2)

    @classmethod
    def of_samples(cls, y: np.ndarray, batch: int) -> "_Moments":
        """Moments of the rows of ``y`` (n, 3); batches of ``batch`` consecutive rows, partial last one dropped."""
        n = y.shape[0]
        mean = y.mean(axis=0)
        d = y - mean
        nb = n // batch
        bm = y[: nb * batch].reshape(nb, batch, 3).mean(axis=1)
        bmean = bm.mean(axis=0) if nb else np.zeros(3)
        bd = bm - bmean
        return cls(n, mean, d.T @ d, nb, bmean, bd.T @ bd)

    @classmethod
    def of_sums(cls, shift, n, s, q, nb, bs, bq) -> "_Moments":
        """From running sums of shifted samples ``y − shift``: ``s`` (3), ``q`` (6: xx xy xz yy yz zz), same for batch means."""
        shift = np.asarray(shift, dtype=float)

        def sym(v):
            return np.array([[v[0], v[1], v[2]], [v[1], v[3], v[4]], [v[2], v[4], v[5]]])

        s = np.asarray(s, dtype=float)
        bs = np.asarray(bs, dtype=float)
        mean_s = s / n
        m2 = sym(q) - np.outer(s, mean_s)
        if nb:
            bmean_s = bs / nb
            bm2 = sym(bq) - np.outer(bs, bmean_s)
            bmean = shift + bmean_s
        else:
            bm2 = np.zeros((3, 3))
            bmean = np.zeros(3)
        return cls(n, shift + mean_s, m2, nb, bmean, bm2)

    def covariance_of_mean(self, method: CovarianceMethod, batch: int) -> tuple[np.ndarray, float]:
        """``(cov of the mean (3, 3), n_eff)`` (module docstring)."""
        sigma = self.m2 / (self.n - 1)
        tau = 1.0
        tr = float(np.trace(sigma))
        if method is CovarianceMethod.BATCH_MEANS and self.nb >= 2 and tr > 0.0:
            tau = max(1.0, batch * float(np.trace(self.bm2)) / (self.nb - 1) / tr)
        return sigma * (tau / self.n), self.n / tau

    def to_dict(self) -> dict:
        return {"n": self.n, "mean": self.mean.tolist(), "m2": self.m2.tolist(),
                "nb": self.nb, "bmean": self.bmean.tolist(), "bm2": self.bm2.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "_Moments":
        return cls(int(d["n"]), np.asarray(d["mean"], float).reshape(3), np.asarray(d["m2"], float).reshape(3, 3),
                   int(d["nb"]), np.asarray(d["bmean"], float).reshape(3), np.asarray(d["bm2"], float).reshape(3, 3))


@dataclass(frozen=True)
class _Group:
    """A position in the making: one interval, or several merged."""

    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    accel: _Moments | None
    gyro: _Moments | None
    temp_sum: float
    temp_n: int
    n_intervals: int = 1

    @property
    def n(self) -> int:
        return (self.accel or self.gyro).n

    def merge(self, other: "_Group") -> "_Group":
        return _Group(
            self.start, other.stop, self.t_start_s, other.t_end_s,
            None if self.accel is None else self.accel.combine(other.accel),
            None if self.gyro is None else self.gyro.combine(other.gyro),
            self.temp_sum + other.temp_sum, self.temp_n + other.temp_n, self.n_intervals + other.n_intervals,
        )

    def position(self, config: PositionConfig, batch: int) -> Position:
        def triad(mom):
            if mom is None:
                return None, None, None
            cov, n_eff = mom.covariance_of_mean(config.covariance, batch)
            return mom.mean.copy(), cov, n_eff

        am, ac, an = triad(self.accel)
        gm, gc, gn = triad(self.gyro)
        return Position(
            t_start_s=self.t_start_s, t_end_s=self.t_end_s, n_samples=self.n,
            accel_mean_mps2=am, accel_cov_mps2=ac, gyro_mean_rps=gm, gyro_cov_rps=gc,
            temp_mean_c=self.temp_sum / self.temp_n if self.temp_n else None,
            index_start=self.start, index_stop=self.stop, n_intervals=self.n_intervals,
            accel_n_eff=an, gyro_n_eff=gn,
        )

    def to_dict(self) -> dict:
        return {"start": self.start, "stop": self.stop, "t_start_s": self.t_start_s, "t_end_s": self.t_end_s,
                "accel": None if self.accel is None else self.accel.to_dict(),
                "gyro": None if self.gyro is None else self.gyro.to_dict(),
                "temp_sum": self.temp_sum, "temp_n": self.temp_n, "n_intervals": self.n_intervals}

    @classmethod
    def from_dict(cls, d: dict) -> "_Group":
        return cls(int(d["start"]), int(d["stop"]), float(d["t_start_s"]), float(d["t_end_s"]),
                   None if d["accel"] is None else _Moments.from_dict(d["accel"]),
                   None if d["gyro"] is None else _Moments.from_dict(d["gyro"]),
                   float(d["temp_sum"]), int(d["temp_n"]), int(d["n_intervals"]))


def _short_rejection(run: StaticInterval, min_static_s: float) -> PositionRejection:
    return PositionRejection(RejectReason.SHORT_INTERVAL, run.start, run.stop, run.t_start_s, run.t_end_s,
                             f"static run of {run.duration_s:.3f} s < min_static_s {min_static_s:g} s")


def _few_rejection(run: StaticInterval, n_left: int, trim: int, min_samples: int) -> PositionRejection:
    return PositionRejection(RejectReason.TOO_FEW_SAMPLES, run.start, run.stop, run.t_start_s, run.t_end_s,
                             f"{n_left} samples left of {run.n_samples} after trimming {trim} per end < min_samples {min_samples}")


def _offer(det_config: StaticDetectorConfig, pending: _Group | None, group: _Group, rotation_deg: float | None):
    """Merge ``group`` into ``pending`` or start a new position: ``(new pending, emitted or None, rejection or None)``."""
    if pending is None:
        return group, None, None
    direction = None if group.accel is None else direction_change_deg(pending.accel.mean, group.accel.mean)
    if is_new_orientation(det_config, direction_deg=direction, rotation_deg=rotation_deg):
        return group, pending, None
    parts = [f"{name} {v:.3f}°" for name, v in (("direction change", direction), ("rotation", rotation_deg)) if v is not None]
    rej = PositionRejection(RejectReason.MERGED, group.start, group.stop, group.t_start_s, group.t_end_s,
                            f"merged into the position from t={pending.t_start_s:.3f} s: {', '.join(parts)}"
                            f" < {det_config.orientation_change_deg:g}°")
    return pending.merge(group), None, rej


# ---------------------------------------------------------------------------
# Batch


def build_positions(session: ImuSession, detection: StaticDetection, *, config: PositionConfig = PositionConfig()) -> PositionsResult:
    """Positions of a session from its static detection (module docstring), in time order.

    Parameters
    ----------
    session : the session ``detection`` was computed on.
    detection : from :func:`estimators.static_detector.detect_static`; its config gives
        ``min_static_s`` and ``orientation_change_deg``, its rate the sample counts.

    The same positions and rejections as a :class:`PositionAccumulator` fed the
    same samples and flushed at the end.
    """
    t = np.asarray(session.t_s, dtype=float)
    accel = None if session.accel_mps2 is None else np.asarray(session.accel_mps2, dtype=float)
    gyro = None if session.gyro_rps is None else np.asarray(session.gyro_rps, dtype=float)
    temp = None if session.temp_c is None else np.asarray(session.temp_c, dtype=float)
    if detection.static.shape != t.shape:
        raise ValueError(f"detection covers {detection.static.shape[0]} samples, the session has {t.shape[0]}")
    det_cfg = detection.config
    rate = detection.rate_hz
    trim = config.trim_samples(rate)
    batch = config.batch_samples(rate)
    acc = detection.accepted
    runs = sorted([(iv, False) for iv in detection.intervals] + [(iv, True) for iv in detection.short_runs],
                  key=lambda r: r[0].start)

    positions: list[Position] = []
    rejections: list[PositionRejection] = []
    pending: _Group | None = None
    last_run_end = -1  # accepted-sample number of the last sample of the pending group's last run
    for run, short in runs:
        first = int(np.searchsorted(acc, run.start))
        last = int(np.searchsorted(acc, run.stop)) - 1
        if short:
            rejections.append(_short_rejection(run, det_cfg.min_static_s))
            continue
        rows = acc[first + trim : last - trim + 1] if last - first + 1 > 2 * trim else acc[:0]
        if rows.size < config.min_samples:
            rejections.append(_few_rejection(run, int(rows.size), trim, config.min_samples))
            continue
        temps = None if temp is None else temp[rows]
        finite_t = None if temps is None else temps[np.isfinite(temps)]
        group = _Group(
            int(rows[0]), int(rows[-1]) + 1, float(t[rows[0]]), float(t[rows[-1]]),
            None if accel is None else _Moments.of_samples(accel[rows], batch),
            None if gyro is None else _Moments.of_samples(gyro[rows], batch),
            0.0 if finite_t is None else float(finite_t.sum()), 0 if finite_t is None else int(finite_t.size),
        )
        rotation = None
        if gyro is not None and pending is not None:
            rotation = _rotation_between(t, gyro, acc, detection.segment_start, pending.gyro.mean, last_run_end, first)
        pending, emitted, rej = _offer(det_cfg, pending, group, rotation)
        if emitted is not None:
            positions.append(emitted.position(config, batch))
        if rej is not None:
            rejections.append(rej)
        last_run_end = last
    if pending is not None:
        positions.append(pending.position(config, batch))
    rejections.sort(key=lambda r: r.start)
    return PositionsResult(tuple(positions), tuple(rejections))


def _rotation_between(t, gyro, acc, segment_start, bias, last_end: int, first: int) -> float | None:
    """Rotation angle (deg) over accepted samples ``(last_end, first]``; None across a segment break."""
    if np.any(segment_start[last_end + 1 : first + 1]):
        return None
    rot = RotationIntegrator(bias)
    rows = acc[last_end : first + 1]
    tt = t[rows].tolist()
    ww = gyro[rows].tolist()
    for k in range(1, len(tt)):
        wx, wy, wz = ww[k]
        rot.add(wx, wy, wz, tt[k] - tt[k - 1])
    return rot.angle_deg


# ---------------------------------------------------------------------------
# Streaming


_NAN = float("nan")


@dataclass
class _RunSums:
    """Running sums of one static run's kept samples, shifted by the first kept sample (plain floats)."""

    n: int = 0
    shift: list = field(default_factory=lambda: [0.0] * 6)
    s: list = field(default_factory=lambda: [0.0] * 6)
    q: list = field(default_factory=lambda: [0.0] * 12)
    part: list = field(default_factory=lambda: [0.0] * 6)
    part_n: int = 0
    nb: int = 0
    bs: list = field(default_factory=lambda: [0.0] * 6)
    bq: list = field(default_factory=lambda: [0.0] * 12)
    temp_sum: float = 0.0
    temp_n: int = 0
    start: int = 0
    stop: int = 0
    t_first: float = 0.0
    t_last: float = 0.0


class PositionAccumulator:
    """Positions from a sample stream: O(1) per sample, checkpointable.

    Owns a :class:`~estimators.static_detector.StreamingStaticDetector`
    (``detector``; its ``static_now`` is the static flag for F0). ``update``
    takes one sample (values of an absent triad are ignored; ``temp_c`` NaN or
    None when unknown) and returns a :class:`Position` when one is complete;
    rejected and merged intervals are appended to ``rejections`` (take them with
    :meth:`drain_rejections`). :meth:`flush` ends the data and returns the
    remaining positions. Same results as :func:`build_positions`.
    """

    def __init__(
        self,
        *,
        rate_hz: float,
        has_accel: bool = True,
        has_gyro: bool = True,
        detector_config: StaticDetectorConfig = StaticDetectorConfig(),
        config: PositionConfig = PositionConfig(),
    ) -> None:
        self.detector = StreamingStaticDetector(detector_config, rate_hz=rate_hz, has_accel=has_accel, has_gyro=has_gyro)
        self.config = config
        # Channel offsets (accel 0, gyro 3) of the triads present, fixed here so the per-sample path builds nothing.
        self._offsets = tuple(o for o, present in ((0, has_accel), (3, has_gyro)) if present)
        self._trim = config.trim_samples(rate_hz)
        self._batch = config.batch_samples(rate_hz)
        self._ring_n = self.detector.window_samples + self._trim + 2
        self._ring = [[0.0] * self._ring_n for _ in range(8)]  # t, ax, ay, az, gx, gy, gz, temp
        self._ring_idx = [0] * self._ring_n
        self._run_open = False
        self._run_count = 0
        self._sums = _RunSums()
        self._pending: _Group | None = None
        self._rot = RotationIntegrator()
        self._rot_active = False
        self.rejections: list[PositionRejection] = []

    # -- per sample ---------------------------------------------------------

    def update(self, t_s: float, ax: float, ay: float, az: float, gx: float, gy: float, gz: float,
               temp_c: float | None = None) -> Position | None:
        det = self.detector
        before = det.n_accepted
        det.update(t_s, ax, ay, az, gx, gy, gz)
        if det.n_accepted != before:
            p = before % self._ring_n
            r = self._ring
            r[0][p] = t_s
            if det.has_accel:
                r[1][p], r[2][p], r[3][p] = ax, ay, az
            if det.has_gyro:
                r[4][p], r[5][p], r[6][p] = gx, gy, gz
            r[7][p] = _NAN if temp_c is None else temp_c
            self._ring_idx[p] = det.n_input - 1
        if det.fin_hi == det.fin_lo and det.closed_run is None and not det.fin_break:
            return None
        return self._after_detector()

    def _after_detector(self) -> Position | None:
        det = self.detector
        emitted = None
        for c in range(det.fin_lo, det.fin_split):
            self._static_sample(c)
        if det.closed_run is not None:
            emitted = self._close_run(det.closed_run, det.closed_run_short)
        if self._rot_active:
            for c in range(det.fin_split, det.fin_hi):
                self._integrate(c)
        if det.fin_break:
            # Across a time gap the rotation is unknown.
            self._rot_active = False
        return emitted

    def _integrate(self, c: int) -> None:
        rn = self._ring_n
        p, p0 = c % rn, (c - 1) % rn
        r = self._ring
        self._rot.add(r[4][p], r[5][p], r[6][p], r[0][p] - r[0][p0])

    def _static_sample(self, c: int) -> None:
        if not self._run_open:
            self._run_open = True
            self._run_count = 0
            self._sums = _RunSums()
            if self._rot_active:
                self._integrate(c)
                self._rot.set_mark()
        elif self._rot_active:
            self._integrate(c)
        self._run_count += 1
        if self._run_count > 2 * self._trim:
            self._add(c - self._trim)

    def _add(self, c: int) -> None:
        p = c % self._ring_n
        r = self._ring
        sm = self._sums
        if sm.n == 0:
            sm.shift = [r[k][p] for k in range(1, 7)]
            sm.start = self._ring_idx[p]
            sm.t_first = r[0][p]
        sm.n += 1
        sm.stop = self._ring_idx[p] + 1
        sm.t_last = r[0][p]
        temp = r[7][p]
        if temp == temp:
            sm.temp_sum += temp
            sm.temp_n += 1
        batch_done = sm.part_n + 1 == self._batch
        sh, s, q, part = sm.shift, sm.s, sm.q, sm.part
        for o in self._offsets:
            y0 = r[1 + o][p] - sh[o]
            y1 = r[2 + o][p] - sh[o + 1]
            y2 = r[3 + o][p] - sh[o + 2]
            s[o] += y0
            s[o + 1] += y1
            s[o + 2] += y2
            k = 2 * o
            q[k] += y0 * y0
            q[k + 1] += y0 * y1
            q[k + 2] += y0 * y2
            q[k + 3] += y1 * y1
            q[k + 4] += y1 * y2
            q[k + 5] += y2 * y2
            part[o] += y0
            part[o + 1] += y1
            part[o + 2] += y2
            if batch_done:
                m0, m1, m2 = part[o] / self._batch, part[o + 1] / self._batch, part[o + 2] / self._batch
                part[o] = part[o + 1] = part[o + 2] = 0.0
                bs, bq = sm.bs, sm.bq
                bs[o] += m0
                bs[o + 1] += m1
                bs[o + 2] += m2
                bq[k] += m0 * m0
                bq[k + 1] += m0 * m1
                bq[k + 2] += m0 * m2
                bq[k + 3] += m1 * m1
                bq[k + 4] += m1 * m2
                bq[k + 5] += m2 * m2
        if batch_done:
            sm.part_n = 0
            sm.nb += 1
        else:
            sm.part_n += 1

    def _close_run(self, run: StaticInterval, short: bool) -> Position | None:
        self._run_open = False
        det = self.detector
        sm = self._sums
        if short:
            self.rejections.append(_short_rejection(run, det.config.min_static_s))
            return None
        if sm.n < self.config.min_samples:
            self.rejections.append(_few_rejection(run, sm.n, self._trim, self.config.min_samples))
            return None

        def moments(o):
            return _Moments.of_sums(sm.shift[o:o + 3], sm.n, sm.s[o:o + 3], sm.q[2 * o:2 * o + 6],
                                    sm.nb, sm.bs[o:o + 3], sm.bq[2 * o:2 * o + 6])

        group = _Group(sm.start, sm.stop, sm.t_first, sm.t_last,
                       moments(0) if det.has_accel else None, moments(3) if det.has_gyro else None,
                       sm.temp_sum, sm.temp_n)
        rotation = self._rot.mark_angle_deg if (self._pending is not None and self._rot_active) else None
        if not det.has_gyro:
            rotation = None
        self._pending, emitted, rej = _offer(det.config, self._pending, group, rotation)
        if rej is not None:
            self.rejections.append(rej)
        if det.has_gyro:
            self._rot.reset(self._pending.gyro.mean.tolist())
            self._rot_active = True
        return None if emitted is None else emitted.position(self.config, self._batch)

    # -- end of data, outputs, checkpoints -----------------------------------

    def flush(self) -> list[Position]:
        """End of data: finalize the detector, close the open run, emit what is pending.

        The accumulator stays usable; the next position starts from scratch.
        """
        out = []
        self.detector.finish()
        emitted = self._after_detector()
        if emitted is not None:
            out.append(emitted)
        if self._pending is not None:
            out.append(self._pending.position(self.config, self._batch))
            self._pending = None
        self._rot_active = False
        return out

    def drain_rejections(self) -> list[PositionRejection]:
        out, self.rejections = self.rejections, []
        return out

    def state_dict(self) -> dict:
        """Plain JSON-able state (detector, ring, open run, pending position, rotation) for checkpoints."""
        return {
            "detector": self.detector.state_dict(),
            "config": {**asdict(self.config), "covariance": self.config.covariance.value},
            "ring": [[None if v != v else v for v in ch] for ch in self._ring],
            "ring_idx": list(self._ring_idx),
            "run_open": self._run_open,
            "run_count": self._run_count,
            "sums": asdict(self._sums),
            "pending": None if self._pending is None else self._pending.to_dict(),
            "rot": self._rot.state_dict(),
            "rot_active": self._rot_active,
            "rejections": [r.to_dict() for r in self.rejections],
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> "PositionAccumulator":
        try:
            det = StreamingStaticDetector.from_state_dict(state["detector"])
            cfg = PositionConfig(**state["config"])
            acc = cls(rate_hz=det.rate_hz, has_accel=det.has_accel, has_gyro=det.has_gyro,
                      detector_config=det.config, config=cfg)
            acc.detector = det
            ring = [[_NAN if v is None else float(v) for v in ch] for ch in state["ring"]]
            if len(ring) != 8 or any(len(ch) != acc._ring_n for ch in ring) or len(state["ring_idx"]) != acc._ring_n:
                raise ValueError(f"ring must hold 8 channels of {acc._ring_n} samples")
            acc._ring = ring
            acc._ring_idx = [int(v) for v in state["ring_idx"]]
            acc._run_open = bool(state["run_open"])
            acc._run_count = int(state["run_count"])
            acc._sums = _RunSums(**state["sums"])
            acc._pending = None if state["pending"] is None else _Group.from_dict(state["pending"])
            acc._rot = RotationIntegrator.from_state_dict(state["rot"])
            acc._rot_active = bool(state["rot_active"])
            acc.rejections = [PositionRejection.from_dict(r) for r in state["rejections"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid PositionAccumulator state: {exc}") from None
        return acc
