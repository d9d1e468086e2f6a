"""Strapdown attitude integration with a coning correction (methods.md M5).

The integrator turns sampled body angular rates into the body-to-reference
attitude quaternion. It works in any right-handed body frame; the Euler-angle
helpers below use the axes of M5 (Bogdanov & Savelyev):

* body axes **X forward, Y up, Z right** (right-handed: X × Y = Z);
* **roll γ about X, yaw ψ about Y, pitch θ about Z**, each positive by the
  right-hand rule about its own axis, composed yaw (outer), pitch, roll (inner)::

      C_rb = R_Y(ψ) · R_Z(θ) · R_X(γ)        (body → reference, "YZX" intrinsic)

* angle arrays are kept in **body-axis order** ``[γ, ψ, θ]`` (the angle about X,
  about Y, about Z), so angle ``i`` goes with gyro channel ``i + 1``.

Quaternions are Hamilton, **scalar last** ``[x, y, z, w]`` (the order of
:class:`scipy.spatial.transform.Rotation`), body → reference, propagated as
``q_k = q_{k-1} ⊗ Δq_k``.

Algorithm
---------
Gyro samples are instantaneous rates, so the angle increment over each sample
interval is the integral of the cubic through the four nearest samples
(4th order, any time stamps). The rotation vector of the interval gets the
classic coning correction from the previous and the current increment (the
Bortz equation's ½·θ×ω term for a rate linear over two intervals; see
Savage, *Strapdown Analytics*, on coning algorithms)::

    φ_k = Δθ_k + (1/12) · Δθ_{k-1} × Δθ_k

which turns the O((ν h)²) drift of the uncorrected algorithm under coning
motion into O((ν h)⁴); general motion keeps Bortz's φ×(φ×ω)/12 term, third
order overall (``tests/test_strapdown.py`` measures all three). M5 needs
this: under the paper's synchronous rocking the body rate carries a rectified
component of ½·A²·ν (≈ 4.3 °/s at 12.2°, 0.53 Hz) that the attitude must
cancel exactly; a relative error of 1e-4 there is a false drift of 1.6 °/h.
(At 100 Hz this integrator's own drift on that stand is 0.001 °/h.)

The cumulative product of the interval quaternions is an associative scan,
computed in vectorized passes (Hillis–Steele inside blocks of 16 samples, then
across the blocks), so a batch of records ``(..., N, 3)`` integrates without a
Python loop over samples.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from estimators._typing import FloatArray, IntArray

EULER_SEQUENCE = "YZX"
"""scipy's intrinsic sequence of ``C_rb = R_Y(ψ) R_Z(θ) R_X(γ)`` (yaw, pitch, roll)."""

ANGLE_NAMES = ("gamma", "psi", "theta")
"""Names of the Euler angles in body-axis order: roll γ (X), yaw ψ (Y), pitch θ (Z)."""

MIN_SAMPLES = 4
"""The cubic quadrature of the increments needs four samples."""

IDENTITY_QUAT = np.array([0.0, 0.0, 0.0, 1.0])


