"""Linear least squares through a QR factorization, the fit every linear method here makes
(the six-position vector fit, M4; a tilt-table axis, M2; a temperature model, M3; the
stabilization and runs of :mod:`estimators.repeatability`): :func:`fit_linear`, and
:func:`linear_solver` for one design and many observations.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from estimators._typing import FloatArray

# A column of the (scaled) design whose R diagonal falls below this fraction of
# the largest one is numerically a combination of the others.
_RANK_RTOL = 1e-10


@dataclass(frozen=True)
class LinearFit:
    """Least-squares estimate of ``y = H θ + r``.

    Attributes
    ----------
    values : (P,) estimate ``θ̂``.
    cov : (P, P) covariance of ``θ̂``.
    residuals : (M,) ``y − H θ̂``, in the unit of ``y``.
    sigma : standard deviation of one equation's error: estimated from the
        residuals (``dof`` finite) or the given one (``dof`` = inf).
    dof : degrees of freedom of ``sigma`` (``M − P``, or ``inf`` when known).
    """

    values: FloatArray
    cov: FloatArray
    residuals: FloatArray
    sigma: float
    dof: float

    @property
    def std(self) -> FloatArray:
        """(P,) standard deviations of the estimate."""
        return np.sqrt(np.diag(self.cov))


def fit_linear(
    h: FloatArray,
    y: FloatArray,
    *,
    sigma_y: float | None = None,
    names: Sequence[str] | None = None,
) -> LinearFit:
    """Least squares through a QR factorization (no normal equations, no inverse).

    Parameters
    ----------
    h : (M, P) design matrix.
    y : (M,) observations.
    sigma_y : the known standard deviation of one observation; None estimates
        it from the residuals (needs ``M > P``).
    names : parameter names, used in the error raised when the equations do
        not determine a parameter.

    Raises
    ------
    ValueError
        Too few equations, or a parameter the equations cannot separate.
    """
    h = np.asarray(h, dtype=float)
    y = np.asarray(y, dtype=float)
    if h.ndim != 2 or y.shape != (h.shape[0],):
        raise ValueError(f"need H of shape (M, P) and y of shape (M,), got {h.shape} and {y.shape}")
    return linear_solver(h, sigma_y=sigma_y, names=names)(y)


def linear_solver(
    h: FloatArray,
    *,
    sigma_y: float | None = None,
    names: Sequence[str] | None = None,
) -> Callable[[FloatArray], LinearFit]:
    """:func:`fit_linear` of the design ``h`` for any observations ``y`` (M,): ``h`` is checked
    and factored once, and each ``y`` costs a product and a triangular solve (a Jacobian by
    central differences fits one design dozens of times). The same operations on the same
    numbers: bit for bit :func:`fit_linear`'s result. Raises its errors about ``h`` here."""
    h = np.asarray(h, dtype=float)
    if h.ndim != 2:
        raise ValueError(f"need H of shape (M, P), got {h.shape}")
    m, p = h.shape
    needed = p if sigma_y is not None else p + 1
    if m < needed:
        raise ValueError(f"{m} equations for {p} unknowns: need at least {needed}")
    # Columns of very different size (a pulse offset next to g·cos α) are scaled
    # to unit norm so the rank test below compares like with like.
    col = np.linalg.norm(h, axis=0)
    if np.any(col == 0.0):
        raise ValueError(
            f"the equations do not involve {_name(names, int(np.flatnonzero(col == 0.0)[0]))}"
        )
    # numpy's QR and solve: the calibrate path then never loads scipy (a third of a second).
    q, r = np.linalg.qr(h / col, mode="reduced")
    d = np.abs(np.diag(r))
    weak = d < _RANK_RTOL * d.max()
    if weak.any():
        raise ValueError(
            f"the equations cannot separate {_name(names, int(np.flatnonzero(weak)[0]))} from the other unknowns"
        )
    # R⁻¹ by an LU solve against the identity: scipy's triangular solve with a
    # matrix right-hand side goes through threaded BLAS and costs milliseconds
    # on a busy machine for a 3×3 system.
    r_inv = np.linalg.solve(r, np.eye(p))
    unit_cov = r_inv @ r_inv.T
    col_outer = np.outer(col, col)

    def fit(y: FloatArray) -> LinearFit:
        y = np.asarray(y, dtype=float)
        if y.shape != (m,):
            raise ValueError(f"need y of shape ({m},), got {y.shape}")
        theta_scaled = np.linalg.solve(r, q.T @ y)
        values = theta_scaled / col
        resid = y - h @ values
        if sigma_y is None:
            dof = float(m - p)
            sigma = float(np.sqrt(resid @ resid / dof))
        else:
            dof = np.inf
            sigma = float(sigma_y)
        cov = sigma**2 * unit_cov / col_outer
        return LinearFit(values=values, cov=cov, residuals=resid, sigma=sigma, dof=dof)

    return fit


def _name(names: Sequence[str] | None, j: int) -> str:
    return names[j] if names is not None else f"parameter {j}"
