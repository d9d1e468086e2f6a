"""Noise of static data: overlapping Allan deviation, white-noise level, quantization step.

Pure numerics on arrays of one static interval (methods.md M1's noise ``n_i``
and M2's quantization). Used by the model audit (:mod:`estimators.audit`) to
fit the baseline noise model from the data itself.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

# scipy is imported in the functions that use it: it takes a large part of a second to import, and
# `calibrate` imports this module (through the audit) for sessions the audit does not simulate too.
from estimators._typing import FloatArray


@dataclass(frozen=True)
class AllanDeviation:
    """Overlapping Allan deviation of a (N, k) static record.

    Attributes
    ----------
    tau_s : (m,) averaging times, s.
    adev : (m, k) Allan deviation per column, in the input's unit.
    n_terms : (m,) number of overlapping second differences behind each value.
    """

    tau_s: FloatArray
    adev: FloatArray
    n_terms: FloatArray


def default_cluster_sizes(
    n_samples: int, *, per_octave: int = 2, max_fraction: float = 0.25
) -> FloatArray:
    """Cluster sizes ``m`` (samples), log-spaced, from 1 to ``max_fraction · n_samples``."""
    top = max(1, int(n_samples * max_fraction))
    m = np.unique(
        np.round(2.0 ** (np.arange(0, np.log2(top) + 1e-9, 1.0 / per_octave))).astype(int)
    )
    return m[m <= top]


def overlapping_allan_deviation(
    x: FloatArray, rate_hz: float, cluster_sizes: FloatArray | None = None
) -> AllanDeviation:
    """Overlapping Allan deviation (IEEE Std 952, eq. of the overlapping estimator).

    ``σ²(τ) = 1 / (2 τ² (N − 2m)) Σ_k (θ_{k+2m} − 2θ_{k+m} + θ_k)²`` with
    ``θ`` the cumulative sum of the samples times ``1/rate`` and ``τ = m/rate``.
    White noise of per-sample standard deviation ``σ`` gives ``σ/√m``.

    Parameters
    ----------
    x : (N,) or (N, k) samples of a static interval, any unit.
    rate_hz : sample rate, Hz.
    cluster_sizes : (m,) cluster sizes in samples (default :func:`default_cluster_sizes`);
        sizes with ``2m ≥ N`` are dropped.
    """
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    n = a.shape[0]
    if n < 3:
        raise ValueError(f"an Allan deviation needs at least 3 samples, got {n}")
    m = default_cluster_sizes(n) if cluster_sizes is None else np.asarray(cluster_sizes, int)
    m = m[(m >= 1) & (2 * m < n)]
    theta = np.vstack([np.zeros((1, a.shape[1])), np.cumsum(a, axis=0)]) / rate_hz
    adev = np.empty((m.size, a.shape[1]))
    for j, mj in enumerate(m):
        d = theta[2 * mj :] - 2.0 * theta[mj:-mj] + theta[: -2 * mj]
        tau = mj / rate_hz
        adev[j] = np.sqrt(np.mean(d * d, axis=0) / (2.0 * tau * tau))
    return AllanDeviation(m / rate_hz, adev, n - 2 * m + 1)


def white_noise_sd(x: FloatArray) -> FloatArray:
    """(k,) per-sample white-noise standard deviation from first differences: ``std(Δx)/√2``.

    Differences remove the mean and any slow wander (bias instability, drift),
    so this is the white level alone even when the record is not stationary.
    """
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.shape[0] < 3:
        raise ValueError(f"a noise level needs at least 3 samples, got {a.shape[0]}")
    sd: FloatArray = np.std(np.diff(a, axis=0), axis=0, ddof=1) / np.sqrt(2.0)
    return sd


def sample_noise_sd(x: FloatArray, window: int) -> FloatArray:
    """(k,) per-sample noise standard deviation about a centred moving mean of ``window`` samples.

    ``var(x − mean_window) = σ²(1 − 1/window)`` for white noise, so the result
    is divided by that factor's root. Unlike :func:`white_noise_sd` it keeps the
    short-lag correlation of a sensor's own low-pass filter (the per-sample
    spread F0 sees), while wander slower than the window drops out. Only full
    windows are used (no edge padding).

    Parameters
    ----------
    x : (N,) or (N, k) samples of one static interval, any unit.
    window : moving-mean length, samples (≥ 2, ≤ N).
    """
    out: FloatArray = np.sqrt(np.diag(sample_noise_cov(x, window)))
    return out


def sample_noise_cov(x: FloatArray, window: int) -> FloatArray:
    """(k, k) per-sample noise covariance between the columns about a centred moving mean of ``window`` samples.

    :func:`sample_noise_sd` is the root of its diagonal; the off-diagonal terms are the noise the
    axes share at the same sample, which a statistic of several axes at once sees (F0 projects the
    noise on the gravity direction: ``uᵀ Σ u``). Same arguments as :func:`sample_noise_sd`, any unit².
    """
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    n = a.shape[0]
    if not 2 <= window <= n:
        raise ValueError(f"window must be within [2, {n}] samples, got {window}")
    c = np.vstack([np.zeros((1, a.shape[1])), np.cumsum(a - a.mean(axis=0), axis=0)])
    moving = (c[window:] - c[:-window]) / window
    d = a[window // 2 : window // 2 + moving.shape[0]] - a.mean(axis=0) - moving
    cov: FloatArray = d.T @ d / d.shape[0]
    return cov / (1.0 - 1.0 / window)


def batch_means_sd(records: list[FloatArray], batch: int) -> FloatArray:
    """(k,) noise level that governs averages: ``√(m · var(batch means))``, pooled over records.

    Each record (a static interval, (N_r, k)) is cut into whole batches of
    ``m = batch`` samples; the batch means' scatter about their record's mean,
    pooled with ``Σ (n_b − 1)`` degrees of freedom, times ``m``. For white noise
    this is the per-sample sd; for noise with short-lag correlation (a sensor's
    own filter) it is ``σ·√(1 + 2Σρ)``, the level at which means average down.
    Records with fewer than two batches are skipped.
    """
    if batch < 1:
        raise ValueError(f"batch must be at least 1 sample, got {batch}")
    total: FloatArray | None = None
    dof = 0
    for pieces in _pieces(records, batch, at_least=2):
        means = pieces.mean(axis=1)
        ss: FloatArray = np.sum((means - means.mean(axis=0)) ** 2, axis=0)
        total = ss if total is None else total + ss
        dof += pieces.shape[0] - 1
    if total is None:
        raise ValueError(f"no record holds two batches of {batch} samples")
    return np.sqrt(batch * total / dof)


def _pieces(records: list[FloatArray], length: int, *, at_least: int) -> Iterator[FloatArray]:
    """Each record cut into consecutive pieces of ``length`` samples, (n, length, axes), the partial
    last piece dropped; records with fewer than ``at_least`` pieces are skipped."""
    for r in records:
        a = np.asarray(r, dtype=float)
        a = a[:, None] if a.ndim == 1 else a
        n = a.shape[0] // length
        if n >= at_least:
            yield a[: n * length].reshape(n, length, -1)


def quantization_step(x: FloatArray, *, rel_tol: float = 0.02, min_levels: int = 3) -> float | None:
    """The output grid step of a record (M2's count size ``k``), or None when the data are not on a grid.

    The smallest positive difference between distinct values is the candidate
    step; the record is on a grid when every distinct value lies within
    ``rel_tol`` of a step multiple from the smallest value, with at least
    ``min_levels`` distinct levels.

    Parameters
    ----------
    x : (N,) samples of one axis, SI.
    """
    v = np.unique(np.asarray(x, dtype=float).ravel())
    v = v[np.isfinite(v)]
    if v.size < min_levels:
        return None
    gaps = np.diff(v)
    step = float(gaps.min())
    if step <= 0.0:
        return None
    k = (v - v[0]) / step
    if np.max(np.abs(k - np.round(k))) > rel_tol:
        return None
    return step


ROUNDING_TERMS = 32
"""Fourier terms of :func:`rounding_mean_var`: the k-th falls as ``e^{−4π²k²σ²/q²}/k²``, so 32 reach
1e-5 of the sum even for noise-free input (σ = 0, where the sum is q²/12)."""


def rounding_mean_var(white_sd: FloatArray, step: FloatArray) -> FloatArray:
    """Variance of the rounding error that stays in a long average of ``round((μ + n)/q)·q`` (M2, no dithering).

    With white noise ``n`` of sd ``σ`` before a grid of step ``q``, the mean
    output of a position is ``μ + β(μ)`` with
    ``β(μ) = Σ_k (−1)^k (q/πk) sin(2πkμ/q) e^{−2π²k²σ²/q²}`` — it does not
    average down. Over positions whose true values ``μ`` fall anywhere on the
    grid its variance is ``Σ_k q²/(2π²k²) e^{−4π²k²σ²/q²}`` (q²/12 at σ = 0;
    negligible once σ ≳ q/2, where M2's half-pulse correction holds).
    Floor (M2's Entier) and round-to-nearest differ by a half step, a constant
    offset the bias takes in: the variance is the same.
    """
    s = np.asarray(white_sd, float)[..., None]
    q = np.asarray(step, float)[..., None]
    k = np.arange(1, ROUNDING_TERMS + 1, dtype=float)
    terms = q**2 / (2.0 * np.pi**2 * k**2) * np.exp(-4.0 * np.pi**2 * k**2 * s**2 / q**2)
    out: FloatArray = np.sum(terms, axis=-1)
    return out


def dequantized_white_sd(quantized_sd: FloatArray, step: FloatArray) -> FloatArray:
    """(k,) white sd before the grid from the within-position sd of grid output (inverse of Sheppard's rule, exact).

    Pooled over positions at values spread over the grid, the output's
    variance about each position's mean is ``σ² + q²/12 − R(σ)`` with ``R``
    :func:`rounding_mean_var` (the part of the rounding error that stays in the
    mean is not scatter about it); solved for ``σ`` (``σ² − R(σ)`` increases
    from ``−q²/12`` at 0, so the root is unique in ``[0, s]``). Sheppard's
    ``σ² = s² − q²/12`` is its limit for noise above about half a step.
    """
    from scipy.optimize import brentq

    s = np.asarray(quantized_sd, float)
    q = np.asarray(step, float)
    out = np.empty_like(s)
    for i, (si, qi) in enumerate(zip(s.ravel(), np.broadcast_to(q, s.shape).ravel(), strict=True)):
        target = si * si - qi * qi / 12.0

        def gap(w: float, target: float = target, qi: float = qi) -> float:
            return w * w - float(rounding_mean_var(np.array(w), np.array(qi))) - target

        out.flat[i] = 0.0 if si <= 0.0 or gap(0.0) >= 0.0 else brentq(gap, 0.0, si, xtol=1e-12 * si)
    return out


def segment_periodogram(
    records: list[FloatArray], segment: int, *, taper: bool = False
) -> tuple[FloatArray, int]:
    """(K, k) mean periodogram of whole ``segment``-sample pieces of the records, and the number of pieces.

    Each record (a static interval, (N_r, k)) is cut into consecutive pieces of
    ``segment`` samples (the partial last one dropped); the periodogram
    ``|Σ_t x_t e^{−2πi j t/L}|² / L`` at the frequencies ``j = 1 … ⌈L/2⌉ − 1``
    (no mean, no Nyquist bin, so a piece's own mean and its wander slower than
    the piece drop out) is averaged over every piece of every record. Per-sample
    units: white noise of sd ``σ`` gives ``σ²`` in every bin. ``taper``: each piece weighted by
    :func:`taper_window` (``|Σ_t w_t x_t e^{…}|² / Σ w_t²``): a slow process's leakage falls below
    −92 dB beyond the window's four bins, and the piece's mean leaves the bins ``j ≥ 4`` exactly.
    """
    if segment < 4:
        raise ValueError(f"a periodogram segment needs at least 4 samples, got {segment}")
    w = taper_window(segment) if taper else np.ones(segment)
    total: FloatArray | None = None
    count = 0
    for pieces in _pieces(records, segment, at_least=1):
        spec = np.fft.rfft(pieces * w[None, :, None], axis=1)[:, 1 : (segment + 1) // 2]
        p: FloatArray = np.sum(np.abs(spec) ** 2, axis=0) / float(np.sum(w**2))
        total = p if total is None else total + p
        count += pieces.shape[0]
    if total is None:
        raise ValueError(f"no record holds a segment of {segment} samples")
    return total / count, count


def gauss_markov_periodogram(phi: float, segment: int) -> FloatArray:
    """(K,) expected periodogram of :func:`segment_periodogram` for a unit-variance first-order Gauss–Markov sequence.

    ``x_t = φ x_{t−1} + w_t`` (``φ = e^{−Δt/τ}``, stationary, variance 1) has the
    autocovariance ``φ^{|h|}``; a piece of ``L`` samples sees it through the
    Fejér weights: ``E I_j = Σ_{|h|<L} (1 − |h|/L) φ^{|h|} cos(2π j h / L)``
    (exact for the finite piece: no leakage approximation).
    """
    return fejer_periodogram(np.power(phi, np.arange(segment), dtype=np.float64), segment)


def taper_window(segment: int) -> FloatArray:
    """The periodic 4-term Blackman–Harris window of ``segment`` samples (:func:`scipy.signal.windows.blackmanharris`):
    sidelobes below −92 dB, its transform zero beyond three bins of 0."""
    from scipy.signal.windows import blackmanharris

    out: FloatArray = np.asarray(blackmanharris(segment, sym=False), dtype=np.float64)
    return out


def fejer_periodogram(acov: FloatArray, segment: int, *, taper: bool = False) -> FloatArray:
    """(K,) expected periodogram of :func:`segment_periodogram` for a sequence of autocovariance ``acov`` (lags 0…L−1).

    ``E I_j = Σ_{|h|<L} c(h) r(h) cos(2π j h / L)`` with the window's lag weights ``c(h) = Σ_t w_t w_{t+h} / Σ w_t²``
    (``1 − |h|/L`` untapered: Fejér's): exact for the finite piece of ``L`` samples.
    """
    h = np.arange(1, segment)
    j = np.arange(1, (segment + 1) // 2)
    if taper:
        tw = taper_window(segment)
        lag = np.correlate(tw, tw, mode="full")[segment:] / float(np.sum(tw**2))
    else:
        lag = 1.0 - h / segment
    w = lag * acov[1:segment]
    out: FloatArray = acov[0] + 2.0 * np.cos(2.0 * np.pi * np.outer(j, h) / segment) @ w
    return out


LOWPASS_ORDERS = (1, 2, 3, 4)
"""Orders of the firmware low-pass :func:`fit_lowpass` tries (Butterworth, as IMU firmware designs them)."""


def lowpass_autocovariance(order: int, cutoff_hz: float, rate_hz: float, lags: int) -> FloatArray:
    """(lags,) autocovariance ``r(h) = Σ_k g_k g_{k+h}`` of unit-variance white noise through the low-pass
    (``g`` its impulse response, :func:`scipy.signal.butter`; ``r(0) = ∫|H|²`` the per-sample variance it
    leaves, ``Σ_h r(h) = |H(0)|² = 1`` the level of long averages)."""
    from scipy.signal import butter, sosfilt

    # The slowest pole's envelope decays by e per 1/(2π f_c sin(π/2n)) s: 40 of those leave nothing.
    tail = int(np.ceil(40.0 * rate_hz / (2.0 * np.pi * cutoff_hz * np.sin(np.pi / (2 * order)))))
    n = lags + tail
    impulse = np.zeros(n)
    impulse[0] = 1.0
    g = sosfilt(butter(order, cutoff_hz, fs=rate_hz, output="sos"), impulse)
    spec = np.fft.rfft(g, 2 * n)
    out: FloatArray = np.fft.irfft(np.abs(spec) ** 2, 2 * n)[:lags]
    return out


def lowpass_mean_variance(order: int, cutoff_hz: float, rate_hz: float, n: int) -> float:
    """Variance of the mean of ``n`` consecutive samples of unit-variance white noise through the low-pass:
    ``(n r(0) + 2 Σ_{h<n} (n − h) r(h)) / n²`` (:func:`lowpass_autocovariance`)."""
    r = lowpass_autocovariance(order, cutoff_hz, rate_hz, n)
    h = np.arange(1, n)
    return float((n * r[0] + 2.0 * np.sum((n - h) * r[1:])) / (n * n))


def gm_mean_variance(phi: FloatArray, n: int) -> FloatArray:
    """Variance of the mean of ``n`` consecutive samples of a unit first-order Gauss–Markov sequence (coefficient ``φ``)."""
    p = np.asarray(phi, float)
    q = np.clip(1.0 - p, 1e-12, None)
    var_sum = n * (1.0 + p) / q - 2.0 * p * (1.0 - p**n) / q**2
    out: FloatArray = var_sum / (n * n)
    return out


@dataclass(frozen=True)
class NoiseColour:
    """Short-lag colour of one triad's noise: white plus a sum of first-order Gauss–Markov terms per axis.

    Attributes
    ----------
    white_sd_si : (3,) per-sample sd of the white part, SI.
    sigma_si : (3, m) per-sample sd of each term, SI (0 for a term not selected).
    tau_s : (3, m) its correlation time, s.
    lr : (3, m) the likelihood ratio with which each term joined (0 when not selected).
    threshold : the ratio a term had to exceed.
    level_ratio : (3,) the model's noise level for long averages over its per-sample level
        (``√(1 + 2Σρ)``: 1 for white noise).
    """

    white_sd_si: FloatArray
    sigma_si: FloatArray
    tau_s: FloatArray
    lr: FloatArray
    threshold: float
    level_ratio: FloatArray

    @property
    def variance_si(self) -> FloatArray:
        """(3,) the terms' per-sample variance, SI²."""
        out: FloatArray = np.sum(self.sigma_si**2, axis=1)
        return out


def _whittle_fit(
    design: FloatArray,
    pgram: FloatArray,
    n_seg: int,
    max_iter: int = 60,
    offset: float = 0.0,
) -> tuple[FloatArray, float]:
    """Variances ``θ ≥ 0`` of ``S = design θ + offset`` maximizing the Whittle likelihood of a mean periodogram over ``n_seg`` pieces.

    ``−ℓ = n Σ_j [ln S_j + Ī_j / S_j]``; projected Fisher scoring (information
    ``n Σ_j a_j a_jᵀ / S_j²``), each step halved until the likelihood improves.
    ``offset``: a known floor of every bin (an output grid's rounding, white after any filter).
    """
    theta = np.zeros(design.shape[1])
    theta[0] = max(float(np.mean(pgram)) - offset, 1e-12 * float(np.mean(pgram))) / float(
        np.mean(design[:, 0])
    )

    def nll(th: FloatArray) -> float:
        s = design @ th + offset
        return float(n_seg * np.sum(np.log(s) + pgram / s))

    cur = nll(theta)
    for _ in range(max_iter):
        s = design @ theta + offset
        grad = n_seg * design.T @ (1.0 / s - pgram / s**2)
        info = n_seg * (design / s[:, None] ** 2).T @ design
        free = (theta > 0.0) | (grad < 0.0)
        step = np.zeros_like(theta)
        f = np.flatnonzero(free)
        sub = info[np.ix_(f, f)] + 1e-12 * np.trace(info) * np.eye(f.size)
        step[f] = np.linalg.solve(sub, -grad[f])
        t = 1.0
        while t > 1e-6:
            cand = np.maximum(theta + t * step, 0.0)
            if np.all(design @ cand + offset > 0.0) and (new := nll(cand)) <= cur:
                break
            t *= 0.5
        else:
            break
        done = cur - new < 1e-9 * abs(cur)
        theta, cur = cand, new
        if done:
            break
    return theta, cur


def fit_noise_colour(
    records: list[FloatArray],
    rate_hz: float,
    segment: int,
    threshold: float,
    *,
    max_tau_s: float,
    max_terms: int = 2,
    n_tau: int = 24,
) -> NoiseColour:
    """White noise plus up to ``max_terms`` Gauss–Markov terms per axis, selected on the periodogram of the static records.

    The periodogram of ``segment``-sample pieces (:func:`segment_periodogram`)
    pooled over the records, with the Whittle likelihood (each bin of a mean
    over ``n`` pieces is ``S·χ²_{2n}/2n``); the model's expectation per bin is
    exact for the finite piece (:func:`gauss_markov_periodogram`). Forward
    selection, as the audit's variance effects: a term (its variance and
    correlation time, profiled on a log grid from a quarter sample to
    ``max_tau_s``, then refined between the grid's neighbours) joins when its
    likelihood ratio exceeds ``threshold`` (χ² with two degrees of freedom at
    the caller's false-naming rate); repeat.
    """
    from scipy.optimize import minimize_scalar

    pgram, n_seg = segment_periodogram(records, segment)
    k = pgram.shape[1]
    log_taus = np.linspace(np.log(0.25 / rate_hz), np.log(max_tau_s), n_tau)

    def shape(log_tau: float) -> FloatArray:
        return gauss_markov_periodogram(float(np.exp(-1.0 / (rate_hz * np.exp(log_tau)))), segment)

    shapes = [shape(v) for v in log_taus]
    sigma, tau_out, lrs = (
        np.zeros((k, max_terms)),
        np.ones((k, max_terms)),
        np.zeros((k, max_terms)),
    )
    ratio, white = np.ones(k), np.zeros(k)
    for i in range(k):
        design = np.ones((pgram.shape[0], 1))
        theta, cur = _whittle_fit(design, pgram[:, i], n_seg)
        chosen: list[float] = []
        for _ in range(max_terms):

            def nll(log_tau: float, design: FloatArray = design, i: int = i) -> float:
                return _whittle_fit(np.column_stack([design, shape(log_tau)]), pgram[:, i], n_seg)[
                    1
                ]

            grid = [
                _whittle_fit(np.column_stack([design, sh]), pgram[:, i], n_seg)[1] for sh in shapes
            ]
            j = int(np.argmin(grid))
            best = minimize_scalar(
                nll,
                bounds=(log_taus[max(j - 1, 0)], log_taus[min(j + 1, n_tau - 1)]),
                method="bounded",
                options={"xatol": 1e-3},
            )
            log_tau = float(best.x) if best.fun < grid[j] else float(log_taus[j])
            new_theta, new = _whittle_fit(
                np.column_stack([design, shape(log_tau)]), pgram[:, i], n_seg
            )
            lr = 2.0 * (cur - new)
            if lr <= threshold or new_theta[-1] <= 0.0:
                break
            design = np.column_stack([design, shape(log_tau)])
            theta, cur = new_theta, new
            chosen.append(float(np.exp(log_tau)))
            lrs[i, len(chosen) - 1] = lr
        phi = np.exp(-1.0 / (rate_hz * np.array(chosen)))
        white[i], sigma[i, : len(chosen)] = np.sqrt(theta[0]), np.sqrt(theta[1:])
        tau_out[i, : len(chosen)] = chosen
        total = float(np.sum(theta))
        if total > 0.0:
            ratio[i] = np.sqrt((theta[0] + np.sum(theta[1:] * (1.0 + phi) / (1.0 - phi))) / total)
    return NoiseColour(white, sigma, tau_out, lrs, threshold, ratio)


def lowpass_spread_share(order: int, cutoff_hz: float, rate_hz: float, window: int) -> float:
    """What :func:`sample_noise_sd` reads, squared, of unit-variance white noise through the low-pass.

    About a centred moving mean of ``w`` samples a sample keeps ``r(0) − (2/w) Σ_j r(|j|) + V_w`` (``j`` its
    offsets in the window, ``V_w`` the window mean's variance, :func:`lowpass_mean_variance`), read over
    ``1 − 1/w``: below ``r(0)`` by about the mean's share ``1/w`` of the input (white noise's ``r(0) = 1``
    hides that in the ``1 − 1/w``).
    """
    r = lowpass_autocovariance(order, cutoff_hz, rate_hz, window)
    offsets = np.abs(np.arange(window) - window // 2)
    kept = (
        r[0]
        - 2.0 * float(np.mean(r[offsets]))
        + lowpass_mean_variance(order, cutoff_hz, rate_hz, window)
    )
    return float(kept / (1.0 - 1.0 / window))


LOWPASS_SKIP_BINS = 3
"""Lowest bins of the tapered periodogram :func:`fit_lowpass` leaves out: the taper's own width (its transform
spans three bins of 0), where the pieces' means and anything slower than a piece lie."""
LOWPASS_GRID = 24
"""Cut-offs on :func:`fit_lowpass`'s log grid per order (refined between the best one's neighbours)."""
LOWPASS_INTERVAL_LR = 3.84
"""Profile-likelihood drop that bounds the low-pass's stated cut-off and orders: χ²₁ at 95 %."""
LOWPASS_JACKKNIFE_GROUPS = 8
"""Groups of records the low-pass's cut-off is refitted without, one at a time (its jackknife variance)."""


@dataclass(frozen=True)
class LowPassFit:
    """The firmware low-pass one triad's static noise went through (:func:`fit_lowpass`).

    Attributes
    ----------
    order, cutoff_hz : the Butterworth filter of highest likelihood.
    cutoff_interval_hz : (low, high) the cut-offs of that order within :data:`LOWPASS_INTERVAL_LR` of it (95 %),
        the likelihood scaled by ``information_share`` (then Student's t² with the jackknife's G − 1 degrees of
        freedom in place of χ²₁); an end of the tried band where it does not fall that far.
    orders_consistent : the orders whose best fit lies within the same limit of the best (scaled alike).
    information_share : the Whittle likelihood's variance of ``ln f_c`` over its jackknife variance, at most 1
        (the periodogram's bins are not independent where the spectrum falls steeply: the likelihood alone
        overstates what they tell); 1 when not asked for.
    lr : ``2(ℓ₁ − ℓ₀)`` against white noise (the three axes' Whittle likelihoods summed), 0 where white fits
        better (the bilinear filter's zero at Nyquist keeps even the highest cut-off tried off white noise).
    lr_by_order : (len(orders),) each order's best ``lr`` (0 likewise).
    input_sd_si : (3,) per-sample sd of the white noise before the filter, SI (the level long averages keep).
    freq_hz : (K,) the periodogram's frequencies; pgram_si2 : (K, 3) its mean in per-sample units (white
        noise of sd σ gives σ² in every bin); fitted_si2 : (K, 3) the fitted filter's expectation plus the floor.
    band_hz : (low, high) the cut-offs tried.
    """

    order: int
    cutoff_hz: float
    cutoff_interval_hz: tuple[float, float]
    orders_consistent: tuple[int, ...]
    information_share: float
    lr: float
    lr_by_order: FloatArray
    input_sd_si: FloatArray
    freq_hz: FloatArray
    pgram_si2: FloatArray
    fitted_si2: FloatArray
    band_hz: tuple[float, float]


def fit_lowpass(
    records: list[FloatArray],
    rate_hz: float,
    segment: int,
    floor_var_si2: FloatArray,
    *,
    orders: tuple[int, ...] = LOWPASS_ORDERS,
    interval_above: float = 0.0,
) -> LowPassFit:
    """White noise through a Butterworth low-pass (order, cut-off) against white noise, on the periodogram of the static records.

    The tapered periodogram of ``segment``-sample pieces (:func:`segment_periodogram`) pooled over the
    records, from its bin :data:`LOWPASS_SKIP_BINS` + 1 on (below, a wander or a hand's wobble far above the
    noise leaks, and it is no filter's business); per axis the Whittle likelihood (:func:`_whittle_fit`) of ``S_j = θ_i E_j(n, f_c) +
    q_i²/12``: ``E_j`` the filter's exact expectation for the finite piece (:func:`fejer_periodogram`
    of :func:`lowpass_autocovariance`), ``θ_i`` the input's per-sample variance, the floor the output
    grid's rounding (``floor_var_si2`` (3,), white after the filter; 0 off a grid). The filter is
    the same on the three axes (one firmware filter per triad): their likelihoods are summed and the
    cut-off profiled on a log grid from the first bin fitted to 0.45 of the rate, then refined; each order of
    ``orders`` likewise. The null is white noise, ``S_j = θ_i + q_i²/12``.

    The cut-off's interval and the orders consistent with the data are read from the likelihood scaled
    by the share of its information the data bear out: the cut-off refitted without each of
    :data:`LOWPASS_JACKKNIFE_GROUPS` groups of records (jackknife variance of ``ln f_c``) against the
    likelihood's curvature, for a fit whose LR exceeds ``interval_above`` (a filter that will be named;
    below it the likelihood as it is: nothing is stated of a filter that is not there).
    """
    from scipy.optimize import brentq, minimize_scalar
    from scipy.stats import t as student_t

    floor = np.asarray(floor_var_si2, float)
    low, high = (LOWPASS_SKIP_BINS + 1) * rate_hz / segment, 0.45 * rate_hz
    grid = np.linspace(np.log(low), np.log(high), LOWPASS_GRID)

    def periodogram(recs: list[FloatArray]) -> tuple[FloatArray, int]:
        pgram, n_seg = segment_periodogram(recs, segment, taper=True)
        return pgram[LOWPASS_SKIP_BINS:], n_seg

    def expectation(order: int, log_fc: float) -> FloatArray:
        r = lowpass_autocovariance(order, float(np.exp(log_fc)), rate_hz, segment)
        return fejer_periodogram(r, segment, taper=True)[LOWPASS_SKIP_BINS:, None]

    def nll_of(pgram: FloatArray, n_seg: int) -> Callable[[int, float], float]:
        def nll(order: int, log_fc: float) -> float:
            e = expectation(order, log_fc)
            return float(
                sum(
                    _whittle_fit(e, pgram[:, i], n_seg, offset=floor[i])[1]
                    for i in range(pgram.shape[1])
                )
            )

        return nll

    def refine(
        nll: Callable[[int, float], float], order: int, lo: float, hi: float
    ) -> tuple[float, float]:
        opt = minimize_scalar(
            lambda v: nll(order, v), bounds=(lo, hi), method="bounded", options={"xatol": 1e-4}
        )
        return float(opt.x), float(opt.fun)

    pgram, n_seg = periodogram(records)
    nll = nll_of(pgram, n_seg)
    ones = np.ones((pgram.shape[0], 1))
    null = sum(
        _whittle_fit(ones, pgram[:, i], n_seg, offset=floor[i])[1] for i in range(pgram.shape[1])
    )
    best: list[tuple[float, float]] = []
    for order in orders:
        values = [nll(order, v) for v in grid]
        j = int(np.argmin(values))
        fine = refine(nll, order, grid[max(j - 1, 0)], grid[min(j + 1, grid.size - 1)])
        best.append(fine if fine[1] < values[j] else (grid[j], values[j]))
    nlls = np.array([b[1] for b in best])
    m = int(np.argmin(nlls))
    order, (log_fc, top) = orders[m], best[m]
    share, jackknifed = 1.0, False
    if 2.0 * (null - top) > interval_above:
        # The likelihood's variance of ln f_c from its curvature; the data's from the jackknife.
        h = 1e-3
        curv = (nll(order, log_fc + h) - 2.0 * top + nll(order, log_fc - h)) / h**2
        groups = [records[g::LOWPASS_JACKKNIFE_GROUPS] for g in range(LOWPASS_JACKKNIFE_GROUPS)]
        if curv > 0 and all(groups):
            loo = np.array(
                [
                    refine(
                        nll_of(
                            *periodogram([r for k, g in enumerate(groups) if k != left for r in g])
                        ),
                        order,
                        max(log_fc - 0.5, grid[0]),
                        min(log_fc + 0.5, grid[-1]),
                    )[0]
                    for left in range(LOWPASS_JACKKNIFE_GROUPS)
                ]
            )
            g = LOWPASS_JACKKNIFE_GROUPS
            var_jack = (g - 1) / g * float(np.sum((loo - loo.mean()) ** 2))
            share = float(min(1.0, (1.0 / curv) / max(var_jack, 1e-300)))
            jackknifed = True

    # The jackknife's variance has G − 1 degrees of freedom: Student's quantile, not the normal one.
    limit = (
        float(student_t.ppf(0.975, LOWPASS_JACKKNIFE_GROUPS - 1)) ** 2
        if jackknifed
        else LOWPASS_INTERVAL_LR
    )

    def drop(v: float) -> float:
        return 2.0 * share * (nll(order, v) - top) - limit

    ends = [
        float(np.exp(edge if drop(edge) <= 0 else brentq(drop, *sorted((log_fc, edge)), xtol=1e-4)))
        for edge in (grid[0], grid[-1])
    ]
    e = expectation(order, log_fc)
    theta = np.array(
        [_whittle_fit(e, pgram[:, i], n_seg, offset=floor[i])[0][0] for i in range(pgram.shape[1])]
    )
    return LowPassFit(
        order,
        float(np.exp(log_fc)),
        (ends[0], ends[1]),
        tuple(o for o, v in zip(orders, nlls, strict=True) if 2.0 * share * (v - top) <= limit),
        share,
        max(float(2.0 * (null - top)), 0.0),
        np.clip(2.0 * (null - nlls), 0.0, None),
        np.sqrt(theta),
        np.arange(LOWPASS_SKIP_BINS + 1, LOWPASS_SKIP_BINS + pgram.shape[0] + 1)
        * rate_hz
        / segment,
        pgram,
        e * theta[None, :] + floor[None, :],
        (low, high),
    )