def quat_multiply(p: FloatArray, q: FloatArray) -> FloatArray:
    """Hamilton product ``p ⊗ q`` of scalar-last quaternions, broadcast over leading axes.

    Parameters
    ----------
    p, q : (..., 4) quaternions ``[x, y, z, w]``.

    Returns
    -------
    (..., 4) the product (the rotation ``q`` followed, in the reference frame, by ``p``).
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    out = np.empty(np.broadcast_shapes(p.shape, q.shape))
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out[..., 0] = pw * qx + px * qw + py * qz - pz * qy
    out[..., 1] = pw * qy - px * qz + py * qw + pz * qx
    out[..., 2] = pw * qz + px * qy - py * qx + pz * qw
    out[..., 3] = pw * qw - px * qx - py * qy - pz * qz
    return out


def quat_from_rotvec(rotvec_rad: FloatArray) -> FloatArray:
    """(..., 4) quaternions of rotation vectors ``(..., 3)`` (rad), exact for any angle."""
    phi = np.asarray(rotvec_rad, float)
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    # sin(a/2)/a = ½·sinc(a/2π) stays finite at a = 0 (numpy's sinc is sin(πx)/(πx)).
    return np.concatenate(
        [0.5 * np.sinc(angle / (2.0 * np.pi)) * phi, np.cos(0.5 * angle)], axis=-1
    )


def _check_rates(t_s: FloatArray, gyro_rps: FloatArray) -> tuple[FloatArray, FloatArray]:
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(gyro_rps, dtype=float)
    if t.ndim != 1 or t.size < MIN_SAMPLES:
        raise ValueError(
            f"t_s must be 1-D with at least {MIN_SAMPLES} samples, got shape {t.shape}"
        )
    if w.ndim < 2 or w.shape[-2:] != (t.size, 3):
        raise ValueError(f"gyro_rps must have shape (..., {t.size}, 3), got {w.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(w))):
        raise ValueError("t_s and gyro_rps must be finite (validate the session first)")
    if np.any(np.diff(t) <= 0.0):
        raise ValueError("t_s must be strictly increasing (validate the session first)")
    return t, w


# Weights of the uniform-step case (h = 1): interior, first and last interval.
_UNIFORM_WEIGHTS = (
    np.array([[-1.0, 13.0, 13.0, -1.0], [9.0, 19.0, -5.0, 1.0], [1.0, -5.0, 19.0, 9.0]]) / 24.0
)


def _interval_weights(t: FloatArray) -> tuple[IntArray, FloatArray]:
    """Quadrature of each sample interval with the cubic through four neighbouring samples.

    Interval ``[t_k, t_{k+1}]`` uses samples ``s_k … s_k + 3`` with
    ``s_k = clip(k − 1, 0, N − 4)`` (centred inside, one-sided at the ends); the
    integral of their Lagrange cubic is taken by two-point Gauss–Legendre, which
    is exact for cubics. Any time stamps; local error O(h⁵). A uniform step
    (to 1e-9 relative) takes the closed-form weights of the same cubic.

    Returns
    -------
    start : (N-1,) first sample ``s_k`` of each stencil.
    weights : (N-1, 4) weights of samples ``s_k … s_k + 3``, s.
    """
    n = t.size
    start = np.clip(np.arange(n - 1) - 1, 0, n - 4)
    h = np.diff(t)
    h_mean = (t[-1] - t[0]) / (n - 1)
    if np.max(np.abs(h - h_mean)) <= 1e-9 * h_mean:
        rows = np.zeros(n - 1, dtype=int)
        rows[0], rows[-1] = 1, 2
        return start, _UNIFORM_WEIGHTS[rows] * h[:, None]
    nodes = t[start[:, None] + np.arange(4)[None]]
    mid = 0.5 * (t[:-1] + t[1:])
    gauss = mid[:, None] + np.array([-1.0, 1.0])[None] * (0.5 * h / np.sqrt(3.0))[:, None]
    weights = np.zeros((n - 1, 4))
    for m in range(4):
        basis = np.ones_like(gauss)
        for other in range(4):
            if other != m:
                basis *= (gauss - nodes[:, other, None]) / (
                    nodes[:, m, None] - nodes[:, other, None]
                )
        weights[:, m] = 0.5 * h * basis.sum(axis=1)
    return start, weights


def rotation_increments(
    t_s: FloatArray, gyro_rps: FloatArray, *, coning: bool = True
) -> FloatArray:
    """Rotation vectors of the sample intervals (module docstring: cubic increments + coning term).

    Parameters
    ----------
    t_s : (N,) sample times, s, strictly increasing, N ≥ 4.
    gyro_rps : (..., N, 3) body angular rate, rad/s.
    coning : add ``(1/12) Δθ_{k-1} × Δθ_k`` (the first interval, without a predecessor, takes its successor).

    Returns
    -------
    (..., N-1, 3) rotation vector of each interval ``[t_{k-1}, t_k]``, rad.
    """
    t, w = _check_rates(t_s, gyro_rps)
    start, weights = _interval_weights(t)
    dtheta = weights[:, 0, None] * w[..., start, :]
    for m in range(1, 4):
        dtheta = dtheta + weights[:, m, None] * w[..., start + m, :]
    if not coning:
        return dtheta
    cross = np.cross(dtheta[..., :-1, :], dtheta[..., 1:, :]) / 12.0
    phi = dtheta.copy()
    phi[..., 1:, :] += cross
    # The first interval has no predecessor; with a linear rate Δθ_0 × Δθ_1 equals Δθ_-1 × Δθ_0.
    phi[..., 0, :] += cross[..., 0, :]
    return phi


_SCAN_BLOCK = 16


def _inclusive_scan(quats: FloatArray) -> FloatArray:
    """Hillis–Steele scan ``q_0 ⊗ … ⊗ q_k`` along axis -2 in ⌈log2 n⌉ passes (order kept)."""
    out = quats.copy()
    n = out.shape[-2]
    step = 1
    while step < n:
        out[..., step:, :] = quat_multiply(out[..., :-step, :], out[..., step:, :])
        step *= 2
    return out


def cumulative_product(quats: FloatArray) -> FloatArray:
    """``q_0 ⊗ q_1 ⊗ … ⊗ q_k`` along axis -2: scans inside blocks of 16, then across the block totals.

    About log2(16) + 2 passes over the samples instead of log2(N).
    """
    n = quats.shape[-2]
    n_blocks = -(-n // _SCAN_BLOCK)
    padded = np.broadcast_to(IDENTITY_QUAT, (*quats.shape[:-2], n_blocks * _SCAN_BLOCK, 4)).copy()
    padded[..., :n, :] = quats
    inner = _inclusive_scan(padded.reshape((*quats.shape[:-2], n_blocks, _SCAN_BLOCK, 4)))
    totals = _inclusive_scan(inner[..., :, -1, :])
    inner[..., 1:, :, :] = quat_multiply(totals[..., :-1, None, :], inner[..., 1:, :, :])
    return inner.reshape(padded.shape)[..., :n, :]


def integrate_attitude(
    t_s: FloatArray,
    gyro_rps: FloatArray,
    *,
    quat0: FloatArray | None = None,
    coning: bool = True,
) -> FloatArray:
    """Attitude quaternions from body rates (methods.md M5; algorithm in the module docstring).

    Parameters
    ----------
    t_s : (N,) sample times, s, strictly increasing, N ≥ 4.
    gyro_rps : (..., N, 3) body angular rate, rad/s (a batch of records shares ``t_s``).
    quat0 : (4,) or (..., 4) attitude at ``t_s[0]``, scalar last; identity if None.
    coning : apply the coning correction (False only to measure what it is worth).

    Returns
    -------
    (..., N, 4) unit quaternions body → reference, scalar last; row 0 is ``quat0``.
    """
    phi = rotation_increments(t_s, gyro_rps, coning=coning)
    q0 = IDENTITY_QUAT if quat0 is None else np.asarray(quat0, dtype=float)
    if (
        q0.shape[-1] != 4
        or not np.all(np.isfinite(q0))
        or np.any(np.linalg.norm(q0, axis=-1) == 0.0)
    ):
        raise ValueError(
            f"quat0 must be finite non-zero quaternion(s) of shape (..., 4), got shape {q0.shape}"
        )
    q0 = np.broadcast_to(q0 / np.linalg.norm(q0, axis=-1, keepdims=True), (*phi.shape[:-2], 4))
    steps = np.concatenate([q0[..., None, :], quat_from_rotvec(phi)], axis=-2)
    q = cumulative_product(steps)
    unit: FloatArray = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return unit


def quat_from_euler(angles_rad: FloatArray) -> FloatArray:
    """(..., 4) quaternions of Euler angles ``(..., 3)`` in body-axis order ``[γ, ψ, θ]`` (rad)."""
    a = np.asarray(angles_rad, dtype=float)
    flat = a.reshape(-1, 3)
    q: FloatArray = Rotation.from_euler(EULER_SEQUENCE, flat[:, [1, 2, 0]]).as_quat()
    return q.reshape((*a.shape[:-1], 4))


def euler_from_quat(quat: FloatArray, *, unwrap: bool = True) -> FloatArray:
    """Euler angles ``[γ, ψ, θ]`` (rad, body-axis order) of quaternions ``(..., 4)``.

    With ``unwrap`` the angles are made continuous along axis -2 (time), so a
    drift past ±180° stays a straight line. Pitch must stay off ±90°.
    """
    q = np.asarray(quat, dtype=float)
    ypr = Rotation.from_quat(q.reshape(-1, 4)).as_euler(EULER_SEQUENCE)
    angles = ypr[:, [2, 0, 1]].reshape((*q.shape[:-1], 3))
    return np.unwrap(angles, axis=-2) if unwrap and angles.ndim >= 2 else angles


def body_rate_from_euler(angles_rad: FloatArray, angle_rates_rps: FloatArray) -> FloatArray:
    """Body angular rate of ``C_rb = R_Y(ψ) R_Z(θ) R_X(γ)`` from Euler angles and their rates.

    ``ω = γ̇·e_X + R_X(γ)ᵀ (θ̇·e_Z) + R_X(γ)ᵀ R_Z(θ)ᵀ (ψ̇·e_Y)``, i.e.::

        ωx = γ̇ + ψ̇ sin θ
        ωy = ψ̇ cos θ cos γ + θ̇ sin γ
        ωz = θ̇ cos γ − ψ̇ cos θ sin γ

    Parameters
    ----------
    angles_rad, angle_rates_rps : (..., 3) ``[γ, ψ, θ]`` and ``[γ̇, ψ̇, θ̇]`` (rad, rad/s).

    Returns
    -------
    (..., 3) body rate ``[ωx, ωy, ωz]``, rad/s.
    """
    a = np.asarray(angles_rad, dtype=float)
    r = np.asarray(angle_rates_rps, dtype=float)
    gamma, theta = a[..., 0], a[..., 2]
    dgamma, dpsi, dtheta = r[..., 0], r[..., 1], r[..., 2]
    return np.stack(
        [
            dgamma + dpsi * np.sin(theta),
            dpsi * np.cos(theta) * np.cos(gamma) + dtheta * np.sin(gamma),
            dtheta * np.cos(gamma) - dpsi * np.cos(theta) * np.sin(gamma),
        ],
        axis=-1,
    )


def rotate_to_body(quat: FloatArray, vec_ref: FloatArray) -> FloatArray:
    """(..., 3) a reference-frame vector ``(3,)`` seen in the body frame: ``C_rbᵀ v``."""
    q = np.asarray(quat, dtype=float)
    flat: FloatArray = Rotation.from_quat(q.reshape(-1, 4)).apply(
        np.asarray(vec_ref, float), inverse=True
    )
    return flat.reshape((*q.shape[:-1], 3))
