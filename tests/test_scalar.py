"""F0, the scalar shell test of methods.md M1, and its derived threshold λ0."""

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from estimators.conventions import (
    EARTH_RATE_RPS,
    Triad,
    normal_gravity_mps2,
    sensor_axes,
    triad_matrix,
)
from estimators.scalar import (
    F0Config,
    F0Monitor,
    F0State,
    compensate,
    derive_lambda0,
    f0_batch,
    f0_session,
    lambda0_lower_bound,
    normalize,
    persistent_failure,
    scalar_residual,
    triad_reference,
)
from estimators.sim import Fault, FaultKind, Grade, multi_position_spec, simulate, static_spec
from estimators.static_detector import StreamingStaticDetector, detect_static

G = 9.80665


def _binomial_bounds(n: int, p: float, alpha: float = 1e-6) -> tuple[float, float]:
    """Two-sided (1 − alpha) range of the number of false alarms among n tests."""
    return stats.binom.interval(1.0 - alpha, n, p)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


# --- normalization and the residual -------------------------------------------------------------


def test_residual_is_half_of_norm_squared_minus_one():
    x = np.array([[1.0, 0.0, 0.0], [0.0, 1.1, 0.0], [0.6, 0.0, 0.8], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(scalar_residual(x), [0.0, 0.105, 0.0, -0.5], atol=1e-15)


def test_residual_pins_the_shape():
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        scalar_residual(np.ones((4, 2)))


def test_reference_is_configured_or_normal_gravity_and_earth_rate_for_gyros():
    assert triad_reference(Triad.ACCEL, gravity_mps2=9.81744) == 9.81744
    assert triad_reference(Triad.ACCEL, latitude_deg=45.0, height_m=100.0) == normal_gravity_mps2(
        45.0, 100.0
    )
    assert triad_reference(Triad.GYRO) == EARTH_RATE_RPS
    with pytest.raises(ValueError, match="exactly one"):
        triad_reference(Triad.ACCEL)
    with pytest.raises(ValueError, match="exactly one"):
        triad_reference(Triad.ACCEL, gravity_mps2=9.8, latitude_deg=10.0)
    with pytest.raises(ValueError, match="within"):
        triad_reference(Triad.ACCEL, gravity_mps2=98.0)


def test_normalize_never_writes_into_its_input():
    x = np.full((2, 3), G)
    y = normalize(x, G)
    assert np.all(x == G) and np.allclose(y, 1.0)


def test_compensation_puts_an_exact_error_model_on_the_unit_sphere():
    # conventions: ã = A u + b exactly, so A⁻¹(ã − b) = u has unit norm.
    rng = np.random.default_rng(3)
    a = triad_matrix(rng.normal(0, 5e-3, 3), sensor_axes(rng.normal(0, 2e-3, 6)))
    b = rng.normal(0, 5e-3, 3)
    u = rng.normal(size=(100, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    x = u @ a.T + b
    assert np.max(np.abs(scalar_residual(x))) > 1e-3
    np.testing.assert_allclose(scalar_residual(compensate(x, b, a)), 0.0, atol=1e-14)

    cfg = F0Config(lambda0=1e-3, reference=G, bias_norm=b, matrix=a)
    res = f0_batch(G * x, np.ones(100, bool), cfg)
    np.testing.assert_allclose(res.residual, 0.0, atol=1e-14)
    mon = F0Monitor(cfg)
    for row in (G * x).tolist():
        assert mon.check(*row, True) is F0State.OK
    assert abs(mon.last_residual) < 1e-14


# --- λ0: hand-derived pieces ---------------------------------------------------------------------


def test_tolerance_offsets_match_hand_maxima():
    base = dict(noise_std_norm=[1e-4] * 3, false_alarm_prob=1e-3)
    tb = np.array([3e-3, 4e-3, 0.0])
    # Bias only: max over |u| = 1 of Σ|b_i u_i| is |b| (Cauchy–Schwarz).
    lam = derive_lambda0(**base, tolerance_norm=np.r_[tb, np.zeros(6)])
    assert lam.tolerance_first_order == pytest.approx(5e-3, rel=1e-9)
    # Second order: ½|b|².
    assert lam.tolerance_second_order == pytest.approx(0.5 * 5e-3**2, rel=1e-12)
    # Scale only: max of Σ e_i u_i² is the largest e_i.
    lam = derive_lambda0(**base, tolerance_norm=[0, 0, 0, 1e-3, 7e-3, 2e-3, 0, 0, 0])
    assert lam.tolerance_first_order == pytest.approx(7e-3, rel=1e-9)
    # One cosine only: max of δ1·|ux uy| is δ1/2.
    lam = derive_lambda0(**base, tolerance_norm=[0, 0, 0, 0, 0, 0, 4e-3, 0, 0])
    assert lam.tolerance_first_order == pytest.approx(2e-3, rel=1e-9)
    # Reference: g off by r scales |ã| by (1 + r).
    lam = derive_lambda0(**base, reference_rel_err=1e-4)
    assert lam.reference_offset == pytest.approx(1e-4 + 0.5e-8, rel=1e-12)
    assert lam.lambda0 == pytest.approx(lam.noise_threshold + lam.reference_offset, rel=1e-12)


def test_quantization_and_averaging_enter_as_variances():
    sig, q = np.array([1e-3, 2e-3, 1e-3]), np.array([3e-3, 3e-3, 3e-3])
    lam = derive_lambda0(noise_std_norm=sig, quantization_norm=q, n_avg=4, false_alarm_prob=1e-3)
    assert lam.noise_std == pytest.approx(math.sqrt((4e-6 + 9e-6 / 12) / 4), rel=1e-12)
    # Small noise: the two-sided Gaussian quantile, shifted by the ½|n|² mean.
    assert lam.noise_threshold == pytest.approx(stats.norm.isf(5e-4) * lam.noise_std, rel=2e-3)


def test_tolerance_bound_holds_for_every_unit_and_orientation():
    # Random units of the exact conventions model; their own |parameters| as tolerances.
    rng = np.random.default_rng(11)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    worst_ratio = 0.0
    for _ in range(40):
        b = rng.normal(0, 5e-3, 3)
        e = rng.normal(0, 5e-3, 3)
        axes = sensor_axes(rng.normal(0, 3e-3, 6))
        d = np.array([axes[0] @ axes[1], axes[0] @ axes[2], axes[1] @ axes[2]])
        lam = derive_lambda0(
            noise_std_norm=[1e-6] * 3, false_alarm_prob=0.5, tolerance_norm=np.abs(np.r_[b, e, d])
        )
        s = scalar_residual(u @ triad_matrix(e, axes).T + b)
        bound = lam.tolerance_first_order + lam.tolerance_second_order
        assert np.max(np.abs(s)) <= bound
        worst_ratio = max(worst_ratio, np.max(np.abs(s)) / bound)
    # ... and is not loose: some unit comes close to it.
    assert worst_ratio > 0.8


def test_the_search_starts_from_the_whole_grid_s_extreme_nodes():
    # tolerance_extremes' search starts from the largest and the least s over every corner of the
    # tolerance box and every direction of the sphere grid. Only the corners whose bounds can reach
    # them are evaluated: the nodes, their values to the bit and the first among equal values must
    # be the whole grid's. The nominal classes' tolerances (equal axes: ties), gyro-sized zero
    # signals (|b| far above 1), single and zero parameters, random ones over seven decades.
    from estimators.nominal_passport import SensorClass, nominal_passport
    from estimators.scalar import (
        _grid_extremes,
        _model_matrices,
        _residual_of,
        _search_grid,
        _static_residual,
    )

    rng = np.random.default_rng(12)
    cases = [tp.tolerance for c in SensorClass for tp in nominal_passport(c).triads.values()] + [
        np.eye(9)[j] * 0.02 for j in range(9)
    ]
    for _ in range(25):
        tol = 10.0 ** rng.uniform(-6.0, 1.0, 9) * (rng.random(9) < 0.8)
        tol[:3] = tol[0] if rng.random() < 0.3 else tol[:3]
        cases.append(tol if np.any(tol) else tol + 1e-3)
    for tol in cases:
        corners, u = _search_grid(tol)
        s = _static_residual(corners, u)
        whole = [(*divmod(f, u.shape[0]), float(s.flat[f])) for f in (np.argmax(s), np.argmin(s))]
        assert _grid_extremes(corners, u) == whole, tol
    # What that rests on: a row's values are the same bits in a stack of any height.
    corners, u = _search_grid(cases[0])
    a, b = _model_matrices(corners), corners[:, :3]
    whole = _residual_of(a, b, u)
    for size in (1, 2, 17, 100):
        rows = np.sort(rng.choice(len(corners), size, replace=False))
        np.testing.assert_array_equal(_residual_of(a[rows], b[rows], u), whole[rows])


def test_grid_extremes_of_overflowing_tolerances_are_the_whole_grids(capfd):
    # Finite tolerances pass tolerance_extremes' check, however large: near 1e300 the model's
    # matrices overflow and the grid holds NaN. The cut must pick the whole grid's nodes as
    # np.argmax/argmin do (the first NaN) and print nothing: LAPACK's SVD, given inf, writes
    # "On entry to DLASCL ..." on the process's stdout, replay --json's event stream.
    from estimators.scalar import _grid_extremes, _search_grid, _static_residual

    for tol in (np.full(9, 1e300), np.r_[0.0, 1e308, 0.0, 1e308, 1e308, 0.0, 1e308, 1e308, 1e308]):
        corners, u = _search_grid(tol)
        with np.errstate(all="ignore"):
            s = _static_residual(corners, u)
            nodes = _grid_extremes(corners, u)
        whole = [
            (*divmod(int(f), u.shape[0]), float(s.flat[f])) for f in (np.argmax(s), np.argmin(s))
        ]
        assert repr(nodes) == repr(whole), tol
    assert capfd.readouterr().out == ""


def test_lambda0_rejects_bad_input():
    with pytest.raises(ValueError, match="noise_std_norm"):
        derive_lambda0(noise_std_norm=[0.0, 1.0, 1.0], false_alarm_prob=1e-3)
    with pytest.raises(ValueError, match="false_alarm_prob"):
        derive_lambda0(noise_std_norm=[1e-3] * 3, false_alarm_prob=0.0)
    with pytest.raises(ValueError, match="tolerance_norm"):
        derive_lambda0(noise_std_norm=[1e-3] * 3, false_alarm_prob=1e-3, tolerance_norm=[1e-3] * 8)
    with pytest.raises(ValueError, match="n_avg"):
        derive_lambda0(noise_std_norm=[1e-3] * 3, false_alarm_prob=1e-3, n_avg=0)


def test_lambda0_lower_bound_lies_below_the_exact_lambda0():
    """lambda0_lower_bound's proof (σΦ⁻¹(1 − p) of the noise part, the tolerance part ≥ 0, the
    reference term exact) against derive_lambda0 on random inputs: noise from the Gaussian path
    (σ < 1e-4) to noise larger than the reference (a MEMS gyro against the Earth rate), p from
    1e-12 to 0.4, unequal axes, quantization, averaging, the reference's error; tolerances on a
    few (their worst case costs 0.1 s each). And it is close where it serves: within 7 % of λ0's
    noise part for an accelerometer's noise (σ < 0.01) at p ≤ 1e-3 (the one-sided tail it takes
    is half the two-sided one there)."""
    rng = np.random.default_rng(33)
    for k in range(80):
        sigma = 10.0 ** rng.uniform(-6.0, 2.0) * rng.uniform(0.3, 1.0, 3)
        inputs = {
            "noise_std_norm": sigma,
            "false_alarm_prob": 10.0 ** rng.uniform(-12.0, math.log10(0.4)),
            "quantization_norm": sigma * rng.uniform(0.0, 3.0, 3) if k % 3 == 0 else None,
            "n_avg": int(rng.integers(1, 9)) if k % 4 == 0 else 1,
            "reference_rel_err": float(rng.uniform(0.0, 0.01)) if k % 2 else 0.0,
            "tolerance_norm": rng.uniform(0.0, 0.02, 9) if k % 40 == 0 else None,
        }
        bound = lambda0_lower_bound(**inputs)
        lam = derive_lambda0(**inputs)
        assert 0.0 < bound <= lam.lambda0, inputs
        if lam.noise_std < 0.01 and lam.false_alarm_prob <= 1e-3:
            assert bound - lam.reference_offset >= 0.93 * lam.noise_threshold, inputs


NOISE_TAIL_ALONE = """
import json, sys
from estimators.scalar import _noise_tail
tails = [_noise_tail(x, sigma) for x, sigma in json.loads(sys.argv[1])]
print(json.dumps({"tails": tails, "scipy.stats": "scipy.stats" in sys.modules}))
"""


def _stats_noise_tail(x: float, sigma: float) -> float:
    """``P(|s| > x)`` of derive_lambda0's noise model from scipy.stats' distributions (its docstring)."""
    if sigma >= 1e-4:
        nc = 1.0 / sigma**2
        up = stats.ncx2.sf((1.0 + 2.0 * x) * nc, 3, nc)
        lo = stats.ncx2.cdf((1.0 - 2.0 * x) * nc, 3, nc) if 2.0 * x < 1.0 else 0.0
        return float(up + lo)
    mean, sd = 1.5 * sigma**2, math.sqrt(sigma**2 + 1.5 * sigma**4)
    return float(stats.norm.sf((x - mean) / sd) + stats.norm.cdf((-x - mean) / sd))


def test_lambda0_s_noise_tail_is_scipy_stats_bit_for_bit_without_importing_it(monkeypatch):
    # scipy.stats takes most of a second to import, and calibrate derives λ0 for its own-session
    # check: the same functions are taken from scipy.special. Navigation-grade noise (the Gaussian
    # below σ = 1e-4), MEMS, and noise near the reference (both tails of the χ², x past ½).
    grid = [
        (k * sigma + 1.5 * sigma**2, sigma)
        for sigma in (3e-5, 1e-4, 1e-3, 0.05, 0.3)
        for k in np.linspace(0.0, 12.0, 25)
    ]
    run = subprocess.run(
        [sys.executable, "-c", NOISE_TAIL_ALONE, json.dumps(grid)],
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        check=True,
    )
    out = json.loads(run.stdout)
    assert not out["scipy.stats"]
    assert out["tails"] == [_stats_noise_tail(x, sigma) for x, sigma in grid]
    # A scipy whose scipy.special lacks the private Boost ufunc (older ones): scipy.stats' own.
    import scipy.special

    from estimators.scalar import _noise_tail

    monkeypatch.setattr(scipy.special, "_ufuncs", SimpleNamespace())
    assert [_noise_tail(x, sigma) for x, sigma in grid] == out["tails"]


# --- λ0: false alarms on fault-free static data ---------------------------------------------------


@pytest.mark.parametrize(
    "sigma",
    [
        1e-3,  # MEMS accelerometer per sample: non-central χ² path
        3e-5,  # navigation-grade: Gaussian path
        0.2,  # noise comparable to the reference: ½|n|² dominates the skew
    ],
)
def test_false_alarm_rate_matches_the_stated_probability(sigma):
    n, p = 2_000_000, 1e-3
    rng = np.random.default_rng(int(sigma * 1e6))
    lam = derive_lambda0(noise_std_norm=[sigma] * 3, false_alarm_prob=p)
    # Four orientations cycling: with isotropic noise the rate does not depend on it.
    u = np.array([_unit([0, 0, 1]), _unit([1, 1, 1]), _unit([1, -2, 0.5]), _unit([-1, 0, 0])])
    x = G * (np.tile(u, (n // 4, 1)) + sigma * rng.standard_normal((n, 3)))
    res = f0_batch(x, np.ones(n, bool), F0Config(lambda0=lam.lambda0, reference=G))
    lo, hi = _binomial_bounds(n, p)
    assert res.n_tests == n
    assert lo <= res.n_fail <= hi


def test_false_alarm_rate_is_the_stated_one_in_the_worst_orientation_only():
    n, p = 1_000_000, 1e-3
    rng = np.random.default_rng(5)
    sig = np.array([1e-3, 5e-4, 5e-4])
    lam = derive_lambda0(noise_std_norm=sig, false_alarm_prob=p)
    cfg = F0Config(lambda0=lam.lambda0, reference=G)
    lo, hi = _binomial_bounds(n, p)
    noise = sig * rng.standard_normal((n, 3))
    along_x = f0_batch(G * (np.array([1.0, 0, 0]) + noise), np.ones(n, bool), cfg)
    along_y = f0_batch(G * (np.array([0, 1.0, 0]) + noise), np.ones(n, bool), cfg)
    assert lo <= along_x.n_fail <= hi
    assert along_y.n_fail < lo


def test_false_alarm_rate_per_averaging_window():
    n_avg, n, p = 8, 1_600_000, 5e-3
    rng = np.random.default_rng(8)
    lam = derive_lambda0(noise_std_norm=[1e-3] * 3, false_alarm_prob=p, n_avg=n_avg)
    x = G * (_unit([1, 2, 2]) + 1e-3 * rng.standard_normal((n, 3)))
    res = f0_batch(x, np.ones(n, bool), F0Config(lambda0=lam.lambda0, reference=G, n_avg=n_avg))
    lo, hi = _binomial_bounds(n // n_avg, p)
    assert res.n_tests == n // n_avg
    assert lo <= res.n_fail <= hi


def test_quantization_term_keeps_the_false_alarm_rate_bounded():
    # Noise of one converter step, rounded to the nearest count: the q²/12 term is needed.
    n, p, q = 2_000_000, 1e-3, 1e-3
    rng = np.random.default_rng(9)
    u = _unit([0.3, -0.4, 1.0])
    x_norm = q * np.round((u + q * rng.standard_normal((n, 3))) / q)
    _lo, hi = _binomial_bounds(n, p)
    with_q = derive_lambda0(noise_std_norm=[q] * 3, quantization_norm=[q] * 3, false_alarm_prob=p)
    without_q = derive_lambda0(noise_std_norm=[q] * 3, false_alarm_prob=p)
    fails = [
        f0_batch(G * x_norm, np.ones(n, bool), F0Config(lambda0=lam.lambda0, reference=G)).n_fail
        for lam in (with_q, without_q)
    ]
    assert fails[0] <= hi
    assert fails[1] > hi


# --- detection -----------------------------------------------------------------------------------


def test_step_fault_is_flagged_at_the_first_sample_after_onset():
    n, onset, sigma, p = 4000, 2500, 1e-3, 1e-6
    rng = np.random.default_rng(21)
    lam = derive_lambda0(noise_std_norm=[sigma] * 3, false_alarm_prob=p)
    # A zero-signal step on the up axis moves s by the step: λ0 + 8σ leaves the shell
    # at every sample with probability 1 − Φ(−8).
    x = np.array([0.0, 0.0, 1.0]) + sigma * rng.standard_normal((n, 3))
    x[onset:, 2] += lam.lambda0 + 8 * sigma
    cfg = F0Config(lambda0=lam.lambda0, reference=G)
    res = f0_batch(G * x, np.ones(n, bool), cfg)
    assert not np.any(res.state[:onset] == F0State.FAIL)
    assert np.all(res.state[onset:] == F0State.FAIL)
    mon = F0Monitor(cfg)
    states = [mon.check(*row, True) for row in (G * x).tolist()]
    np.testing.assert_array_equal(np.array(states, np.int8), res.state)


def _compensation_of(truth, spec):
    """F0 compensation of a simulated unit's exact accelerometer model (the half-step FLOOR offset included)."""
    model = spec.model.accel
    g = truth.gravity_true_mps2
    q = model.find("quantization").step_si
    bias = np.array(model.find("bias").bias_si) - 0.5 * np.array(q)
    a = triad_matrix(
        np.array(model.find("scale_factor").scale_err), model.find("non_orthogonality").axes
    )
    noise = model.find("white_noise").sample_sd(spec.rate_hz)
    return g, bias / g, a, np.array(noise) / g, np.array(q) / g


def test_simulated_bias_step_is_flagged_at_onset_with_the_streaming_detector():
    # MEMS unit at rest, its passport compensated, bias step on the up axis at 20 s.
    base = static_spec(duration_s=40.0, grade=Grade.MEMS)
    truth0 = simulate(base, seed=4).truth
    g, b, a, noise, q = _compensation_of(truth0, base)
    lam = derive_lambda0(noise_std_norm=noise, quantization_norm=q, false_alarm_prob=1e-6)
    step = lam.lambda0 + 8 * lam.noise_std
    up_axis = int(np.argmax(np.abs(truth0.specific_force_b_mps2[0])))
    spec = static_spec(
        duration_s=40.0,
        grade=Grade.MEMS,
        faults=(Fault(FaultKind.STEP, Triad.ACCEL, up_axis, 20.0, step),),
    )
    sim = simulate(spec, seed=4)
    onset = int(np.searchsorted(sim.session.t_s, 20.0))
    cfg = F0Config(lambda0=lam.lambda0, reference=g, bias_norm=b, matrix=a)

    det = StreamingStaticDetector(rate_hz=sim.spec.rate_hz)
    mon = F0Monitor(cfg)
    states = []
    for t, (ax, ay, az), (gx, gy, gz) in zip(
        sim.session.t_s.tolist(),
        sim.session.accel_mps2.tolist(),
        sim.session.gyro_rps.tolist(),
        strict=False,
    ):
        states.append(
            mon.check(ax, ay, az, det.static_now)
        )  # the static verdict before this sample
        det.update(t, ax, ay, az, gx, gy, gz)
    states = np.array(states, np.int8)
    assert states[onset] == F0State.FAIL
    assert not np.any(states[:onset] == F0State.FAIL)
    assert not np.any(states[onset:] == F0State.OK)

    batch = f0_batch(sim.session.accel_mps2, detect_static(sim.session).static, cfg)
    assert batch.state[onset] == F0State.FAIL
    assert not np.any(batch.state[:onset] == F0State.FAIL)
    assert np.all(batch.state[onset:] == F0State.FAIL)


def test_f0_is_not_applicable_while_the_unit_moves():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=6, static_s=4.0, transition_s=3.0)
    sim = simulate(spec, seed=12)
    g, b, a, noise, q = _compensation_of(sim.truth, spec)
    lam = derive_lambda0(noise_std_norm=noise, quantization_norm=q, false_alarm_prob=1e-6)
    cfg = F0Config(lambda0=lam.lambda0, reference=g, bias_norm=b, matrix=a)
    static = detect_static(sim.session).static
    res = f0_batch(sim.session.accel_mps2, static, cfg)
    # The middle half of each 3 s minimum-jerk turn (≥ 0.75 s from rest): the rate there is
    # ≥ 1.05·Θ/T, which sweeps the specific force by degrees within one 0.5 s window,
    # far above the 0.05 m/s² spread a quiet window may have.
    t = sim.session.t_s
    t_rest = t[sim.truth.static]
    k = np.clip(np.searchsorted(t_rest, t), 1, t_rest.size - 1)
    from_rest_s = np.minimum(np.abs(t - t_rest[k - 1]), np.abs(t_rest[k] - t))
    turning = from_rest_s > 0.75
    assert turning.sum() > 500
    assert np.all(res.state[turning] == F0State.NOT_APPLICABLE)
    assert np.all(res.state[~static] == F0State.NOT_APPLICABLE)
    assert np.all(np.isnan(res.residual[~static]))
    assert res.n_fail == 0 and res.n_tests == static.sum()


# --- per sample = batch, bad input, checkpoints -----------------------------------------------------


def _messy_stream(rng, n=3000):
    x = G * (_unit([0.2, 0.1, 1.0]) + 2e-3 * rng.standard_normal((n, 3)))
    x[rng.choice(n, 40, replace=False), rng.integers(0, 3, 40)] = np.nan
    x[rng.choice(n, 5, replace=False), 1] = np.inf
    static = np.ones(n, bool)
    for start in rng.choice(n - 50, 12, replace=False):
        static[start : start + rng.integers(1, 40)] = False
    return x, static


@pytest.mark.parametrize("n_avg", [1, 7])
def test_monitor_gives_the_batch_decisions_and_counts_bad_samples(n_avg):
    rng = np.random.default_rng(30 + n_avg)
    x, static = _messy_stream(rng)
    lam = derive_lambda0(noise_std_norm=[2e-3] * 3, false_alarm_prob=0.05, n_avg=n_avg)
    cfg = F0Config(
        lambda0=lam.lambda0,
        reference=G,
        bias_norm=(1e-3, 0, -1e-3),
        matrix=np.eye(3) * 1.001,
        n_avg=n_avg,
    )
    res = f0_batch(x, static, cfg)
    mon = F0Monitor(cfg)
    states = np.array(
        [mon.check(*row, bool(s)) for row, s in zip(x.tolist(), static, strict=True)], np.int8
    )
    np.testing.assert_array_equal(states, res.state)
    bad = ~np.isfinite(x).all(axis=1)
    assert mon.n_rejected == res.n_rejected == bad.sum()
    assert np.all(res.state[bad] == F0State.NOT_APPLICABLE)
    assert mon.n_tests == res.n_tests and mon.n_fail == res.n_fail
    assert 0 < res.n_fail < res.n_tests  # both outcomes occur, so the comparison has content


def test_monitor_checkpoint_round_trip_mid_window():
    rng = np.random.default_rng(40)
    x, static = _messy_stream(rng)
    cfg = F0Config(lambda0=3e-3, reference=G, n_avg=5)
    whole = F0Monitor(cfg)
    expected = [whole.check(*row, bool(s)) for row, s in zip(x.tolist(), static, strict=True)]
    first = F0Monitor(cfg)
    got = [
        first.check(*row, bool(s)) for row, s in zip(x[:1503].tolist(), static[:1503], strict=True)
    ]
    resumed = F0Monitor.from_state_dict(cfg, json.loads(json.dumps(first.state_dict())))
    got += [
        resumed.check(*row, bool(s))
        for row, s in zip(x[1503:].tolist(), static[1503:], strict=True)
    ]
    assert got == expected
    assert resumed.state_dict() == whole.state_dict()
    with pytest.raises(ValueError, match="invalid F0Monitor state"):
        F0Monitor.from_state_dict(cfg, {"window_sum": [0, 0]})


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="lambda0"):
        F0Config(lambda0=0.0, reference=G)
    with pytest.raises(ValueError, match="singular"):
        F0Config(lambda0=1e-3, reference=G, matrix=np.ones((3, 3)))
    with pytest.raises(ValueError, match="n_avg"):
        F0Config(lambda0=1e-3, reference=G, n_avg=0)
    with pytest.raises(ValueError, match="static must be a bool array"):
        f0_batch(np.ones((3, 3)), np.ones(3), F0Config(lambda0=1e-3, reference=G))


def _runs_brute(state, persist):
    """Index of the sample completing the first `persist` FAILs in a row, by counting (the definition)."""
    run = 0
    for i, s in enumerate(state):
        run = run + 1 if s == F0State.FAIL else 0
        if run >= persist:
            return i
    return -1


@pytest.mark.parametrize("persist", [1, 2, 4, 9])
def test_persistent_failure_is_the_first_run_of_persist_failures_however_the_samples_are_cut(
    persist,
):
    rng = np.random.default_rng(persist)
    for _ in range(200):
        state = rng.choice(
            [F0State.OK, F0State.FAIL, F0State.NOT_APPLICABLE],
            size=int(rng.integers(1, 60)),
            p=[0.3, 0.55, 0.15],
        )
        state = state.astype(np.int8)
        expected = _runs_brute(state, persist)
        k, run = persistent_failure(state, 0, persist)
        assert k == expected
        tail = (
            len(state) - 1 - max([i for i, s in enumerate(state) if s != F0State.FAIL], default=-1)
        )
        assert run == tail
        cuts = np.unique(np.concatenate([[0, len(state)], rng.integers(0, len(state), 3)]))
        run, found = 0, -1
        for a, b in itertools.pairwise(cuts):
            k, run = persistent_failure(state[a:b], run, persist)
            if found < 0 and k >= 0:
                found = a + k
        assert found == expected
    with pytest.raises(ValueError):
        persistent_failure(np.zeros(3, np.int8), 0, 0)


def test_f0_over_a_session_dates_the_first_persistent_run_and_counts_shorter_ones_as_knocks():
    """A resting unit at exactly g: one sample out of the shell (a knock), then a run of three
    beyond it with a non-static sample between two failing ones (which ends a run, as in the
    service), then a persistent run of four from t = 0.5 s."""
    n = 100
    t = np.arange(n) * 0.01
    x = np.tile([0.0, 0.0, 9.8], (n, 1))
    static = np.ones(n, dtype=bool)
    out = 9.8 * np.sqrt(1.1)  # s = 0.05
    x[10, 2] = out
    x[[20, 22], 2] = out
    static[21] = False
    x[50:54, 2] = out
    cfg = F0Config(lambda0=0.01, reference=9.8)
    f0 = f0_session(t, x, static, cfg, persist=2)
    assert (f0.tested, f0.failed, f0.runs, f0.persistent_runs, f0.knocks) == (99, 7, 4, 1, 3)
    assert f0.persistent and f0.onset_t_s == t[50] and f0.first_fail_t_s == t[10]
    assert f0.persistent_failed == 4 and f0.onset_residual == pytest.approx(0.05)
    assert f0.worst == f0.persistent_worst == pytest.approx(0.05)
    # The bare predicate (persistence of one sample): every failing run is a failure.
    assert f0_session(t, x, static, cfg, persist=1).onset_t_s == t[10]
    # Nothing out of the shell: no run, no onset.
    quiet = f0_session(t, np.tile([0.0, 0.0, 9.8], (n, 1)), static, cfg, persist=2)
    assert (quiet.failed, quiet.runs, quiet.onset_t_s, quiet.worst) == (0, 0, None, None)
    with pytest.raises(ValueError, match="persist"):
        f0_session(t, x, static, cfg, persist=0)
