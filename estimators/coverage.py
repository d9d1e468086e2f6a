"""Coverage of a verdict: which checks ran, how small a fault each would have caught, and which did not run.

Silence is never health (methods.md M1 and the project brief): a verdict says
what it tested, on how many samples or positions, the **minimum detectable
fault** (MDF) of each check that ran, and why each check that did not run could
not. "No fault" is said only when every check that applies ran
(:func:`verdict`).

The minimum detectable fault
----------------------------
The MDF of a check is the smallest deviation of a parameter from its passport
nominal that the check detects with probability at least ``power`` (0.95) at its
stated false-alarm rate, for the orientations or positions the data actually
held. Given per axis: the zero signal in SI (m/s² or rad/s) and the scale error
(relative); "% of the tolerance" is ``100·MDF/tolerance`` of the same parameter.

**F0** (methods.md M1, :mod:`estimators.scalar`). With the unit at rest along
the unit gravity direction ``u`` (body frame) and the passport's errors
compensated, a zero-signal fault ``b`` (normalized, ``b_si / ref``) on axis
``i`` gives ``|u + b eᵢ|² = 1 + 2 b uᵢ + b²``, so it moves the tested
statistic ``s = ½(|ã|² − 1)`` by ``b uᵢ + ½b²``; a scale fault ``e`` on axis
``i`` moves it by ``e uᵢ² + ½e² uᵢ²``. To first order (the MDF small against 1:
the neglected ``½b²`` is a relative ``b/(2uᵢ)`` of the shift) the shift is
``Δ = b uᵢ`` or ``e uᵢ²``. A sample fails where ``|s| > λ0``; with the per-sample
noise of ``s`` at most ``σ`` (the worst axis, :class:`estimators.scalar.Lambda0`
``noise_std``), a sample of a faulted unit fails with probability at least
``Φ((Δ − λ0)/σ)``, and F0 declares a failure after ``persist`` failing samples
in a row (:func:`estimators.scalar.persistent_failure`). The first ``persist``
samples at an orientation all fail with probability ``Φ((Δ − λ0)/σ)^persist``,
which reaches ``power`` at ``Δ = λ0 + k σ`` with ``k = Φ⁻¹(power^(1/persist))``
(:func:`persistence_margin`). The largest ``|uᵢ|`` seen at rest gives the
smallest fault, so::

    mdf_bias_i  = (λ0 + k σ) · ref / max|uᵢ|        (SI)
    mdf_scale_i = (λ0 + k σ) / max uᵢ²

(infinite for an axis that never saw gravity). The first-order shift holds for a
fault small against the reference: an axis whose MDF would reach the reference
itself (a zero signal of 1 g, a scale error of 100 %) saw too little gravity to be
tested, and its MDF is infinite too. A session holding many samples at
that orientation detects the fault with a higher probability still: the MDF is
a bound that holds for any session length.

**F1…F9** (methods.md M1, :mod:`estimators.diagnosis`). Predicate ``j`` fails
when ``|ê_j − ν_j| > λ_j + z s_j``; for a true deviation ``Δ`` the estimate
``ê_j − ν_j ~ N(Δ, s_j²)`` passes that threshold with probability ``power`` at::

    mdf_j = λ_j + (z + z_power) s_j,      z_power = Φ⁻¹(power)

(the other tail is negligible). ``s_j = (threshold_j − λ_j)/z`` is read back
from the diagnosis; zero signals are given in SI (× the estimate's reference).

**Cross-IMU norm** (in flight, :mod:`estimators.cross_imu_norm`): the shift of the
norm difference its CUSUM finds within a mean delay of 5 s, ``μ* σ̂`` (derived there);
a zero signal along the specific force (or the rotation) moves the norm by itself, a scale
error ``e`` of an axis carrying the specific force ``|f|`` by ``e |f|``: :func:`norm_coverage`.

**Gross plausibility** (the gross test on window means at rest). The test fails
where the mean of a rest window departs from its reference by more than the
tolerance plus ``z_α σ_mean`` (``z_α = Φ⁻¹(1 − α/2)``, two-sided, α the false
alarm probability per window). A zero-signal fault ``b_si`` on axis ``i`` moves
``|a|`` by ``b_si uᵢ``, a scale fault ``e`` by ``e·ref·uᵢ²``, hence::

    mdf_bias_i  = (tol + (z_α + z_power) σ_mean) / max|uᵢ|
    mdf_scale_i = (tol + (z_α + z_power) σ_mean) / (ref · max uᵢ²)

All functions are pure: they take plain numbers, so any check can state its coverage.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from statistics import NormalDist
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray
from estimators.conventions import AXES, Triad

if TYPE_CHECKING:  # the diagnosis pulls in the nine-parameter fit: not needed to read coverage
    from estimators.diagnosis import Diagnosis

DEFAULT_POWER = 0.95
"""Probability with which a fault of the size of the MDF is detected."""

Triple = tuple[float, float, float]

IN_FLIGHT_WITHIN_S = 10.0
"""The in-flight checks state the fault they find within this time of its onset, s."""

OBSERVABLE_SHARE = 0.5
"""An axis whose share of the specific force, rms of ``f̃_i/|f̃|`` in flight, is below this is not
observable by an in-flight check on ``|f̃|``: its MDF would be more than twice the norm's."""


