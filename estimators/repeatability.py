"""Credibility of a passport without a reference instrument (methods.md M2).

Uspensky & Khatsko (M2) cannot compare their estimates with a certified
reference, so they judge them by three indirect checks, which this module
implements for any linear least-squares passport (a tilt-table axis, M2, or a
triad from multi-position sessions, M1):

1. **stabilization**: the estimate computed from the first ``m`` equations
   settles as ``m`` grows (:func:`stabilization`);
2. **residuals** of the measured series against the series modelled with the
   estimate (:attr:`LinearFit.residuals`);
3. **reproducibility** over runs (separate power-ups of the sensor): per-run
   estimates with confidence intervals, the across-run mean and standard
   deviation, and the **intersection of the per-run intervals**, whose middle
   is the passport value (:func:`run_spread`).

Intervals are Student-t intervals with the run's residual degrees of freedom
(infinite when the noise level was known rather than estimated).

For a whole triad, :func:`triad_runs` estimates M1's nine parameters in each
of several multi-position sessions and :func:`passport_from_runs` turns their
intersection into a :class:`~estimators.passport.TriadPassport` whose
tolerances are the runs' envelope (the reproducibility the unit showed).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import PARAM_NAMES, Triad
from estimators.least_squares import LinearFit as LinearFit
from estimators.least_squares import fit_linear as fit_linear
from estimators.ninepar import Estimate, Method, estimate_triad, position_arrays, regressors
from estimators.passport import Provenance, TriadPassport, reference_kind
from estimators.positions import Position


def t_quantile(level: float, dof: float | FloatArray) -> FloatArray:
    """Two-sided Student-t factor for a confidence ``level`` (normal for infinite dof)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {level!r}")
    import scipy.stats  # only the intervals need it; it takes most of a second to import

    return np.asarray(scipy.stats.t.ppf(0.5 * (1.0 + level), dof), dtype=float)


@dataclass(frozen=True)
class Stabilization:
    """Estimates from the first ``m`` equations, for growing ``m`` (M2 check 1).

    Attributes
    ----------
    n_equations : (K,) number of equations used, ``P + 1 … M``.
    values : (K, P) estimates.
    std : (K, P) their standard deviations.
    settled_at : (P,) smallest ``m`` from which every later estimate lies within
        the final estimate's confidence interval.
    """

    n_equations: IntArray
    values: FloatArray
    std: FloatArray
    settled_at: IntArray


def stabilization(
    h: FloatArray, y: FloatArray, *, level: float = 0.95, names: Sequence[str] | None = None
) -> Stabilization:
    """Re-solve with the first ``m`` equations for ``m = P + 1 … M`` (M2 check 1).

    The paper's Fig. 1: estimates jump while few equations constrain them and
    settle as more are added. Prefixes that cannot yet separate the unknowns
    are reported as NaN. ``h`` (M, P) and ``y`` (M,) as in :func:`fit_linear`.
    """
    h = np.asarray(h, dtype=float)
    y = np.asarray(y, dtype=float)
    m, p = h.shape
    counts = np.arange(p + 1, m + 1)
    values = np.full((counts.size, p), np.nan)
    std = np.full((counts.size, p), np.nan)
    for i, k in enumerate(counts):
        try:
            fit = fit_linear(h[:k], y[:k], names=names)
        except ValueError:
            continue
        values[i] = fit.values
        std[i] = fit.std
    if counts.size == 0 or np.isnan(values[-1]).any():
        raise ValueError(f"the {m} equations cannot determine the {p} unknowns")
    half = t_quantile(level, m - p) * std[-1]
    inside = np.abs(values - values[-1]) <= half
    # settled_at: the first prefix after the last one that fell outside.
    settled = np.empty(p, dtype=int)
    for j in range(p):
        outside = np.flatnonzero(~inside[:, j])
        settled[j] = counts[outside[-1] + 1] if outside.size else counts[0]
    return Stabilization(n_equations=counts, values=values, std=std, settled_at=settled)


@dataclass(frozen=True)
class RunEstimate:
    """One run's estimate: values (P,), covariance (P, P), degrees of freedom of its noise level."""

    values: FloatArray
    cov: FloatArray
    dof: float = np.inf

    @classmethod
    def from_fit(cls, fit: LinearFit) -> RunEstimate:
        return cls(values=fit.values, cov=fit.cov, dof=fit.dof)


