"""Diagnosis: the predicates F1…F9 of a triad against its passport (methods.md M1).

M1 declares ``F_j = 1 iff |ê_j − passport_j| ≤ λ_j``. Taken literally this
flags every parameter whose estimate merely wanders by noise outside λ, so this
project combines tolerance and uncertainty explicitly:

    predicate F_j fails  iff  |ê_j − ν_j| > λ_j + z·s_j,     s_j = (σ_j² + σp_j²)^½

with ``ê_j`` the new estimate and ``σ_j`` its standard deviation, ``ν_j`` the
passport's nominal value, ``λ_j`` its tolerance and ``σp_j`` the nominal's own
standard deviation (``ê − ν`` carries both). Reading: the sensor is healthy
while its true parameter is within ``λ_j`` of the nominal; a healthy sensor then
has ``|ê_j − ν_j| ≤ λ_j + |noise|``, and the noise exceeds ``z·s_j`` with
probability ``2(1 − Φ(z))``. ``z = Φ⁻¹(1 − α/(2m))`` with ``m`` the number of
predicates evaluated for the triad (Bonferroni), so one diagnosis of one triad
raises a false alarm with probability at most ``α`` (default 1e-3; z ≈ 3.9 for
m = 9). Hence a nominal value *outside* the estimate's confidence interval but
*inside* the tolerance is not a fault: ``|ê − ν| ≤ λ`` alone never fails. A
fault of size Δ is detected with high probability once ``Δ > λ + (z + 2) s``.

A predicate is NOT_EVALUATED (never a fault) when the estimate has no
parameters (geometry not observable yet), when the estimate flags that
parameter as not observable, or when the passport does.

When the estimate records its normalizing reference and it differs from the
passport's (another site's g), the passport's biases are converted to the
estimate's normalization (``b·ref_passport / ref_estimate``); scale errors and
cosines are dimensionless and need no conversion.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from statistics import NormalDist
from typing import Any

import numpy as np

from estimators._typing import FloatArray
from estimators.conventions import DEFAULT_FALSE_ALARM_PROB as DEFAULT_FALSE_ALARM_PROB
from estimators.conventions import N_PARAMS, PARAM_AXIS, PARAM_CAUSE, PARAM_NAMES, Cause, Triad
from estimators.ninepar import Estimate
from estimators.passport import Passport, TriadPassport

PREDICATES = tuple(f"F{j + 1}" for j in range(N_PARAMS))
"""Names of the predicates; ``PREDICATES[j]`` tests parameter ``PARAM_NAMES[j]``."""


class Outcome(StrEnum):
    """Outcome of one predicate."""

    PASS = "pass"
    FAIL = "fail"
    NOT_EVALUATED = "not_evaluated"


@dataclass(frozen=True)
class PredicateResult:
    """One predicate's outcome with its numbers (normalized, in the estimate's normalization).

    Attributes
    ----------
    predicate : ``"F1"`` … ``"F9"``.
    outcome : :class:`Outcome`.
    estimate : ``ê_j`` or None when not evaluated for lack of an estimate.
    nominal, tolerance : passport ``ν_j`` and ``λ_j``.
    sigma : standard deviation of ``ê_j`` (None without estimate).
    threshold : ``λ_j + z·s_j`` the difference was compared with (None when not evaluated).
    reason : why not evaluated ("" otherwise).
    """

    predicate: str
    outcome: Outcome
    estimate: float | None
    nominal: float
    tolerance: float
    sigma: float | None
    threshold: float | None
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "predicate": self.predicate,
            "param": PARAM_NAMES[PREDICATES.index(self.predicate)],
            "outcome": self.outcome.value,
            "estimate": self.estimate,
            "nominal": self.nominal,
            "tolerance": self.tolerance,
            "sigma": self.sigma,
            "threshold": self.threshold,
            "reason": self.reason,
        }


@dataclass(frozen=True)
class Finding:
    """A failed predicate: which triad, which sensor axis (or axis pair), what cause (methods.md M1).

    Attributes
    ----------
    predicate : ``"F1"`` … ``"F9"``.
    triad : :class:`~estimators.conventions.Triad`.
    axis : ``x y z`` or ``xy xz yz`` (:data:`~estimators.conventions.PARAM_AXIS`).
    cause : :class:`~estimators.conventions.Cause`.
    estimate, nominal, tolerance, sigma : normalized; ``sigma`` is the estimate's standard deviation.
    """

    predicate: str
    triad: Triad
    axis: str
    cause: Cause
    estimate: float
    nominal: float
    tolerance: float
    sigma: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "predicate": self.predicate,
            "triad": self.triad.value,
            "axis": self.axis,
            "cause": self.cause.value,
            "estimate": self.estimate,
            "nominal": self.nominal,
            "tolerance": self.tolerance,
            "sigma": self.sigma,
        }


@dataclass(frozen=True)
class Diagnosis:
    """Outcome of F1…F9 for one triad.

    Attributes
    ----------
    triad : the triad.
    false_alarm_prob : α of this diagnosis.
    z : critical value used (None when nothing was evaluated).
    results : nine :class:`PredicateResult`, in predicate order.
    findings : the failed predicates as :class:`Finding`.
    """

    triad: Triad
    false_alarm_prob: float
    z: float | None
    results: tuple[PredicateResult, ...]
    findings: tuple[Finding, ...]

    @property
    def n_evaluated(self) -> int:
        return sum(r.outcome is not Outcome.NOT_EVALUATED for r in self.results)

    def to_dict(self) -> dict[str, Any]:
        return {
            "triad": self.triad.value,
            "false_alarm_prob": self.false_alarm_prob,
            "z": self.z,
            "predicates": [r.to_dict() for r in self.results],
            "faults": [f.to_dict() for f in self.findings],
        }


def critical_z(false_alarm_prob: float, n_tests: int) -> float:
    """Two-sided Bonferroni critical value ``Φ⁻¹(1 − α/(2m))`` for ``m = n_tests`` predicates."""
    if not 0.0 < false_alarm_prob < 1.0:
        raise ValueError(f"false_alarm_prob must be in (0, 1), got {false_alarm_prob!r}")
    if n_tests < 1:
        raise ValueError(f"n_tests must be at least 1, got {n_tests!r}")
    # Φ⁻¹ from the standard library (scipy.stats takes most of a second to import): isf(q) = −Φ⁻¹(q).
    return -NormalDist().inv_cdf(false_alarm_prob / (2.0 * n_tests))


def diagnose(
    estimate: Estimate,
    passport: TriadPassport,
    *,
    false_alarm_prob: float = DEFAULT_FALSE_ALARM_PROB,
) -> Diagnosis:
    """Evaluate F1…F9 of one triad (decision rule in the module docstring).

    Parameters
    ----------
    estimate : the new estimate of the triad.
    passport : the triad's passport (same triad, else ``ValueError``).
    false_alarm_prob : probability α that this diagnosis flags a healthy triad.
    """
    if estimate.triad is not passport.triad:
        raise ValueError(
            f"estimate of the {estimate.triad.value} triad against the {passport.triad.value} passport"
        )
    critical_z(false_alarm_prob, 1)  # validates α even when no predicate ends up evaluated
    nominal, tolerance, sigma_p = _in_estimate_units(passport, estimate.reference)
    skip = _skip_reasons(estimate, passport)
    n_evaluated = sum(not reason for reason in skip)
    z = critical_z(false_alarm_prob, n_evaluated) if n_evaluated else None
    results: list[PredicateResult] = []
    findings: list[Finding] = []
    for j in range(N_PARAMS):
        predicate, nom, tol = PREDICATES[j], float(nominal[j]), float(tolerance[j])
        est, sigma = _opt(estimate.params, j), _opt(estimate.sigma, j)
        if skip[j]:
            results.append(
                PredicateResult(
                    predicate=predicate,
                    outcome=Outcome.NOT_EVALUATED,
                    estimate=est,
                    nominal=nom,
                    tolerance=tol,
                    sigma=sigma,
                    threshold=None,
                    reason=skip[j],
                )
            )
            continue
        # Not skipped: the estimate has params (so sigma), and z exists (n_evaluated >= 1).
        assert est is not None and sigma is not None and z is not None
        threshold = float(tolerance[j] + z * np.hypot(sigma, sigma_p[j]))
        failed = abs(est - nominal[j]) > threshold
        results.append(
            PredicateResult(
                predicate=predicate,
                outcome=Outcome.FAIL if failed else Outcome.PASS,
                estimate=est,
                nominal=nom,
                tolerance=tol,
                sigma=sigma,
                threshold=threshold,
            )
        )
        if failed:
            findings.append(
                Finding(
                    predicate=predicate,
                    triad=estimate.triad,
                    axis=PARAM_AXIS[j],
                    cause=PARAM_CAUSE[j],
                    estimate=est,
                    nominal=nom,
                    tolerance=tol,
                    sigma=sigma,
                )
            )
    return Diagnosis(estimate.triad, false_alarm_prob, z, tuple(results), tuple(findings))


def diagnose_unit(
    estimates: Mapping[Triad, Estimate],
    passport: Passport,
    *,
    false_alarm_prob: float = DEFAULT_FALSE_ALARM_PROB,
) -> tuple[Diagnosis, ...]:
    """:func:`diagnose` for each triad of ``estimates`` that the passport covers, in triad order.

    ``false_alarm_prob`` applies per triad (a unit with two triads: at most 2α).
    A triad without a passport raises ``ValueError`` naming it.
    """
    out = []
    for triad in sorted(estimates, key=lambda t: Triad(t).value):
        triad = Triad(triad)
        if triad not in passport.triads:
            raise ValueError(
                f"the passport of unit {passport.unit_id!r} has no {triad.value} triad"
            )
        out.append(
            diagnose(estimates[triad], passport.triads[triad], false_alarm_prob=false_alarm_prob)
        )
    return tuple(out)


def _in_estimate_units(
    passport: TriadPassport, reference: float | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    factor = np.ones(N_PARAMS)
    if reference is not None:
        factor[0:3] = passport.reference / reference
    return passport.nominal * factor, passport.tolerance * factor, passport.sigma * factor


def _skip_reasons(estimate: Estimate, passport: TriadPassport) -> list[str]:
    sigma = estimate.sigma
    if estimate.params is None or sigma is None:
        return [f"no estimate: {estimate.reason}"] * N_PARAMS
    reasons = []
    for j in range(N_PARAMS):
        if not estimate.observable[j]:
            reasons.append(f"{PARAM_NAMES[j]} not observable in this estimate (σ {sigma[j]:.3g})")
        elif not passport.observable[j]:
            reasons.append(f"{PARAM_NAMES[j]} has no resolved passport value")
        else:
            reasons.append("")
    return reasons


def _opt(values: FloatArray | None, j: int) -> float | None:
    return None if values is None else float(values[j])
