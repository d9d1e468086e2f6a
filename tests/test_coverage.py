"""Coverage and the minimum detectable fault (estimators.coverage): the MDF each check states is the
fault it finds, checked by simulation (faults at 1.5× the MDF found in ≥ 95 of 100 seeded trials, at
0.5× in ≤ 20), and the verdict says "no fault" only with full coverage."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ninepar_support import mems_accel

from estimators.conventions import Triad
from estimators.coverage import (
    Check,
    CheckCoverage,
    ImuCoverage,
    Verdict,
    f0_mdf,
    gross_mdf,
    ninepar_coverage,
    persistence_margin,
    untested_lines,
    verdict,
)
from estimators.diagnosis import diagnose
from estimators.ninepar import Method, estimate_refined
from estimators.passport import Provenance, ReferenceKind, TriadPassport
from estimators.scalar import F0Config, derive_lambda0, f0_batch, persistent_failure

G = 9.80665
TRIALS = 100
RATE_HZ = 200.0
PERSIST = 4  # 0.02 s at 200 Hz, the pipeline's default persistence
SIGMA_NORM = 1e-3  # per-sample noise of the normalized output (about 1 mg)
FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
SAMPLES_PER_FACE = 200  # 1 s at rest on each face


def _f0_detections(
    config: F0Config, bias_si: np.ndarray, scale: np.ndarray, seed: int
) -> tuple[int, np.ndarray]:
    """Trials (of TRIALS) in which F0 declares a failure on a six-face rest session of a unit with
    the given zero signals (SI) and scale errors, and the max |u_i| of the first trial's samples."""
    rng = np.random.default_rng(seed)
    u = np.repeat(FACES, SAMPLES_PER_FACE, axis=0)
    truth = (u * (1.0 + scale)) * G + bias_si
    static = np.ones(u.shape[0], bool)
    found, max_u = 0, np.zeros(3)
    for trial in range(TRIALS):
        x = truth + rng.normal(0.0, SIGMA_NORM * G, u.shape)
        res = f0_batch(x, static, config)
        found += persistent_failure(res.state, 0, PERSIST)[0] >= 0
        if trial == 0:
            max_u = np.max(np.abs(x) / np.linalg.norm(x, axis=1, keepdims=True), axis=0)
    return found, max_u


@pytest.mark.parametrize(
    "tolerance",
    [np.zeros(9), np.array([5e-3] * 3 + [5e-3] * 3 + [1e-3] * 3)],
    ids=["noise-only shell", "tolerance shell"],
)
def test_f0_mdf_is_what_a_rest_session_detects(tolerance):
    lam = derive_lambda0(
        noise_std_norm=np.full(3, SIGMA_NORM), false_alarm_prob=1e-9, tolerance_norm=tolerance
    )
    config = F0Config(lambda0=lam.lambda0, reference=G)
    zero = np.zeros(3)
    healthy, max_u = _f0_detections(config, zero, zero, seed=1)
    assert healthy == 0
    mdf_bias, mdf_scale = f0_mdf(
        lambda0=lam.lambda0, noise_std=lam.noise_std, persist=PERSIST, max_abs_u=max_u, reference=G
    )
    for factor, lo, hi in ((1.5, 95, TRIALS), (0.5, 0, 20)):
        # A zero signal on x (which saw gravity on two faces) and a scale error on z.
        b = np.array([factor * mdf_bias[0], 0.0, 0.0])
        found_b, _ = _f0_detections(config, b, zero, seed=2)
        e = np.array([0.0, 0.0, factor * mdf_scale[2]])
        found_e, _ = _f0_detections(config, zero, e, seed=3)
        assert lo <= found_b <= hi, (factor, found_b, mdf_bias)
        assert lo <= found_e <= hi, (factor, found_e, mdf_scale)


def test_f0_mdf_grows_as_the_axis_saw_less_gravity_and_is_infinite_unseen():
    bias, scale = f0_mdf(
        lambda0=0.01, noise_std=0.001, persist=1, max_abs_u=(1.0, 0.5, 0.0), reference=G
    )
    shift = 0.01 + persistence_margin(1) * 0.001
    assert bias[0] == pytest.approx(shift * G)
    assert bias[1] == pytest.approx(2 * shift * G)
    assert scale[1] == pytest.approx(4 * shift)
    assert math.isinf(bias[2]) and math.isinf(scale[2])


def test_persistence_margin_gives_the_power_for_the_whole_run():
    from statistics import NormalDist

    for persist in (1, 4, 20):
        k = persistence_margin(persist)
        assert NormalDist().cdf(k) ** persist == pytest.approx(0.95)


def _triad_passport(nominal, tolerance) -> TriadPassport:
    return TriadPassport(
        triad=Triad.ACCEL,
        reference=G,
        reference_kind=ReferenceKind.GRAVITY,
        nominal=np.asarray(nominal, float),
        tolerance=np.asarray(tolerance, float),
        sigma=np.zeros(9),
        observable=np.ones(9, bool),
        noise_std=np.full(3, 1e-3),
        sample_rate_hz=100.0,
        provenance=Provenance(Method.REFINED, 18, 0.95, nominal - 1e-6, nominal + 1e-6),
    )


