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

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import Triad
from estimators.session import ImuSession
from estimators.static_detector import (
    FinalDecisions,
    RotationIntegrator,
    StaticDetection,
    StaticDetectorConfig,
    StaticInterval,
    StreamingStaticDetector,
    SwitchedRing,
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
    accel_mean_mps2: FloatArray | None
    accel_cov_mps2: FloatArray | None
    gyro_mean_rps: FloatArray | None
    gyro_cov_rps: FloatArray | None
    temp_mean_c: float | None = None
    index_start: int | None = None
    index_stop: int | None = None
    n_intervals: int = 1
    accel_n_eff: float | None = None
    gyro_n_eff: float | None = None

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def mean(self, triad: Triad) -> FloatArray | None:
        """(3,) mean output of ``triad`` in its SI unit, or None."""
        return self.accel_mean_mps2 if Triad(triad) is Triad.ACCEL else self.gyro_mean_rps

    def cov(self, triad: Triad) -> FloatArray | None:
        """(3, 3) covariance of that mean, or None."""
        return self.accel_cov_mps2 if Triad(triad) is Triad.ACCEL else self.gyro_cov_rps

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (arrays as nested lists)."""
        out: dict[str, Any] = {}
        for key, value in asdict(self).items():
            out[key] = value.tolist() if isinstance(value, np.ndarray) else value
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Position:
        arrays = {
            "accel_mean_mps2": (3,),
            "accel_cov_mps2": (3, 3),
            "gyro_mean_rps": (3,),
            "gyro_cov_rps": (3, 3),
        }
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


class CovarianceMethod(StrEnum):
    """How the covariance of a position's mean is estimated (module docstring)."""

    SAMPLE = "sample"
    BATCH_MEANS = "batch_means"


class RejectReason(StrEnum):
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

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "reason": self.reason.value}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PositionRejection:
        try:
            return cls(
                RejectReason(data["reason"]),
                int(data["start"]),
                int(data["stop"]),
                float(data["t_start_s"]),
                float(data["t_end_s"]),
                str(data["detail"]),
            )
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
        if (
            isinstance(self.min_samples, bool)
            or not isinstance(self.min_samples, (int, np.integer))
            or self.min_samples < 2
        ):
            raise ValueError(f"min_samples must be an integer >= 2, got {self.min_samples!r}")
        object.__setattr__(self, "covariance", CovarianceMethod(self.covariance))

    def trim_samples(self, rate_hz: float) -> int:
        return round(self.trim_s * rate_hz)

    def batch_samples(self, rate_hz: float) -> int:
        return max(1, round(self.batch_s * rate_hz))


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
    mean: FloatArray
    m2: FloatArray
    nb: int
    bmean: FloatArray
    bm2: FloatArray

    @staticmethod
    def _pool(
        na: int, ma: FloatArray, sa: FloatArray, nb: int, mb: FloatArray, sb: FloatArray
    ) -> tuple[int, FloatArray, FloatArray]:
        # Chan et al.'s pairwise update: exact, no subtraction of large sums.
        if na == 0:
            return nb, mb, sb
        if nb == 0:
            return na, ma, sa
        n = na + nb
        d = mb - ma
        return n, ma + d * (nb / n), sa + sb + np.outer(d, d) * (na * nb / n)

    def combine(self, other: _Moments) -> _Moments:
        n, mean, m2 = self._pool(self.n, self.mean, self.m2, other.n, other.mean, other.m2)
        nb, bmean, bm2 = self._pool(self.nb, self.bmean, self.bm2, other.nb, other.bmean, other.bm2)
        return _Moments(n, mean, m2, nb, bmean, bm2)

    @classmethod
    def of_samples(cls, y: FloatArray, batch: int) -> _Moments:
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
    def of_sums(
        cls,
        shift: ArrayLike,
        n: int,
        s: ArrayLike,
        q: Sequence[float],
        nb: int,
        bs: ArrayLike,
        bq: Sequence[float],
    ) -> _Moments:
        """From running sums of shifted samples ``y − shift``: ``s`` (3), ``q`` (6: xx xy xz yy yz zz), same for batch means."""
        shift_v = np.asarray(shift, dtype=float)

        def sym(v: Sequence[float]) -> FloatArray:
            return np.array([[v[0], v[1], v[2]], [v[1], v[3], v[4]], [v[2], v[4], v[5]]])

        s_v = np.asarray(s, dtype=float)
        bs_v = np.asarray(bs, dtype=float)
        mean_s = s_v / n
        m2 = sym(q) - np.outer(s_v, mean_s)
        if nb:
            bmean_s = bs_v / nb
            bm2 = sym(bq) - np.outer(bs_v, bmean_s)
            bmean = shift_v + bmean_s
        else:
            bm2 = np.zeros((3, 3))
            bmean = np.zeros(3)
        return cls(n, shift_v + mean_s, m2, nb, bmean, bm2)

    def covariance_of_mean(self, method: CovarianceMethod, batch: int) -> tuple[FloatArray, float]:
        """``(cov of the mean (3, 3), n_eff)`` (module docstring)."""
        sigma = self.m2 / (self.n - 1)
        tau = 1.0
        tr = float(np.trace(sigma))
        if method is CovarianceMethod.BATCH_MEANS and self.nb >= 2 and tr > 0.0:
            tau = max(1.0, batch * float(np.trace(self.bm2)) / (self.nb - 1) / tr)
        return sigma * (tau / self.n), self.n / tau

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "mean": self.mean.tolist(),
            "m2": self.m2.tolist(),
            "nb": self.nb,
            "bmean": self.bmean.tolist(),
            "bm2": self.bm2.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> _Moments:
        return cls(
            int(d["n"]),
            np.asarray(d["mean"], float).reshape(3),
            np.asarray(d["m2"], float).reshape(3, 3),
            int(d["nb"]),
            np.asarray(d["bmean"], float).reshape(3),
            np.asarray(d["bm2"], float).reshape(3, 3),
        )


