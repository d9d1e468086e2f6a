"""Strapdown attitude integrator (methods.md M5): exact cases, coning, Euler kinematics."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimators.strapdown import (
    body_rate_from_euler,
    euler_from_quat,
    integrate_attitude,
    quat_from_euler,
    quat_multiply,
    rotate_to_body,
)


def _angle_between(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of ``q_a⁻¹ ⊗ q_b``."""
    return (Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()


def test_constant_rate_rotation_is_exact_for_any_time_stamps():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.005, 0.015, 2000))  # jittered stamps around 100 Hz
    w = np.array([0.7, -1.1, 0.4])  # rad/s, far from small angles over 20 s
    q = integrate_attitude(t, np.tile(w, (t.size, 1)))
    truth = Rotation.from_rotvec((t - t[0])[:, None] * w[None]).as_quat()
    # A constant rate has zero coning term and a cubic integrates it exactly: only rounding is left.
    assert np.max(_angle_between(truth, q)) < 1e-11


def test_rotation_about_a_fixed_axis_has_the_cubic_rules_error():
    t = np.arange(0.0, 10.0, 0.01)
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    rate = 0.5 * np.sin(2 * np.pi * 0.5 * t) + 0.2 * t**2  # a cubic part integrates exactly
    q = integrate_attitude(t, rate[:, None] * axis[None])
    angle = 0.5 * (1.0 - np.cos(2 * np.pi * 0.5 * t)) / (2 * np.pi * 0.5) + 0.2 * t**3 / 3.0
    truth = Rotation.from_rotvec(angle[:, None] * axis[None]).as_quat()
    # No coning term (parallel increments); the cubic's error is (11/720)·h⁵·f⁗ per step, f⁗ = 0.5π⁴ sin πt,
    # so the accumulated error peaks after each half period at (11/720)·h⁴·0.5π⁴·(2/π).
    predicted = 11.0 / 720.0 * 0.01**4 * 0.5 * np.pi**4 * 2.0 / np.pi
    assert np.max(_angle_between(truth, q)) == pytest.approx(predicted, rel=0.05)


def _classic_coning(
    beta_rad: float, cone_rps: float, rate_hz: float, duration_s: float, *, coning: bool
) -> float:
    """Drift rate (rad/s) of the integrated attitude against the exact classic coning attitude."""
    t = np.arange(0.0, duration_s + 0.5 / rate_hz, 1.0 / rate_hz)
    s, c = np.sin(beta_rad / 2), np.cos(beta_rad / 2)
    # Truth: rotation vector of fixed length β turning in the x-y plane; its body rate in closed form.
    truth = np.column_stack(
        [s * np.cos(cone_rps * t), s * np.sin(cone_rps * t), np.zeros_like(t), np.full_like(t, c)]
    )
    w = np.column_stack(
        [
            -cone_rps * np.sin(beta_rad) * np.sin(cone_rps * t),
            cone_rps * np.sin(beta_rad) * np.cos(cone_rps * t),
            np.full_like(t, -2.0 * cone_rps * s * s),
        ]
    )
    q = integrate_attitude(t, w, quat0=truth[0], coning=coning)
    return float(_angle_between(truth[-1], q[-1]) / t[-1])


def test_coning_correction_removes_the_coning_drift():
    beta, cone = np.radians(2.0), 2 * np.pi * 5.0
    rectified = cone * (1.0 - np.cos(beta))  # the mean body rate the attitude must cancel
    drift = {
        (fs, con): _classic_coning(beta, cone, fs, 10.0, coning=con)
        for fs in (100.0, 200.0)
        for con in (False, True)
    }
    for fs in (100.0, 200.0):
        # Without the correction the algorithm drifts by rectified·(Ωh)²/6 to first order in (Ωh)².
        predicted = rectified * (cone / fs) ** 2 / 6.0
        assert drift[(fs, False)] == pytest.approx(predicted, rel=0.03)
    # With it the drift is fourth order in the step (halving h divides it by ~16) ...
    assert 12.0 < drift[(100.0, True)] / drift[(200.0, True)] < 20.0
    assert 3.6 < drift[(100.0, False)] / drift[(200.0, False)] < 4.4
    # ... and at 100 Hz (Ωh = 0.31) it is already more than 20 times smaller.
    assert drift[(100.0, True)] < drift[(100.0, False)] / 20.0


