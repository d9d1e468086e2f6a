"""Nine-parameter estimation (methods.md M1): simulate known errors, recover them within the stated covariance."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from ninepar_support import TriadCase, mems_accel, mems_gyro, nav_gyro, single_axis_directions
from scipy.stats import binom, chi2

from estimators.conventions import N_PARAMS, PARAM_NAMES, STANDARD_GRAVITY_MPS2, Triad
from estimators.ninepar import (
    Estimate,
    Method,
    RecursiveNineParam,
    Verdict,
    canonical_triad_matrix,
    cramer_rao_bound,
    ellipsoid_residual,
    equation_sigma,
    estimate_linear,
    estimate_refined,
    estimate_triad,
    regressors,
    scheme_directions,
)
from estimators.positions import Position

P_MISS_3SIGMA = 2.0 * 0.0013498980316301  # P(|N(0,1)| > 3)
TAIL = 1.0e-5  # probability with which each statistical bound below may be exceeded by chance


def _monte_carlo(
    case: TriadCase, trials: int, seed: int
) -> tuple[np.ndarray, np.ndarray, list[Estimate]]:
    """Normalized errors (trials, 9), NEES (trials,) and the estimates of the refined estimator."""
    means = case.draw(np.random.default_rng(seed), trials)
    estimates = [estimate_refined(m, case.cov, case.triad) for m in means]
    errors = np.array([e.params - case.params for e in estimates])
    z = errors / np.array([e.sigma for e in estimates])
    nees = np.array(
        [err @ np.linalg.solve(e.cov, err) for err, e in zip(errors, estimates, strict=True)]
    )
    return z, nees, estimates


def _assert_consistent(z: np.ndarray, nees: np.ndarray) -> None:
    trials = z.shape[0]
    n = z.size
    misses = int(np.sum(np.abs(z) > 3.0))
    # 3σ coverage: the miss count is binomial(n, 0.27 %); bound at the 1e-5 upper tail.
    assert misses <= binom.isf(TAIL, n, P_MISS_3SIGMA), f"{misses} of {n} errors beyond 3σ"
    # NEES: the sum over trials is χ²(9·trials) when the covariance is right (both sides).
    low, high = (
        chi2.ppf(TAIL, N_PARAMS * trials) / trials,
        chi2.isf(TAIL, N_PARAMS * trials) / trials,
    )
    assert low <= nees.mean() <= high, (
        f"mean NEES {nees.mean():.3f} outside [{low:.3f}, {high:.3f}]"
    )


def test_regressors_are_the_m1_row():
    g = np.array([[0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    h = regressors(g)
    np.testing.assert_allclose(h[0], [0.6, 0.0, 0.8, 0.36, 0.0, 0.64, 0.0, 0.48, 0.0])
    np.testing.assert_allclose(h[1], [0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -0.0])
    with pytest.raises(ValueError, match=r"shape \(n, 3\), got \(3,\)"):
        regressors(np.zeros(3))


def test_scalar_equation_is_the_first_order_expansion_of_the_ellipsoid():
    # f(θ) ≈ y − Hθ with y = ½(|ã|²−1), H = regressors(ã): the remainder is second order in θ.
    rng = np.random.default_rng(3)
    case = mems_accel(rng)
    m = case.means_true
    for scale in (1.0, 0.1):
        theta = scale * case.params
        f, _, _ = ellipsoid_residual(theta, m)
        y = 0.5 * (np.sum(m * m, axis=1) - 1.0)
        first_order = y - regressors(m) @ theta
        assert np.max(np.abs(f - first_order)) < 10.0 * np.max(np.abs(theta)) ** 2


def test_noise_free_positions_give_the_true_parameters_exactly():
    case = mems_accel(np.random.default_rng(4))
    est = estimate_refined(case.means_true, case.cov, case.triad)
    np.testing.assert_allclose(est.params, case.params, rtol=0, atol=1e-12)
    assert est.chi2 < 1e-12
    # The paper's linear estimator is only first order: its error is of the order of θ².
    lin = estimate_linear(case.means_true, case.cov, case.triad)
    assert 1e-7 < np.max(np.abs(lin.params - case.params)) < 10.0 * np.max(np.abs(case.params)) ** 2


def test_jacobian_of_the_refined_residual_matches_finite_differences():
    rng = np.random.default_rng(5)
    params = np.concatenate([rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 3)])
    means = (
        scheme_directions(18) @ canonical_triad_matrix(params).T
        + params[:3]
        + rng.normal(0, 0.01, (18, 3))
    )
    _, df_dp, df_dm = ellipsoid_residual(params, means)
    h = 1e-6
    num_p = np.column_stack(
        [
            (
                ellipsoid_residual(params + h * e, means)[0]
                - ellipsoid_residual(params - h * e, means)[0]
            )
            / (2 * h)
            for e in np.eye(9)
        ]
    )
    num_m = np.column_stack(
        [
            (
                ellipsoid_residual(params, means + h * e)[0]
                - ellipsoid_residual(params, means - h * e)[0]
            )
            / (2 * h)
            for e in np.eye(3)
        ]
    )
    # Central differences: truncation ~h²·f''' and rounding ~eps/h, both below 1e-8 here.
    np.testing.assert_allclose(df_dp, num_p, rtol=0, atol=1e-8)
    np.testing.assert_allclose(df_dm, num_m, rtol=0, atol=1e-8)


def test_cramer_rao_bound_equals_the_full_nuisance_parameter_fisher_matrix():
    # Independent derivation: measurements ã_k = A(θ) u(α_k, β_k) + b with the two angles of
    # every direction as nuisance parameters, numerical Jacobian, Schur complement.
    rng = np.random.default_rng(6)
    params = np.concatenate(
        [rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3)]
    )
    rot, _ = np.linalg.qr(
        rng.normal(size=(3, 3))
    )  # keeps every direction away from the angle poles
    u = scheme_directions(18) @ rot.T
    n = u.shape[0]
    angles = np.column_stack([np.arctan2(u[:, 1], u[:, 0]), np.arcsin(u[:, 2])])
    cov = np.einsum("ni,ij->nij", rng.uniform(0.5, 2.0, (n, 3)) * 1e-8, np.eye(3))

    def model(x: np.ndarray) -> np.ndarray:
        th, ang = x[:9], x[9:].reshape(n, 2)
        dirs = np.column_stack(
            [
                np.cos(ang[:, 1]) * np.cos(ang[:, 0]),
                np.cos(ang[:, 1]) * np.sin(ang[:, 0]),
                np.sin(ang[:, 1]),
            ]
        )
        return (dirs @ canonical_triad_matrix(th).T + th[:3]).ravel()

    x0 = np.concatenate([params, angles.ravel()])
    h = 1e-6
    jac = np.column_stack(
        [(model(x0 + h * e) - model(x0 - h * e)) / (2 * h) for e in np.eye(x0.size)]
    )
    weight = np.zeros((3 * n, 3 * n))
    for k in range(n):
        weight[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = np.linalg.inv(cov[k])
    fisher = jac.T @ weight @ jac
    f_tt, f_tn, f_nn = fisher[:9, :9], fisher[:9, 9:], fisher[9:, 9:]
    crb_full = np.linalg.inv(f_tt - f_tn @ np.linalg.solve(f_nn, f_tn.T))
    crb = cramer_rao_bound(model(x0).reshape(n, 3), cov, params)
    np.testing.assert_allclose(np.sqrt(np.diag(crb)), np.sqrt(np.diag(crb_full)), rtol=1e-4)


def test_mems_accelerometer_errors_are_consistent_with_the_covariance():
    z, nees, estimates = _monte_carlo(mems_accel(np.random.default_rng(10)), trials=300, seed=11)
    _assert_consistent(z, nees)
    assert all(e.verdict is Verdict.OBSERVABLE for e in estimates)
    # The residual chi-square per position follows χ²(n − 9) as well.
    chi2_sum = sum(e.chi2 for e in estimates)
    dof = sum(e.dof for e in estimates)
    assert chi2.ppf(TAIL, dof) <= chi2_sum <= chi2.isf(TAIL, dof)


def test_navigation_gyro_against_earth_rate_is_resolved_and_consistent():
    z, nees, estimates = _monte_carlo(nav_gyro(np.random.default_rng(12)), trials=300, seed=13)
    _assert_consistent(z, nees)
    assert all(e.verdict is Verdict.OBSERVABLE for e in estimates)


def test_mems_gyro_with_short_positions_is_not_observable_and_says_so():
    # Bias ≈ 140 Ω, noise of a 10 s mean ≈ 0.38 Ω: 3× that noise exceeds the 1/√3 spread the best
    # scheme reaches on the unit sphere, so the cause is the noise against Ω, not the rotation axes.
    case = mems_gyro(np.random.default_rng(14), seconds_per_position=10.0)
    est = estimate_refined(case.draw(np.random.default_rng(15), 1)[0], case.cov, case.triad)
    assert est.verdict is Verdict.NOT_OBSERVABLE_YET
    assert est.params is None and est.cov is None and not est.observable.any()
    noise = float(
        re.search(r"the position means' noise \(([0-9.]+) Ω along the normal", est.reason).group(1)
    )
    assert 3.0 * noise >= 1.0 / np.sqrt(3.0)
    assert "too large against the reference to tell the positions' geometry" in est.reason
    assert "Earth rate is not resolvable by this gyro" in est.reason
    assert "rotation axes" not in est.reason
    assert all(name in est.reason for name in PARAM_NAMES)


@pytest.mark.parametrize(("sigma", "noise_cause"), [(0.15, False), (0.2, True)])
def test_geometry_blames_the_noise_only_when_no_scheme_could_pass(sigma, noise_cause):
    # A single-axis circle fails either way; 3σ = 0.45 < 1/√3 could still be resolved by a scheme
    # around two axes (the reason names the axes), 3σ = 0.6 ≥ 1/√3 could not (it names the noise).
    base = mems_accel(np.random.default_rng(26))
    dirs = single_axis_directions([0, 0, 1], 18, cone_deg=60.0)
    cov = np.repeat((sigma**2 * np.eye(3))[None], 18, axis=0)
    case = TriadCase(base.triad, base.bias, base.scale, base.angles, dirs, cov)
    est = estimate_linear(case.means_true, case.cov, case.triad)
    assert est.verdict is Verdict.NOT_OBSERVABLE_YET and est.params is None
    assert ("gravity is not resolvable by this accelerometer triad" in est.reason) is noise_cause
    assert ("fewer than two rotation axes" in est.reason) is not noise_cause


def test_mems_gyro_with_long_positions_resolves_its_bias_only():
    # 300 s means (≈ 0.07 Ω noise): the bias (≈ 140 Ω) is found to σ ≈ 0.03 Ω, scale and cosines
    # (σ ≈ 0.04…0.08 against a limit of 0.01) are not.
    case = mems_gyro(np.random.default_rng(16), seconds_per_position=300.0)
    est = estimate_refined(case.draw(np.random.default_rng(17), 1)[0], case.cov, case.triad)
    assert est.verdict is Verdict.PARTIALLY_OBSERVABLE
    np.testing.assert_array_equal(est.observable, [True] * 3 + [False] * 6)
    assert all(name in est.reason for name in PARAM_NAMES[3:]) and not any(
        f"{n} (" in est.reason for n in PARAM_NAMES[:3]
    )
    assert np.all(np.abs(est.params[:3] - case.params[:3]) <= 5.0 * est.sigma[:3])


@pytest.mark.parametrize("n", [0, 1, 8])
def test_fewer_than_nine_positions_are_not_observable_yet(n):
    case = mems_accel(np.random.default_rng(20))
    est = estimate_refined(case.means_true[:n], case.cov[:n], case.triad)
    assert est.verdict is Verdict.NOT_OBSERVABLE_YET and est.params is None
    assert f"{n} positions; the nine parameters need at least 9" in est.reason


@pytest.mark.parametrize(
    ("axis", "cone_deg"), [([1, 0, 0], 90.0), ([1, 2, 3], 60.0), ([0, 0, 1], 20.0)]
)
def test_rotation_about_a_single_axis_is_not_observable_yet(axis, cone_deg):
    base = mems_accel(np.random.default_rng(21))
    case = TriadCase(
        base.triad,
        base.bias,
        base.scale,
        base.angles,
        single_axis_directions(axis, 18, cone_deg=cone_deg),
        base.cov,
    )
    for method in (estimate_linear, estimate_refined):
        est = method(case.draw(np.random.default_rng(22), 1)[0], case.cov, case.triad)
        assert est.verdict is Verdict.NOT_OBSERVABLE_YET and est.params is None
        assert "fewer than two rotation axes" in est.reason


def test_two_separate_rotation_circles_and_the_six_position_test_are_judged_by_their_covariance():
    """Not by a fixed condition number (both exceed 1e9): two circles leave the combinations they do
    not excite not observable, their biases resolved; six faces leave d undetermined (3σ beyond a
    cosine of 1), refused with the least excited combination."""
    base = mems_accel(np.random.default_rng(23))
    two_circles = np.vstack(
        [single_axis_directions([1, 0, 0], 9), single_axis_directions([1, 1, 1], 9)]
    )
    for dirs, weakest in ((two_circles, ""), (scheme_directions(6), "d")):
        cov = np.repeat(base.cov[:1], len(dirs), axis=0)
        case = TriadCase(base.triad, base.bias, base.scale, base.angles, dirs, cov)
        means = case.draw(np.random.default_rng(24), 1)[0]
        if len(dirs) < 9:  # the six positions twice: enough equations, still no cross products
            means, cov = (
                np.vstack([means, case.draw(np.random.default_rng(25), 1)[0]]),
                np.vstack([cov, cov]),
            )
        est = estimate_refined(means, cov, case.triad)
        assert est.condition > 1e9
        if weakest:
            assert est.verdict is Verdict.NOT_OBSERVABLE_YET and est.params is None
            assert (
                "condition number of HᵀH" in est.reason
                and f"least excited: {weakest}" in est.reason
            )
        else:
            assert est.verdict is Verdict.PARTIALLY_OBSERVABLE
            assert list(est.observable) == [True] * 3 + [False] * 6


def test_recursive_form_tracks_the_refined_batch_estimate():
    # Same data, positions in random order. The recursive state linearizes each new equation at
    # the estimate of the moment instead of the final one: the difference is second order in the
    # error of that estimate (≤ 0.002 σ after the 18-position warm-up in the benchmark); bound
    # 0.01 σ, and the covariance within 1 % of the batch covariance.
    rng = np.random.default_rng(30)
    for n_positions in (30, 100):
        case = mems_accel(rng, n_positions)
        for means in case.draw(rng, 5):
            order = rng.permutation(n_positions)
            rec = RecursiveNineParam(case.triad)
            updates = [rec.update(means[k], case.cov[k]) for k in order]
            batch = estimate_refined(means, case.cov, case.triad)
            est = rec.estimate()
            assert est.method is Method.RECURSIVE and est.n_positions == n_positions
            assert np.max(np.abs(est.params - batch.params) / batch.sigma) < 0.01
            np.testing.assert_allclose(est.sigma, batch.sigma, rtol=0.01)
            recursive = [u for u in updates if u.nis is not None]
            assert len(recursive) == n_positions - rec.warmup_positions and all(
                u.iterations >= 1 for u in recursive
            )


def test_recursive_innovations_are_chi_square_distributed():
    rng = np.random.default_rng(31)
    case = mems_accel(rng, 60)
    nis = []
    for means in case.draw(rng, 10):
        rec = RecursiveNineParam(case.triad)
        nis += [
            u.nis
            for u in (rec.update(m, c) for m, c in zip(means, case.cov, strict=True))
            if u.nis is not None
        ]
    nis = np.array(nis)
    assert chi2.ppf(TAIL, nis.size) <= nis.sum() <= chi2.isf(TAIL, nis.size)


def test_recursive_state_survives_a_checkpoint_round_trip():
    rng = np.random.default_rng(32)
    case = mems_accel(rng, 30)
    means = case.draw(rng, 1)[0]
    for split in (5, 20):  # while buffering, and after initialization
        rec = RecursiveNineParam(case.triad, reference=9.81)
        for k in range(split):
            rec.update(means[k], case.cov[k])
        restored = RecursiveNineParam.from_state_dict(json.loads(json.dumps(rec.state_dict())))
        for k in range(split, 30):
            rec.update(means[k], case.cov[k])
            restored.update(means[k], case.cov[k])
        a, b = rec.estimate(), restored.estimate()
        np.testing.assert_array_equal(a.params, b.params)
        np.testing.assert_array_equal(a.cov, b.cov)
        assert (a.chi2, a.n_positions, a.reference) == (b.chi2, b.n_positions, b.reference)


def test_recursive_form_before_initialization_and_with_bad_input():
    case = mems_accel(np.random.default_rng(33))
    rec = RecursiveNineParam(case.triad)
    for k in range(5):
        assert not rec.update(case.means_true[k], case.cov[k]).initialized
    est = rec.estimate()
    assert (
        est.verdict is Verdict.NOT_OBSERVABLE_YET
        and est.params is None
        and "5 positions" in est.reason
    )
    with pytest.raises(ValueError, match="non-finite"):
        rec.update([np.nan, 0.0, 1.0], case.cov[0])
    with pytest.raises(ValueError, match="axes x, y, z have no spread at all"):
        rec.update(case.means_true[5], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not positive definite"):
        rec.update(case.means_true[5], np.full((3, 3), 1e-6))
    assert rec.n_positions == 5
    with pytest.raises(ValueError, match="kind"):
        RecursiveNineParam.from_state_dict({"kind": "something else"})
    state = rec.state_dict()
    state["x"] = [0.0] * 8
    with pytest.raises(ValueError, match="'x' must be a finite array of shape"):
        RecursiveNineParam.from_state_dict(state)


def test_recursive_buffer_is_bounded_while_the_geometry_stays_degenerate():
    base = mems_accel(np.random.default_rng(34))
    dirs = single_axis_directions([0, 1, 0], 40)
    case = TriadCase(
        base.triad, base.bias, base.scale, base.angles, dirs, np.repeat(base.cov[:1], 40, axis=0)
    )
    rec = RecursiveNineParam(case.triad, warmup_positions=9, max_buffer=16)
    for m, c in zip(case.means_true, case.cov, strict=True):
        rec.update(m, c)
    assert rec.n_positions == 16 and rec.n_dropped == 24
    assert "fewer than two rotation axes" in rec.estimate().reason


def test_estimate_triad_normalizes_si_positions():
    case = mems_accel(np.random.default_rng(40))
    g = 9.79
    means = case.draw(np.random.default_rng(41), 1)[0]
    positions = [
        Position(float(k), k + 10.0, 1000, m * g, c * g * g, None, None, 20.0)
        for k, (m, c) in enumerate(zip(means, case.cov, strict=True))
    ]
    est = estimate_triad(positions, Triad.ACCEL, g)
    ref = estimate_refined(means, case.cov, case.triad)
    np.testing.assert_allclose(
        est.params, ref.params, rtol=0, atol=1e-9 * np.max(ref.sigma) + 1e-15
    )
    assert est.reference == g and est.method is Method.REFINED
    assert estimate_triad(positions, Triad.ACCEL, g, method=Method.LINEAR).method is Method.LINEAR
    with pytest.raises(ValueError, match="position 0 has no gyro"):
        estimate_triad(positions, Triad.GYRO, 7.29e-5)
    with pytest.raises(ValueError, match="RecursiveNineParam"):
        estimate_triad(positions, Triad.ACCEL, g, method=Method.RECURSIVE)


def test_bad_positions_are_rejected_with_the_offending_value():
    case = mems_accel(np.random.default_rng(42))
    means = case.means_true.copy()
    means[3, 1] = np.inf
    with pytest.raises(ValueError, match=r"position 3 has a non-finite mean"):
        estimate_refined(means, case.cov, case.triad)
    with pytest.raises(
        ValueError, match=r"covariances must have shape \(18, 3, 3\), got \(17, 3, 3\)"
    ):
        estimate_linear(case.means_true, case.cov[:17], case.triad)
    asym = case.cov.copy()
    asym[2, 0, 1] = 1e-9
    with pytest.raises(ValueError, match="position 2 covariance is not symmetric"):
        estimate_refined(case.means_true, asym, case.triad)


def test_equation_sigma_is_the_propagated_noise_of_the_scalar_equation():
    case = mems_accel(np.random.default_rng(43))
    rng = np.random.default_rng(44)
    draws = case.draw(rng, 4000)
    f = np.array([ellipsoid_residual(case.params, m)[0] for m in draws])
    predicted = equation_sigma(case.params, case.means_true, case.cov)
    # Sample std of 4000 draws: relative standard error 1/sqrt(2·4000) ≈ 1.1 %; 5σ bound.
    np.testing.assert_allclose(f.std(axis=0), predicted, rtol=0.06)


def test_estimate_to_dict_is_strict_json():
    case = mems_accel(np.random.default_rng(45))
    est = estimate_triad(
        [
            Position(
                0.0, 1.0, 1000, m * STANDARD_GRAVITY_MPS2, c * STANDARD_GRAVITY_MPS2**2, None, None
            )
            for m, c in zip(case.means_true, case.cov, strict=True)
        ],
        Triad.ACCEL,
        STANDARD_GRAVITY_MPS2,
    )
    text = json.dumps(est.to_dict(), allow_nan=False)
    back = json.loads(text)
    assert (
        back["verdict"] == "observable"
        and back["param_names"] == list(PARAM_NAMES)
        and len(back["sigma"]) == 9
    )
    missing = estimate_refined(case.means_true[:3], case.cov[:3], case.triad).to_dict()
    assert missing["params"] is None and missing["condition_number"] is None
    json.dumps(missing, allow_nan=False)


@pytest.mark.parametrize(("gain", "hint"), [(180.0 / np.pi, True), (0.5, False)])
def test_a_fit_that_leaves_the_physical_domain_says_so_apart_from_too_few_positions(gain, hint):
    """A navigation gyro whose rates are all multiplied (values in deg/s read as rad/s, or a gross
    scale fault): the eighteen positions determine the parameters, the exact fit leaves the domain,
    and the estimate says that (the chain calls the triad SUSPECT), naming deg/s when the gains
    are 180/π; the same positions unscaled are observable."""
    rng = np.random.default_rng(5)
    case = nav_gyro(rng)
    means = case.draw(rng, 1)[0]
    assert not estimate_refined(means, case.cov, case.triad).fit_left_domain
    est = estimate_refined(gain * means, gain**2 * case.cov, case.triad)
    assert est.fit_left_domain and est.params is None
    assert est.verdict is Verdict.NOT_OBSERVABLE_YET and est.to_dict()["fit_left_domain"] is True
    assert ("values in deg/s read as rad/s" in est.reason) is hint
    few = estimate_refined(gain * means[:8], gain**2 * case.cov[:8], case.triad)
    assert not few.fit_left_domain