def _present(moments: _Moments | None) -> _Moments:
    """Moments of a triad the session has: groups of one session carry the same triads (at least one)."""
    assert moments is not None
    return moments


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
        return _present(self.accel or self.gyro).n

    def merge(self, other: _Group) -> _Group:
        return _Group(
            self.start,
            other.stop,
            self.t_start_s,
            other.t_end_s,
            None if self.accel is None else self.accel.combine(_present(other.accel)),
            None if self.gyro is None else self.gyro.combine(_present(other.gyro)),
            self.temp_sum + other.temp_sum,
            self.temp_n + other.temp_n,
            self.n_intervals + other.n_intervals,
        )

    def position(self, config: PositionConfig, batch: int) -> Position:
        def triad(
            mom: _Moments | None,
        ) -> tuple[FloatArray | None, FloatArray | None, float | None]:
            if mom is None:
                return None, None, None
            cov, n_eff = mom.covariance_of_mean(config.covariance, batch)
            return mom.mean.copy(), cov, n_eff

        am, ac, an = triad(self.accel)
        gm, gc, gn = triad(self.gyro)
        return Position(
            t_start_s=self.t_start_s,
            t_end_s=self.t_end_s,
            n_samples=self.n,
            accel_mean_mps2=am,
            accel_cov_mps2=ac,
            gyro_mean_rps=gm,
            gyro_cov_rps=gc,
            temp_mean_c=self.temp_sum / self.temp_n if self.temp_n else None,
            index_start=self.start,
            index_stop=self.stop,
            n_intervals=self.n_intervals,
            accel_n_eff=an,
            gyro_n_eff=gn,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "start": self.start,
            "stop": self.stop,
            "t_start_s": self.t_start_s,
            "t_end_s": self.t_end_s,
            "accel": None if self.accel is None else self.accel.to_dict(),
            "gyro": None if self.gyro is None else self.gyro.to_dict(),
            "temp_sum": self.temp_sum,
            "temp_n": self.temp_n,
            "n_intervals": self.n_intervals,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> _Group:
        return cls(
            int(d["start"]),
            int(d["stop"]),
            float(d["t_start_s"]),
            float(d["t_end_s"]),
            None if d["accel"] is None else _Moments.from_dict(d["accel"]),
            None if d["gyro"] is None else _Moments.from_dict(d["gyro"]),
            float(d["temp_sum"]),
            int(d["temp_n"]),
            int(d["n_intervals"]),
        )


def _short_rejection(run: StaticInterval, min_static_s: float) -> PositionRejection:
    return PositionRejection(
        RejectReason.SHORT_INTERVAL,
        run.start,
        run.stop,
        run.t_start_s,
        run.t_end_s,
        f"static run of {run.duration_s:.3f} s < min_static_s {min_static_s:g} s",
    )


def _few_rejection(
    run: StaticInterval, n_left: int, trim: int, min_samples: int
) -> PositionRejection:
    return PositionRejection(
        RejectReason.TOO_FEW_SAMPLES,
        run.start,
        run.stop,
        run.t_start_s,
        run.t_end_s,
        f"{n_left} samples left of {run.n_samples} after trimming {trim} per end < min_samples {min_samples}",
    )


def _offer(
    det_config: StaticDetectorConfig,
    pending: _Group | None,
    group: _Group,
    rotation: Callable[[], float | None],
) -> tuple[_Group, _Group | None, PositionRejection | None]:
    """Merge ``group`` into ``pending`` or start a new position: ``(new pending, emitted or None, rejection or None)``.

    ``rotation()`` gives the rotation between them (deg; None where unknown), asked only where the
    specific force leaves the answer open (:func:`is_new_orientation`: a turn of the specific force
    by ``orientation_change_deg`` is a new position whatever the gyros say): integrating the gyros
    is a Python step per sample (:class:`RotationIntegrator`).
    """
    if pending is None:
        return group, None, None
    direction = (
        None
        if group.accel is None
        else direction_change_deg(_present(pending.accel).mean, group.accel.mean)
    )
    turned = direction is not None and not direction < det_config.orientation_change_deg
    rotation_deg = None if turned else rotation()
    if is_new_orientation(det_config, direction_deg=direction, rotation_deg=rotation_deg):
        return group, pending, None
    parts = [
        f"{name} {v:.3f}°"
        for name, v in (("direction change", direction), ("rotation", rotation_deg))
        if v is not None
    ]
    rej = PositionRejection(
        RejectReason.MERGED,
        group.start,
        group.stop,
        group.t_start_s,
        group.t_end_s,
        f"merged into the position from t={pending.t_start_s:.3f} s: {', '.join(parts)}"
        f" < {det_config.orientation_change_deg:g}°",
    )
    return pending.merge(group), None, rej


# ---------------------------------------------------------------------------
# Batch


def build_positions(
    session: ImuSession, detection: StaticDetection, *, config: PositionConfig = PositionConfig()
) -> PositionsResult:
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
        raise ValueError(
            f"detection covers {detection.static.shape[0]} samples, the session has {t.shape[0]}"
        )
    det_cfg = detection.config
    rate = detection.rate_hz
    trim = config.trim_samples(rate)
    batch = config.batch_samples(rate)
    acc = detection.accepted
    runs = sorted(
        [(iv, False) for iv in detection.intervals] + [(iv, True) for iv in detection.short_runs],
        key=lambda r: r[0].start,
    )

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
            int(rows[0]),
            int(rows[-1]) + 1,
            float(t[rows[0]]),
            float(t[rows[-1]]),
            None if accel is None else _Moments.of_samples(accel[rows], batch),
            None if gyro is None else _Moments.of_samples(gyro[rows], batch),
            0.0 if finite_t is None else float(finite_t.sum()),
            0 if finite_t is None else int(finite_t.size),
        )
        rotation: Callable[[], float | None] = _unknown_rotation
        if gyro is not None and pending is not None:
            rotation = functools.partial(
                _rotation_between,
                t,
                gyro,
                acc,
                detection.segment_start,
                _present(pending.gyro).mean,
                last_run_end,
                first,
            )
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


