"""Statistics of a session that the service relies on, measured and simulated (issue 4, step 2–3).

Every statistic is computed by the same function on the measured session and
on each Monte Carlo replica, so their ratio and tail probability say how well
the simulation reproduces the unit:

* ``chi2_per_dof`` (accelerometers): the exact scalar equation of M1 per
  position, normalized by its predicted sigma, squared and summed over
  ``n − 9`` — the headline (≈ 1 when the white-noise model holds);
* ``halves_rms`` per axis: difference of a position's first- and second-half
  means over its predicted standard deviation ``2σ_mean`` (RMS over positions):
  correlated noise or motion inside positions;
* ``f0_sd`` and ``f0_q999`` (accelerometers): per-sample F0 statistic
  ``s = ½(|ã|² − 1)`` of the compensated output in static samples (M1's F0);
* ``allan`` per axis: overlapping Allan deviation of the longest position at
  ``τ = L/8`` (:mod:`estimators.noise`);
* ``param_scatter`` (accelerometers): the 9 estimates from the first and the
  second half of the positions, ``mean((p₁ − p₂)² / (σ₁² + σ₂²))`` (≈ 1,
  :func:`param_scatter`);
* ``means_rms`` per axis (gyros): scatter of the position means about the
  session mean over each mean's sd (a MEMS gyro's scalar is not observable;
  this is where g-sensitivity and wander show).

The statistics of what happens inside a position (:data:`INSIDE_POSITION_STATISTICS`)
can be restricted to the positions a model describes (``described`` of
:func:`triad_statistics`): a position the audit names as moved by hand
(``nonstatic_positions``) shows its motion there, and a model that does not
move it cannot describe them. The scalar fit's statistics (``chi2_per_dof``,
``param_scatter``) keep every position: a turn inside a position changes the
direction of its mean, not the norm the fit sees.

:func:`triad_curves` keeps, by the same rule for the measured session and every
replica, the few curves the report plots (:class:`TriadCurves`): the
normalized residual per position, the Allan deviation curve of the longest
position and the distribution of the F0 statistic of 1 s window means.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.audit import MIN_POSITIONS
from estimators.chain import ChainResult
from estimators.conventions import AXES, Triad, reference_magnitude
from estimators.ninepar import canonical_triad_matrix, ellipsoid_residual, position_arrays
from estimators.noise import overlapping_allan_deviation
from estimators.positions import Position
from estimators.scalar import F0Config, f0_batch

INSIDE_POSITION_STATISTICS = ("halves_rms", "f0_sd", "f0_q999", "allan", "means_rms")
"""Statistics made of what happens inside a position: its halves, its samples, its Allan record, a gyro's
mean rate (module docstring); :func:`triad_statistics` computes them over the positions a model describes."""

F0_KEPT_VALUES = 512
"""Most F0 values a :class:`TriadCurves` keeps: beyond that, quantiles at evenly spaced probabilities."""


@dataclass(frozen=True)
class PositionTable:
    """Position-level arrays of one triad (normalized by the triad's reference).

    Attributes
    ----------
    t_mid_s : (n,) mid time of each position, s from the session start.
    temp_c : (n,) mean temperature, °C, or None.
    mean : (n, 3) normalized position means; cov : (n, 3, 3) covariance of those means.
    halves : (n, 3) first-half minus second-half mean, normalized; NaN for a position merged
        from several intervals (its span holds the turn in between).
    temp_halves_c : (n,) first-half minus second-half mean temperature, °C (NaN as for ``halves``), or None.
    n_samples : (n,) samples per position; duration_s : (n,) lengths, s.
    spans : (n, 2) sample index spans ``[start, stop)``.
    grid_var : (3,) normalized variance of the rounding error every position mean keeps on a coarse
        grid (:func:`estimators.noise.rounding_mean_var`): in the means, not in ``cov`` (it does not
        average down, and both halves of a position share it, so their difference does not see it).
    batch_means : per position, the (n_b, 3) normalized means of its consecutive noise windows (the chain's
        batch length; the partial last one dropped), or empty when not read (:func:`with_batch_means`).
    batch_var : (3,) normalized variance of one such batch mean from the noise alone, without any wander.
    """

    t_mid_s: FloatArray
    temp_c: FloatArray | None
    mean: FloatArray
    cov: FloatArray
    halves: FloatArray
    temp_halves_c: FloatArray | None
    n_samples: IntArray
    duration_s: FloatArray
    spans: IntArray
    grid_var: FloatArray = field(default_factory=lambda: np.zeros(3))
    batch_means: tuple[FloatArray, ...] = ()
    batch_var: FloatArray = field(default_factory=lambda: np.zeros(3))


def position_span(position: Position) -> tuple[int, int]:
    """Sample span ``[start, stop)`` of a position found in the audited session."""
    if position.index_start is None or position.index_stop is None:
        raise ValueError(
            "a position without its sample span: the audit needs positions found in the session itself"
        )
    return position.index_start, position.index_stop


def position_table(
    chain: ChainResult,
    x_si: FloatArray,
    t_s: FloatArray,
    triad: Triad,
    temp_c: FloatArray | None = None,
) -> PositionTable:
    """The :class:`PositionTable` of ``triad`` from a chain result and the session's samples.

    ``x_si`` (N, 3) are the triad's samples, SI; ``temp_c`` (N,) the session's temperature, °C, or None.
    """
    ref = reference_magnitude(triad, chain.gravity_mps2)
    mean, cov = position_arrays(chain.positions, triad, ref)
    spans = np.array([position_span(p) for p in chain.positions], dtype=int).reshape(-1, 2)
    halves = np.full((len(spans), 3), np.nan)
    temp_halves = None if temp_c is None else np.full(len(spans), np.nan)
    for k, ((a, b), pos) in enumerate(zip(spans, chain.positions, strict=True)):
        if pos.n_intervals != 1:
            continue
        h = (a + b) // 2
        halves[k] = (x_si[a:h].mean(axis=0) - x_si[h:b].mean(axis=0)) / ref
        if temp_c is not None and temp_halves is not None:
            temp_halves[k] = temp_c[a:h].mean() - temp_c[h:b].mean()
    temps = [p.temp_mean_c for p in chain.positions]
    temp = None if any(v is None for v in temps) or not temps else np.array(temps, float)
    return PositionTable(
        t_mid_s=np.array([0.5 * (p.t_start_s + p.t_end_s) for p in chain.positions])
        - float(t_s[0]),
        temp_c=temp,
        mean=mean,
        cov=cov,
        halves=halves,
        temp_halves_c=temp_halves if temp is not None else None,
        n_samples=np.array([p.n_samples for p in chain.positions], int),
        duration_s=np.array([p.duration_s for p in chain.positions]),
        spans=spans,
    )


def with_noise_cov(
    tab: PositionTable, noise_sd_norm: FloatArray, grid_var_norm: FloatArray | None = None
) -> PositionTable:
    """``tab`` with each position's covariance of the mean ``diag(σ²)/n`` from one noise level (3,), normalized,
    and the rounding variance its means keep on a coarse grid (``grid_var_norm`` (3,), :attr:`PositionTable.grid_var`).

    The candidates' reference (:mod:`estimators.audit.candidates`): pooled over
    the whole session it is precise, where the chain's per-position batch-means
    covariance scatters by tens of percent (ten batches of a 5 s position) and
    takes in part of a bias wander it is meant to reveal.
    """
    sd = np.asarray(noise_sd_norm, float).reshape(3)
    cov = np.einsum("k,ij->kij", 1.0 / tab.n_samples, np.diag(sd**2))
    grid = np.zeros(3) if grid_var_norm is None else np.asarray(grid_var_norm, float).reshape(3)
    return replace(tab, cov=cov, grid_var=grid)


def with_batch_means(
    tab: PositionTable, x_si: FloatArray, batch: int, reference: float, noise_var_si: FloatArray
) -> PositionTable:
    """``tab`` with the means of consecutive ``batch``-sample windows of every position (``x_si`` (N, 3), SI) and
    the variance of one from the noise alone (``noise_var_si`` (3,), SI²), both normalized by ``reference``."""
    means = tuple(
        x_si[a : a + (b - a) // batch * batch].reshape(-1, batch, 3).mean(axis=1) / reference
        for a, b in tab.spans
    )
    return replace(
        tab, batch_means=means, batch_var=np.asarray(noise_var_si, float).reshape(3) / reference**2
    )


def subset_table(tab: PositionTable, keep: BoolArray) -> PositionTable:
    """The positions ``keep`` (bool (n,)) of ``tab``."""
    k = np.asarray(keep, bool)

    def pick(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else a[k]

    return PositionTable(
        tab.t_mid_s[k],
        pick(tab.temp_c),
        tab.mean[k],
        tab.cov[k],
        tab.halves[k],
        pick(tab.temp_halves_c),
        tab.n_samples[k],
        tab.duration_s[k],
        tab.spans[k],
        tab.grid_var,
        tuple(tab.batch_means[i] for i in np.flatnonzero(k)) if tab.batch_means else (),
        tab.batch_var,
    )


def static_mask(n: int, spans: IntArray) -> BoolArray:
    """(n,) bool: samples inside the position spans."""
    mask = np.zeros(n, bool)
    for a, b in spans:
        mask[a:b] = True
    return mask


def longest_span(tab: PositionTable) -> tuple[int, int]:
    """Sample span ``[start, stop)`` of the longest position of ``tab`` (the Allan deviation's record)."""
    k = int(np.argmax(tab.spans[:, 1] - tab.spans[:, 0]))
    return int(tab.spans[k, 0]), int(tab.spans[k, 1])


def f0_window_samples(rate_hz: float) -> int:
    """Samples of the F0 window the audit tests with: 1 s of data (at least one sample)."""
    return max(1, round(rate_hz))


def f0_config(params: FloatArray, reference: float, lambda0: float, n_avg: int = 1) -> F0Config:
    """F0 settings that compensate the estimated nine parameters (M1)."""
    return F0Config(
        lambda0=lambda0,
        reference=reference,
        bias_norm=tuple(params[:3]),
        matrix=canonical_triad_matrix(params),
        n_avg=n_avg,
    )


def param_scatter(params: FloatArray, tab: PositionTable) -> float | None:
    """``mean_j (p₁ − p₂)_j² / (σ₁² + σ₂²)_j`` of the 9 parameters fitted on the first and second half of the positions.

    Each half is one Gauss–Newton step of the exact scalar equation (M1) from
    the whole session's ``params``, weighted by the predicted sigma, with its
    covariance ``(AᵀA)⁻¹`` (from the QR factor, no inverse of AᵀA): ≈ 1 when the
    halves differ by noise only. A half whose geometry is poor still gives an
    answer with a large covariance (the chain's observability gate would
    refuse it, and the statistic would vanish exactly where it matters).
    None when a half has fewer than ``MIN_POSITIONS`` positions.
    """
    f, sigma, jac, _ = scalar_residuals(params, tab)
    half = f.size // 2
    if half < MIN_POSITIONS:
        return None
    est, var = [], []
    for sl in (slice(0, half), slice(half, None)):
        a = jac[sl] / sigma[sl, None]
        step, *_ = np.linalg.lstsq(a, -f[sl] / sigma[sl], rcond=None)
        # numpy's stub types every mode as QRResult; mode="r" returns R alone.
        r: FloatArray = np.linalg.qr(a, mode="r")  # type: ignore[assignment]
        r_inv = np.linalg.solve(r, np.eye(r.shape[0]))
        est.append(step)
        var.append(np.sum(r_inv**2, axis=1))
    return float(np.mean((est[0] - est[1]) ** 2 / (var[0] + var[1])))


def triad_statistics(
    chain: ChainResult,
    x_si: FloatArray,
    t_s: FloatArray,
    triad: Triad,
    rate_hz: float,
    described: BoolArray | None = None,
) -> dict[str, float]:
    """Flat ``{name: value}`` statistics of one triad (module docstring); absent ones are left out.

    ``described`` (n,) bool over the chain's positions: those the model describes, over which the
    :data:`INSIDE_POSITION_STATISTICS` are computed (None: every position).
    """
    triad = Triad(triad)
    out: dict[str, float] = {}
    if len(chain.positions) == 0:
        return out
    whole = position_table(chain, x_si, t_s, triad)
    tab = whole if described is None else subset_table(whole, described)
    if tab.spans.shape[0] == 0:
        raise ValueError(
            "described keeps none of the positions: nothing inside a position to describe"
        )
    sd_half = 2.0 * np.sqrt(np.einsum("kii->ki", tab.cov))
    ok = (sd_half > 0) & np.isfinite(tab.halves)
    for i, ax in enumerate(AXES):
        if ok[:, i].any():
            out[f"halves_rms_{ax}"] = float(
                np.sqrt(np.mean((tab.halves[ok[:, i], i] / sd_half[ok[:, i], i]) ** 2))
            )
    a, b = longest_span(tab)
    first = x_si[a:b]
    if first.shape[0] >= 16:
        m = max(1, first.shape[0] // 8)
        adev = overlapping_allan_deviation(first, rate_hz, np.array([m])).adev[0]
        for i, ax in enumerate(AXES):
            out[f"allan_{ax}"] = float(adev[i])
    est = chain.triads[triad].estimate
    if triad is Triad.ACCEL and est.params is not None and len(chain.positions) >= MIN_POSITIONS:
        if est.chi2_per_dof is not None:
            out["chi2_per_dof"] = float(est.chi2_per_dof)
        ref = reference_magnitude(triad, chain.gravity_mps2)
        s = f0_batch(
            x_si, static_mask(x_si.shape[0], tab.spans), f0_config(est.params, ref, 1.0)
        ).residual
        s = s[np.isfinite(s)]
        out["f0_sd"] = float(np.std(s))
        out["f0_q999"] = float(np.quantile(np.abs(s - np.mean(s)), 0.999))
        scatter = param_scatter(np.asarray(est.params, float), whole)
        if scatter is not None:
            out["param_scatter"] = scatter
    if triad is Triad.GYRO:
        # Between-position scatter of the gyro means about their session mean, over each mean's sd:
        # a constant bias and the Earth rate give ≈ 1 (MEMS), g-sensitivity and wander more.
        dev = (tab.mean - tab.mean.mean(axis=0)) / np.sqrt(np.einsum("kii->ki", tab.cov))
        for i, ax in enumerate(AXES):
            out[f"means_rms_{ax}"] = float(np.sqrt(np.mean(dev[:, i] ** 2)))
    return out


@dataclass(frozen=True)
class TriadCurves:
    """The curves of one session the report plots (a few hundred numbers; no samples are kept).

    Attributes
    ----------
    residual_norm : (n,) exact scalar residual of each position (M1) over its predicted sigma,
        after the session's own fit; None for a gyro triad or too few positions.
    allan_tau_s : (m,) averaging times, s; allan_si : (m, 3) overlapping Allan deviation of the
        longest position, SI (empty when it is too short). The cluster sizes are
        :func:`estimators.noise.default_cluster_sizes`, so curves of different lengths share a prefix.
    f0_window : (q,) sorted F0 statistic ``s`` (M1) of the window means of :func:`f0_window_samples`
        samples, normalized; at most :data:`F0_KEPT_VALUES` (quantiles beyond); None as for ``residual_norm``.
    """

    residual_norm: FloatArray | None
    allan_tau_s: FloatArray
    allan_si: FloatArray
    f0_window: FloatArray | None


def triad_curves(
    chain: ChainResult, x_si: FloatArray, t_s: FloatArray, triad: Triad, rate_hz: float
) -> TriadCurves:
    """The :class:`TriadCurves` of one triad of a session (module docstring)."""
    triad = Triad(triad)
    tab = position_table(chain, x_si, t_s, triad)
    a, b = longest_span(tab) if len(chain.positions) else (0, 0)
    if b - a >= 16:
        ad = overlapping_allan_deviation(x_si[a:b], rate_hz)
        tau, adev = ad.tau_s, ad.adev
    else:
        tau, adev = np.zeros(0), np.zeros((0, 3))
    est = chain.triads[triad].estimate
    if triad is not Triad.ACCEL or est.params is None or len(chain.positions) < MIN_POSITIONS:
        return TriadCurves(None, tau, adev, None)
    f, sigma, _, _ = scalar_residuals(np.asarray(est.params, float), tab)
    ref = reference_magnitude(triad, chain.gravity_mps2)
    s = f0_batch(
        x_si,
        static_mask(x_si.shape[0], tab.spans),
        f0_config(est.params, ref, 1.0, f0_window_samples(rate_hz)),
    ).residual
    # Every static row carries its run's last completed window: a window's value starts where it changes.
    first = np.concatenate([[True], s[1:] != s[:-1]])
    s = np.sort(s[first & np.isfinite(s)])
    if s.size > F0_KEPT_VALUES:
        s = np.quantile(s, (np.arange(F0_KEPT_VALUES) + 0.5) / F0_KEPT_VALUES)
    return TriadCurves(f / sigma, tau, adev, s)


def scalar_residuals(
    params: FloatArray, tab: PositionTable
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Exact scalar equation per position (M1): residual, its sigma, ∂f/∂params (n, 9), ∂f/∂ã (n, 3).

    The sigma holds the mean's noise and the rounding error a coarse grid leaves in it (``tab.grid_var``).
    """
    f, jac, grad = ellipsoid_residual(params, tab.mean)
    sigma = np.sqrt(
        np.einsum("ni,nij,nj->n", grad, tab.cov, grad) + np.einsum("ni,i->n", grad**2, tab.grid_var)
    )
    return f, sigma, jac, grad


@dataclass(frozen=True)
class Comparison:
    """One statistic, measured against its simulated distribution.

    ``ratio`` = measured / median simulated; ``tail_prob`` = fraction of
    replicas at or above the measured value (near 0: the simulation
    under-predicts the statistic; near 1: it over-predicts).
    ``positions_left_out``: the positions (measured indices) the statistic was computed without, on
    both sides (:data:`INSIDE_POSITION_STATISTICS`); empty when it holds every position.
    """

    statistic: str
    triad: Triad
    axis: str | None
    measured: float
    simulated_median: float
    simulated_p05: float
    simulated_p95: float
    ratio: float
    tail_prob: float
    positions_left_out: tuple[int, ...] = ()

    @property
    def inside(self) -> bool:
        """The measured value lies within the replicas' 5–95 % band."""
        return self.simulated_p05 <= self.measured <= self.simulated_p95

    def to_dict(self) -> dict[str, Any]:
        return {
            "statistic": self.statistic,
            "triad": self.triad.value,
            "axis": self.axis,
            "measured": self.measured,
            "simulated_median": self.simulated_median,
            "simulated_p05": self.simulated_p05,
            "simulated_p95": self.simulated_p95,
            "ratio": self.ratio,
            "tail_prob": self.tail_prob,
            "inside_band": self.inside,
            "positions_left_out": list(self.positions_left_out),
        }


def compare(
    triad: Triad,
    measured: dict[str, float],
    replicas: list[dict[str, float]],
    left_out: tuple[int, ...] = (),
) -> list[Comparison]:
    """Measured statistics against the replicas' distributions (names present in both).

    ``left_out``: the positions both sides computed the :data:`INSIDE_POSITION_STATISTICS` without.
    """
    out = []
    for name, value in measured.items():
        sims = np.array([r[name] for r in replicas if name in r], float)
        if sims.size == 0:
            continue
        med = float(np.median(sims))
        above = float(np.mean(sims >= value))
        axis = name.rsplit("_", 1)[1] if name.rsplit("_", 1)[-1] in AXES else None
        base = name if axis is None else name.rsplit("_", 1)[0]
        out.append(
            Comparison(
                base,
                triad,
                axis,
                float(value),
                med,
                float(np.quantile(sims, 0.05)),
                float(np.quantile(sims, 0.95)),
                float(value / med) if med != 0 else float("inf"),
                above,
                left_out if base in INSIDE_POSITION_STATISTICS else (),
            )
        )
    return out
