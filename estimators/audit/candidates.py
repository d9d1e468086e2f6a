"""Candidate effects fitted at the position level, and the selection criterion (issue 4, step 4).

Criterion. An effect is selected when two tests agree:

1. **Held-out positions**: the leave-one-position-out residual (exact for
   linear least squares through the hat matrix, ``e_k / (1 − h_kk)``) must be
   smaller with the effect than without it;
2. **Likelihood ratio** ``LR`` above its quantile at a family-wise
   false-naming rate of :data:`FAMILY_ALPHA` split over the candidates tried
   (Bonferroni): for mean effects the exact F test (the residual scale is
   estimated, ``n − p − k`` degrees of freedom; the χ² limit is far too
   liberal in the tail at 20–40 positions), for variance effects χ² with one
   degree of freedom (conservative at the boundary ``v = 0``).

Why both: the held-out criterion alone behaves like AIC and names a spurious
one-parameter effect about 15 % of the time; BIC's ``ln n`` penalty is about
6 % per candidate at 38 positions, i.e. ~40 % over a dozen candidates. The
Bonferroni quantile states the false-naming rate the audit promises. The
``score`` of a candidate is ``LR − threshold`` (selected when > 0 and the
held-out residual improves).

Effects (``y`` the baseline scalar residual of M1 per position, accelerometers;
gyro candidates use the gyro position means, since a MEMS gyro's scalar is not
observable against the Earth rate):

* ``bias_drift``: per axis, ``∂f/∂b_i·(t_k − t_0)`` (accel), ``t_k`` on a gyro mean;
* ``temperature_bias`` / ``temperature_scale``: per axis, ``∂f/∂b_i·ΔT_k`` /
  ``∂f/∂e_i·ΔT_k`` (M3); gyro: ``ΔT_k`` on the mean;
* ``scale_nonlinearity``: per axis, ``∂f/∂e_i·[ã_i, ã_i²]`` (M3's K2, K3: ``y_i(1 + K2 y_i + K3 y_i²)``);
* ``g_sensitivity``: per gyro axis, the mean on ``[1, f_x, f_y, f_z]`` (M4);
* ``bias_instability``: a variance that does not average down: residual
  variance ``σ_k² + v`` against ``σ_k²`` (accel); gyro per axis likewise on
  the means;
* ``nonstatic_positions``: motion inside positions turns the sensed direction,
  so it adds half-to-half differences *perpendicular* to gravity; tested as
  extra perpendicular variance beyond an isotropic (sensor) excess, the latter
  measured along gravity (where a small turn changes nothing to first order);
* ``quantization``: read from the output grid (:func:`estimators.noise.quantization_step`), part of the baseline;
* ``gravity_mismatch``: a wrong local g is a common scale error of the three
  accelerometers, absorbed by ``e_x, e_y, e_z``: identifiable only against a passport.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2
from scipy.stats import f as f_dist

from estimators.conventions import AXES, EARTH_RATE_RPS, Triad

from .statistics import PositionTable

FAMILY_ALPHA = 0.01
"""Family-wise probability of naming any effect on a session the baseline explains."""

MIN_TEMP_SPAN_C = 2.0
"""Temperature span below which temperature effects are not identifiable, °C."""

CANDIDATE_NAMES = (
    "bias_instability",
    "bias_drift",
    "temperature_bias",
    "temperature_scale",
    "scale_nonlinearity",
    "g_sensitivity",
    "quantization",
    "gravity_mismatch",
    "nonstatic_positions",
)


@dataclass(frozen=True)
class Candidate:
    """One effect fitted on one triad (and axis).

    Attributes
    ----------
    effect, triad, axis : what and where (axis None for a triad-level effect).
    identifiable : False when the data cannot tell (``reason`` says why).
    lr : likelihood-ratio statistic; threshold : its selection quantile.
    cv_ratio : held-out residual with / without the effect (< 1: better).
    params : fitted parameters (normalized units named in the keys).
    selected : the criterion's verdict.
    reason : one line of evidence or why not identifiable.
    """

    effect: str
    triad: Triad
    axis: str | None
    identifiable: bool
    lr: float = 0.0
    threshold: float = float("inf")
    cv_ratio: float = 1.0
    params: dict = field(default_factory=dict)
    selected: bool = False
    reason: str = ""

    @property
    def score(self) -> float:
        return self.lr - self.threshold

    def to_dict(self) -> dict:
        return {
            "effect": self.effect,
            "triad": self.triad.value,
            "axis": self.axis,
            "identifiable": self.identifiable,
            "score": float(self.score) if self.identifiable and np.isfinite(self.score) else None,
            "lr": float(self.lr),
            "threshold": None if not np.isfinite(self.threshold) else float(self.threshold),
            "cv_ratio": float(self.cv_ratio),
            "params": self.params,
            "selected": self.selected,
            "reason": self.reason,
        }


def _loo_rss(a: np.ndarray, z: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(RSS, leave-one-out RSS, coefficients) of the weighted least squares ``z ≈ a θ``."""
    q, _ = np.linalg.qr(a)
    coef, *_ = np.linalg.lstsq(a, z, rcond=None)
    e = z - a @ coef
    h = np.einsum("ij,ij->i", q, q)
    loo = e / np.clip(1.0 - h, 1e-9, None)
    return float(e @ e), float(loo @ loo), coef