def test_f1_f9_mdf_is_what_the_diagnosis_detects():
    case = mems_accel(np.random.default_rng(11))
    tp = _triad_passport(case.params, np.array([2e-4] * 3 + [2e-4] * 3 + [1e-4] * 3))
    means = case.draw(np.random.default_rng(12), 1)[0]
    diag = diagnose(estimate_refined(means, case.cov, Triad.ACCEL, reference=G), tp)
    cov = ninepar_coverage(diag, positions=18, reference=G, passport_observable=np.ones(9, bool))
    assert cov.ran and cov.mdf_bias_si is not None and cov.mdf_scale is not None
    for j, mdf_norm in ((0, cov.mdf_bias_si[0] / G), (5, cov.mdf_scale[2])):
        for factor, lo, hi in ((1.5, 95, TRIALS), (0.5, 0, 20)):
            faulty = case.with_fault(j, factor * mdf_norm)
            draws = faulty.draw(np.random.default_rng(100 + j), TRIALS)
            found = sum(
                f"F{j + 1}"
                in {
                    f.predicate
                    for f in diagnose(
                        estimate_refined(m, case.cov, Triad.ACCEL, reference=G), tp
                    ).findings
                }
                for m in draws
            )
            assert lo <= found <= hi, (j, factor, found, mdf_norm)


def test_ninepar_coverage_names_what_was_not_evaluated():
    case = mems_accel(np.random.default_rng(11))
    observable = np.ones(9, bool)
    observable[6:] = False
    tp = _triad_passport(case.params, np.full(9, 1e-4))
    est = estimate_refined(case.draw(np.random.default_rng(1), 1)[0], case.cov, Triad.ACCEL)
    tp_partial = TriadPassport(**{**tp.__dict__, "observable": observable})
    diag = diagnose(est, tp_partial)
    # The passport does not resolve F7…F9: they do not apply, the check ran in full.
    assert ninepar_coverage(diag, positions=18, reference=G, passport_observable=observable).ran
    # The passport resolves them but the diagnosis did not evaluate them: partial.
    part = ninepar_coverage(diag, positions=18, reference=G, passport_observable=np.ones(9, bool))
    assert not part.ran and part.missing and part.reason.startswith("F7,F8,F9 not evaluated")


def test_gross_mdf_adds_the_window_noise_margins():
    bias, scale = gross_mdf(
        tolerance_si=1.0,
        sigma_mean_si=0.01,
        false_alarm_prob=1e-3,
        max_abs_u=(1, 1, 0.5),
        reference=G,
    )
    shift = 1.0 + (3.2905 + 1.6449) * 0.01
    assert bias[0] == pytest.approx(shift, rel=1e-4)
    assert bias[2] == pytest.approx(2 * shift, rel=1e-4)
    assert scale[2] == pytest.approx(4 * shift / G, rel=1e-4)


def _imu(*checks: CheckCoverage) -> ImuCoverage:
    return ImuCoverage(0, checks)


def test_verdict_says_no_fault_only_when_every_applicable_check_ran():
    f0 = CheckCoverage(Check.F0, Triad.ACCEL, ran=True, samples=100)
    gyro = CheckCoverage(
        Check.F0, Triad.GYRO, ran=False, applies=False, reason="gyro cannot see the Earth rate"
    )
    untested = CheckCoverage(
        Check.F1_F9, Triad.ACCEL, ran=False, positions=3, reason="3 positions, 9 needed"
    )
    assert verdict(False, [_imu(f0, gyro)]) is Verdict.NO_FAULT
    assert verdict(False, [_imu(f0, gyro, untested)]) is Verdict.NO_FINDING
    assert verdict(True, [_imu(f0, untested)]) is Verdict.FAULT
    assert untested_lines([_imu(f0, gyro, untested)]) == ["IMU0 accel F1-F9: 3 positions, 9 needed"]


def test_a_status_summary_says_a_reason_once_for_the_checks_it_stopped():
    """The daemon's status without a passport (default_grade "none"): four checks stopped by one long
    reason, which watch's line repeated four times; it is said once, after the checks it stopped."""
    why = "passport of v1 IMU0 (/srv/passports/v1/imu0.passport.json): missing: no passport file"
    stopped = [
        CheckCoverage(check, triad, ran=False, reason=why)
        for triad in (Triad.ACCEL, Triad.GYRO)
        for check in (Check.F0, Check.F1_F9)
    ]
    gross = CheckCoverage(Check.GROSS, Triad.ACCEL, ran=True, samples=40)
    summary = _imu(gross, *stopped).summary()
    assert summary.count(why) == 1
    assert (
        summary
        == f"tested: accel gross; untested: accel F0, accel F1-F9, gyro F0, gyro F1-F9 ({why})"
    )


def test_coverage_round_trips_through_its_dict_with_unseen_axes():
    c = CheckCoverage(
        Check.F0, Triad.ACCEL, ran=True, samples=5, mdf_bias_si=(0.1, math.inf, 0.2),
        mdf_scale=(0.01, math.inf, 0.02), tolerance_bias_si=(0.05, 0.05, 0.05), false_alarm_prob=1e-9,
    )  # fmt: skip
    imu = ImuCoverage(2, (c,))
    assert ImuCoverage.from_dict(imu.to_dict()) == imu
    line = imu.lines()[0]
    assert "y not seen" in line and "x 0.1 m/s² (200 % of tol.)" in line