def _unknown_rotation() -> float | None:
    """No gyros, or no position before: no rotation to compare."""
    return None


def _rotation_between(
    t: FloatArray,
    gyro: FloatArray,
    acc: IntArray,
    segment_start: BoolArray,
    bias: FloatArray,
    last_end: int,
    first: int,
) -> float | None:
    """Rotation angle (deg) over accepted samples ``(last_end, first]``; None across a segment break."""
    if np.any(segment_start[last_end + 1 : first + 1]):
        return None
    rot = RotationIntegrator(bias)
    rows = acc[last_end : first + 1]
    tt = t[rows]
    rot.add_many(gyro[rows[1:]], tt[1:] - tt[:-1])
    return rot.angle_deg


# ---------------------------------------------------------------------------
# Streaming


_NAN = float("nan")
_MIN_VECTOR = 64
"""Shortest stretch :meth:`PositionAccumulator.update_batch` vectorizes: below, numpy's per-call cost exceeds the loop's."""


@dataclass
class _RunSums:
    """Running sums of one static run's kept samples, shifted by the first kept sample (plain floats)."""

    n: int = 0
    shift: list[float] = field(default_factory=lambda: [0.0] * 6)
    s: list[float] = field(default_factory=lambda: [0.0] * 6)
    q: list[float] = field(default_factory=lambda: [0.0] * 12)
    part: list[float] = field(default_factory=lambda: [0.0] * 6)
    part_n: int = 0
    nb: int = 0
    bs: list[float] = field(default_factory=lambda: [0.0] * 6)
    bq: list[float] = field(default_factory=lambda: [0.0] * 12)
    temp_sum: float = 0.0
    temp_n: int = 0
    start: int = 0
    stop: int = 0
    t_first: float = 0.0
    t_last: float = 0.0


