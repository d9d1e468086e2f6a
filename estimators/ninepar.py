"""The nine error parameters of a triad from static positions (methods.md M1).

M1 stacks one scalar equation per static position and solves for
``[bx by bz ex ey ez d1 d2 d3]`` (order and exact meaning:
:mod:`estimators.conventions`). This module gives three estimators of the same
parameters, all working on *normalized* position means ``ã_k`` (n, 3) and the
covariances of those means ``P_k`` (n, 3, 3) (SI means divided by the triad's
reference g or Ω; :func:`position_arrays` does that from
:class:`~estimators.positions.Position` objects):

* :func:`estimate_linear`, the paper's estimator: ``y = H e`` with
  ``y_k = ½(|ã_k|² − 1)`` and the regressors ``H_k`` of the *measured* ``ã_k``
  (:func:`regressors`), weighted least squares with each equation weighted by
  its variance ``ã_kᵀ P_k ã_k``. First order: its model error is of the order
  of the squared parameters.
* :func:`estimate_refined`: the exact model. With ``D = diag(1 + e)`` and
  ``C`` the matrix of cosines between the sensitive axes (unit diagonal,
  ``C12 = d1``, ``C13 = d2``, ``C23 = d3``), ``A Aᵀ = D C D`` and each position
  satisfies the ellipsoid equation

      f_k(θ) = ½ (z_kᵀ C⁻¹ z_k − 1) = 0,     z_k = D⁻¹ (ã_k − b)

  (whose first-order expansion is M1's scalar calibration equation,
  ``f_k ≈ y_k − H_k θ``). Each residual is divided by its standard deviation
  ``σ_k = (∇ã f_kᵀ P_k ∇ã f_k)^½``, which makes the weighted least squares the
  first-order maximum-likelihood estimator of the errors-in-variables problem
  (the unknown true direction of each position costs two of its three
  measured components; only the component normal to the ellipsoid carries
  information). It attains the Cramér–Rao bound to first order in the noise
  (:func:`cramer_rao_bound`; ``benchmarks/bench_ninepar.py`` measures it).
  Weights are evaluated at the current estimate and held fixed inside each
  ``scipy.optimize.least_squares`` solve; solves are repeated until the
  estimate moves by less than 1e-4 σ (two passes when the noise is small
  against the reference).
* :class:`RecursiveNineParam`, the streaming form: filterpy's Kalman filter
  update (its numbers, :mod:`estimators.kalman_update`) with a static 9-state,
  one scalar pseudo-measurement per new position (the ellipsoid equation
  linearized at the current estimate, iterated: IEKF), Joseph-form covariance
  update, O(1) per position. It buffers a warm-up
  (18 positions by default, with an observable geometry), starts from the
  refined batch solution on them, and from then on updates recursively; it
  stays within 0.001 σ of the refined batch estimate.

Observability (M1 leaves it open; decided here)
-----------------------------------------------
*Geometry* (no number is returned, verdict ``NOT_OBSERVABLE_YET``):

1. fewer than nine positions;
2. positions around fewer than two rotation axes. Turning the unit about one
   axis moves the reference direction on one circle of the unit sphere; its
   image ``A u + b`` is a plane section of the ellipsoid, so the position
   means are *coplanar*, and a quadric through coplanar points is not unique
   (rank of the scalar equations ≤ 7). Precisely: with ``s⊥`` the RMS
   distance of the ``ã_k`` from their best-fitting plane (square root of the
   smallest eigenvalue of their scatter about the centroid) and ``σ⊥`` the RMS
   noise of the means along that plane's normal, the positions count as one
   rotation axis iff ``s⊥ ≤ max(min_plane_spread, noise_factor·σ⊥)``
   (defaults 0.05 of the reference and 3). Translation invariant, so a bias
   larger than the reference (a MEMS gyro against Ω) does not fake it. When
   ``noise_factor·σ⊥`` alone reaches ``1/√3`` — the largest ``s⊥`` of any
   scheme on the unit sphere (the scatter of unit vectors has trace at most 1,
   so its smallest eigenvalue is at most 1/3) — no scheme could pass: the
   noise of the means, not the rotation axes, is the cause, and the reason
   says so (a MEMS gyro against Ω: the reference is not resolvable by it);
3. rank of ``HᵀH`` below 9, with ``H = regressors(û_k)`` and ``û_k`` the unit
   directions of the means about their best-fitting sphere centre (the geometry
   of the scheme, independent of the noise level and of the bias), or a
   parameter the linear fit's own covariance leaves undetermined: its σ at least
   :data:`UNDETERMINED_SIGMA` (1/3, normalized), so that its 3σ interval reaches a
   cosine of 1, a gain error of 100 % or a bias of the whole reference: the
   positions cannot even place it inside the physical domain (the exact fit
   then runs off along it, which is no fault of the unit). The reason names the least excited parameter combination
   and the condition number (e.g. a six-position scheme does not excite
   ``d1 d2 d3``). Not a fixed condition number: how ill-conditioned a geometry
   may be depends on the noise of its means, which the covariance weighs (a
   hand-posed ten-pose session, condition number 4e5, resolves eight of the nine
   parameters of a MEMS accelerometer; a limit of 1e4 refused all nine and left
   the session to a six-position fit its tilts contradict). ``max_condition``
   (default none) remains as a caller's cap. Note that M1's "rotate about at
   least two axes" means *combined* rotations: two separate circles (turn about
   one axis, return, turn about another) are still degenerate, since the pair
   of their planes is a quadric through both: the covariance of the
   combinations they do not excite leaves them not observable.

*Precision* (per parameter, :class:`ObservabilityRule`): parameter ``j`` is
observable iff ``σ_j ≤ fraction · range_j``: its standard deviation is at most
10 % of the largest value it can take in a working triad. ``range`` is the
reference itself (1, normalized) for the biases: a bias that is not known to
10 % of g or Ω is not resolved by a scalar method whose signal is that
reference; and 0.1 for scale errors and for the cosines (a 10 % scale error or
a 0.1 rad mounting error is a broken sensor, not a calibration value). So for
a MEMS gyro against Ω (bias ≈ 100 Ω, a 10 s mean good to ≈ 0.4 Ω) the scale
errors and cosines are flagged (they would need means good to ≈ 0.01 Ω) and
the biases too unless the positions last minutes, while navigation-grade gyros
(bias 0.01 °/h ≈ 7e-4 Ω, means good to ≈ 5e-4 Ω) and MEMS accelerometers are
resolved. Verdict: ``OBSERVABLE`` (all nine),
``PARTIALLY_OBSERVABLE`` (some), ``NOT_OBSERVABLE_YET`` (none, or the geometry
fails); numbers are reported whenever the geometry passes, so the caller sees
how far from resolved they are, and the diagnosis skips the flagged ones.

*Domain*: a refined solution whose gains ``1 + e_i`` leave (0.1, 10) or whose
sensitive axes are nearly coplanar (smallest eigenvalue of ``C`` ≤ 0.1) is not
a triad but a fit that ran away along a noise-dominated direction (an ellipsoid
fit to very noisy points can grow without bound); it is reported as
``NOT_OBSERVABLE_YET`` with that reason instead of a number.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import numpy as np

from estimators._typing import ArrayT, BoolArray, FloatArray
from estimators.conventions import N_PARAMS, PARAM_NAMES, Triad
from estimators.kalman_update import kalman_update
from estimators.positions import Position
from estimators.scalar import normalize, scalar_residual

SOURCE_SCALAR = "M1 scalar fit"
SOURCE_VECTOR = "M4 six-position vector fit"
SOURCE_STATIC_MEANS = "M4 mean of the static positions"
SOURCE_TURNS = "M4 full turns"
SOURCE_NONE = "not determined"
"""How a parameter of an :class:`Estimate` was obtained (``Estimate.sources``)."""

MIN_POSITIONS = N_PARAMS
"""Nine unknowns need at least nine scalar equations (methods.md M1: n ≥ 9)."""

PHYSICAL_GAIN_RANGE = (0.1, 10.0)
"""Open range of the gains ``1 + e_i`` of a refined solution that is still a triad."""

PHYSICAL_MIN_AXES_EIGENVALUE = 0.1
"""Smallest eigenvalue of the cosine matrix ``C`` of a refined solution (1 for orthogonal axes, 0 for coplanar)."""


class Method(StrEnum):
    """Which estimator produced an :class:`Estimate`."""

    LINEAR = "linear"
    REFINED = "refined"
    RECURSIVE = "recursive"
    SIX_POSITION = "six_position"
    COMBINED = "combined"


class Verdict(StrEnum):
    """Whether the positions so far determine the nine parameters."""

    OBSERVABLE = "observable"
    PARTIALLY_OBSERVABLE = "partially_observable"
    NOT_OBSERVABLE_YET = "not_observable_yet"


@dataclass(frozen=True)
class ObservabilityRule:
    """Per-parameter precision rule: observable iff ``σ_j ≤ fraction · range_j`` (module docstring).

    Attributes
    ----------
    fraction : share of the range the standard deviation may reach (default 0.1).
    bias_range : largest normalized bias of interest (default 1: the reference itself).
    scale_range : largest relative scale-factor error of a working sensor (default 0.1).
    nonorth_range : largest cosine between sensitive axes of a working triad (default 0.1).
    """

    fraction: float = 0.1
    bias_range: float = 1.0
    scale_range: float = 0.1
    nonorth_range: float = 0.1

    def __post_init__(self) -> None:
        for name in ("fraction", "bias_range", "scale_range", "nonorth_range"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0.0:
                raise ValueError(
                    f"ObservabilityRule.{name} must be a positive finite number, got {value!r}"
                )

    def max_sigma(self) -> FloatArray:
        """(9,) largest standard deviation of each parameter that still counts as observable."""
        ranges = np.repeat([self.bias_range, self.scale_range, self.nonorth_range], 3)
        return self.fraction * ranges


@dataclass(frozen=True)
class GeometryRule:
    """Geometry thresholds (module docstring, items 2 and 3).

    Attributes
    ----------
    min_plane_spread : smallest RMS distance of the normalized means from one plane, in
        units of the reference, for the positions to count as two rotation axes (default 0.05).
    noise_factor : that spread must also exceed this many noise standard deviations along
        the plane's normal (default 3).
    max_condition : largest condition number of ``HᵀH`` accepted (default: none, the covariance
        judges, item 3).
    """

    min_plane_spread: float = 0.05
    noise_factor: float = 3.0
    max_condition: float = np.inf

    def __post_init__(self) -> None:
        for name in ("min_plane_spread", "noise_factor", "max_condition"):
            value = getattr(self, name)
            if np.isnan(value) or value <= 0.0 or (name != "max_condition" and np.isinf(value)):
                raise ValueError(
                    f"GeometryRule.{name} must be a positive finite number, got {value!r}"
                )


DEFAULT_OBSERVABILITY = ObservabilityRule()
DEFAULT_GEOMETRY = GeometryRule()


@dataclass(frozen=True, eq=False)
class Estimate:
    """The nine parameters of one triad with their covariance and the observability verdict.

    Attributes
    ----------
    triad : which triad.
    method : which estimator.
    verdict : see :class:`Verdict`.
    reason : one line: why not (or not fully) observable, or what was resolved.
    n_positions : positions used.
    params : (9,) ``[bx by bz ex ey ez d1 d2 d3]`` normalized, or None when the geometry fails.
    cov : (9, 9) covariance of ``params``, or None with it.
    observable : (9,) bool, per-parameter precision rule (all False without params).
    rank : numerical rank of the geometry matrix ``HᵀH`` (0 with fewer than nine positions).
    condition : condition number of ``HᵀH`` (inf when rank-deficient or not computed).
    chi2 : sum of squared normalized residuals at the solution (None without params).
    dof : degrees of freedom of ``chi2``: ``n_positions − 9`` (may be 0).
    reference : the value the means were normalized by, m/s² (accel) or rad/s (gyro), if known.
    sources : (9,) how each parameter was obtained (e.g. "M1 scalar fit", "M4 six-position
        vector fit", "M4 full turns"), or None: all by ``method``.
    fit_left_domain : the positions determined the nine parameters but the exact fit left the
        physical domain (:func:`estimate_refined`): a fault far beyond the scheme's, values in other
        units, a session of another unit, or noise too large; not "too few positions".
    reference_unresolvable : the position means' noise is too large against the reference for any
        position scheme to resolve it (a MEMS gyro against the Earth rate): no session of this
        sensor can fit its nine parameters, so the predicates F1…F9 (and F0) cannot apply to it.
    """

    triad: Triad
    method: Method
    verdict: Verdict
    reason: str
    n_positions: int
    params: FloatArray | None
    cov: FloatArray | None
    observable: BoolArray
    rank: int
    condition: float
    chi2: float | None
    dof: int
    reference: float | None = None
    sources: tuple[str, ...] | None = None
    fit_left_domain: bool = False
    reference_unresolvable: bool = False

    @property
    def sigma(self) -> FloatArray | None:
        """(9,) standard deviations, or None without params."""
        return None if self.cov is None else np.sqrt(np.diag(self.cov))

    @property
    def chi2_per_dof(self) -> float | None:
        """Normalized residual chi-square per degree of freedom (≈ 1 when the noise model holds)."""
        if self.chi2 is None or self.dof <= 0:
            return None
        return self.chi2 / self.dof

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready plain dict (non-finite numbers become None)."""
        sigma = self.sigma
        return {
            "triad": self.triad.value,
            "method": self.method.value,
            "verdict": self.verdict.value,
            "reason": self.reason,
            "n_positions": self.n_positions,
            "reference": self.reference,
            "param_names": list(PARAM_NAMES),
            "params": None if self.params is None else [float(v) for v in self.params],
            "sigma": None if sigma is None else [float(v) for v in sigma],
            "cov": None if self.cov is None else [[float(v) for v in row] for row in self.cov],
            "observable": [bool(v) for v in self.observable],
            "rank": self.rank,
            "condition_number": _finite_or_none(self.condition),
            "chi2": _finite_or_none(self.chi2),
            "dof": self.dof,
            "chi2_per_dof": _finite_or_none(self.chi2_per_dof),
            "sources": None if self.sources is None else list(self.sources),
            "fit_left_domain": self.fit_left_domain,
            "reference_unresolvable": self.reference_unresolvable,
        }


# --------------------------------------------------------------------------- model


def regressors(u: FloatArray) -> FloatArray:
    """M1 regressor rows ``[gx gy gz gx² gy² gz² gx·gy gx·gz gy·gz]``.

    Parameters
    ----------
    u : (n, 3) normalized directions or normalized position means (dimensionless).

    Returns
    -------
    (n, 9) matrix ``H`` of methods.md M1, columns in :data:`~estimators.conventions.PARAM_NAMES` order.
    """
    u = np.asarray(u, dtype=float)
    if u.ndim != 2 or u.shape[1] != 3:
        raise ValueError(f"directions must have shape (n, 3), got {u.shape}")
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    return np.column_stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])


