"""An IMU session in SI units, and its validation with counted rejections.

A session is what every offline tool consumes (calibrate, diagnose, audit):
time stamps and the two triads, optionally temperature. Units follow
:mod:`estimators.conventions`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimators._typing import BoolArray, FloatArray
from estimators.quantiles import median

ACCEL_IMPLAUSIBLE_MPS2 = 1e6
"""Beyond about 100,000 g no accelerometer measures: a larger value is a corrupt record, not a sample."""
GYRO_IMPLAUSIBLE_RPS = 1e4
"""Beyond about 570,000 °/s no gyro measures: a larger value is a corrupt record, not a sample."""


def plausible_rows(accel_mps2: FloatArray | None, gyro_rps: FloatArray | None) -> BoolArray:
    """(N,) rows whose every value is within what a sensor measures (:data:`ACCEL_IMPLAUSIBLE_MPS2`,
    :data:`GYRO_IMPLAUSIBLE_RPS`); NaN compares as plausible here (non-finite rows are told apart)."""
    rows = next(a for a in (accel_mps2, gyro_rps) if a is not None).shape[0]
    ok = np.ones(rows, dtype=bool)
    for triad, bound in ((accel_mps2, ACCEL_IMPLAUSIBLE_MPS2), (gyro_rps, GYRO_IMPLAUSIBLE_RPS)):
        if triad is not None:
            ok &= ~(np.abs(triad) > bound).any(axis=1)
    return ok


def finite_rows(
    t_s: FloatArray, accel_mps2: FloatArray, gyro_rps: FloatArray, temp_c: FloatArray | None
) -> BoolArray:
    """(N,) samples whose time stamp and values (temperature too, when given) are all finite."""
    finite: BoolArray = (
        np.isfinite(t_s) & np.isfinite(accel_mps2).all(axis=1) & np.isfinite(gyro_rps).all(axis=1)
    )
    if temp_c is not None:
        finite &= np.isfinite(temp_c)
    return finite


def all_usable(
    t_s: FloatArray, accel_mps2: FloatArray, gyro_rps: FloatArray, temp_c: FloatArray | None
) -> bool:
    """Whether every sample is finite and plausible (:func:`finite_rows` and :func:`plausible_rows`
    true on every row), one reduction an array: a triad's largest magnitude is NaN when any value
    is, and NaN and ±inf both fail the bound."""
    return bool(
        np.isfinite(t_s).all()
        and np.abs(accel_mps2).max(initial=0.0) <= ACCEL_IMPLAUSIBLE_MPS2
        and np.abs(gyro_rps).max(initial=0.0) <= GYRO_IMPLAUSIBLE_RPS
        and (temp_c is None or np.isfinite(temp_c).all())
    )


class SessionError(ValueError):
    """The session cannot be used at all (the message says why, in one line)."""


@dataclass(frozen=True)
class ImuSession:
    """Samples of one IMU.

    Attributes
    ----------
    t_s : (N,) sample times, s, strictly increasing after validation.
    accel_mps2 : (N, 3) specific force, m/s², sensor axes; or None (no accelerometer triad).
    gyro_rps : (N, 3) angular rate, rad/s, sensor axes; or None (no gyro triad).
    temp_c : (N,) temperature, °C; or None.
    """

    t_s: FloatArray
    accel_mps2: FloatArray | None
    gyro_rps: FloatArray | None
    temp_c: FloatArray | None = None

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def rate_hz(self) -> float:
        """Median sample rate, Hz."""
        if self.n_samples < 2:
            raise SessionError("a session needs at least two samples to have a rate")
        return float(1.0 / median(np.diff(self.t_s)))

    def select(self, mask_or_slice: BoolArray | slice) -> ImuSession:
        """A sub-session (boolean mask or slice over samples)."""

        def pick(a: FloatArray | None) -> FloatArray | None:
            return None if a is None else a[mask_or_slice]

        return ImuSession(
            self.t_s[mask_or_slice], pick(self.accel_mps2), pick(self.gyro_rps), pick(self.temp_c)
        )


@dataclass
class Rejections:
    """Counts of samples removed by validation, by reason (nothing is dropped silently)."""

    counts: dict[str, int] = field(default_factory=dict)

    def add(self, reason: str, n: int) -> None:
        if n:
            self.counts[reason] = self.counts.get(reason, 0) + int(n)

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def validate_session(
    session: ImuSession,
    *,
    accel_limit_mps2: float | None = None,
    gyro_limit_rps: float | None = None,
) -> tuple[ImuSession, Rejections]:
    """Check a session and drop unusable samples, counting each reason.

    Rules: shapes must agree (else :class:`SessionError`); samples with a
    non-finite value, a value beyond what any sensor measures
    (:data:`ACCEL_IMPLAUSIBLE_MPS2`, :data:`GYRO_IMPLAUSIBLE_RPS`), a time stamp
    that is not later than the last kept one (duplicate or going back), or a
    value at or beyond a saturation limit are dropped and counted. Raises :class:`SessionError` if nothing usable is left.

    Parameters
    ----------
    accel_limit_mps2, gyro_limit_rps : full-scale ranges; a sample with any axis
        at or beyond them is saturated (its true value is unknown).
    """
    t = np.asarray(session.t_s, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise SessionError(f"t_s must be a non-empty 1-D array, got shape {t.shape}")
    if session.accel_mps2 is None and session.gyro_rps is None:
        raise SessionError("the session has neither accelerometer nor gyro samples")
    arrays: dict[str, FloatArray | None] = {}
    for name, arr, shape in (
        ("accel_mps2", session.accel_mps2, (t.size, 3)),
        ("gyro_rps", session.gyro_rps, (t.size, 3)),
        ("temp_c", session.temp_c, (t.size,)),
    ):
        if arr is None:
            arrays[name] = None
            continue
        a = np.asarray(arr, dtype=float)
        if a.shape != shape:
            raise SessionError(f"{name} must have shape {shape}, got {a.shape}")
        arrays[name] = a

    rej = Rejections()
    finite = np.isfinite(t)
    for name in ("accel_mps2", "gyro_rps"):
        triad = arrays[name]
        if triad is not None:
            finite &= np.isfinite(triad).all(axis=1)
    if arrays["temp_c"] is not None:
        finite &= np.isfinite(arrays["temp_c"])
    rej.add("non_finite", int((~finite).sum()))
    keep = finite.copy()
    # A finite but absurd value (one corrupt record of 1e300) would overflow the squares of every
    # later sum: it is no sample.
    absurd = keep & ~plausible_rows(arrays["accel_mps2"], arrays["gyro_rps"])
    rej.add("implausible_value", int(absurd.sum()))
    keep &= ~absurd

    for name, limit in (("accel_mps2", accel_limit_mps2), ("gyro_rps", gyro_limit_rps)):
        triad = arrays[name]
        if limit is not None and triad is not None:
            sat = keep & (np.abs(triad) >= limit).any(axis=1)
            rej.add(f"saturated_{name.split('_')[0]}", int(sat.sum()))
            keep &= ~sat

    # A time stamp must be later than the last *kept* one: a running maximum over
    # the kept samples finds duplicates and steps back in one vectorized pass.
    idx = np.flatnonzero(keep)
    if idx.size:
        tk = t[idx]
        prev_max = np.maximum.accumulate(np.concatenate([[-np.inf], tk[:-1]]))
        bad = tk <= prev_max
        rej.add("non_monotonic_time", int(bad.sum()))
        keep[idx[bad]] = False

    if not keep.any():
        raise SessionError(f"no usable samples left after validation (rejected: {rej.counts})")
    out = ImuSession(
        t[keep],
        None if arrays["accel_mps2"] is None else arrays["accel_mps2"][keep],
        None if arrays["gyro_rps"] is None else arrays["gyro_rps"][keep],
        None if arrays["temp_c"] is None else arrays["temp_c"][keep],
    )
    return out, rej
