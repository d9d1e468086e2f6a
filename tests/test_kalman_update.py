"""The Kalman measurement update (estimators.kalman_update) is filterpy's ``KalmanFilter.update`` to
the bit, filterpy the oracle: on random filters and on the recursive nine-parameter estimator's own
updates (methods.md M1)."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from ninepar_support import mems_accel, nav_accel, nav_gyro

from estimators import ninepar
from estimators.kalman_update import KalmanUpdate, kalman_update
from estimators.ninepar import RecursiveNineParam


def filterpy_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, H: np.ndarray):
    """The oracle: a filterpy filter holding the prior ``(x, P)``, updated with ``z``, ``R`` and ``H``."""
    kf = KalmanFilter(dim_x=x.shape[0], dim_z=z.shape[0])
    kf.x, kf.P = x.copy(), P.copy()
    kf.update(z, R=R, H=H)
    return KalmanUpdate(kf.x, kf.P, kf.y, kf.S)


def assert_same_bits(a: KalmanUpdate, b: KalmanUpdate) -> None:
    for name in ("x", "P", "y", "S"):
        u, v = getattr(a, name), getattr(b, name)
        assert u.shape == v.shape and u.tobytes() == v.tobytes(), name


def _covariance(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random positive-definite (n, n) matrix, its scales spread over six decades."""
    scale = 10.0 ** rng.uniform(-6.0, 0.0, n)
    a = rng.standard_normal((n, n)) * scale
    return a @ a.T + np.diag(scale**2) * 1e-3


def test_update_gives_filterpys_numbers_on_random_filters():
    # Each filter runs a sequence of updates, every posterior the next prior, so rounding differences
    # would compound; state sizes 1-9 and measurement sizes 1-3 (the estimator's is 9 and 1).
    rng = np.random.default_rng(20261207)
    for _ in range(150):
        n, m = int(rng.integers(1, 10)), int(rng.integers(1, 4))
        x, P = rng.standard_normal((n, 1)) * 10.0 ** rng.uniform(-6.0, 2.0), _covariance(rng, n)
        for _ in range(6):
            z, R = rng.standard_normal((m, 1)), _covariance(rng, m)
            H = rng.standard_normal((m, n)) * 10.0 ** rng.uniform(-3.0, 3.0)
            prior = (x.copy(), P.copy())
            post = kalman_update(x, P, z, R, H)
            assert_same_bits(post, filterpy_update(x, P, z, R, H))
            np.testing.assert_array_equal(x, prior[0])  # the prior is not changed
            np.testing.assert_array_equal(P, prior[1])
            x, P = post.x, post.P


def test_a_singular_innovation_covariance_raises_as_filterpys():
    x, P = np.zeros((2, 1)), np.eye(2)
    z, R, H = np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 2))
    with pytest.raises(np.linalg.LinAlgError, match="Singular"):
        filterpy_update(x, P, z, R, H)
    with pytest.raises(np.linalg.LinAlgError, match="Singular"):
        kalman_update(x, P, z, R, H)


def test_recursive_estimator_holds_filterpys_state(monkeypatch):
    # The estimator's own use: after its warm-up, each position is one scalar update with its own R,
    # relinearized from the same prior until the step is small (IEKF). Run each sequence once through
    # filterpy and once through kalman_update: every update's outcome and the final state agree.
    rng = np.random.default_rng(77)
    cases = (mems_accel(rng, 40), nav_accel(rng, 40), nav_gyro(rng, 40))
    iterations: list[int] = []
    r_values: set[float] = set()

    def recording(x, P, z, R, H):
        r_values.add(float(R[0, 0]))
        return kalman_update(x, P, z, R, H)

    for case in cases:
        for means in case.draw(rng, 3):
            runs = []
            for update in (filterpy_update, recording):
                monkeypatch.setattr(ninepar, "kalman_update", update)
                rec = RecursiveNineParam(case.triad)
                steps = [rec.update(m, c) for m, c in zip(means, case.cov, strict=True)]
                runs.append((steps, rec.state_dict()))
            assert runs[0] == runs[1]
            iterations += [s.iterations for s in runs[1][0] if s.nis is not None]
    assert max(iterations) >= 2 and len(r_values) > 100


def test_a_state_restored_from_any_memory_order_updates_as_filterpys():
    # filterpy's filter, as the estimator held it, updated C-ordered copies of the state whatever
    # arrays it was given; the dot products' last bits depend on the order. A checkpoint's P given
    # as a Fortran-ordered array (a transpose, np.load) must update as the same P given as lists.
    rng = np.random.default_rng(78)
    case = mems_accel(rng, 30)
    (means,) = case.draw(rng, 1)
    positions = list(zip(means, case.cov, strict=True))
    rec = RecursiveNineParam(case.triad)
    for m, c in positions[:20]:
        rec.update(m, c)
    state = rec.state_dict()
    lists = RecursiveNineParam.from_state_dict(state)
    fortran = RecursiveNineParam.from_state_dict({**state, "P": np.asfortranarray(state["P"])})
    for m, c in positions[20:]:
        assert lists.update(m, c) == fortran.update(m, c)
    assert lists.state_dict() == fortran.state_dict()
