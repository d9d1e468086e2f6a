"""The Kalman filter's measurement update, filterpy's numbers without filterpy's import (methods.md M1).

filterpy's ``KalmanFilter.update(z, R=R, H=H)`` (filterpy 1.4.5, ``filterpy/kalman/kalman_filter.py``)
computes, with ``numpy.dot`` and ``numpy.linalg.inv``::

    y = z − H x                                   innovation
    S = H (P Hᵀ) + R                              its covariance
    K = (P Hᵀ) S⁻¹                                gain
    x⁺ = x + K y
    P⁺ = ((I − K H) P)(I − K H)ᵀ + (K R) Kᵀ       Joseph form

:func:`kalman_update` performs the same numpy operations in the same order, so its results are
filterpy's to the bit (``tests/test_kalman_update.py`` checks it on random sequences and on the
recursive nine-parameter estimator's own updates, filterpy the oracle). The Joseph form keeps
``P⁺`` symmetric positive semi-definite for any gain, which the shorter ``(I − K H) P`` does not
under rounding. The nine-parameter estimator's streaming form (:class:`estimators.ninepar.
RecursiveNineParam`) runs M1's ellipsoid equation through it as a scalar pseudo-measurement.

Why: ``import filterpy.kalman`` loads filterpy's whole package, whose ``filterpy.stats`` imports
scipy.stats and scipy.ndimage: 0.26 s of CPU at the start of every replay and daemon, for the
nine lines above (benchmarks/bench_replay_formats.py measures the replay).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators._typing import FloatArray


@dataclass(frozen=True)
class KalmanUpdate:
    """One measurement update's posterior and evidence: state ``x`` (n, 1), covariance ``P``
    (n, n), innovation ``y`` (m, 1) and its covariance ``S`` (m, m), filterpy's names."""

    x: FloatArray
    P: FloatArray
    y: FloatArray
    S: FloatArray


def kalman_update(
    x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray, H: FloatArray
) -> KalmanUpdate:
    """filterpy's ``KalmanFilter.update(z, R=R, H=H)`` from prior ``x`` (n, 1), ``P`` (n, n), with
    measurement ``z`` (m, 1), its noise covariance ``R`` (m, m) and ``H`` (m, n). The inputs are
    not changed. A singular ``S`` raises ``numpy.linalg.LinAlgError``, as filterpy's does."""
    y = z - np.dot(H, x)
    pht = np.dot(P, H.T)
    s = np.dot(H, pht) + R
    k = np.dot(pht, np.linalg.inv(s))
    i_kh = np.eye(x.shape[0]) - np.dot(k, H)
    return KalmanUpdate(
        x=x + np.dot(k, y),
        P=np.dot(np.dot(i_kh, P), i_kh.T) + np.dot(np.dot(k, R), k.T),
        y=y,
        S=s,
    )