@dataclass(frozen=True)
class RunSpread:
    """Reproducibility of a passport over runs (M2 checks 3 and 4).

    Attributes
    ----------
    names : (P,) parameter names.
    level : confidence level of every interval.
    values, std : (R, P) per-run estimates and standard deviations.
    lower, upper : (R, P) per-run confidence intervals.
    mean, spread : (P,) across-run mean and standard deviation (ddof 1) of the estimates.
    mean_lower, mean_upper : (P,) confidence interval of the across-run mean (t, R − 1 dof).
    common_lower, common_upper : (P,) intersection of the per-run intervals
        (``common_lower > common_upper`` when it is empty).
    reproducible : (P,) the intersection is not empty.
    value : (P,) passport value: the middle of the intersection; where it is
        empty, the inverse-variance weighted mean (and ``reproducible`` is False).
    tolerance : (P,) half-width about ``value`` of the envelope of the run
        intervals: every run's interval lies in ``value ± tolerance``, so a
        later estimate of the same unit deviating by more is a change.
    chi2, chi2_dof, p_value : (P,) scatter of the run estimates about their weighted mean
        against their own standard deviations; a small p-value says the runs
        differ by more than their stated uncertainty.
    """

    names: tuple[str, ...]
    level: float
    values: FloatArray
    std: FloatArray
    lower: FloatArray
    upper: FloatArray
    mean: FloatArray
    spread: FloatArray
    mean_lower: FloatArray
    mean_upper: FloatArray
    common_lower: FloatArray
    common_upper: FloatArray
    reproducible: BoolArray
    value: FloatArray
    tolerance: FloatArray
    chi2: FloatArray
    chi2_dof: int
    p_value: FloatArray

    @property
    def n_runs(self) -> int:
        return int(self.values.shape[0])

    @property
    def all_reproducible(self) -> bool:
        return bool(self.reproducible.all())

    def not_reproducible(self) -> tuple[str, ...]:
        """Names of the parameters whose run intervals do not intersect."""
        return tuple(n for n, ok in zip(self.names, self.reproducible, strict=True) if not ok)


def run_spread(
    runs: Sequence[RunEstimate], *, names: Sequence[str], level: float = 0.95
) -> RunSpread:
    """Per-run intervals, across-run statistics and their intersection (M2 checks 3–4).

    Parameters
    ----------
    runs : R ≥ 2 estimates of the same P parameters (separate runs of one unit).
    names : P parameter names.
    level : confidence level of each run's interval.
    """
    names = tuple(names)
    if len(runs) < 2:
        raise ValueError(f"reproducibility needs at least 2 runs, got {len(runs)}")
    vals = np.array([np.asarray(r.values, dtype=float) for r in runs])
    if vals.ndim != 2 or vals.shape[1] != len(names):
        raise ValueError(
            f"every run must estimate the {len(names)} parameters {names}, got shape {vals.shape}"
        )
    std = np.array([np.sqrt(np.diag(np.asarray(r.cov, dtype=float))) for r in runs])
    if not np.all(std > 0.0):
        raise ValueError("every run needs a positive standard deviation for each parameter")
    half = np.array([t_quantile(level, r.dof) for r in runs])[:, None] * std
    lower, upper = vals - half, vals + half
    n_runs = vals.shape[0]
    mean = vals.mean(axis=0)
    spread = vals.std(axis=0, ddof=1)
    mean_half = t_quantile(level, n_runs - 1) * spread / np.sqrt(n_runs)
    common_lower, common_upper = lower.max(axis=0), upper.min(axis=0)
    reproducible = common_lower <= common_upper
    w = 1.0 / std**2
    wmean = (w * vals).sum(axis=0) / w.sum(axis=0)
    value = np.where(reproducible, 0.5 * (common_lower + common_upper), wmean)
    tolerance = np.maximum(upper - value, value - lower).max(axis=0)
    chi2 = (w * (vals - wmean) ** 2).sum(axis=0)
    import scipy.stats

    p_value = scipy.stats.chi2.sf(chi2, n_runs - 1)
    return RunSpread(
        names=names,
        level=float(level),
        values=vals,
        std=std,
        lower=lower,
        upper=upper,
        mean=mean,
        spread=spread,
        mean_lower=mean - mean_half,
        mean_upper=mean + mean_half,
        common_lower=common_lower,
        common_upper=common_upper,
        reproducible=reproducible,
        value=value,
        tolerance=tolerance,
        chi2=chi2,
        chi2_dof=n_runs - 1,
        p_value=p_value,
    )


