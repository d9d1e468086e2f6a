"""Diagnosis F1…F9 (methods.md M1): injected single-parameter faults are isolated; healthy units raise nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from ninepar_support import TriadCase, mems_accel, mems_gyro, nav_accel, nav_gyro
from scipy.stats import binom

from estimators.conventions import EARTH_RATE_RPS, N_PARAMS, PARAM_AXIS, PARAM_CAUSE, Cause, Triad
from estimators.diagnosis import PREDICATES, Outcome, critical_z, diagnose, diagnose_unit
from estimators.ninepar import Estimate, Method, Verdict, estimate_refined
from estimators.passport import (
    Grade,
    Passport,
    Provenance,
    ReferenceKind,
    TriadPassport,
    passport_from_estimates,
)

GRAVITY_MPS2 = 9.80665
REFERENCE = {Triad.ACCEL: GRAVITY_MPS2, Triad.GYRO: EARTH_RATE_RPS}
UNITS = {
    Grade.MEMS: {
        Triad.ACCEL: mems_accel,
        Triad.GYRO: lambda rng: mems_gyro(rng, seconds_per_position=300.0),
    },
    Grade.NAVIGATION: {Triad.ACCEL: nav_accel, Triad.GYRO: nav_gyro},
}
TRIALS = 10


def _calibrated_unit(grade: Grade, seed: int) -> tuple[dict[Triad, TriadCase], Passport]:
    """True triads of a unit and the passport of one fault-free calibration run (default tolerance rule)."""
    rng = np.random.default_rng(seed)
    cases = {t: make(rng) for t, make in UNITS[grade].items()}
    estimates = {
        t: estimate_refined(c.draw(rng, 1)[0], c.cov, t, reference=REFERENCE[t])
        for t, c in cases.items()
    }
    passport = passport_from_estimates(
        estimates,
        unit_id=f"synthetic-{grade.value}",
        sensor_model="synthetic",
        sensor_ids={},
        created="2024-05-01",
        noise_std={t: np.full(3, 1e-3) for t in cases},
        sample_rate_hz=100.0,
        grade=grade,
    )
    return cases, passport


def _run(cases: dict[Triad, TriadCase], passport: Passport, rng: np.random.Generator, trials: int):
    """Diagnoses of ``trials`` fresh sessions of every triad."""
    draws = {t: c.draw(rng, trials) for t, c in cases.items()}
    for i in range(trials):
        estimates = {
            t: estimate_refined(draws[t][i], c.cov, t, reference=REFERENCE[t])
            for t, c in cases.items()
        }
        yield diagnose_unit(estimates, passport)


def _fault_cases():
    for grade, triads in UNITS.items():
        for triad in triads:
            # A MEMS gyro against Ω resolves only its biases (test_ninepar): faults there.
            params = range(3) if (grade, triad) == (Grade.MEMS, Triad.GYRO) else range(N_PARAMS)
            for j in params:
                yield pytest.param(
                    grade, triad, j, id=f"{grade.value}-{triad.value}-{PREDICATES[j]}"
                )


@pytest.mark.parametrize(("grade", "triad", "j"), list(_fault_cases()))
def test_a_single_parameter_fault_at_five_tolerances_is_isolated(grade, triad, j):
    cases, passport = _calibrated_unit(grade, seed=100)
    tol = passport.triads[triad].tolerance[j]
    faulty = cases[triad].with_fault(j, 5.0 * tol)
    moved = (faulty.params - cases[triad].params) / tol
    # The injected change is 5 λ on parameter j and negligible elsewhere (angles move cosines to first order).
    assert moved[j] == pytest.approx(5.0, rel=0.02) and np.max(np.abs(np.delete(moved, j))) < 0.05
    rng = np.random.default_rng(200 + j)
    for diagnoses in _run({**cases, triad: faulty}, passport, rng, TRIALS):
        findings = [f for d in diagnoses for f in d.findings]
        assert [(f.predicate, f.triad, f.axis, f.cause) for f in findings] == [
            (PREDICATES[j], triad, PARAM_AXIS[j], PARAM_CAUSE[j])
        ]
        f = findings[0]
        assert abs(f.estimate - f.nominal) > f.tolerance and f.sigma > 0.0


@pytest.mark.parametrize("grade", list(UNITS))
def test_a_fault_free_batch_raises_no_fault(grade):
    cases, passport = _calibrated_unit(grade, seed=101)
    n_diagnoses = 0
    for diagnoses in _run(cases, passport, np.random.default_rng(300), 50):
        assert [f for d in diagnoses for f in d.findings] == []
        n_diagnoses += len(diagnoses)
    assert n_diagnoses == 100


def test_unobservable_parameters_are_never_faults():
    # MEMS gyro against Ω: its scale and non-orthogonality are not observable (σ ≈ 0.1), so a 1 %
    # scale fault — five times the MEMS floor — is NOT_EVALUATED, not a finding.
    cases, passport = _calibrated_unit(Grade.MEMS, seed=102)
    faulty = cases[Triad.GYRO].with_fault(4, 1.0e-2)
    for diagnoses in _run({**cases, Triad.GYRO: faulty}, passport, np.random.default_rng(301), 5):
        gyro = next(d for d in diagnoses if d.triad is Triad.GYRO)
        assert gyro.findings == ()
        assert [r.outcome for r in gyro.results[3:]] == [Outcome.NOT_EVALUATED] * 6
        assert "not observable" in gyro.results[4].reason
        assert gyro.n_evaluated == 3 and gyro.z == pytest.approx(critical_z(1e-3, 3))


def test_false_alarm_rate_of_one_diagnosis_is_at_most_the_stated_probability():
    # Zero tolerance and an exact passport: only noise can fail a predicate. Bonferroni over the
    # nine predicates bounds the rate by α; nearly independent estimates give close to α
    # (1 − (1 − α/9)⁹ ≈ 0.18 for α = 0.2, large enough for a two-sided binomial check).
    case = mems_accel(np.random.default_rng(103))
    alpha, trials = 0.2, 400
    tp = _triad_passport(case.params, tolerance=np.full(9, 1e-15), sigma=np.zeros(9))
    alarms = 0
    for means in case.draw(np.random.default_rng(302), trials):
        d = diagnose(estimate_refined(means, case.cov, Triad.ACCEL), tp, false_alarm_prob=alpha)
        alarms += bool(d.findings)
    assert binom.ppf(1e-5, trials, alpha / 2) <= alarms <= binom.isf(1e-5, trials, alpha)


def _triad_passport(
    nominal, *, tolerance, sigma, observable=None, triad=Triad.ACCEL, reference=GRAVITY_MPS2
) -> TriadPassport:
    nominal = np.asarray(nominal, float)
    kind = ReferenceKind.GRAVITY if triad is Triad.ACCEL else ReferenceKind.EARTH_RATE
    return TriadPassport(
        triad=triad,
        reference=reference,
        reference_kind=kind,
        nominal=nominal,
        tolerance=tolerance,
        sigma=sigma,
        observable=np.ones(9, bool) if observable is None else np.asarray(observable, bool),
        noise_std=np.full(3, 1e-3),
        sample_rate_hz=100.0,
        provenance=Provenance(Method.REFINED, 18, 0.95, nominal - 1e-6, nominal + 1e-6),
    )


def _estimate(params, sigma, *, observable=None, triad=Triad.ACCEL, reference=None) -> Estimate:
    return Estimate(
        triad=triad,
        method=Method.REFINED,
        verdict=Verdict.OBSERVABLE,
        reason="",
        n_positions=18,
        params=np.asarray(params, float),
        cov=np.diag(np.broadcast_to(np.asarray(sigma, float) ** 2, (9,))),
        observable=np.ones(9, bool) if observable is None else np.asarray(observable, bool),
        rank=9,
        condition=6.0,
        chi2=9.0,
        dof=9,
        reference=reference,
    )


def test_decision_rule_combines_tolerance_and_uncertainty():
    lam, sigma, sigma_p = 1e-3, 1e-5, 2e-5
    z = critical_z(1e-3, 9)
    s = np.hypot(sigma, sigma_p)
    tp = _triad_passport(np.zeros(9), tolerance=np.full(9, lam), sigma=np.full(9, sigma_p))
    # Index 0: nominal far outside the estimate's confidence interval but inside the tolerance: pass.
    # Index 1/2: just beyond / just within λ + z·s.
    est = np.zeros(9)
    est[0], est[1], est[2] = 0.9 * lam, -(lam + 1.01 * z * s), lam + 0.99 * z * s
    d = diagnose(_estimate(est, sigma), tp)
    assert abs(est[0]) > 50 * sigma
    assert [r.outcome for r in d.results[:3]] == [Outcome.PASS, Outcome.FAIL, Outcome.PASS]
    assert d.results[1].threshold == pytest.approx(lam + z * s)
    (f,) = d.findings
    assert (f.predicate, f.triad, f.axis, f.cause, f.nominal, f.tolerance, f.sigma) == (
        "F2",
        Triad.ACCEL,
        "y",
        Cause.ZERO_SIGNAL,
        0.0,
        lam,
        sigma,
    )


def test_predicates_without_an_observable_estimate_or_passport_value_are_not_evaluated():
    tp = _triad_passport(
        np.zeros(9), tolerance=np.full(9, 1e-3), sigma=np.zeros(9), observable=[True] * 8 + [False]
    )
    far = np.full(9, 1.0)
    d = diagnose(_estimate(far, 1e-5, observable=[False] + [True] * 8), tp)
    assert (
        d.results[0].outcome is Outcome.NOT_EVALUATED and "bx not observable" in d.results[0].reason
    )
    assert (
        d.results[8].outcome is Outcome.NOT_EVALUATED
        and "no resolved passport value" in d.results[8].reason
    )
    assert [f.predicate for f in d.findings] == list(PREDICATES[1:8])
    assert d.z == pytest.approx(critical_z(1e-3, 7))

    none = Estimate(
        Triad.ACCEL,
        Method.REFINED,
        Verdict.NOT_OBSERVABLE_YET,
        "4 positions",
        4,
        None,
        None,
        np.zeros(9, bool),
        0,
        np.inf,
        None,
        0,
    )
    d = diagnose(none, tp)
    assert (
        d.findings == ()
        and d.z is None
        and all(r.outcome is Outcome.NOT_EVALUATED for r in d.results)
    )
    assert "no estimate: 4 positions" in d.results[0].reason
    json.dumps(d.to_dict(), allow_nan=False)


def test_passport_biases_are_converted_to_the_estimates_reference():
    # A passport made where g = 9.80 used where g = 9.78: the same bias in m/s² is a larger normalized bias.
    bias_mps2 = 0.05
    tp = _triad_passport(
        [bias_mps2 / 9.80] + [0.0] * 8,
        tolerance=np.full(9, 1e-6),
        sigma=np.zeros(9),
        reference=9.80,
    )
    est = _estimate([bias_mps2 / 9.78] + [0.0] * 8, 1e-7, reference=9.78)
    assert diagnose(est, tp).findings == ()
    # Without the reference the normalized biases differ by 1.04e-5 > λ + zσ ≈ 1.4e-6.
    assert [f.predicate for f in diagnose(_estimate(est.params, 1e-7), tp).findings] == ["F1"]


def test_mismatched_triads_are_rejected():
    tp = _triad_passport(np.zeros(9), tolerance=np.full(9, 1e-3), sigma=np.zeros(9))
    with pytest.raises(ValueError, match="estimate of the gyro triad against the accel passport"):
        diagnose(_estimate(np.zeros(9), 1e-5, triad=Triad.GYRO), tp)
    passport = Passport("unit-1", "m", {}, "2024-05-01", {Triad.ACCEL: tp})
    with pytest.raises(ValueError, match="has no gyro triad"):
        diagnose_unit({Triad.GYRO: _estimate(np.zeros(9), 1e-5, triad=Triad.GYRO)}, passport)
    with pytest.raises(ValueError, match="false_alarm_prob must be in"):
        diagnose(_estimate(np.zeros(9), 1e-5), tp, false_alarm_prob=0.0)