def _seq_sum(start: float, values: FloatArray) -> float:
    """``start + v₀ + v₁ + …`` added one by one, left to right (what a running ``+=`` gives, bit for bit)."""
    if values.size == 0:
        return start
    return float(np.cumsum(np.concatenate([[start], values]))[-1])


def _seq_sum_rows(start: FloatArray, rows: FloatArray) -> FloatArray:
    """(K,) ``start + rows[0] + rows[1] + …`` per column, added row by row (:func:`_seq_sum` per column)."""
    if rows.shape[0] == 0:
        return start
    stacked = np.empty((rows.shape[0] + 1, rows.shape[1]))  # C order, whatever rows' order
    stacked[0], stacked[1:] = start, rows
    if stacked.shape[1] == 1:  # one column is summed pairwise: cumsum adds in turn
        last: FloatArray = np.cumsum(stacked, axis=0)[-1]
        return last
    # Down the rows of a C-ordered array of two columns or more, a sum adds the rows in turn (numpy
    # sums pairwise only along the fast axis): the cumsum's last row, in a fifth of its time.
    sums: FloatArray = stacked.sum(axis=0)
    return sums


@dataclass(frozen=True)
class _Extended:
    """Accepted samples ``base …``: the ring before a batch, then the batch; columns t, ax … gz, temp, and input indices."""

    base: int
    cols: list[FloatArray]
    idx: IntArray


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
        self.detector = StreamingStaticDetector(
            detector_config, rate_hz=rate_hz, has_accel=has_accel, has_gyro=has_gyro
        )
        self.config = config
        # Channel offsets (accel 0, gyro 3) of the triads present, fixed here so the per-sample path builds nothing.
        self._offsets = tuple(o for o, present in ((0, has_accel), (3, has_gyro)) if present)
        # The same as channel indices, and the (q index, channel, channel) of _add's products, for the batch path.
        self._chans = [o + i for o in self._offsets for i in range(3)]
        prods = [
            (2 * o + kk, o + u, o + v)
            for o in self._offsets
            for kk, (u, v) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
        ]
        base = {ch: i for i, ch in enumerate(self._chans)}
        self._pairs = tuple(
            np.array(v)
            for v in (
                [p[0] for p in prods],
                [base[p[1]] for p in prods],
                [base[p[2]] for p in prods],
            )
        )
        self._trim = config.trim_samples(rate_hz)
        self._batch = config.batch_samples(rate_hz)
        self._ring_n = self.detector.window_samples + self._trim + 2
        self._ring = SwitchedRing(
            [[0.0] * self._ring_n for _ in range(8)]
        )  # t, ax, ay, az, gx, gy, gz, temp
        self._ring_idx = SwitchedRing([0] * self._ring_n, int)
        self._run_open = False
        self._run_count = 0
        self._sums = _RunSums()
        self._pending: _Group | None = None
        self._rot = RotationIntegrator()
        self._rot_active = False
        self.rejections: list[PositionRejection] = []

    # -- per sample ---------------------------------------------------------

    def update(
        self,
        t_s: float,
        ax: float,
        ay: float,
        az: float,
        gx: float,
        gy: float,
        gz: float,
        temp_c: float | None = None,
    ) -> Position | None:
        det = self.detector
        before = det.n_accepted
        det.update(t_s, ax, ay, az, gx, gy, gz)
        if det.n_accepted != before:
            p = before % self._ring_n
            r = self._ring.lists()
            r[0][p] = t_s
            if det.has_accel:
                r[1][p], r[2][p], r[3][p] = ax, ay, az
            if det.has_gyro:
                r[4][p], r[5][p], r[6][p] = gx, gy, gz
            r[7][p] = _NAN if temp_c is None else temp_c
            self._ring_idx.lists()[p] = det.n_input - 1
        if det.fin_hi == det.fin_lo and det.closed_run is None and not det.fin_break:
            return None
        return self._after_detector()

    def update_batch(
        self,
        t_s: FloatArray,
        accel_mps2: FloatArray | None,
        gyro_rps: FloatArray | None,
        temp_c: FloatArray | None = None,
    ) -> tuple[list[Position], FinalDecisions]:
        """:meth:`update` over N samples: the same positions, rejections, decisions and state.

        Parameters
        ----------
        t_s : (N,) time stamps, s.
        accel_mps2 : (N, 3) specific force, m/s² (None when the accumulator has no accelerometers).
        gyro_rps : (N, 3) angular rate, rad/s (None without gyros).
        temp_c : (N,) temperature, °C, NaN where unknown, or None.

        Returns ``(positions, decisions)``: the positions completed, and the detector
        decisions that became final (:class:`~estimators.static_detector.FinalDecisions`,
        the ``fin_*`` outputs of every :meth:`update` call joined). The stretch of a batch after the detector's window is full
        whose samples are all accepted into the open segment runs vectorized
        (:meth:`StreamingStaticDetector.update_batch`); a batch with a rejected sample or
        a time gap, and the first samples of a segment, go through :meth:`update`.
        """
        det = self.detector
        t = np.asarray(t_s, dtype=float).reshape(-1)
        n = t.shape[0]
        triads = {}
        for name, arr, present in (
            ("accel_mps2", accel_mps2, det.has_accel),
            ("gyro_rps", gyro_rps, det.has_gyro),
        ):
            if present:
                if arr is None:
                    raise ValueError(
                        f"{name} is required: the accumulator was built with that triad"
                    )
                triads[name] = np.asarray(arr, dtype=float)
                if triads[name].shape != (n, 3):
                    raise ValueError(f"{name} must have shape ({n}, 3), got {triads[name].shape}")
        accel = triads.get("accel_mps2")
        gyro = triads.get("gyro_rps")
        temp = np.full(n, np.nan) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(-1)
        if temp.shape != (n,):
            raise ValueError(f"temp_c must have shape ({n},), got {temp.shape}")
        positions: list[Position] = []
        steps: list[tuple[int, int, int, bool]] = []
        start = det.next_final
        i = 0
        while i < n and not det.steady():
            self._update_row(t, accel, gyro, temp, i, positions, steps)
            i += 1
        if i < n and (
            n - i < _MIN_VECTOR
            or not det.clean_batch(
                t[i:], None if accel is None else accel[i:], None if gyro is None else gyro[i:]
            )
        ):
            for k in range(i, n):
                self._update_row(t, accel, gyro, temp, k, positions, steps)
            i = n
        decisions = FinalDecisions.from_steps(start, steps)
        if i < n:
            decisions = decisions.then(
                self._steady_batch(
                    t[i:],
                    None if accel is None else accel[i:],
                    None if gyro is None else gyro[i:],
                    temp[i:],
                    positions,
                )
            )
        return positions, decisions

    def _update_row(
        self,
        t: FloatArray,
        accel: FloatArray | None,
        gyro: FloatArray | None,
        temp: FloatArray,
        i: int,
        positions: list[Position],
        steps: list[tuple[int, int, int, bool]],
    ) -> None:
        det = self.detector
        ax, ay, az = (0.0, 0.0, 0.0) if accel is None else accel[i].tolist()
        gx, gy, gz = (0.0, 0.0, 0.0) if gyro is None else gyro[i].tolist()
        tc = float(temp[i])
        pos = self.update(float(t[i]), ax, ay, az, gx, gy, gz, None if tc != tc else tc)
        if pos is not None:
            positions.append(pos)
        if det.fin_hi > det.fin_lo:
            steps.append((det.fin_lo, det.fin_split, det.fin_hi, det.fin_break))

    def _steady_batch(
        self,
        t: FloatArray,
        accel: FloatArray | None,
        gyro: FloatArray | None,
        temp: FloatArray,
        positions: list[Position],
    ) -> FinalDecisions:
        """Clean samples in the steady state: each finalizes one decision (detector's ``update_batch``)."""
        det = self.detector
        n = t.shape[0]
        w = det.window_samples
        rn = self._ring_n
        c0 = det.n_accepted
        idx0 = det.n_input
        static, closes = det.update_batch(t, accel, gyro)
        # Accepted samples c0 − rn … c0 + n − 1: the ring, then the batch (absent triads keep the ring's values).
        old = np.arange(c0 - rn, c0) % rn
        every = np.arange(c0 - rn, c0 + n) % rn
        ring = self._ring.array()
        cols = [np.concatenate([ring[0][old], t])]
        for o, x in ((0, accel), (3, gyro)):
            for k in range(3):
                cols.append(
                    ring[1 + o + k][every]
                    if x is None
                    else np.concatenate([ring[1 + o + k][old], x[:, k]])
                )
        cols.append(np.concatenate([ring[7][old], temp]))
        idx = np.concatenate([self._ring_idx.array()[old], idx0 + np.arange(n)])
        ext = _Extended(base=c0 - rn, cols=cols, idx=idx)

        j0 = c0 - w + 1  # decision finalized by the first sample
        edges = np.flatnonzero(static[1:] != static[:-1]) + 1
        # A run that closed at a static decision ended at a jump: a new run starts there.
        jumps = sorted(a for a in closes if static[a])
        bounds = sorted({0, *edges.tolist(), *jumps, n})
        for a, b in itertools.pairwise(bounds):
            ja, jb = j0 + a, j0 + b
            if a in closes:
                emitted = self._close_run(*closes[a])
                if emitted is not None:
                    positions.append(emitted)
            if static[a]:
                if not self._run_open:
                    self._run_open = True
                    self._run_count = 0
                    self._sums = _RunSums()
                    if self._rot_active:
                        self._integrate_ext(ext, ja, ja + 1)
                        self._rot.set_mark()
                    first = ja + 1
                else:
                    first = ja
                # Sample number r of the run (1-based) adds sample j − trim once r > 2·trim.
                r0 = self._run_count
                if self._rot_active and first < jb:
                    self._integrate_ext(ext, first, self._first_sure(ext, first, jb, ja, r0))
                self._run_count += b - a
                skip = max(0, 2 * self._trim - r0)
                if ja + skip < jb:
                    self._add_many(ext, ja + skip - self._trim, jb - self._trim)
            elif self._rot_active:
                self._integrate_ext(ext, ja, jb)
        # The ring keeps the last rn accepted samples (absent triads keep their old values).
        tail = np.arange(max(0, n - rn), n)
        pos = (c0 + tail) % rn
        rows = [0, *(1 + c for c in self._chans), 7]
        self._ring.array()[np.ix_(np.asarray(rows), pos)] = np.vstack(
            [cols[k][rn + tail] for k in rows]
        )
        self._ring_idx.array()[pos] = idx[rn + tail]
        return FinalDecisions(j0, static, np.zeros(n, dtype=bool))

    def _first_sure(self, ext: _Extended, lo: int, hi: int, ja: int, r0: int) -> int:
        """First static sample in ``[lo, hi)`` from which :meth:`_run_sure` holds (``hi`` if none).

        The run holds ``r0`` samples before ``ja``; sample ``j`` is judged with the
        kept samples added before it, as the per-sample path does.
        """
        sm = self._sums
        tt = ext.cols[0]
        trim2 = 2 * self._trim
        d = np.arange(lo - ja, hi - ja)
        n_before = sm.n + np.maximum(0, r0 + d - max(r0, trim2))
        if sm.n:
            t_first = sm.t_first
        else:
            first_add = ja + max(0, trim2 - r0)
            if first_add >= hi:
                return hi
            t_first = tt[first_add - self._trim - ext.base]
        sure = (n_before >= self.config.min_samples) & (
            tt[lo - ext.base : hi - ext.base] - t_first >= self.detector.config.min_static_s
        )
        k = int(np.argmax(sure))
        return lo + k if sure[k] else hi

    def _integrate_ext(self, ext: _Extended, lo: int, hi: int) -> None:
        """:meth:`_integrate` for accepted samples ``[lo, hi)`` from the extended arrays."""
        k0, k1 = lo - ext.base, hi - ext.base
        if k1 > k0:
            tt = ext.cols[0]
            gyro = np.column_stack([ext.cols[c][k0:k1] for c in (4, 5, 6)])
            self._rot.add_many(gyro, tt[k0:k1] - tt[k0 - 1 : k1 - 1])

    def _add_many(self, ext: _Extended, lo: int, hi: int) -> None:
        """:meth:`_add` for accepted samples ``[lo, hi)``: the same sequential sums, by ``cumsum``."""
        k0, k1 = lo - ext.base, hi - ext.base
        sm = self._sums
        cols = ext.cols
        if sm.n == 0:
            sm.shift = [float(cols[k][k0]) for k in range(1, 7)]
            sm.start = int(ext.idx[k0])
            sm.t_first = float(cols[0][k0])
        sm.n += k1 - k0
        sm.stop = int(ext.idx[k1 - 1]) + 1
        sm.t_last = float(cols[0][k1 - 1])
        temps = cols[7][k0:k1]
        temps = temps[~np.isnan(temps)]
        if temps.size:
            sm.temp_sum = _seq_sum(sm.temp_sum, temps)
            sm.temp_n += int(temps.size)
        bt = self._batch
        m = k1 - k0
        head = min(m, bt - sm.part_n)  # samples that complete (or extend) the open batch
        n_full = (m - head) // bt
        tail = m - head - n_full * bt
        done_first = sm.part_n + head == bt
        chans, pairs = self._chans, self._pairs
        y = np.column_stack([cols[1 + c][k0:k1] for c in chans]) - np.asarray(sm.shift)[chans]
        s_arr, q_arr, part = np.asarray(sm.s), np.asarray(sm.q), np.asarray(sm.part)
        s_arr[chans] = _seq_sum_rows(s_arr[chans], y)
        q_arr[pairs[0]] = _seq_sum_rows(q_arr[pairs[0]], y[:, pairs[1]] * y[:, pairs[2]])
        first = _seq_sum_rows(part[chans], y[:head])
        # Each batch's rows added in turn (_seq_sum_rows: the channels are the fast axis).
        whole = np.ascontiguousarray(y[head : head + n_full * bt])
        full = whole.reshape(n_full, bt, len(chans)).sum(axis=1)
        if done_first:
            means = np.vstack([first, full]) / bt
            part[chans] = _seq_sum_rows(np.zeros(len(chans)), y[m - tail :])
        else:
            means = full / bt
            part[chans] = first
        bs_arr, bq_arr = np.asarray(sm.bs), np.asarray(sm.bq)
        bs_arr[chans] = _seq_sum_rows(bs_arr[chans], means)
        bq_arr[pairs[0]] = _seq_sum_rows(bq_arr[pairs[0]], means[:, pairs[1]] * means[:, pairs[2]])
        sm.s, sm.q, sm.part, sm.bs, sm.bq = (
            s_arr.tolist(),
            q_arr.tolist(),
            part.tolist(),
            bs_arr.tolist(),
            bq_arr.tolist(),
        )
        nb_new = int(done_first) + n_full
        sm.nb += nb_new
        sm.part_n = tail if done_first else sm.part_n + head

    def _after_detector(self) -> Position | None:
        det = self.detector
        emitted = None
        # A run that ended at a jump closes before the static decision after the jump opens the next.
        if det.closed_run is not None and det.fin_jump:
            emitted = self._close_run(det.closed_run, det.closed_run_short)
        for c in range(det.fin_lo, det.fin_split):
            self._static_sample(c)
        if det.closed_run is not None and not det.fin_jump:
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
        r = self._ring.lists()
        self._rot.add(r[4][p], r[5][p], r[6][p], r[0][p] - r[0][p0])

    def _static_sample(self, c: int) -> None:
        if not self._run_open:
            self._run_open = True
            self._run_count = 0
            self._sums = _RunSums()
            if self._rot_active:
                self._integrate(c)
                self._rot.set_mark()
        elif self._rot_active and not self._run_sure(c):
            self._integrate(c)
        self._run_count += 1
        if self._run_count > 2 * self._trim:
            self._add(c - self._trim)

    def _run_sure(self, c: int) -> bool:
        """Whether the open run will be accepted whatever follows sample ``c``.

        Then its close resets the rotation, so integrating its samples from ``c``
        on cannot change any output: the hot path skips them. The run spans at
        least ``t(c) − t(first kept sample)`` and already keeps ``min_samples``.
        """
        sm = self._sums
        return (
            sm.n >= self.config.min_samples
            and self._ring.lists()[0][c % self._ring_n] - sm.t_first
            >= self.detector.config.min_static_s
        )

    def _add(self, c: int) -> None:
        p = c % self._ring_n
        r = self._ring.lists()
        sm = self._sums
        if sm.n == 0:
            sm.shift = [r[k][p] for k in range(1, 7)]
            sm.start = self._ring_idx.lists()[p]
            sm.t_first = r[0][p]
        sm.n += 1
        sm.stop = self._ring_idx.lists()[p] + 1
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
                m0, m1, m2 = (
                    part[o] / self._batch,
                    part[o + 1] / self._batch,
                    part[o + 2] / self._batch,
                )
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

        def moments(o: int) -> _Moments:
            return _Moments.of_sums(
                sm.shift[o : o + 3],
                sm.n,
                sm.s[o : o + 3],
                sm.q[2 * o : 2 * o + 6],
                sm.nb,
                sm.bs[o : o + 3],
                sm.bq[2 * o : 2 * o + 6],
            )

        group = _Group(
            sm.start,
            sm.stop,
            sm.t_first,
            sm.t_last,
            moments(0) if det.has_accel else None,
            moments(3) if det.has_gyro else None,
            sm.temp_sum,
            sm.temp_n,
        )
        known = self._pending is not None and self._rot_active and det.has_gyro
        rot = self._rot
        self._pending, emitted, rej = _offer(
            det.config, self._pending, group, lambda: rot.mark_angle_deg if known else None
        )
        if rej is not None:
            self.rejections.append(rej)
        if det.has_gyro:
            self._rot.reset(_present(self._pending.gyro).mean.tolist())
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

    def state_dict(self) -> dict[str, Any]:
        """Plain JSON-able state (detector, ring, open run, pending position, rotation) for checkpoints."""
        return {
            "detector": self.detector.state_dict(),
            "config": {**asdict(self.config), "covariance": self.config.covariance.value},
            "ring": [[None if v != v else v for v in ch] for ch in self._ring.snapshot()],
            "ring_idx": self._ring_idx.snapshot(),
            "run_open": self._run_open,
            "run_count": self._run_count,
            "sums": asdict(self._sums),
            "pending": None if self._pending is None else self._pending.to_dict(),
            "rot": self._rot.state_dict(),
            "rot_active": self._rot_active,
            "rejections": [r.to_dict() for r in self.rejections],
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> PositionAccumulator:
        try:
            det = StreamingStaticDetector.from_state_dict(state["detector"])
            cfg = PositionConfig(**state["config"])
            acc = cls(
                rate_hz=det.rate_hz,
                has_accel=det.has_accel,
                has_gyro=det.has_gyro,
                detector_config=det.config,
                config=cfg,
            )
            acc.detector = det
            ring = [[_NAN if v is None else float(v) for v in ch] for ch in state["ring"]]
            if (
                len(ring) != 8
                or any(len(ch) != acc._ring_n for ch in ring)
                or len(state["ring_idx"]) != acc._ring_n
            ):
                raise ValueError(f"ring must hold 8 channels of {acc._ring_n} samples")
            acc._ring = SwitchedRing(ring)
            acc._ring_idx = SwitchedRing([int(v) for v in state["ring_idx"]], int)
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