# --- a triad passport from repeated multi-position sessions (M2's methodology on M1's estimates) ---


@dataclass(frozen=True)
class TriadRuns:
    """The nine parameters of one triad estimated in each of several sessions, and their spread.

    Attributes
    ----------
    estimates : one :class:`~estimators.ninepar.Estimate` per run.
    spread : :func:`run_spread` of their parameters (names :data:`estimators.conventions.PARAM_NAMES`).
    stabilizations : per run, M1's linear equations re-solved with the first m positions.
    observable : (9,) observable in every run (the precision rule of :mod:`estimators.ninepar`).
    """

    estimates: tuple[Estimate, ...]
    spread: RunSpread
    stabilizations: tuple[Stabilization, ...]
    observable: BoolArray


def triad_runs(
    positions_per_run: Sequence[Sequence[Position]],
    triad: Triad,
    reference: float,
    *,
    level: float = 0.95,
) -> TriadRuns:
    """Estimate the nine parameters in every run (refined M1 estimator) and intersect the runs.

    Parameters
    ----------
    positions_per_run : per run, its static positions (:class:`estimators.positions.Position`, SI).
    triad : which triad (:class:`estimators.conventions.Triad`).
    reference : local g (m/s²) or Ω (rad/s).
    level : confidence level of the per-run intervals.
    """
    estimates: list[Estimate] = []
    runs: list[RunEstimate] = []
    stabs: list[Stabilization] = []
    for k, positions in enumerate(positions_per_run):
        est = estimate_triad(positions, triad, reference, method=Method.REFINED)
        if est.params is None or est.cov is None:
            raise ValueError(f"run {k + 1}: {est.reason}")
        estimates.append(est)
        runs.append(RunEstimate(est.params, est.cov))
        mean, _ = position_arrays(positions, triad, reference)
        stabs.append(
            stabilization(
                regressors(mean),
                0.5 * (np.einsum("ij,ij->i", mean, mean) - 1.0),
                level=level,
                names=PARAM_NAMES,
            )
        )
    spread = run_spread(runs, names=PARAM_NAMES, level=level)
    observable = np.logical_and.reduce([np.asarray(e.observable, dtype=bool) for e in estimates])
    return TriadRuns(
        estimates=tuple(estimates),
        spread=spread,
        stabilizations=tuple(stabs),
        observable=observable,
    )


def passport_from_runs(
    runs: TriadRuns, *, noise_std: FloatArray, sample_rate_hz: float
) -> TriadPassport:
    """A :class:`TriadPassport` whose values, intervals and tolerances come from the runs (M2 → M1).

    Nominal: the intersection value; confidence interval: the intersection;
    sigma: its half-width over the normal quantile of the level; tolerance: the
    envelope of the run intervals (:attr:`RunSpread.tolerance`), i.e. the
    reproducibility the unit showed. A parameter whose run intervals do not
    intersect, or that a run could not resolve, is marked not observable and
    gets ``value ± tolerance`` as its interval.
    """
    sp = runs.spread
    z = float(t_quantile(sp.level, np.inf))
    lo = np.where(sp.reproducible, sp.common_lower, sp.value - sp.tolerance)
    hi = np.where(sp.reproducible, sp.common_upper, sp.value + sp.tolerance)
    first = runs.estimates[0]
    assert first.reference is not None  # triad_runs gives every estimate its reference
    return TriadPassport(
        triad=first.triad,
        reference=float(first.reference),
        reference_kind=reference_kind(first.triad),
        nominal=sp.value,
        tolerance=sp.tolerance,
        sigma=(hi - lo) / (2.0 * z),
        observable=np.asarray(runs.observable & sp.reproducible, dtype=bool),
        noise_std=noise_std,
        sample_rate_hz=sample_rate_hz,
        provenance=Provenance(
            Method.REFINED,
            int(sum(e.n_positions for e in runs.estimates)),
            sp.level,
            lo,
            hi,
            procedure="M2 repeated multi-position runs",
            n_runs=len(runs.estimates),
            reproducible=np.asarray(sp.reproducible, dtype=bool),
        ),
    )