class Check(StrEnum):
    """A check a verdict may rest on."""

    F0 = "F0"
    F1_F9 = "F1-F9"
    GROSS = "gross"
    STREAM = "stream"
    CROSS_IMU = "cross_imu"
    THRUST_AXIS = "thrust_axis"
    CROSS_IMU_NORM = "cross_imu_norm"


class Verdict(StrEnum):
    """What a verdict may say (:func:`verdict`)."""

    FAULT = "fault"
    NO_FAULT = "no fault"
    NO_FINDING = "no finding within coverage"


@dataclass(frozen=True)
class CheckCoverage:
    """What one check of one triad (or of the stream) covered.

    Attributes
    ----------
    check : the :class:`Check`.
    triad : the triad, None for the stream and cross-IMU checks.
    ran : the check ran in full.
    applies : False when the check cannot apply to this sensor at all (a MEMS gyro
        against the Earth rate): then its not running is no missing coverage.
    samples : samples tested (the gross test: windows at rest; the cross-IMU norm: seconds).
    positions : positions used (F1…F9).
    mdf_bias_si : per axis, minimum detectable zero signal, m/s² or rad/s (inf: axis not seen).
    mdf_scale : per axis, minimum detectable relative scale error (0.02 = 2 %).
    tolerance_bias_si, tolerance_scale : the passport's tolerances of the same parameters.
    false_alarm_prob : the check's false-alarm probability, per test as the check states it.
    reason : why it did not run, or what of it did not ("" when it ran in full).
    """

    check: Check
    triad: Triad | None
    ran: bool
    applies: bool = True
    samples: int = 0
    positions: int = 0
    mdf_bias_si: Triple | None = None
    mdf_scale: Triple | None = None
    tolerance_bias_si: Triple | None = None
    tolerance_scale: Triple | None = None
    false_alarm_prob: float | None = None
    reason: str = ""

    @property
    def missing(self) -> bool:
        """A check that applies and did not run in full: the verdict cannot say "no fault"."""
        return self.applies and not self.ran

    @property
    def name(self) -> str:
        return self.check.value if self.triad is None else f"{self.triad.value} {self.check.value}"

    def to_dict(self) -> dict[str, Any]:
        def triple(v: Triple | None) -> list[float | None] | None:
            # JSON has no infinity: an axis the check did not see is null.
            return None if v is None else [x if math.isfinite(x) else None for x in v]

        return {
            "check": self.check.value,
            "triad": None if self.triad is None else self.triad.value,
            "ran": self.ran,
            "applies": self.applies,
            "samples": self.samples,
            "positions": self.positions,
            "mdf_bias_si": triple(self.mdf_bias_si),
            "mdf_scale": triple(self.mdf_scale),
            "tolerance_bias_si": triple(self.tolerance_bias_si),
            "tolerance_scale": triple(self.tolerance_scale),
            "false_alarm_prob": self.false_alarm_prob,
            "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CheckCoverage:
        """Inverse of :meth:`to_dict` (null axes are infinite again)."""

        def triple(v: Any) -> Triple | None:
            if v is None:
                return None
            x = tuple(math.inf if a is None else float(a) for a in v)
            if len(x) != 3:
                raise ValueError(f"coverage: a per-axis value needs 3 numbers, got {v!r}")
            return (x[0], x[1], x[2])

        fa = d.get("false_alarm_prob")
        return cls(
            check=Check(d["check"]),
            triad=None if d.get("triad") is None else Triad(d["triad"]),
            ran=bool(d["ran"]),
            applies=bool(d.get("applies", True)),
            samples=int(d.get("samples", 0)),
            positions=int(d.get("positions", 0)),
            mdf_bias_si=triple(d.get("mdf_bias_si")),
            mdf_scale=triple(d.get("mdf_scale")),
            tolerance_bias_si=triple(d.get("tolerance_bias_si")),
            tolerance_scale=triple(d.get("tolerance_scale")),
            false_alarm_prob=None if fa is None else float(fa),
            reason=str(d.get("reason", "")),
        )

    def line(self, unit: str = "") -> str:
        """One human line: what ran on how much and its MDF per axis (SI and % of tolerance), or why not."""
        if not self.ran and not self.applies:
            return f"{self.name}: does not apply ({self.reason})"
        if not self.ran and self.mdf_bias_si is None:
            return f"{self.name}: NOT TESTED ({self.reason})"
        if self.check is Check.THRUST_AXIS and self.mdf_bias_si is not None:
            return self._in_flight_line(self.mdf_bias_si, unit)
        if self.check is Check.CROSS_IMU_NORM and self.mdf_bias_si is not None:
            mdf = self.mdf_bias_si
            blind = [AXES[k] for k in range(3) if not math.isfinite(mdf[k])]
            seen = ", ".join(
                f"{AXES[k]} {mdf[k]:.2g}{unit}" for k in range(3) if AXES[k] not in blind
            )
            if len(blind) == 3:
                return (
                    f"{self.name}: in flight tested on {self.samples:,} s; a zero signal on "
                    f"{', '.join(blind)} not observable ({self.reason})"
                )
            return (
                f"{self.name}: in flight tested on {self.samples:,} s, MDF "
                + (
                    f"{seen}; {', '.join(blind)} not observable"
                    if blind
                    else f"{mdf[0]:.2g}{unit} of the norm"
                )
                + f" ({self.reason})"
            )
        amount = (
            f"{self.positions} position{'s' * (self.positions != 1)}"
            if self.check is Check.F1_F9
            else f"{self.samples:,} windows at rest"
            if self.check is Check.GROSS
            else f"{self.samples:,} samples"
        )
        parts = [f"{self.name}: {'ran' if self.ran else 'PARTLY'} on {amount}"]
        if self.mdf_bias_si is not None:
            parts.append(
                "min. detectable zero signal "
                + _axes(self.mdf_bias_si, self.tolerance_bias_si, lambda v: f"{v:.3g}{unit}")
            )
        if self.mdf_scale is not None:
            parts.append(
                "scale "
                + _axes(self.mdf_scale, self.tolerance_scale, lambda v: f"{100.0 * v:.3g} %")
            )
        if self.false_alarm_prob is not None:
            parts.append(f"false alarm {self.false_alarm_prob:.2g}")
        if self.reason:
            parts.append(self.reason)
        return "; ".join(parts)

    def _in_flight_line(self, mdf: Triple, unit: str) -> str:
        """``in flight: z accelerometer tested against GNSS …, MDF … in 10 s; x, y not observable``."""
        scale = self.mdf_scale or (math.inf,) * 3
        seen = [
            f"{AXES[k]} {mdf[k]:.2g}{unit}"
            + (f" (scale {100.0 * scale[k]:.2g} %)" if math.isfinite(scale[k]) else "")
            for k in range(3)
            if math.isfinite(mdf[k])
        ]
        blind = [AXES[k] for k in range(3) if not math.isfinite(mdf[k])]
        tested = " ".join(AXES[k] for k in range(3) if math.isfinite(mdf[k]))
        parts = [
            f"{self.name}: in flight: {tested} accelerometer tested against GNSS on "
            f"{self.samples:,} epochs, MDF {', '.join(seen)} in {IN_FLIGHT_WITHIN_S:g} s"
        ]
        if blind:
            parts.append(f"{', '.join(blind)} not observable")
        if self.false_alarm_prob is not None:
            parts.append(f"false alarms {self.false_alarm_prob:.2g} per flight hour")
        if self.reason:
            parts.append(self.reason)
        return "; ".join(parts)


def _axes(mdf: Triple, tol: Triple | None, fmt: Any) -> str:
    out = []
    for k, axis in enumerate(AXES):
        v = mdf[k]
        if not math.isfinite(v):
            out.append(f"{axis} not seen")
            continue
        pct = ""
        if tol is not None and tol[k] > 0.0:
            pct = f" ({100.0 * v / tol[k]:.0f} % of tol.)"
        out.append(f"{axis} {fmt(v)}{pct}")
    return ", ".join(out)


@dataclass(frozen=True)
class ImuCoverage:
    """Every check's coverage for one IMU."""

    imu: int
    checks: tuple[CheckCoverage, ...]

    @property
    def untested(self) -> tuple[CheckCoverage, ...]:
        """The checks that apply and did not run in full."""
        return tuple(c for c in self.checks if c.missing)

    def untested_by_reason(self) -> list[tuple[str, list[str]]]:
        """The untested checks' names grouped by their reason, in order: one reason often stops
        several checks (no passport: four), and is said once."""
        by_reason: dict[str, list[str]] = {}
        for c in self.untested:
            by_reason.setdefault(c.reason, []).append(c.name)
        return list(by_reason.items())

    def to_dict(self) -> dict[str, Any]:
        return {"imu": self.imu, "checks": [c.to_dict() for c in self.checks]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ImuCoverage:
        return cls(int(d["imu"]), tuple(CheckCoverage.from_dict(c) for c in d["checks"]))

    def lines(self) -> list[str]:
        """One line per check (units by triad)."""
        unit = {Triad.ACCEL: " m/s²", Triad.GYRO: " rad/s", None: ""}
        return [f"IMU{self.imu} {c.line(unit[c.triad])}" for c in self.checks]

    def summary(self) -> str:
        """A short line for a status: the checks that ran, and those that did not and why."""
        ran = [c.name for c in self.checks if c.ran]
        untested = [f"{', '.join(names)} ({why})" for why, names in self.untested_by_reason()]
        return "; ".join(
            [
                *(["tested: " + ", ".join(ran)] if ran else []),
                *(["untested: " + ", ".join(untested)] if untested else []),
            ]
        )


def verdict(fault_found: bool, coverages: Iterable[ImuCoverage]) -> Verdict:
    """The verdict: a fault outranks missing coverage; "no fault" only when every check that applies ran."""
    if fault_found:
        return Verdict.FAULT
    if any(cov.untested for cov in coverages):
        return Verdict.NO_FINDING
    return Verdict.NO_FAULT


def untested_lines(coverages: Sequence[ImuCoverage]) -> list[str]:
    """What was not tested and why, one line per IMU and reason (for ``no finding within coverage``)."""
    out = []
    for cov in coverages:
        out += [
            f"IMU{cov.imu} {', '.join(names)}: {why}" for why, names in cov.untested_by_reason()
        ]
    return out


# ------------------------------------------------------------------ minimum detectable faults


def persistence_margin(persist: int, power: float = DEFAULT_POWER) -> float:
    """``k = Φ⁻¹(power^(1/persist))``: noise margin for ``persist`` failing samples in a row (module docstring)."""
    if persist < 1:
        raise ValueError(f"persist must be >= 1, got {persist!r}")
    _check_prob(power, "power")
    return NormalDist().inv_cdf(power ** (1.0 / persist))


def _check_prob(p: float, name: str) -> None:
    if not 0.0 < p < 1.0:
        raise ValueError(f"{name} must be in (0, 1), got {p!r}")


def _max_u(max_abs_u: ArrayLike) -> FloatArray:
    u = np.asarray(max_abs_u, dtype=float).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.any(u < 0):
        raise ValueError(f"max_abs_u must be 3 finite numbers >= 0, got {max_abs_u!r}")
    out: FloatArray = np.minimum(u, 1.0)
    return out


def _per_axis(shift: float, u: FloatArray, power: int, limit: float) -> Triple:
    """``shift / uᵢ^power`` per axis; infinite where it reaches ``limit`` (module docstring: not seen)."""
    with np.errstate(divide="ignore"):
        v = np.where(u > 0.0, shift / u**power, math.inf)
    v[v >= limit] = math.inf
    return (float(v[0]), float(v[1]), float(v[2]))


def f0_mdf(
    *,
    lambda0: float,
    noise_std: float,
    persist: int,
    max_abs_u: ArrayLike,
    reference: float,
    power: float = DEFAULT_POWER,
) -> tuple[Triple, Triple]:
    """MDF of F0 (module docstring): ``(zero signal per axis in SI, relative scale per axis)``.

    Parameters
    ----------
    lambda0 : F0's threshold (dimensionless, in units of ``s``).
    noise_std : per-sample standard deviation of the normalized output (worst axis).
    persist : failing samples in a row that make a failure.
    max_abs_u : (3,) largest ``|ã_i|/|ã|`` per axis over the tested rest samples.
    reference : the triad's reference in SI (g in m/s², Ω in rad/s).
    power : detection probability.
    """
    if not (math.isfinite(lambda0) and lambda0 > 0 and math.isfinite(noise_std) and noise_std >= 0):
        raise ValueError(f"lambda0 must be > 0 and noise_std >= 0, got {lambda0!r}, {noise_std!r}")
    u = _max_u(max_abs_u)
    shift = lambda0 + persistence_margin(persist, power) * noise_std
    bias = _per_axis(shift * reference, u, 1, reference)
    return bias, _per_axis(shift, u, 2, 1.0)


def predicate_mdf(
    *, tolerance: float, threshold: float, z: float, power: float = DEFAULT_POWER
) -> float:
    """MDF of one predicate F_j (module docstring): ``λ + (z + z_power)·s`` with ``s = (threshold − λ)/z``."""
    if z <= 0:
        raise ValueError(f"z must be > 0, got {z!r}")
    _check_prob(power, "power")
    s = (threshold - tolerance) / z
    return tolerance + (z + NormalDist().inv_cdf(power)) * s


def tolerance_triples(tolerance: ArrayLike, reference: float) -> tuple[Triple, Triple]:
    """A passport triad's tolerances as a coverage states them: ``(zero signals SI, scale errors)``
    per axis, from its (9,) normalized ``tolerance`` and its ``reference`` (SI)."""
    tol = np.asarray(tolerance, dtype=float).reshape(-1)
    if tol.shape != (9,):
        raise ValueError(f"tolerance must be 9 numbers, got {tolerance!r}")
    return _triple(tol[:3] * reference), _triple(tol[3:6])


def gross_mdf(
    *,
    tolerance_si: float,
    sigma_mean_si: float,
    false_alarm_prob: float,
    max_abs_u: ArrayLike,
    reference: float,
    power: float = DEFAULT_POWER,
) -> tuple[Triple, Triple]:
    """MDF of the gross test on window means at rest (module docstring): ``(zero signal SI, scale)`` per axis.

    Parameters
    ----------
    tolerance_si : the test's tolerance on the window mean's departure from its reference, SI.
    sigma_mean_si : standard deviation of a window mean, SI.
    false_alarm_prob : two-sided false-alarm probability per window.
    max_abs_u : (3,) largest ``|u_i|`` per axis over the windows tested.
    reference : the magnitude a scale error multiplies (g for the accelerometers), SI.
    power : detection probability.
    """
    _check_prob(false_alarm_prob, "false_alarm_prob")
    _check_prob(power, "power")
    if not (tolerance_si >= 0 and sigma_mean_si >= 0 and reference > 0):
        raise ValueError(
            f"tolerance, sigma must be >= 0 and reference > 0, got {tolerance_si!r}, {sigma_mean_si!r}, {reference!r}"
        )
    u = _max_u(max_abs_u)
    nd = NormalDist()
    shift = (
        tolerance_si
        + (nd.inv_cdf(1.0 - 0.5 * false_alarm_prob) + nd.inv_cdf(power)) * sigma_mean_si
    )
    return _per_axis(shift, u, 1, reference), _per_axis(shift / reference, u, 2, 1.0)


def ninepar_coverage(
    diagnosis: Diagnosis,
    *,
    positions: int,
    reference: float,
    passport_observable: ArrayLike,
    power: float = DEFAULT_POWER,
) -> CheckCoverage:
    """F1…F9's coverage from a diagnosis (module docstring): MDF per axis of zero signal (SI) and scale.

    Parameters
    ----------
    diagnosis : the diagnosis of the triad (normalized by ``reference``).
    positions : positions the estimate rests on.
    reference : the estimate's normalizing reference, SI.
    passport_observable : (9,) bool, parameters the passport resolves (the others do not apply).
    power : detection probability.

    The check ran in full when every parameter the passport resolves was evaluated;
    a parameter not evaluated has an infinite MDF and is named in ``reason``.
    """
    applicable = np.asarray(passport_observable, dtype=bool).reshape(-1)
    if applicable.shape != (9,):
        raise ValueError(f"passport_observable must be 9 bools, got {passport_observable!r}")
    mdf = np.full(9, math.inf)
    tol = np.array([r.tolerance for r in diagnosis.results], dtype=float)
    skipped = []
    for j, r in enumerate(diagnosis.results):
        if r.threshold is not None and diagnosis.z is not None:
            mdf[j] = predicate_mdf(
                tolerance=r.tolerance, threshold=r.threshold, z=diagnosis.z, power=power
            )
        elif applicable[j]:
            skipped.append(r.predicate)
    triad = diagnosis.triad
    if not applicable.any():
        return CheckCoverage(
            Check.F1_F9, triad, ran=False, applies=False, positions=positions,
            reason="the passport resolves no parameter of this triad",
        )  # fmt: skip
    reason = ""
    if skipped:
        first = next(r.reason for r in diagnosis.results if r.predicate == skipped[0])
        reason = f"{','.join(skipped)} not evaluated ({first})"
    evaluated = diagnosis.n_evaluated > 0
    return CheckCoverage(
        Check.F1_F9,
        triad,
        ran=not skipped,
        positions=positions,
        mdf_bias_si=_triple(mdf[:3] * reference) if evaluated else None,
        mdf_scale=_triple(mdf[3:6]) if evaluated else None,
        tolerance_bias_si=_triple(tol[:3] * reference),
        tolerance_scale=_triple(tol[3:6]),
        false_alarm_prob=diagnosis.false_alarm_prob,
        reason=reason,
    )


def _triple(v: FloatArray) -> Triple:
    return (float(v[0]), float(v[1]), float(v[2]))


def norm_coverage(
    triad: Triad,
    *,
    tested_s: float,
    mdf_si: float,
    reference_si: float | None,
    false_alarms_per_hour: float,
    pair: tuple[int, int],
    reason: str = "",
    share: ArrayLike | None = None,
) -> CheckCoverage:
    """The cross-IMU norm's coverage for one triad (module docstring): tested seconds (in
    ``samples``), the MDF of the norm as a zero signal along the sensed vector, and, given the
    magnitude it was sensed at (``reference_si``: g in hover), the scale MDF ``mdf/ref``. Given
    the IMU's ``share`` of the sensed vector per axis (rms of ``v_i/|v|``), an axis's zero signal
    moves the norm by ``share_i`` of itself and its scale by ``share_i²``: ``mdf/share_i`` and
    ``mdf/(ref·share_i²)``, an axis below :data:`OBSERVABLE_SHARE` not observable (infinite), as
    the thrust-axis check states it; without it (a gyro) no axis's zero signal is claimed. Not run
    (``tested_s`` 0) it says why (``reason``)."""
    where = (
        f"IMU{pair[1]} against IMU{pair[0]}, {false_alarms_per_hour:g} false alarms per flight hour"
    )
    if tested_s <= 0.0:
        return CheckCoverage(Check.CROSS_IMU_NORM, triad, ran=False, reason=reason or where)
    if share is None:
        # A gyro: a zero signal δ_i moves |ω|² by 2 ω_i δ_i, whose block mean cancels wherever the
        # rotation about the axis changes sign (a yaw left then right), so no axis is claimed;
        # a 0.002 rad/s zero signal went unfound in mostly-yaw simulated flights.
        return CheckCoverage(
            Check.CROSS_IMU_NORM,
            triad,
            ran=True,
            samples=round(tested_s),
            mdf_bias_si=(math.inf, math.inf, math.inf),
            reason=f"{where}; the norm's MDF {mdf_si:.2g}, an axis's zero signal seen only while "
            "the rotation about it keeps one sign",
        )
    u = np.asarray(share, float)
    u = np.where(u >= OBSERVABLE_SHARE, u, 0.0)
    with np.errstate(divide="ignore"):
        bias, scale = mdf_si / u, mdf_si / ((reference_si or 1.0) * u**2)
    return CheckCoverage(
        Check.CROSS_IMU_NORM,
        triad,
        ran=True,
        samples=round(tested_s),
        mdf_bias_si=(float(bias[0]), float(bias[1]), float(bias[2])),
        mdf_scale=None
        if reference_si is None
        else (float(scale[0]), float(scale[1]), float(scale[2])),
        reason=where,
    )