def cosine_matrix(params: FloatArray) -> FloatArray:
    """(3, 3) Gram matrix ``C`` of the unit sensitive axes: unit diagonal, ``C12=d1, C13=d2, C23=d3``."""
    d1, d2, d3 = _as_params(params)[6:9]
    return np.array([[1.0, d1, d2], [d1, 1.0, d3], [d2, d3, 1.0]])


def canonical_triad_matrix(params: FloatArray) -> FloatArray:
    """A triad matrix ``A`` (rows ``(1+e_i) s_iᵀ``) with the given nine parameters.

    The nine parameters fix ``A Aᵀ = D C D`` only; this picks the lower-triangular
    ``A = D·chol(C)`` (sensor x along body x, sensor y in the body x-y plane). Any
    ``A R`` with ``R`` a rotation has the same parameters (conventions.py).
    """
    p = _as_params(params)
    return (1.0 + p[3:6]).reshape(3, 1) * np.linalg.cholesky(cosine_matrix(p))


def ellipsoid_residual(
    params: FloatArray, mean_norm: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Exact scalar equation of each position and its derivatives (module docstring).

    ``f_k = ½(z_kᵀ C⁻¹ z_k − 1)``, ``z_k = D⁻¹(ã_k − b)``; zero for noise-free means.
    With ``w_k = C⁻¹ z_k``: ``∂f/∂b = −D⁻¹w``, ``∂f/∂e_i = −w_i z_i /(1+e_i)``,
    ``∂f/∂d1 = −w_x w_y``, ``∂f/∂d2 = −w_x w_z``, ``∂f/∂d3 = −w_y w_z``, ``∂f/∂ã = D⁻¹w``.

    Parameters
    ----------
    params : (9,) parameters.
    mean_norm : (n, 3) normalized position means.

    Returns
    -------
    f : (n,), df_dparams : (n, 9), df_dmean : (n, 3).
    """
    p = _as_params(params)
    scale = 1.0 + p[3:6]
    z = (np.asarray(mean_norm, dtype=float) - p[0:3]) / scale
    # C is 3x3 and may be indefinite away from the solution: LU solve, never an inverse.
    w = np.linalg.solve(cosine_matrix(p), z.T).T
    f = 0.5 * (np.einsum("ij,ij->i", z, w) - 1.0)
    df_dp = np.empty((z.shape[0], N_PARAMS))
    df_dp[:, 0:3] = -w / scale
    df_dp[:, 3:6] = -w * z / scale
    df_dp[:, 6] = -w[:, 0] * w[:, 1]
    df_dp[:, 7] = -w[:, 0] * w[:, 2]
    df_dp[:, 8] = -w[:, 1] * w[:, 2]
    return f, df_dp, w / scale


def equation_sigma(params: FloatArray, mean_norm: FloatArray, cov_norm: FloatArray) -> FloatArray:
    """(n,) standard deviation of each ``f_k`` from the covariance of its mean: ``(∇ã fᵀ P ∇ã f)^½``."""
    _, _, grad = ellipsoid_residual(params, mean_norm)
    var: FloatArray = np.einsum("ni,nij,nj->n", grad, cov_norm, grad)
    return np.sqrt(var)


def cramer_rao_bound(
    mean_true_norm: FloatArray, cov_norm: FloatArray, params: FloatArray
) -> FloatArray:
    """Cramér–Rao bound (9, 9) of the parameters for a position scheme and noise level.

    Model: ``ã_k = A u_k + b + n_k``, ``n_k ~ N(0, P_k)``, with the directions ``u_k``
    unknown (two nuisance angles each). Eliminating the nuisance leaves, per
    position, only the displacement of the ellipsoid along its normal, so the
    Fisher information is ``Σ ∇θf_k ∇θf_kᵀ / σ_k²`` at the noise-free means
    (``tests/test_ninepar.py`` checks it against the full nuisance-parameter
    Fisher matrix). Inverted through the SVD of the whitened Jacobian.

    Parameters
    ----------
    mean_true_norm : (n, 3) noise-free normalized means ``A u_k + b``.
    cov_norm : (n, 3, 3) covariance of the means.
    params : (9,) true parameters.
    """
    mean, cov = _check_positions(mean_true_norm, cov_norm)
    sigma = equation_sigma(params, mean, cov)
    _, jac, _ = ellipsoid_residual(params, mean)
    return _cov_from_jacobian(jac / sigma[:, None])


def scheme_directions(n_positions: int) -> FloatArray:
    """Unit reference directions ``u_k`` (n, 3) of a standard position scheme.

    * 6: the six-position test (each axis up and down, methods.md M4); does not
      excite the non-orthogonality cosines (used to show the geometry check).
    * 9: the six plus the three diagonals of the coordinate planes (the minimal M1 scheme).
    * 18: the six plus the twelve edge midpoints of the cube (all ±45° tilts in the
      coordinate planes), the usual multi-position scheme.
    * any other n ≥ 9: a Fibonacci lattice (near-uniform on the sphere).
    """
    if n_positions == 6:
        return np.vstack([np.eye(3), -np.eye(3)])
    if n_positions == 9:
        diag = np.array([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]) / np.sqrt(2.0)
        return np.vstack([np.eye(3), -np.eye(3), diag])
    if n_positions == 18:
        edges = [
            np.roll([sa, sb, 0.0], shift) / np.sqrt(2.0)
            for shift in range(3)
            for sa in (1.0, -1.0)
            for sb in (1.0, -1.0)
        ]
        return np.vstack([np.eye(3), -np.eye(3), np.array(edges)])
    if n_positions < MIN_POSITIONS:
        raise ValueError(
            f"a scheme needs 6, or at least {MIN_POSITIONS} positions, got {n_positions}"
        )
    k = np.arange(n_positions) + 0.5
    z = 1.0 - 2.0 * k / n_positions
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class _Geometry:
    ok: bool
    reason: str
    rank: int
    condition: float
    gram: FloatArray | None  # HᵀH of the unit directions about the fitted centre
    centre: FloatArray | None  # best-fitting sphere centre, normalized
    reference_unresolvable: bool = False  # the means' noise exceeds any scheme's spread
    weakest: str = ""  # the least excited parameter combination


UNDETERMINED_SIGMA = 1.0 / 3.0
"""A parameter whose σ (normalized) reaches this is not determined by the positions: 3σ spans the
physical domain (module docstring, item 3)."""


def _undetermined(geo: _Geometry, cov_p: FloatArray) -> _Geometry:
    """``geo`` failed when the fit's covariance ``cov_p`` leaves a parameter undetermined."""
    sigma = np.sqrt(np.clip(np.diag(cov_p), 0.0, None))
    if np.all(sigma < UNDETERMINED_SIGMA):
        return geo
    worst = int(np.argmax(sigma))
    return replace(
        geo,
        ok=False,
        reason=f"positions do not excite all nine parameters: σ of {PARAM_NAMES[worst]} "
        f"{sigma[worst]:.3g} from the fit's covariance (normalized; 3σ spans the physical domain "
        f"from {UNDETERMINED_SIGMA:.3g}), condition number of HᵀH {geo.condition:.3g}; least excited: {geo.weakest}",
    )


MAX_PLANE_SPREAD = 1.0 / np.sqrt(3.0)
"""Largest RMS distance from their best-fitting plane that unit vectors can have (module docstring, item 2)."""

_REFERENCE_WORDS = {
    Triad.ACCEL: ("g", "gravity", "accelerometer triad"),
    Triad.GYRO: ("Ω", "Earth rate", "gyro"),
}
"""Per triad: symbol of the reference, its name, the sensor (for the reasons of the geometry check)."""


def _check_geometry(
    mean: FloatArray, cov: FloatArray, rule: GeometryRule, triad: Triad
) -> _Geometry:
    n = mean.shape[0]
    if n < MIN_POSITIONS:
        return _Geometry(
            False,
            f"{n} positions; the nine parameters need at least {MIN_POSITIONS}",
            0,
            np.inf,
            None,
            None,
        )
    centred = mean - mean.mean(axis=0)
    evals, evecs = np.linalg.eigh(centred.T @ centred / n)
    normal = evecs[:, 0]
    spread = float(np.sqrt(max(evals[0], 0.0)))
    noise = float(np.sqrt(np.mean(np.einsum("i,nij,j->n", normal, cov, normal))))
    noise_limit = rule.noise_factor * noise
    limit = max(rule.min_plane_spread, noise_limit)
    if spread <= limit:
        symbol, name, sensor = _REFERENCE_WORDS[Triad(triad)]
        if noise_limit >= MAX_PLANE_SPREAD:
            reason = (
                f"the position means' noise ({noise:.2g} {symbol} along the normal of their best-fitting plane) is too large "
                f"against the reference to tell the positions' geometry: {rule.noise_factor:g}× that noise "
                f"({noise_limit:.3g} {symbol}) exceeds the largest spread any position scheme can reach ({MAX_PLANE_SPREAD:.2f} {symbol}); "
                f"{name} is not resolvable by this {sensor} (longer positions or a less noisy {sensor} would be needed)"
            )
        else:
            reason = (
                f"positions around fewer than two rotation axes: the means lie within {spread:.3g} {symbol} (RMS) of one plane "
                f"with normal {np.array2string(normal, precision=3)}, limit {limit:.3g} {symbol} "
                f"(max of {rule.min_plane_spread:g} and {rule.noise_factor:g}× noise {noise:.3g})"
            )
        return _Geometry(
            False,
            reason,
            0,
            np.inf,
            None,
            None,
            reference_unresolvable=bool(noise_limit >= MAX_PLANE_SPREAD),
        )
    # Sphere |ã|² = 2cᵀã + k, linear in (c, k): defined once the means are not coplanar.
    sol, *_ = np.linalg.lstsq(
        np.column_stack([2.0 * mean, np.ones(n)]), np.einsum("ij,ij->i", mean, mean), rcond=None
    )
    centre = sol[:3]
    h = regressors(_unit_rows(mean - centre))
    gram = h.T @ h
    rank, condition, weakest = _rank_condition(gram)
    if rank < N_PARAMS or condition > rule.max_condition:
        return _Geometry(
            False,
            f"positions do not excite all nine parameters: rank {rank}, condition number of HᵀH {condition:.3g} "
            f"(limit {rule.max_condition:g}); least excited: {weakest}",
            rank,
            condition,
            gram,
            centre,
            weakest=weakest,
        )
    return _Geometry(True, "", rank, condition, gram, centre, weakest=weakest)


def _rank_condition(gram: FloatArray) -> tuple[int, float, str]:
    """Rank, condition number and the least excited parameter combination of a 9x9 Gram matrix."""
    evals, evecs = np.linalg.eigh(gram)
    top = evals[-1]
    tol = top * N_PARAMS * np.finfo(float).eps
    rank = int(np.sum(evals > tol))
    condition = float(top / evals[0]) if evals[0] > tol else float("inf")
    weak = evecs[:, 0]
    names = [
        f"{PARAM_NAMES[j]} ({weak[j]:+.2f})"
        for j in np.argsort(-np.abs(weak))
        if abs(weak[j]) > 0.3
    ]
    return rank, condition, " ".join(names)


# --------------------------------------------------------------------------- estimators


def estimate_linear(
    mean_norm: FloatArray,
    cov_norm: FloatArray,
    triad: Triad,
    *,
    reference: float | None = None,
    observability: ObservabilityRule = DEFAULT_OBSERVABILITY,
    geometry: GeometryRule = DEFAULT_GEOMETRY,
) -> Estimate:
    """The paper's linear least squares ``ê = argmin ‖W^½ (y − H e)‖`` (methods.md M1).

    ``y_k = ½(|ã_k|² − 1)``, ``H = regressors(ã)`` of the measured means, weights
    ``1 / (ã_kᵀ P_k ã_k)``; solved by ``lstsq`` on the whitened system, covariance
    ``(HᵀWH)⁻¹`` through the SVD of the whitened regressors.

    Parameters
    ----------
    mean_norm : (n, 3) normalized position means.
    cov_norm : (n, 3, 3) covariance of each mean, normalized.
    triad : the triad they belong to.
    reference : the normalizing value (m/s² or rad/s), recorded in the estimate.
    """
    mean, cov = _check_positions(mean_norm, cov_norm)
    geo = _check_geometry(mean, cov, geometry, triad)
    if not geo.ok:
        return _not_observable(triad, Method.LINEAR, geo, mean.shape[0], reference)
    params, cov_p, chi2 = _linear_solve(mean, cov, np.zeros(3))
    if not (geo := _undetermined(geo, cov_p)).ok:
        return _not_observable(triad, Method.LINEAR, geo, mean.shape[0], reference)
    return _finish(
        triad, Method.LINEAR, params, cov_p, chi2, mean.shape[0], geo, observability, reference
    )


def estimate_refined(
    mean_norm: FloatArray,
    cov_norm: FloatArray,
    triad: Triad,
    *,
    reference: float | None = None,
    observability: ObservabilityRule = DEFAULT_OBSERVABILITY,
    geometry: GeometryRule = DEFAULT_GEOMETRY,
    max_passes: int = 6,
) -> Estimate:
    """The exact ellipsoid model by weighted nonlinear least squares (module docstring).

    Starts from the linear solution computed about the best-fitting sphere centre
    (the paper's estimator when the bias is small, still a good start when the
    bias exceeds the reference). Covariance ``(JᵀJ)⁻¹`` of the whitened Jacobian at
    the solution; no rescaling by the residual chi-square (the weights are
    absolute), which is reported instead.

    Parameters
    ----------
    mean_norm, cov_norm, triad, reference : as :func:`estimate_linear`.
    max_passes : reweighting passes (weights re-evaluated at the new estimate).
    """
    mean, cov = _check_positions(mean_norm, cov_norm)
    return _refined(
        mean, cov, Triad(triad), Method.REFINED, reference, observability, geometry, max_passes
    )[0]


def _refined(
    mean: FloatArray,
    cov: FloatArray,
    triad: Triad,
    method: Method,
    reference: float | None,
    observability: ObservabilityRule,
    geometry: GeometryRule,
    max_passes: int = 6,
) -> tuple[Estimate, _Geometry]:
    """:func:`estimate_refined` on validated arrays, with the geometry it found."""
    geo = _check_geometry(mean, cov, geometry, triad)
    if not geo.ok:
        return _not_observable(triad, method, geo, mean.shape[0], reference), geo
    assert geo.centre is not None  # a geometry that is ok has its centre
    start, start_cov, _ = _linear_solve(mean, cov, geo.centre)
    if not (geo := _undetermined(geo, start_cov)).ok:
        return _not_observable(triad, method, geo, mean.shape[0], reference), geo
    params, cov_p, chi2, note = _refine(mean, cov, start, max_passes)
    if note:
        failed = _Geometry(False, note, geo.rank, geo.condition, geo.gram, geo.centre)
        est = _not_observable(triad, method, failed, mean.shape[0], reference)
        return replace(est, fit_left_domain=True), failed
    return _finish(
        triad, method, params, cov_p, chi2, mean.shape[0], geo, observability, reference
    ), geo


def position_arrays(
    positions: Sequence[Position], triad: Triad, reference: float
) -> tuple[FloatArray, FloatArray]:
    """Normalized means (n, 3) and covariances (n, 3, 3) of one triad from SI positions.

    Parameters
    ----------
    positions : static positions (SI: m/s² and rad/s, covariance of the means).
    triad : which triad to take.
    reference : g in m/s² for the accelerometers, Ω in rad/s for the gyros.
    """
    triad = Triad(triad)
    means, covs = [], []
    for k, pos in enumerate(positions):
        mean, cov = pos.mean(triad), pos.cov(triad)
        if mean is None or cov is None:
            raise ValueError(f"position {k} has no {triad.value} mean/covariance")
        means.append(mean)
        covs.append(cov)
    mean_norm = normalize(np.array(means, dtype=float).reshape(-1, 3), reference)
    return _check_positions(mean_norm, np.array(covs, dtype=float).reshape(-1, 3, 3) / reference**2)


def estimate_triad(
    positions: Sequence[Position],
    triad: Triad,
    reference_mps2_or_rps: float,
    *,
    method: Method = Method.REFINED,
    observability: ObservabilityRule = DEFAULT_OBSERVABILITY,
    geometry: GeometryRule = DEFAULT_GEOMETRY,
) -> Estimate:
    """Normalize SI positions by the triad's reference and estimate (linear or refined).

    Parameters
    ----------
    positions : static positions in SI units.
    triad : which triad.
    reference_mps2_or_rps : local g (m/s²) for the accelerometers, Ω (rad/s) for the gyros.
    method : :attr:`Method.LINEAR` or :attr:`Method.REFINED` (the recursive form is a class).
    """
    method = Method(method)
    if method is Method.RECURSIVE:
        raise ValueError(
            "method 'recursive' is the streaming class RecursiveNineParam, not a batch function"
        )
    mean, cov = position_arrays(positions, triad, reference_mps2_or_rps)
    solver = estimate_linear if method is Method.LINEAR else estimate_refined
    return solver(
        mean,
        cov,
        Triad(triad),
        reference=float(reference_mps2_or_rps),
        observability=observability,
        geometry=geometry,
    )


def _linear_solve(
    mean: FloatArray, cov: FloatArray, centre: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Paper's weighted linear LS on the means taken about ``centre`` (bias = centre + estimate)."""
    rel = mean - centre
    y = scalar_residual(rel)
    h = regressors(rel)
    sigma = np.sqrt(np.einsum("ni,nij,nj->n", rel, cov, rel))
    hw, yw = h / sigma[:, None], y / sigma
    params, *_ = np.linalg.lstsq(hw, yw, rcond=None)
    chi2 = float(np.sum((yw - hw @ params) ** 2))
    params[0:3] += centre
    return params, _cov_from_jacobian(hw), chi2


def _refine(
    mean: FloatArray, cov: FloatArray, start: FloatArray, max_passes: int
) -> tuple[FloatArray, FloatArray, float, str]:
    # scipy.optimize loads on the first fit, not with the module: a session whose geometry
    # fails (six faces) never needs it.
    from scipy.optimize import least_squares

    params = start.copy()
    for _ in range(max_passes):
        if not physical(params):
            break
        sigma = equation_sigma(params, mean, cov)
        try:
            sol = least_squares(
                lambda p, sigma=sigma: ellipsoid_residual(p, mean)[0] / sigma,
                params,
                jac=lambda p, sigma=sigma: ellipsoid_residual(p, mean)[1] / sigma[:, None],
                method="lm",
                x_scale="jac",
                xtol=1e-12,
                ftol=1e-12,
                gtol=1e-12,
            )
        except (np.linalg.LinAlgError, ValueError):
            # A trial step made C singular or a residual non-finite: the fit ran out of the domain.
            params = np.full(N_PARAMS, np.nan)
            break
        step = sol.x - params
        params = sol.x
        cov_p = _cov_from_jacobian(sol.jac)
        if np.all(np.abs(step) <= 1e-4 * np.sqrt(np.diag(cov_p))):
            break
    if not physical(params):
        return (
            params,
            np.full((N_PARAMS, N_PARAMS), np.inf),
            np.inf,
            (
                "the fit left the physical domain (gain 1+e outside (0.1, 10) or sensitive axes nearly coplanar): "
                f"{np.array2string(params, precision=3)}{_unit_hint(params)}; a fault far beyond this scheme's, "
                "values in other units, another unit's session, or noise too large for it"
            ),
        )
    sigma = equation_sigma(params, mean, cov)
    f, jac, _ = ellipsoid_residual(params, mean)
    return params, _cov_from_jacobian(jac / sigma[:, None]), float(np.sum((f / sigma) ** 2)), ""


def physical(params: FloatArray) -> bool:
    """Within the domain of a triad that still works (module docstring)."""
    if not np.all(np.isfinite(params)):
        return False
    gain = 1.0 + params[3:6]
    if np.any(gain <= PHYSICAL_GAIN_RANGE[0]) or np.any(gain >= PHYSICAL_GAIN_RANGE[1]):
        return False
    return bool(np.linalg.eigvalsh(cosine_matrix(params))[0] > PHYSICAL_MIN_AXES_EIGENVALUE)


def _cov_from_jacobian(jac_w: FloatArray) -> FloatArray:
    """``(JᵀJ)⁻¹`` of a whitened Jacobian from its SVD, ``V S⁻² Vᵀ`` (no normal equations formed)."""
    _, s, vt = np.linalg.svd(jac_w, full_matrices=False)
    if s.size < N_PARAMS or s[-1] <= np.finfo(float).eps * s[0] * N_PARAMS:
        return np.full((N_PARAMS, N_PARAMS), np.inf)
    cov: FloatArray = (vt.T / s**2) @ vt
    return 0.5 * (cov + cov.T)


def _judge(cov: FloatArray, rule: ObservabilityRule) -> tuple[BoolArray, Verdict, str]:
    sigma = np.sqrt(np.diag(cov))
    limit = rule.max_sigma()
    observable = np.isfinite(sigma) & (sigma <= limit)
    if observable.all():
        return observable, Verdict.OBSERVABLE, "all nine parameters resolved"
    names = ", ".join(
        f"{PARAM_NAMES[j]} (σ {sigma[j]:.3g} > {limit[j]:.3g})" for j in np.flatnonzero(~observable)
    )
    verdict = Verdict.NOT_OBSERVABLE_YET if not observable.any() else Verdict.PARTIALLY_OBSERVABLE
    return (
        observable,
        verdict,
        f"not observable (σ above {rule.fraction:g} of the parameter's range): {names}",
    )


def _finish(
    triad: Triad,
    method: Method,
    params: FloatArray,
    cov: FloatArray,
    chi2: float,
    n: int,
    geo: _Geometry,
    rule: ObservabilityRule,
    reference: float | None,
) -> Estimate:
    observable, verdict, reason = _judge(cov, rule)
    return Estimate(
        triad=Triad(triad),
        method=method,
        verdict=verdict,
        reason=reason,
        n_positions=n,
        params=_frozen(params),
        cov=_frozen(cov),
        observable=_frozen(observable),
        rank=geo.rank,
        condition=geo.condition,
        chi2=chi2,
        dof=n - N_PARAMS,
        reference=reference,
    )


def judged_estimate(
    triad: Triad,
    method: Method,
    params: FloatArray,
    cov: FloatArray,
    *,
    n_positions: int,
    reference: float,
    sources: tuple[str, ...],
    observability: ObservabilityRule = DEFAULT_OBSERVABILITY,
    known: BoolArray | None = None,
) -> Estimate:
    """An estimate made by another method than M1's fit (the six-position vector fit, full
    turns, or a combination), with the same per-parameter precision rule.

    ``known`` (9,) bool marks the parameters the method determines at all (default: all);
    the others are not observable whatever their covariance says.
    """
    observable, verdict, reason = _judge(cov, observability)
    if known is not None and not np.all(known):
        observable = observable & np.asarray(known, dtype=bool)
        verdict = Verdict.PARTIALLY_OBSERVABLE if observable.any() else Verdict.NOT_OBSERVABLE_YET
        missing = " ".join(PARAM_NAMES[j] for j in np.flatnonzero(~np.asarray(known, dtype=bool)))
        reason = f"{reason}; not determined by {method.value}: {missing}"
    return Estimate(
        triad=Triad(triad),
        method=method,
        verdict=verdict,
        reason=reason,
        n_positions=n_positions,
        params=_frozen(np.asarray(params, dtype=float)),
        cov=_frozen(np.asarray(cov, dtype=float)),
        observable=_frozen(observable),
        rank=N_PARAMS,
        condition=float("nan"),
        chi2=None,
        dof=0,
        reference=float(reference),
        sources=tuple(sources),
    )


_DEG_PER_RAD = 180.0 / np.pi


def _unit_hint(params: FloatArray) -> str:
    """What gains all near 180/π say: rates in degrees read as radians (the reverse, gains near π/180,
    leaves means too small for the geometry check to pass, which says so itself)."""
    gain = 1.0 + params[3:6]
    if np.all(np.abs(gain / _DEG_PER_RAD - 1.0) < 0.05):
        return f" (gains near {_DEG_PER_RAD:.4g}: values in deg/s read as rad/s?)"
    return ""


def _not_observable(
    triad: Triad, method: Method, geo: _Geometry, n: int, reference: float | None
) -> Estimate:
    return not_observable_estimate(
        triad, method, geo.reason, n, reference,
        rank=geo.rank, condition=geo.condition,
        reference_unresolvable=geo.reference_unresolvable,
    )  # fmt: skip


def not_observable_estimate(
    triad: Triad,
    method: Method,
    why: str,
    n: int,
    reference: float | None,
    *,
    rank: int = 0,
    condition: float = float("inf"),
    reference_unresolvable: bool = False,
) -> Estimate:
    """An estimate with no parameters from ``n`` positions, saying ``why`` (geometry, noise, a
    fitter that refused them): nothing observable, every parameter named as not."""
    return Estimate(
        triad=Triad(triad),
        method=method,
        verdict=Verdict.NOT_OBSERVABLE_YET,
        reason=f"{why}; not observable: {' '.join(PARAM_NAMES)}",
        n_positions=n,
        params=None,
        cov=None,
        observable=_frozen(np.zeros(N_PARAMS, dtype=bool)),
        rank=rank,
        condition=condition,
        chi2=None,
        dof=max(n - N_PARAMS, 0),
        reference=reference,
        reference_unresolvable=reference_unresolvable,
    )


# --------------------------------------------------------------------------- recursive form


@dataclass(frozen=True)
class RecursiveUpdate:
    """Evidence of one recursive update (before initialization only ``initialized`` is set).

    Attributes
    ----------
    initialized : whether the filter holds an estimate after this update.
    innovation : ``−f_k`` at the prior estimate (normalized scalar), or None.
    innovation_var : its predicted variance ``h P hᵀ + σ_k²``, or None.
    nis : normalized innovation squared ``innovation² / innovation_var`` (χ²(1) when consistent), or None.
    iterations : relinearizations used (IEKF).
    """

    initialized: bool
    innovation: float | None = None
    innovation_var: float | None = None
    nis: float | None = None
    iterations: int = 0


_STATE_KIND = "ins.health.ninepar.recursive"
_STATE_VERSION = 1


@dataclass
class _Buffer:
    means: list[FloatArray] = field(default_factory=list)
    covs: list[FloatArray] = field(default_factory=list)


class RecursiveNineParam:
    """Streaming nine-parameter estimate of one triad, O(1) per position (methods.md M1).

    *Warm-up.* The first positions are buffered (at most ``max_buffer``; if the
    geometry stays degenerate the oldest are dropped and counted). Meanwhile
    :meth:`estimate` is the refined batch estimate over the buffer. Once the
    buffer holds ``warmup_positions`` (default 18) and passes the geometry
    check, the refined batch solution becomes the filter state ``(x, P)`` and
    the buffer is emptied. Waiting for more than the minimal nine positions
    keeps the first linearization point close: the recursive answer differs
    from the batch one by a term quadratic in the error of the state it
    linearizes at (``benchmarks/bench_ninepar.py`` measures it: up to 0.04 σ when
    starting from 9 ill-conditioned positions, below 0.001 σ after an 18-position warm-up).

    *Recursion.* Each later position is one scalar pseudo-measurement through
    filterpy's ``KalmanFilter.update`` (Joseph form; :func:`estimators.kalman_update.
    kalman_update` computes its numbers without filterpy's import): the ellipsoid equation
    ``f_k(θ) = 0`` linearized at ``θ_i``, ``h_i θ = h_i θ_i − f_k(θ_i)`` with
    ``R = σ_k²(θ_i)``, relinearized from the same prior until the step is below
    1e-4 σ (iterated EKF). The state is static (no process noise): this is the
    batch solution updated recursively, in O(1) time and memory per position.
    The residual chi-square accumulates the normalized innovations (χ² with
    ``n − 9`` degrees of freedom together with the warm-up's batch residual).
    """

    def __init__(
        self,
        triad: Triad,
        *,
        reference: float | None = None,
        observability: ObservabilityRule = DEFAULT_OBSERVABILITY,
        geometry: GeometryRule = DEFAULT_GEOMETRY,
        warmup_positions: int = 2 * MIN_POSITIONS,
        max_buffer: int = 64,
        max_iterations: int = 5,
    ) -> None:
        if not MIN_POSITIONS <= warmup_positions <= max_buffer:
            raise ValueError(
                f"need {MIN_POSITIONS} ≤ warmup_positions ≤ max_buffer, got {warmup_positions!r} and {max_buffer!r}"
            )
        if max_iterations < 1:
            raise ValueError(f"max_iterations must be at least 1, got {max_iterations!r}")
        self.triad = Triad(triad)
        self.reference = reference
        self.observability = observability
        self.geometry = geometry
        self.warmup_positions = int(warmup_positions)
        self.max_buffer = int(max_buffer)
        self.max_iterations = int(max_iterations)
        # The state (N_PARAMS, 1) and its covariance, as filterpy's KalmanFilter starts them.
        self._x = np.zeros((N_PARAMS, 1))
        self._p = np.eye(N_PARAMS)
        self._initialized = False
        self._buffer = _Buffer()
        self._gram = np.zeros((N_PARAMS, N_PARAMS))
        self._chi2 = 0.0
        self._n_positions = 0
        self._n_dropped = 0

    @property
    def initialized(self) -> bool:
        """Whether the warm-up is over and the state is updated recursively."""
        return self._initialized

    @property
    def n_positions(self) -> int:
        """Positions that contribute to the current estimate (buffered or absorbed)."""
        return self._n_positions

    @property
    def n_dropped(self) -> int:
        """Positions dropped from a full buffer while the geometry stayed degenerate."""
        return self._n_dropped

    def update(self, mean_norm: FloatArray, cov_norm: FloatArray) -> RecursiveUpdate:
        """Add one position: normalized mean (3,) and covariance of that mean (3, 3).

        Invalid input raises ``ValueError`` and leaves the state unchanged.
        """
        mean, cov = _check_positions(
            np.asarray(mean_norm, dtype=float).reshape(1, -1),
            np.asarray(cov_norm, dtype=float)[None],
        )
        if not self._initialized:
            return self._buffer_position(mean[0], cov[0])
        return self._absorb(mean[0], cov[0])

    def estimate(self) -> Estimate:
        """The current estimate (during warm-up: the refined batch estimate over the buffer)."""
        if not self._initialized:
            return self._warmup_estimate()[0]
        rank, condition, _ = _rank_condition(self._gram)
        geo = _Geometry(True, "", rank, condition, self._gram, None)
        params = self._x[:, 0].copy()
        return _finish(
            self.triad,
            Method.RECURSIVE,
            params,
            self._p.copy(),
            self._chi2,
            self._n_positions,
            geo,
            self.observability,
            self.reference,
        )

    def _warmup_estimate(self) -> tuple[Estimate, _Geometry]:
        n = len(self._buffer.means)
        means = np.array(self._buffer.means).reshape(n, 3)
        covs = np.array(self._buffer.covs).reshape(n, 3, 3)
        return _refined(
            means,
            covs,
            self.triad,
            Method.RECURSIVE,
            self.reference,
            self.observability,
            self.geometry,
        )

    def _buffer_position(self, mean: FloatArray, cov: FloatArray) -> RecursiveUpdate:
        buf = self._buffer
        buf.means.append(mean)
        buf.covs.append(cov)
        self._n_positions += 1
        if len(buf.means) > self.max_buffer:
            del buf.means[0], buf.covs[0]
            self._n_positions -= 1
            self._n_dropped += 1
        if len(buf.means) < self.warmup_positions:
            return RecursiveUpdate(initialized=False)
        est, geo = self._warmup_estimate()
        if est.params is None:
            return RecursiveUpdate(initialized=False)
        self._x = est.params.reshape(-1, 1).copy()
        # An estimate with params comes with its covariance, chi-square and a passed geometry.
        assert est.cov is not None and est.chi2 is not None and geo.gram is not None
        self._p = est.cov.copy()
        self._gram = geo.gram.copy()
        self._chi2 = float(est.chi2)
        self._buffer = _Buffer()
        self._initialized = True
        return RecursiveUpdate(initialized=True)

    def _absorb(self, mean: FloatArray, cov: FloatArray) -> RecursiveUpdate:
        x_prior, p_prior = self._x, self._p
        x_i, p_i = x_prior, p_prior
        innovation: float | None = None
        innovation_var: float | None = None
        iterations = 0
        for iterations in range(1, self.max_iterations + 1):  # noqa: B007 (the count reached is returned)
            f, df_dp, df_dm = ellipsoid_residual(x_i[:, 0], mean[None])
            r = float(df_dm[0] @ cov @ df_dm[0])
            h = df_dp  # (1, 9)
            z = h @ x_i - f[0]
            # Each pass updates the same prior, linearized at the last pass's state (IEKF).
            post = kalman_update(x_prior, p_prior, z.reshape(1, 1), np.array([[r]]), h)
            if innovation is None:
                innovation, innovation_var = float(post.y[0, 0]), float(post.S[0, 0])
            step = post.x - x_i
            x_i, p_i = post.x, post.P
            if np.all(np.abs(step[:, 0]) <= 1e-4 * np.sqrt(np.diag(p_i))):
                break
        # max_iterations >= 1: the first pass has set both.
        assert innovation is not None and innovation_var is not None
        self._x, self._p = x_i, p_i
        nis = innovation**2 / innovation_var
        self._chi2 += nis
        self._n_positions += 1
        h_geo = regressors(_unit_rows((mean - self._x[0:3, 0])[None]))
        self._gram += h_geo.T @ h_geo
        return RecursiveUpdate(True, innovation, innovation_var, nis, iterations)

    def state_dict(self) -> dict[str, Any]:
        """The whole state as a plain dict (lists and numbers) for checkpoints."""
        return {
            "kind": _STATE_KIND,
            "version": _STATE_VERSION,
            "triad": self.triad.value,
            "reference": self.reference,
            "observability": [
                self.observability.fraction,
                self.observability.bias_range,
                self.observability.scale_range,
                self.observability.nonorth_range,
            ],
            "geometry": [
                self.geometry.min_plane_spread,
                self.geometry.noise_factor,
                self.geometry.max_condition,
            ],
            "warmup_positions": self.warmup_positions,
            "max_buffer": self.max_buffer,
            "max_iterations": self.max_iterations,
            "initialized": self._initialized,
            "buffer_means": [m.tolist() for m in self._buffer.means],
            "buffer_covs": [c.tolist() for c in self._buffer.covs],
            "x": self._x[:, 0].tolist(),
            "P": self._p.tolist(),
            "gram": self._gram.tolist(),
            "chi2": self._chi2,
            "n_positions": self._n_positions,
            "n_dropped": self._n_dropped,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> RecursiveNineParam:
        """Rebuild a filter from :meth:`state_dict`; a malformed state raises ``ValueError``."""
        if not isinstance(state, dict) or state.get("kind") != _STATE_KIND:
            raise ValueError(
                f"not a recursive nine-parameter state (kind {state.get('kind') if isinstance(state, dict) else type(state).__name__!r})"
            )
        if state.get("version") != _STATE_VERSION:
            raise ValueError(
                f"recursive state version {state.get('version')!r} is not supported (this build reads {_STATE_VERSION})"
            )
        try:
            obj = cls(
                Triad(state["triad"]),
                reference=state["reference"],
                observability=ObservabilityRule(*state["observability"]),
                geometry=GeometryRule(*state["geometry"]),
                warmup_positions=int(state["warmup_positions"]),
                max_buffer=int(state["max_buffer"]),
                max_iterations=int(state["max_iterations"]),
            )
            x = _state_array(state["x"], (N_PARAMS,), "x")
            p = _state_array(state["P"], (N_PARAMS, N_PARAMS), "P")
            gram = _state_array(state["gram"], (N_PARAMS, N_PARAMS), "gram")
            means = [_state_array(m, (3,), "buffer_means") for m in state["buffer_means"]]
            covs = [_state_array(c, (3, 3), "buffer_covs") for c in state["buffer_covs"]]
            initialized = state["initialized"]
            chi2, n_pos, n_drop = (
                float(state["chi2"]),
                int(state["n_positions"]),
                int(state["n_dropped"]),
            )
        except KeyError as exc:
            raise ValueError(f"recursive state lacks field {exc.args[0]!r}") from None
        except TypeError as exc:
            raise ValueError(f"recursive state has a field of the wrong type: {exc}") from None
        if not isinstance(initialized, bool) or len(means) != len(covs) or (initialized and means):
            raise ValueError("recursive state is inconsistent (initialized flag vs buffer)")
        if means:
            _check_positions(np.array(means), np.array(covs))
        # C-ordered copies, as filterpy's filter updated them: the products' bits depend on the order.
        obj._x = x.reshape(-1, 1).copy()
        obj._p = p.copy()
        obj._gram = gram
        obj._buffer = _Buffer(means, covs)
        obj._initialized = initialized
        obj._chi2, obj._n_positions, obj._n_dropped = chi2, n_pos, n_drop
        return obj


# --------------------------------------------------------------------------- helpers


def _as_params(params: FloatArray) -> FloatArray:
    p = np.asarray(params, dtype=float)
    if p.shape != (N_PARAMS,):
        raise ValueError(f"params must have shape ({N_PARAMS},), got {p.shape}")
    return p


def _check_positions(mean_norm: FloatArray, cov_norm: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Validated float copies of means (n, 3) and covariances (n, 3, 3): finite, symmetric, positive definite."""
    mean = np.array(mean_norm, dtype=float)
    cov = np.array(cov_norm, dtype=float)
    if mean.ndim != 2 or mean.shape[1] != 3:
        raise ValueError(f"position means must have shape (n, 3), got {mean.shape}")
    if cov.shape != (mean.shape[0], 3, 3):
        raise ValueError(
            f"position covariances must have shape ({mean.shape[0]}, 3, 3), got {cov.shape}"
        )
    bad = ~np.isfinite(mean).all(axis=1) | ~np.isfinite(cov).all(axis=(1, 2))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"position {k} has a non-finite mean or covariance: mean {mean[k].tolist()}"
        )
    asym = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2)) > 1e-9 * np.abs(cov).max(
        axis=(1, 2)
    )
    if asym.any():
        k = int(np.flatnonzero(asym)[0])
        raise ValueError(f"position {k} covariance is not symmetric: {cov[k].tolist()}")
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    if cov.shape[0]:
        eig_min = np.linalg.eigvalsh(cov)[:, 0]
        nonpos = eig_min <= 0.0
        if nonpos.any():
            k = int(np.flatnonzero(nonpos)[0])
            # A channel without spread (to rounding) is what a user can act on; the eigenvalue is not.
            flat = [a for a in range(3) if cov[k, a, a] <= max(1e-12 * np.trace(cov[k]), 1e-30)]
            if flat:
                axes = ", ".join("xyz"[a] for a in flat)
                raise ValueError(
                    f"position {k}: {'axes' if len(flat) > 1 else 'axis'} {axes} "
                    f"{'have' if len(flat) > 1 else 'has'} no spread at all (a stuck channel, or output "
                    "quantized coarser than its noise: include the quantization variance step²/12/n of each axis)"
                )
            raise ValueError(
                f"position {k} covariance is not positive definite (smallest eigenvalue {eig_min[k]:.3g}); "
                "include the quantization variance step²/12/n of each axis"
            )
    return mean, cov


def _unit_rows(v: FloatArray) -> FloatArray:
    """Rows scaled to unit length (a zero row stays zero instead of becoming NaN)."""
    norm: FloatArray = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.maximum(norm, np.finfo(float).tiny)


def _state_array(value: Any, shape: tuple[int, ...], name: str) -> FloatArray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape or not np.isfinite(arr).all():
        raise ValueError(
            f"recursive state field {name!r} must be a finite array of shape {shape}, got {value!r}"
        )
    return arr


def _frozen(arr: ArrayT) -> ArrayT:
    out = arr.copy(order="K")
    out.setflags(write=False)
    return out


def _finite_or_none(value: float | None) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)
