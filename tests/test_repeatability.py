"""M2's credibility checks: least squares with covariance, stabilization, run intervals and their intersection."""

import numpy as np
import pytest
import scipy.stats

from estimators.conventions import PARAM_NAMES, Triad
from estimators.repeatability import (
    RunEstimate,
    fit_linear,
    passport_from_runs,
    run_spread,
    stabilization,
    t_quantile,
    triad_runs,
)
from estimators.sim import Fault, FaultKind, Grade, multi_position_spec, simulate
from estimators.sixpos import quantizer_offset, session_positions


def test_fit_linear_matches_the_hand_solution_of_a_straight_line():
    # y = 1 + 2x exactly at x = 0, 1, 2, 3, with a known σ: θ = [1, 2], cov = σ²(HᵀH)⁻¹.
    x = np.arange(4.0)
    h = np.column_stack([np.ones(4), x])
    fit = fit_linear(h, 1.0 + 2.0 * x, sigma_y=0.5)
    np.testing.assert_allclose(fit.values, [1.0, 2.0], atol=1e-12)
    # HᵀH = [[4, 6], [6, 14]], det 20 → inverse [[14, −6], [−6, 4]] / 20.
    np.testing.assert_allclose(
        fit.cov, 0.25 * np.array([[14.0, -6.0], [-6.0, 4.0]]) / 20.0, rtol=1e-12
    )
    assert fit.dof == np.inf


def test_fit_linear_intervals_cover_at_their_level():
    # 2000 regressions of 8 equations, noise level estimated from the residuals:
    # the t interval must cover the true slope 95 % of the time (binomial sd 0.5 %).
    rng = np.random.default_rng(11)
    x = np.linspace(-1.0, 1.0, 8)
    h = np.column_stack([np.ones_like(x), x, x * x])
    truth = np.array([0.3, -1.2, 0.5])
    half = t_quantile(0.95, 5)
    hits = 0
    n = 2000
    for _ in range(n):
        fit = fit_linear(h, h @ truth + 0.1 * rng.standard_normal(x.size))
        hits += np.abs(fit.values[1] - truth[1]) <= half * fit.std[1]
    assert abs(hits / n - 0.95) < 4 * np.sqrt(0.95 * 0.05 / n)


def test_fit_linear_names_the_parameter_it_cannot_separate():
    h = np.column_stack([np.ones(5), np.full(5, 2.0), np.arange(5.0)])
    with pytest.raises(ValueError, match="cannot separate b"):
        fit_linear(h, np.arange(5.0), names=("a", "b", "c"))
    with pytest.raises(ValueError, match="3 equations for 3 unknowns: need at least 4"):
        fit_linear(np.eye(3), np.ones(3))


def test_stabilization_ends_at_the_full_fit_and_waits_for_a_level_change():
    x = np.linspace(0.0, 1.0, 20)
    h = np.column_stack([np.ones_like(x), x])
    rng = np.random.default_rng(3)
    y = 2.0 - x + 1e-3 * rng.standard_normal(x.size)
    st = stabilization(h, y)
    assert st.n_equations[0] == 3 and st.n_equations[-1] == 20
    np.testing.assert_allclose(st.values[-1], fit_linear(h, y).values, rtol=1e-12)
    assert np.all(np.abs(st.values[:, 1] + 1.0) < 6 * st.std[:, 1])
    # The second half of the series moves by 10 σ: the slope cannot settle before it has seen that half.
    y_moved = y.copy()
    y_moved[10:] += 0.01
    moved = stabilization(h, y_moved)
    assert moved.settled_at[1] > 10 and moved.settled_at[1] >= st.settled_at[1]


