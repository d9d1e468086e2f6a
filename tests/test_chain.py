"""The offline chain end to end: simulated sessions → positions → estimates → predicates.

The position-level statistics of the estimators live in test_ninepar.py and
test_diagnosis.py; here the whole chain runs on sample-level simulated sessions,
so detection, trimming, covariance of the means and quantization all play.
"""

import numpy as np
import pytest
from scipy.stats import binom, chi2

from estimators.chain import ChainConfig, run_chain
from estimators.conventions import PARAM_AXIS, PARAM_CAUSE, Triad
from estimators.ninepar import Verdict
from estimators.passport import Grade, passport_from_estimates, per_sample_noise_std
from estimators.session import SessionError
from estimators.sim import (
    Fault,
    FaultKind,
    Rounding,
    grade_error_model,
    multi_position_spec,
    simulate,
)
from estimators.static_detector import StaticDetectorConfig

GRAVITY_45_MPS2 = 9.806197769  # the simulator's default: WGS-84 at 45°, 0 m


def _unit(unit_seed):
    return grade_error_model(Grade.MEMS, rng=np.random.default_rng(1000 + unit_seed))


def _effective_params(model, triad, truth):
    """A floor converter (M2's Entier) reads half a count low on average: the bias a calibration sees."""
    q = model.triad(triad).find("quantization")
    out = truth.params(triad).copy()
    if q is not None and q.rounding is Rounding.FLOOR:
        out[:3] -= 0.5 * np.asarray(q.step_si) / truth.reference(triad)
    return out


def _chain(session, passport=None):
    return run_chain(session, ChainConfig(gravity_mps2=GRAVITY_45_MPS2), passport)


def _assert_consistent(z):
    """(units, 9) normalized errors: 3σ coverage near 99.7 % and a spread not far below 1."""
    n = z.size
    # Under the covariance each error leaves 3σ with p = 0.0027: allow the count whose binomial tail is < 1e-3.
    assert (np.abs(z) > 3).sum() <= int(binom.ppf(1 - 1e-3, n, 0.0027))
    # A covariance too large would hide real faults: the mean square must pass the lower 1e-3 χ² bound (0.71 for 180).
    assert np.mean(z**2) > chi2.ppf(1e-3, n) / n


def test_calibration_errors_are_consistent_with_the_reported_covariance():
    # 20 MEMS units × 9 accelerometer parameters = 180 normalized errors.
    z = []
    for seed in range(20):
        model = _unit(seed)
        res = simulate(multi_position_spec(model=model), seed=seed)
        est = _chain(res.session).triads[Triad.ACCEL].estimate
        z.append((est.params - _effective_params(model, Triad.ACCEL, res.truth)) / est.sigma)
    _assert_consistent(np.array(z))


def test_navigation_gyro_calibration_is_consistent_with_the_reported_covariance():
    # 20 navigation-grade units, 18 positions of 20 s: Ω is resolved (means good to ≈ 2e-3 Ω).
    # The detector thresholds come from the unit's white noise: the defaults are set for MEMS
    # units and would let the slow end of each turn (≫ Ω) into a navigation gyro's positions.
    z = []
    for seed in range(20):
        model = grade_error_model(Grade.NAVIGATION, rng=np.random.default_rng(2000 + seed))
        res = simulate(multi_position_spec(model=model), seed=seed)
        noise_mps2, noise_rps = (
            float(model.triad(t).find("white_noise").sample_sd(res.spec.rate_hz).max())
            for t in Triad
        )
        detector = StaticDetectorConfig.from_noise(
            accel_noise_mps2=noise_mps2, gyro_noise_rps=noise_rps
        )
        est = (
            run_chain(res.session, ChainConfig(gravity_mps2=GRAVITY_45_MPS2, detector=detector))
            .triads[Triad.GYRO]
            .estimate
        )
        assert est.verdict is Verdict.OBSERVABLE and est.n_positions == 18
        z.append((est.params - _effective_params(model, Triad.GYRO, res.truth)) / est.sigma)
    _assert_consistent(np.array(z))


@pytest.fixture(scope="module")
def calibrated_unit():
    model = _unit(7)
    res = simulate(multi_position_spec(model=model), seed=70)
    chain = _chain(res.session)
    est = chain.triads[Triad.ACCEL].estimate
    passport = passport_from_estimates(
        {Triad.ACCEL: est},
        unit_id="sim-7",
        sensor_model="simulated MEMS",
        sensor_ids={},
        created="2026-11-22",
        noise_std={Triad.ACCEL: per_sample_noise_std(chain.positions, Triad.ACCEL, est.reference)},
        sample_rate_hz=res.session.rate_hz,
        grade=Grade.MEMS,
    )
    return model, passport


def test_a_fault_free_session_of_the_same_unit_raises_no_fault(calibrated_unit):
    model, passport = calibrated_unit
    for seed in (71, 72, 73):
        chain = _chain(simulate(multi_position_spec(model=model), seed=seed).session, passport)
        assert chain.faults == ()
        assert chain.triads[Triad.ACCEL].diagnosis.n_evaluated == 9


@pytest.mark.parametrize("param", range(9))
def test_each_single_parameter_fault_at_five_tolerances_is_isolated(calibrated_unit, param):
    model, passport = calibrated_unit
    tol = passport.triads[Triad.ACCEL].tolerance[param]
    for seed, sign in ((100 + param, 1.0), (200 + param, -1.0)):
        fault = Fault(FaultKind.STEP, Triad.ACCEL, param, 0.0, sign * 5.0 * tol)
        chain = _chain(
            simulate(multi_position_spec(model=model, faults=(fault,)), seed=seed).session, passport
        )
        assert [(f.triad, f.axis, f.cause) for f in chain.faults] == [
            (Triad.ACCEL, PARAM_AXIS[param], PARAM_CAUSE[param])
        ]


def test_mems_gyro_is_reported_not_observable_rather_than_estimated():
    res = simulate(multi_position_spec(model=_unit(1)), seed=1)
    est = _chain(res.session).triads[Triad.GYRO].estimate
    assert not est.observable.any() and est.params is None
    # The cause is the noise of 20 s gyro means against Ω, not the (two-axis) position scheme.
    assert (
        "Earth rate is not resolvable by this gyro" in est.reason
        and "rotation axes" not in est.reason
    )


def test_too_few_positions_give_not_observable_yet_and_no_predicates(calibrated_unit):
    model, passport = calibrated_unit
    chain = _chain(
        simulate(multi_position_spec(model=model, n_positions=6), seed=5).session, passport
    )
    r = chain.triads[Triad.ACCEL]
    assert r.estimate.params is None and "nine" in r.estimate.reason
    assert r.diagnosis.n_evaluated == 0 and chain.faults == ()


def test_bad_samples_are_counted_and_the_chain_still_runs(calibrated_unit):
    model, passport = calibrated_unit
    s = simulate(multi_position_spec(model=model), seed=9).session
    s.accel_mps2[1000:1010, 0] = np.nan
    s.t_s[2000] = s.t_s[1999]
    chain = _chain(s, passport)
    assert chain.sample_rejections.counts == {"non_finite": 10, "non_monotonic_time": 1}
    assert len(chain.positions) == 18 and chain.faults == ()


def test_a_session_with_nothing_usable_is_an_error():
    s = simulate(multi_position_spec(n_positions=2, static_s=2.0), seed=0).session
    s.accel_mps2[:] = np.inf
    with pytest.raises(SessionError, match="no usable samples"):
        _chain(s)
