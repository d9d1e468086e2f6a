"""The offline chain end to end: simulated sessions → positions → estimates → predicates.

The position-level statistics of the estimators live in test_ninepar.py and
test_diagnosis.py; here the whole chain runs on sample-level simulated sessions,
so detection, trimming, covariance of the means and quantization all play.
"""

import numpy as np
import pytest
from scipy.stats import binom

from estimators.chain import ChainConfig, run_chain
from estimators.conventions import PARAM_AXIS, PARAM_CAUSE, Triad
from estimators.passport import Grade, passport_from_estimates, per_sample_noise_std
from estimators.session import SessionError
from estimators.sim import Fault, FaultKind, Rounding, grade_error_model, multi_position_spec, simulate

GRAVITY_45_MPS2 = 9.806197769  # the simulator's default: WGS-84 at 45°, 0 m


def _unit(unit_seed):
    return grade_error_model(Grade.MEMS, rng=np.random.default_rng(1000 + unit_seed))


def _effective_accel_params(model, truth_params, gravity_mps2):
    """A floor converter (M2's Entier) reads half a count low on average: the bias a calibration sees."""
    q = model.accel.find("quantization")
    out = np.array(truth_params, dtype=float)
    if q is not None and q.rounding is Rounding.FLOOR:
        out[:3] -= 0.5 * np.asarray(q.step_si) / gravity_mps2
    return out


def _chain(session, passport=None):
    return run_chain(session, ChainConfig(gravity_mps2=GRAVITY_45_MPS2), passport)


def test_calibration_errors_are_consistent_with_the_reported_covariance():
    # 20 units × 9 parameters = 180 normalized errors; under the covariance each
    # leaves 3σ with p = 0.0027. Allow the count whose binomial tail is < 1e-3.
    n_units = 20
    z = []
    for seed in range(n_units):
        model = _unit(seed)
        res = simulate(multi_position_spec(model=model), seed=seed)
        est = _chain(res.session).triads[Triad.ACCEL].estimate
        truth = _effective_accel_params(model, res.truth.accel_params, GRAVITY_45_MPS2)
        z.append((est.params - truth) / est.sigma)
    z = np.array(z)
    n = z.size
    limit = int(binom.ppf(1 - 1e-3, n, 0.0027))
    assert (np.abs(z) > 3).sum() <= limit
    # A covariance too large would hide real faults: the spread must not be far below 1
    # (χ² bound on the variance of 180 unit normals at 1e-3: 0.72).
    assert np.mean(z**2) > 0.72


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
        chain = _chain(simulate(multi_position_spec(model=model, faults=(fault,)), seed=seed).session, passport)
        assert [(f.triad, f.axis, f.cause) for f in chain.faults] == [(Triad.ACCEL, PARAM_AXIS[param], PARAM_CAUSE[param])]


def test_mems_gyro_is_reported_not_observable_rather_than_estimated():
    res = simulate(multi_position_spec(model=_unit(1)), seed=1)
    est = _chain(res.session).triads[Triad.GYRO].estimate
    assert not est.observable.any()
    assert est.reason


def test_too_few_positions_give_not_observable_yet_and_no_predicates(calibrated_unit):
    model, passport = calibrated_unit
    chain = _chain(simulate(multi_position_spec(model=model, n_positions=6), seed=5).session, passport)
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