def mean_test(base: np.ndarray, extra: np.ndarray, z: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Likelihood ratio (common scale free), held-out ratio, the extra coefficients and their standard errors.

    ``base`` (n, p) and ``extra`` (n, k) are already weighted regressors, ``z`` (n,) the weighted data.
    The standard errors take the weights as exact (the detection scale of the effect).
    """
    rss0, loo0, _ = _loo_rss(base, z)
    full = np.hstack([base, extra])
    rss1, loo1, coef = _loo_rss(full, z)
    n = z.size
    lr = float(n * np.log(rss0 / max(rss1, 1e-300)))
    r = np.linalg.qr(full, mode="r")
    rinv = np.linalg.solve(r, np.eye(r.shape[0]))
    se = np.sqrt(np.sum(rinv**2, axis=1))
    k = base.shape[1]
    return lr, loo1 / loo0, coef[k:], se[k:]


def excess_variance(r: np.ndarray, var0: np.ndarray) -> tuple[float, float]:
    """ML extra variance ``v ≥ 0`` of ``r ~ N(0, var0 + v)`` and its likelihood ratio against ``v = 0``."""

    def nll(v):
        s = var0 + v
        return 0.5 * np.sum(np.log(s) + r * r / s)

    top = max(float(np.mean(r * r)) * 4.0, 1e-30)
    # The tolerance must be relative: normalized variances are ~1e-8, far below the default absolute 1e-5.
    v = float(minimize_scalar(nll, bounds=(0.0, top), method="bounded", options={"xatol": 1e-6 * top}).x)
    if nll(0.0) <= nll(v):
        v = 0.0
    return v, float(max(0.0, 2.0 * (nll(0.0) - nll(v))))


@dataclass(frozen=True)
class MeanTest:
    """One mean-structure candidate's last test (see :func:`forward_select`)."""

    lr: float
    threshold: float
    cv_ratio: float
    coef: np.ndarray
    se: np.ndarray
    selected: bool


def forward_select(base: np.ndarray, z: np.ndarray, regs: dict, n_tests: int) -> dict:
    """Greedy forward selection of mean effects (weighted columns ``regs[key]`` (n, k)).

    Every remaining candidate is tested against the baseline plus the effects
    already selected; the one with the largest margin over its threshold that
    also lowers the held-out residual joins; repeat until none does. A sibling
    that only rides on a selected effect's correlation (e.g. ``temperature_scale``
    next to ``temperature_bias`` of the same axis) is then judged on what it adds.
    """
    tests: dict = {}
    current = base
    remaining = list(regs)
    while remaining:
        for key in remaining:
            lr, cv, coef, se = mean_test(current, regs[key], z)
            tests[key] = MeanTest(lr, _threshold_mean(regs[key].shape[1], z.size, current.shape[1], n_tests), cv, coef, se, False)
        passing = [k for k in remaining if tests[k].lr > tests[k].threshold and tests[k].cv_ratio < 1.0]
        if not passing:
            break
        best = max(passing, key=lambda k: tests[k].lr - tests[k].threshold)
        t = tests[best]
        tests[best] = MeanTest(t.lr, t.threshold, t.cv_ratio, t.coef, t.se, True)
        current = np.hstack([current, regs[best]])
        remaining.remove(best)
    return tests


def excess_after(base: np.ndarray, chosen: np.ndarray, z: np.ndarray, var0: np.ndarray) -> tuple[float, float]:
    """Extra variance (and its LR) of the residual left after the baseline and the chosen mean effects.

    ``base`` (n, p), ``chosen`` (n, k) and ``z`` are weighted by ``1/√var0``; each
    residual is divided by ``√(1 − h)`` (its leverage) so the fitted columns do
    not pass for a deficit of variance.
    """
    a = np.hstack([base, chosen])
    q, _ = np.linalg.qr(a)
    coef, *_ = np.linalg.lstsq(a, z, rcond=None)
    h = np.einsum("ij,ij->i", q, q)
    r = (z - a @ coef) * np.sqrt(var0) / np.sqrt(np.clip(1.0 - h, 1e-3, None))
    return excess_variance(r, var0)


def not_identifiable(effect: str, triad: Triad, axis: str | None, reason: str) -> Candidate:
    return Candidate(effect, triad, axis, False, reason=reason)


def temperature_reason(tab: PositionTable) -> str | None:
    """Why temperature effects are not identifiable on this table, or None when they are."""
    if tab.temp_c is None:
        return "not identifiable: the session has no temperature"
    span = float(np.ptp(tab.temp_c))
    if span < MIN_TEMP_SPAN_C:
        return f"not identifiable: temperature spans {span:.2f} °C (< {MIN_TEMP_SPAN_C} °C)"
    return None


def _threshold(k: int, n_tests: int) -> float:
    return float(chi2.isf(FAMILY_ALPHA / max(n_tests, 1), k))


def _threshold_mean(k: int, n: int, p: int, n_tests: int) -> float:
    """LR threshold of a mean effect: the exact F test (scale estimated from ``n − p − k`` dof) written as ``n ln(RSS0/RSS1)``."""
    dof = n - p - k
    if dof < 1:
        return float("inf")
    crit = float(f_dist.isf(FAMILY_ALPHA / max(n_tests, 1), k, dof))
    return float(n * np.log1p(k * crit / dof))


def accel_candidates(tab: PositionTable, params: np.ndarray, jac: np.ndarray, residual: np.ndarray, sigma: np.ndarray, n_tests: int) -> list[Candidate]:
    """Candidates of the accelerometer triad from the baseline fit (module docstring)."""
    tri = Triad.ACCEL
    out: list[Candidate] = []
    var0 = sigma**2
    # Weights of the mean tests carry a provisional excess so unexplained scatter cannot pass for structure.
    v, _ = excess_after(jac / sigma[:, None], np.zeros((sigma.size, 0)), residual / sigma, var0)
    w = 1.0 / np.sqrt(var0 + v)
    base = jac * w[:, None]
    z = residual * w
    dt = tab.t_mid_s - tab.t_mid_s.mean()
    temp_reason = temperature_reason(tab)
    dtemp = None if temp_reason else tab.temp_c - tab.temp_c.mean()
    regs, keys = {}, {}
    for i, ax in enumerate(AXES):
        regs[("bias_drift", ax)] = jac[:, [i]] * dt[:, None]
        keys[("bias_drift", ax)] = ("rate_norm_per_s",)
        regs[("scale_nonlinearity", ax)] = jac[:, [3 + i]] * np.column_stack([tab.mean[:, i], tab.mean[:, i] ** 2])
        keys[("scale_nonlinearity", ax)] = ("k2_norm", "k3_norm")
        if dtemp is not None:
            regs[("temperature_bias", ax)] = jac[:, [i]] * dtemp[:, None]
            keys[("temperature_bias", ax)] = ("coef_norm_per_c",)
            regs[("temperature_scale", ax)] = jac[:, [3 + i]] * dtemp[:, None]
            keys[("temperature_scale", ax)] = ("coef_per_c",)
        else:
            out += [not_identifiable(n, tri, ax, temp_reason) for n in ("temperature_bias", "temperature_scale")]
    tests = forward_select(base, z, {k: x * w[:, None] for k, x in regs.items()}, n_tests)
    chosen = []
    for (name, ax), t in tests.items():
        # The baseline residual is f(p) ≈ J δp + x θ with θ the effect; f = −(model error) → sign flips.
        fitted = {k: float(-c) for k, c in zip(keys[(name, ax)], t.coef)} | {f"{k}_se": float(e) for k, e in zip(keys[(name, ax)], t.se)}
        if t.selected:
            chosen.append(regs[(name, ax)] / sigma[:, None])
        out.append(Candidate(name, tri, ax, True, t.lr, t.threshold, t.cv_ratio, fitted, t.selected,
                             f"position residuals follow the {name} regressor of axis {ax}: LR {t.lr:.1f} (threshold {t.threshold:.1f}), held-out ratio {t.cv_ratio:.3f}"))
    # Variance last: after the selected mean effects, so a deterministic effect is not also named as instability.
    extra = np.hstack(chosen) if chosen else np.zeros((sigma.size, 0))
    v, lr_v = excess_after(jac / sigma[:, None], extra, residual / sigma, var0)
    thr1 = _threshold(1, n_tests)
    out.insert(0, Candidate("bias_instability", tri, None, True, lr_v, thr1, 1.0, {"excess_sd_norm": float(np.sqrt(v))}, lr_v > thr1,
                            f"scalar residual scatter exceeds the white prediction by an extra sd of {np.sqrt(v):.3g} (normalized) that does not average down"))
    out.append(nonstatic_candidate(tab, n_tests))
    out.append(not_identifiable("gravity_mismatch", tri, None,
                                "not identifiable: a wrong local g is a common scale error absorbed by ex, ey, ez; needs a passport (known scale factors)"))
    return out


def nonstatic_candidate(tab: PositionTable, n_tests: int) -> Candidate:
    """Extra half-to-half variance perpendicular to gravity beyond an isotropic excess (module docstring)."""
    u = tab.mean / np.linalg.norm(tab.mean, axis=1, keepdims=True)
    helper = np.where(np.abs(u[:, [0]]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    p1 = np.cross(u, helper)
    p1 /= np.linalg.norm(p1, axis=1, keepdims=True)
    p2 = np.cross(u, p1)
    comp, var0, perp = [], [], []
    for basis, is_perp in ((u, False), (p1, True), (p2, True)):
        comp.append(np.einsum("ki,ki->k", tab.halves, basis))
        var0.append(4.0 * np.einsum("ki,kij,kj->k", basis, tab.cov, basis))
        perp.append(np.full(len(u), is_perp))
    d, v0, pp = np.concatenate(comp), np.concatenate(var0), np.concatenate(perp)
    # A small turn leaves the component along gravity unchanged (second order): it alone measures the sensor excess.
    iso, _ = excess_variance(d[~pp], v0[~pp])
    extra, lr = excess_variance(d[pp], v0[pp] + iso)
    thr = _threshold(1, n_tests)
    angle = float(np.sqrt(extra / 2.0))
    return Candidate("nonstatic_positions", Triad.ACCEL, None, True, lr, thr, 1.0,
                     {"perp_excess_sd_norm": float(np.sqrt(extra)), "isotropic_excess_sd_norm": float(np.sqrt(iso)), "angle_rms_rad": angle},
                     lr > thr,
                     f"half-to-half differences perpendicular to gravity exceed the isotropic excess by sd {np.sqrt(extra):.3g} (normalized): LR {lr:.1f} (threshold {thr:.1f})")


def gyro_candidates(tab: PositionTable, f_b_mps2: np.ndarray, n_tests: int) -> list[Candidate]:
    """Gyro candidates on the position means (M4); the Earth rate enters as extra variance ``Ω²/3``."""
    tri = Triad.GYRO
    out: list[Candidate] = []
    dt = tab.t_mid_s - tab.t_mid_s.mean()
    temp_reason = temperature_reason(tab)
    thr1 = _threshold(1, n_tests)
    for i, ax in enumerate(AXES):
        y = tab.mean[:, i]
        var0 = tab.cov[:, i, i] + 1.0 / 3.0  # the Earth rate (normalized: 1) on an axis of unknown heading
        w0 = 1.0 / np.sqrt(var0)
        v, _ = excess_after(w0[:, None], np.zeros((y.size, 0)), y * w0, var0)
        w = 1.0 / np.sqrt(var0 + v)
        base = w[:, None]
        regs = {"bias_drift": (dt[:, None], ("rate_rps_per_s",)), "g_sensitivity": (f_b_mps2, ("gx_rps_per_mps2", "gy_rps_per_mps2", "gz_rps_per_mps2"))}
        if temp_reason is None:
            regs["temperature_bias"] = ((tab.temp_c - tab.temp_c.mean())[:, None], ("coef_rps_per_c",))
        tests = forward_select(base, y * w, {k: x * w[:, None] for k, (x, _) in regs.items()}, n_tests)
        chosen = []
        for name, t in tests.items():
            keys = regs[name][1]
            fitted = {k: float(c * EARTH_RATE_RPS) for k, c in zip(keys, t.coef)} | {f"{k}_se": float(e * EARTH_RATE_RPS) for k, e in zip(keys, t.se)}
            if t.selected:
                chosen.append(regs[name][0] * w0[:, None])
            out.append(Candidate(name, tri, ax, True, t.lr, t.threshold, t.cv_ratio, fitted, t.selected,
                                 f"gyro {ax} position means follow the {name} regressor: LR {t.lr:.1f} (threshold {t.threshold:.1f}), held-out ratio {t.cv_ratio:.3f}"))
        extra = np.hstack(chosen) if chosen else np.zeros((y.size, 0))
        v, lr_v = excess_after(w0[:, None], extra, y * w0, var0)
        out.append(Candidate("bias_instability", tri, ax, True, lr_v, thr1, 1.0, {"excess_sd_norm": float(np.sqrt(v))}, lr_v > thr1,
                             f"gyro {ax} position means scatter beyond noise and Earth rate by sd {np.sqrt(v):.3g} Ω"))
        if temp_reason is not None:
            out.append(not_identifiable("temperature_bias", tri, ax, temp_reason))
        out.append(not_identifiable("temperature_scale", tri, ax, "not identifiable: the gyro scale needs a known rate (the Earth rate is below a MEMS gyro's noise)"))
        out.append(not_identifiable("scale_nonlinearity", tri, ax, "not identifiable: static positions give the gyros only the Earth rate"))
    return out