def test_euler_angles_round_trip_and_follow_the_papers_axes():
    rng = np.random.default_rng(2)
    angles = rng.uniform([-3.0, -3.0, -1.4], [3.0, 3.0, 1.4], (200, 3))  # [γ, ψ, θ]
    back = euler_from_quat(quat_from_euler(angles), unwrap=False)
    np.testing.assert_allclose(back, angles, atol=1e-12)
    # Yaw alone turns the forward axis X about the vertical Y towards −Z (right-hand rule about Y).
    x_fwd = Rotation.from_quat(quat_from_euler(np.array([0.0, np.pi / 2, 0.0]))).apply(
        [1.0, 0.0, 0.0]
    )
    np.testing.assert_allclose(x_fwd, [0.0, 0.0, -1.0], atol=1e-15)
    # Pitch alone lifts the nose: X turns towards Y (up).
    x_fwd = Rotation.from_quat(quat_from_euler(np.array([0.0, 0.0, np.pi / 2]))).apply(
        [1.0, 0.0, 0.0]
    )
    np.testing.assert_allclose(x_fwd, [0.0, 1.0, 0.0], atol=1e-15)


def _euler_trajectory_error(rate_hz: float) -> float:
    """Largest attitude error (rad) over 20 s of three-axis sinusoidal Euler motion."""
    t = np.arange(0.0, 20.0, 1.0 / rate_hz)
    nu = 2 * np.pi * np.array([0.53, 0.31, 0.47])
    amp = np.radians([12.0, 20.0, 15.0])
    angles = amp * np.sin(nu * t[:, None] + [0.3, 1.0, 2.0])
    rates = amp * nu * np.cos(nu * t[:, None] + [0.3, 1.0, 2.0])
    q = integrate_attitude(t, body_rate_from_euler(angles, rates), quat0=quat_from_euler(angles[0]))
    return float(np.max(_angle_between(quat_from_euler(angles), q)))


def test_body_rates_of_an_euler_trajectory_integrate_back_to_it():
    coarse, fine = _euler_trajectory_error(100.0), _euler_trajectory_error(200.0)
    # General (non-coning) motion leaves Bortz's φ×(φ×ω)/12 term: third order globally.
    assert 6.0 < coarse / fine < 10.0
    # At 100 Hz that is below 1e-6 rad in 20 s (< 0.01 °/h), far below what M5 measures.
    assert coarse < 1e-6


def test_a_batch_integrates_like_its_members():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 5.0, 0.01)
    w = rng.normal(0.0, 0.5, (2, t.size, 3))
    batch = integrate_attitude(t, w)
    for b in range(2):
        np.testing.assert_allclose(batch[b], integrate_attitude(t, w[b]), atol=1e-15)


def test_quaternion_helpers_agree_with_scipy():
    rng = np.random.default_rng(4)
    p, q = Rotation.random(5, random_state=rng), Rotation.random(5, random_state=rng)
    np.testing.assert_allclose(
        np.abs(np.sum(quat_multiply(p.as_quat(), q.as_quat()) * (p * q).as_quat(), axis=1)),
        1.0,
        atol=1e-14,
    )
    v = np.array([0.1, 9.8, -0.3])
    np.testing.assert_allclose(rotate_to_body(p.as_quat(), v), p.inv().apply(v), atol=1e-13)


@pytest.mark.parametrize(
    ("t", "w", "match"),
    [
        (np.arange(3.0), np.zeros((3, 3)), "at least 4 samples"),
        (np.array([0.0, 1.0, 1.0, 2.0]), np.zeros((4, 3)), "strictly increasing"),
        (np.arange(5.0), np.full((5, 3), np.nan), "finite"),
        (np.arange(5.0), np.zeros((5, 2)), "shape"),
    ],
)
def test_bad_input_is_rejected_with_a_reason(t, w, match):
    with pytest.raises(ValueError, match=match):
        integrate_attitude(t, w)