def test_run_spread_intersects_hand_made_intervals():
    # Known σ (dof inf): 95 % half-width 1.96σ. Runs at 0 and 1 with σ = 1/1.96 give [−1, 1] and [0, 2].
    s = 1.0 / scipy.stats.norm.ppf(0.975)
    runs = [
        RunEstimate(np.array([0.0]), np.array([[s * s]])),
        RunEstimate(np.array([1.0]), np.array([[s * s]])),
    ]
    sp = run_spread(runs, names=("p",))
    np.testing.assert_allclose(
        [sp.common_lower[0], sp.common_upper[0], sp.value[0]], [0.0, 1.0, 0.5], atol=1e-12
    )
    assert sp.all_reproducible
    # Every run interval lies in value ± tolerance: [−1, 2] about 0.5 needs 1.5.
    assert sp.tolerance[0] == pytest.approx(1.5)
    assert sp.spread[0] == pytest.approx(np.std([0.0, 1.0], ddof=1))


def test_run_spread_flags_disjoint_runs_and_their_chi_square():
    runs = [
        RunEstimate(np.array([0.0, 0.0]), np.eye(2) * 0.01),
        RunEstimate(np.array([1.0, 0.01]), np.eye(2) * 0.01),
    ]
    sp = run_spread(runs, names=("moved", "kept"))
    assert sp.not_reproducible() == ("moved",)
    assert sp.value[0] == pytest.approx(0.5)  # weighted mean where the intervals do not meet
    assert sp.p_value[0] < 1e-6 < sp.p_value[1]


def test_run_spread_rejects_a_single_run_and_mismatched_names():
    one = RunEstimate(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="at least 2 runs"):
        run_spread([one], names=("a", "b"))
    with pytest.raises(ValueError, match="every run must estimate the 3 parameters"):
        run_spread([one, one], names=("a", "b", "c"))


def _sessions(n_runs, faults_in_run=None, seed=20):
    out = []
    for k in range(n_runs):
        faults = faults_in_run if k == n_runs - 1 and faults_in_run else ()
        res = simulate(
            multi_position_spec(grade=Grade.MEMS, static_s=6.0, transition_s=3.0, faults=faults),
            seed + k,
        )
        out.append(res)
    return out


@pytest.fixture(scope="module")
def clean_runs():
    return _sessions(3)


def test_triad_passport_from_clean_runs_holds_the_truth_within_its_tolerances(clean_runs):
    g = clean_runs[0].truth.gravity_mps2
    positions = [session_positions(r.session, min_static_s=2.0) for r in clean_runs]
    runs = triad_runs(positions, Triad.ACCEL, g)
    tp = passport_from_runs(runs, noise_std=np.full(3, 1e-3), sample_rate_hz=100.0)
    truth = clean_runs[0].truth.accel_params.copy()
    truth[:3] += (
        quantizer_offset(clean_runs[0].truth.model.accel) / g
    )  # the output's bias includes the rounding offset
    assert runs.spread.all_reproducible and tp.observable.all()
    assert np.all(np.abs(tp.nominal - truth) <= tp.tolerance)
    assert np.all(tp.provenance.ci_low <= tp.nominal) and np.all(
        tp.nominal <= tp.provenance.ci_high
    )
    assert tp.provenance.n_runs == 3 and tp.provenance.reproducible.all()
    assert [st.n_equations[-1] for st in runs.stabilizations] == [18, 18, 18]


def test_a_bias_change_in_one_run_breaks_the_reproducibility_of_that_bias_only(clean_runs):
    g = clean_runs[0].truth.gravity_mps2
    # Step of 20 σ of a run's bias estimate in bx from the start of the last run.
    shifted = _sessions(3, faults_in_run=(Fault(FaultKind.STEP, Triad.ACCEL, 0, 0.0, 5e-4),))
    positions = [session_positions(r.session, min_static_s=2.0) for r in clean_runs[:2]] + [
        session_positions(shifted[-1].session, min_static_s=2.0)
    ]
    runs = triad_runs(positions, Triad.ACCEL, g)
    assert runs.spread.not_reproducible() == ("bx",)
    tp = passport_from_runs(runs, noise_std=np.full(3, 1e-3), sample_rate_hz=100.0)
    assert list(np.array(PARAM_NAMES)[~tp.observable]) == ["bx"]
