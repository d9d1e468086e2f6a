"""Candidate effects fitted at the position level, and the selection criterion (issue 4, step 4).

Data. Two position-level records carry everything the candidates need:

* the **scalar residual** of the baseline fit per position (accelerometers,
  exact M1 equation, its predicted sigma from the position covariance), or the
  **position mean** per axis (gyros: a MEMS gyro's scalar is not observable
  against the Earth rate, which enters as an extra variance ``Ω²/3`` per axis);
* the **half-to-half difference** of each position's mean (first half minus
  second half; its predicted covariance is ``4×`` the covariance of the mean).

Criterion. An effect is selected when its test passes at a stated family-wise
false-naming rate :data:`FAMILY_ALPHA`, split over the candidates actually
tried (Bonferroni):

* **mean effects** (deterministic regressors: drift, temperature,
  non-linearity, g-sensitivity) by greedy forward selection: the exact F test
  written as ``LR = n ln(RSS₀/RSS₁)`` (the residual scale is estimated,
  ``n − p − k`` degrees of freedom; the χ² limit is far too liberal in the tail
  at 20–40 positions), **and** the leave-one-position-out residual (exact
  through the hat matrix, ``e_k/(1 − h_kk)``) must shrink: a held-out check no
  bigger model passes for free. The weights carry the variance excess left
  after the chosen effects, iterated to a fixed point (:func:`_means_with_excess`);
* **variance effects** (bias instability, motion inside positions) by greedy
  forward selection on the likelihood ratio of a variance-component model
  (:func:`fit_variance`, :func:`select_variance`), against χ² with as many
  degrees of freedom as components (conservative at the boundary ``θ = 0``,
  where the null law is a χ² mixture).

Disturbed positions. Motion in a few positions (a hand on the unit) is not a
wander of every position: after the fits, a position whose half-to-half
differences lie beyond the fitted model at the family-wise rate split over
tests and positions is flagged (:func:`disturbed_positions`), left out, and
everything is refitted (``nonstatic_positions`` then names the positions).

Reference noise. The variance of a position mean is taken as ``diag(σ²)/n``
with ``σ`` the baseline's noise for averages (batch means of the chain's batch
length, pooled over the session: :func:`estimators.audit.statistics.with_noise_cov`),
not the chain's per-position batch-means covariance: that one scatters by tens
of percent (ten batches in a 5 s position) and is pooled over the three axes,
so one axis' wander would inflate the others'.

Why not the held-out criterion alone: it behaves like AIC and names a spurious
one-parameter effect about 15 % of the time; BIC's ``ln n`` penalty is about 6 %
per candidate at 38 positions, i.e. ~40 % over a dozen candidates. The
Bonferroni quantile states the false-naming rate the audit promises. The
``score`` of a candidate is ``LR − threshold``.

Effects (``J`` = ∂f/∂params of the exact scalar equation, ``u`` the unit
direction of gravity in the sensor axes, ``ΔT`` temperature about its mean):

* ``bias_drift``: per axis, ``J_b_i·(t_k − t̄)`` (accel), ``t_k`` on a gyro mean;
* ``temperature_bias`` / ``temperature_scale``: per axis, ``J_b_i·ΔT_k`` /
  ``J_e_i·ΔT_k`` (M3); gyro: ``ΔT_k`` on the mean; only with a temperature
  span of at least :data:`MIN_TEMP_SPAN_C`;
* ``scale_nonlinearity``: per axis, ``J_e_i·[ã_i, ã_i²]`` (M3's K2, K3);
* ``cross_axis_nonlinearity``: for the triad, ``Σ_i J_b_i·ã_j ã_k`` (the second-order cross terms Kxy;
  the norm sees them only through ``u_x u_y u_z``, the same for every axis: :func:`cross_axis_effect`);
* ``temperature_hysteresis``: per axis, ``J_b_i·sign(dT/dt)_k`` (a bias that differs heating and cooling);
  on a gyro mean ``sign(dT/dt)_k``;
* ``bias_step`` / ``nonorthogonality_change``: per axis ``J_b_i`` (a gyro mean: 1), for the accelerometer
  triad ``J_d`` (three cosines), from position ``b`` on, profiled over the ``n − 1`` breaks (a knock or a
  mounting slip in a turn); the threshold splits the candidate's share of the rate over the breaks, the ranking uses the
  single test's margin (:func:`forward_select`): a deterministic effect is not beaten by one that
  explains less behind a lower threshold; once several are selected each break is re-profiled with the
  others refitted (:func:`_reprofiled`), and a change whose axis is not told is re-simulated on the alike
  axis of the smallest step (:func:`smallest_alike`);
* ``clipping``: samples held on a rail, read from the samples (:func:`clipping_candidates`);
* ``spectral_line``: a peak of the static samples' spectrum over its floor (:func:`line_candidates`);
* ``lowpass`` (noise colour): the static noise through a firmware Butterworth low-pass, order and
  cut-off fitted on its spectrum (:func:`lowpass_candidate`);
* ``g_sensitivity``: per gyro axis, the mean on the specific force ``[f_x, f_y, f_z]`` (M4),
  after the vertical Earth rate ``c·Ω·u_i`` with ``|c| ≤ 1`` (:func:`vertical_earth_rate`);
* ``bias_instability``: per sensor axis, bias wander that does not average
  down. Two variance components: ``w_i`` on the half-to-half differences along
  sensor axis ``i`` (wander inside a position) and ``v_i`` on the scalar
  residuals with weight ``J_b_i²`` (wander between positions; the scalar
  residual sees axis ``i`` through ``u_i²``, so the varied orientations tell
  the axes apart); 2 degrees of freedom;
* ``nonstatic_positions``: motion inside a position turns the sensed
  direction, so it adds half-to-half variance *perpendicular to gravity*
  (``p (I − u uᵀ)``) and leaves the norm (the scalar residual) alone, and the
  gyros see the turning rates on every axis (``q I`` on their halves); tested
  against the sensor-axis components above, which do not rotate with the unit;
* ``quantization``: read from the output grid (:func:`estimators.noise.quantization_step`), part of the baseline;
* ``gravity_mismatch``: a wrong local g is a common scale error of the three
  accelerometers, absorbed by ``e_x, e_y, e_z``: identifiable only against a passport.

For a selected ``bias_instability`` the extension needs a process: a
Gauss–Markov bias per axis whose two moments (inside and between positions)
match the data, fitted by :func:`fit_gauss_markov` on the same likelihood.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import numpy as np

# scipy is imported in the functions that use it: it takes a large part of a second to import, and
# `calibrate` imports this module (through the audit) for sessions the audit does not simulate too.
from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import AXES, EARTH_RATE_RPS, Triad
from estimators.noise import LOWPASS_ORDERS, fit_lowpass
from estimators.temperature import chosen_order, held_out_scores

from .statistics import PositionTable

CandidateParams: TypeAlias = dict[str, Any]
"""The fitted values of a candidate by key: numbers, or a [low, high] list for a band (JSON-ready)."""

FAMILY_ALPHA = 0.01
"""Family-wise probability of naming any effect on a session the baseline explains."""

MIN_TEMP_SPAN_C = 2.0
"""Temperature span below which temperature effects are not identifiable, °C."""

GM_MIN_TAU_WINDOWS = 1.0
"""Shortest correlation time of a fitted wander, in noise windows: anything faster is in the noise
reference itself (noise colour), and a Gauss–Markov fit pushed there would trade it for a per-sample
variance the data do not have."""

EARTH_RATE_VAR_NORM = 1.0 / 3.0
"""Variance of the Earth rate on one gyro axis of unknown heading, in units of Ω² (normalized)."""

CANDIDATE_NAMES = (
    "bias_instability",
    "bias_drift",
    "temperature_bias",
    "temperature_scale",
    "scale_nonlinearity",
    "cross_axis_nonlinearity",
    "bias_step",
    "nonorthogonality_change",
    "temperature_hysteresis",
    "clipping",
    "spectral_line",
    "lowpass",
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
    cv_ratio : held-out residual with / without the effect (< 1: better; 1 for variance effects).
    params : fitted parameters (units in the keys; ``_norm``: a fraction of the triad's reference).
    selected : the criterion's verdict.
    reason : one line of evidence or why not identifiable.
    in_baseline : the effect is part of the baseline fit (quantization on a grid), so it is not a cause.
    """

    effect: str
    triad: Triad
    axis: str | None
    identifiable: bool
    lr: float = 0.0
    threshold: float = float("inf")
    cv_ratio: float = 1.0
    params: CandidateParams = field(default_factory=dict)
    selected: bool = False
    reason: str = ""
    in_baseline: bool = False

    @property
    def score(self) -> float:
        return self.lr - self.threshold

    def to_dict(self) -> dict[str, Any]:
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
            "in_baseline": self.in_baseline,
            "reason": self.reason,
        }


# --- mean effects ------------------------------------------------------------


def _loo_rss(a: FloatArray, z: FloatArray) -> tuple[float, float, FloatArray]:
    """(RSS, leave-one-out RSS, coefficients) of the weighted least squares ``z ≈ a θ``."""
    q, _ = np.linalg.qr(a)
    coef = np.asarray(np.linalg.lstsq(a, z, rcond=None)[0], dtype=np.float64)
    e = z - a @ coef
    h = np.einsum("ij,ij->i", q, q)
    loo = e / np.clip(1.0 - h, 1e-9, None)
    return float(e @ e), float(loo @ loo), coef


def mean_test(
    base: FloatArray, extra: FloatArray, z: FloatArray, known_scale: bool = False
) -> tuple[float, float, FloatArray, FloatArray]:
    """Likelihood ratio, held-out ratio, the extra coefficients and their standard errors.

    ``base`` (n, p) and ``extra`` (n, k) are already weighted regressors, ``z`` (n,) the weighted data.
    The LR is the common scale's free (``n ln(RSS₀/RSS₁)``), or with ``known_scale`` the weights' own
    (``RSS₀ − RSS₁``, χ²ₖ under the null): then what another effect leaves does not dilute it.
    The standard errors take the weights as exact (the detection scale of the effect). An effect the
    positions cannot tell from the base (the joint design singular: a change at the last break of 12
    positions against nine parameters) has LR 0 and infinite standard errors: it cannot be named.
    """
    full = np.hstack([base, extra])
    # numpy's stub types every mode as QRResult; mode="r" returns R alone.
    r: FloatArray = np.linalg.qr(full, mode="r")  # type: ignore[assignment]
    diag = np.abs(np.diag(r))
    if full.shape[1] >= z.size or diag.min() <= 1e-10 * diag.max():
        return 0.0, 1.0, np.zeros(extra.shape[1]), np.full(extra.shape[1], np.inf)
    rss0, loo0, _ = _loo_rss(base, z)
    rss1, loo1, coef = _loo_rss(full, z)
    n = z.size
    lr = float(rss0 - rss1) if known_scale else float(n * np.log(rss0 / max(rss1, 1e-300)))
    rinv = np.linalg.solve(r, np.eye(r.shape[0]))
    se = np.sqrt(np.sum(rinv**2, axis=1))
    k = base.shape[1]
    return lr, loo1 / loo0, coef[k:], se[k:]


@dataclass(frozen=True)
class MeanTest:
    """One mean-structure candidate's last test (see :func:`forward_select`).

    ``rivals``: for a selected candidate, every candidate's LR in the round it joined (against the
    same model): a profiled change's likelihood over its breaks, for the interval of its time.
    ``rival_fits``: for a selected change, each rival's (coefficients, standard errors) against the same
    model (what the change would be on another axis at its break, :func:`alike_axes`).
    """

    lr: float
    threshold: float
    cv_ratio: float
    coef: FloatArray
    se: FloatArray
    selected: bool
    rivals: dict[int, float] = field(default_factory=dict)
    rival_fits: dict[int, tuple[FloatArray, FloatArray]] = field(default_factory=dict)


def forward_select(
    base: FloatArray,
    z: FloatArray,
    regs: dict[int, FloatArray],
    n_tests: int,
    multiplicity: dict[int, int] | None = None,
    known_scale: bool = False,
    changes: dict[int, object] | None = None,
) -> dict[int, MeanTest]:
    """Stepwise selection of mean effects (weighted columns ``regs[key]`` (n, k)), every step a joint refit.

    Forward: every remaining candidate is tested against the baseline plus the
    effects already selected; of those that pass their threshold and also lower
    the held-out residual, the one with the largest margin over the threshold of
    a single test joins. Backward: each selected effect is then tested against
    all the others (refitted jointly); while one fails, the one with the least
    margin leaves. Swap, when no effect joins: a selected effect is replaced by
    an unselected one that passes in its place with the larger margin (the
    forward step's ranking; on their own thresholds a profiled step would lose
    to a drift that explains less). Repeat until a set comes back. An effect
    chosen early can be a proxy of two that are there together (a step taking
    half of a drift, a change of the cosines half of a drift and half of a K2):
    once the others are in, it explains nothing of its own and leaves, and the
    effect it stood for is found in its place. The set kept is the one visited
    with the best joint fit less a single test's threshold per effect: a swap
    back to such a proxy, which then drops both, does not end the search on it.

    ``multiplicity[key]`` (default 1): the candidate is one of that many tried for
    one effect (a step profiled over the breaks between positions): its threshold
    splits its share of the family-wise rate over them, but it is ranked against
    the others on the single test's margin, so a profiled effect that explains
    more is not beaten by one with a lower threshold that explains less.

    ``known_scale``: the weights are the data's sd (:func:`mean_test`): each effect is tested on what
    it explains, not against a scale the others' leftovers inflate, so effects that are there
    together are found together; thresholds χ²ₖ at the same split rate.

    ``changes[key]``: which profiled change the candidate is one break of (its effect and axis). Once a
    change is selected next to others, every selected change's break is re-profiled with the others
    refitted, until none moves (:func:`_reprofiled`): the first change's break was fixed before a second
    joined, so a step on two axes at one turn was placed at two turns, each wrong.

    Every selected effect's test is the last joint one (against all the others); a change's ``rivals``
    are every candidate's LR against the same model, its own breaks' with the other changes re-profiled
    (:func:`_change_profile`, the profile of its break); an unselected candidate's test is against the
    final set.
    """
    mult = multiplicity or {}
    group = changes or {}

    def threshold(k: int, p: int, tests_: int) -> float:
        return _threshold(k, tests_) if known_scale else _threshold_mean(k, z.size, p, tests_)

    def test(key: int, given: list[int]) -> MeanTest:
        current = np.hstack([base, *(regs[j] for j in given)])
        lr, cv, coef, se = mean_test(current, regs[key], z, known_scale)
        k, p = regs[key].shape[1], current.shape[1]
        return MeanTest(lr, threshold(k, p, n_tests * mult.get(key, 1)), cv, coef, se, False)

    def single_margin(key: int, t: MeanTest, given: list[int]) -> float:
        p = base.shape[1] + sum(regs[j].shape[1] for j in given)
        return t.lr - threshold(regs[key].shape[1], p, n_tests)

    def passes(t: MeanTest) -> bool:
        return t.lr > t.threshold and t.cv_ratio < 1.0

    def score(sel: list[int]) -> float:
        """The joint fit's LR less a single test's threshold per effect; −∞ when one fails against the others."""
        if not sel:
            return 0.0
        if any(not passes(test(k, [j for j in sel if j != k])) for k in sel):
            return -np.inf
        lr = mean_test(base, np.hstack([regs[j] for j in sel]), z, known_scale)[0]
        return lr - sum(threshold(regs[j].shape[1], base.shape[1], n_tests) for j in sel)

    selected: list[int] = []
    seen: set[frozenset[int]] = {frozenset()}
    best: tuple[float, list[int]] = (0.0, [])
    while True:
        outside = [k for k in regs if k not in selected]
        tests = {k: test(k, selected) for k in outside}
        passing = [k for k in outside if passes(tests[k])]
        if passing:
            selected = [*selected, max(passing, key=lambda k: single_margin(k, tests[k], selected))]
        else:
            selected = _swapped(selected, regs, test, passes, single_margin)
        selected = _reprofiled(selected, group, test)
        while len(selected) > 1:
            joint = {k: test(k, [j for j in selected if j != k]) for k in selected}
            failing = [k for k in selected if not passes(joint[k])]
            if not failing:
                break
            selected.remove(
                min(
                    failing,
                    key=lambda k: single_margin(k, joint[k], [j for j in selected if j != k]),
                )
            )
        if frozenset(selected) in seen:
            break
        seen.add(frozenset(selected))
        best = max(best, (score(selected), selected), key=lambda b: b[0])
    selected = best[1]
    out = {k: test(k, selected) for k in regs if k not in selected}
    for k in selected:
        others = [j for j in selected if j != k]
        t = test(k, others)
        if mult.get(k, 1) > 1:
            fits = {j: test(j, others) for j in regs if j not in others}
            rivals = _change_profile(k, others, {j: u.lr for j, u in fits.items()}, group, test)
            rival_fits = {j: (u.coef, u.se) for j, u in fits.items()}
        else:
            rivals, rival_fits = {}, {}
        out[k] = MeanTest(t.lr, t.threshold, t.cv_ratio, t.coef, t.se, True, rivals, rival_fits)
    return out


def _reprofiled(
    selected: list[int], group: dict[int, object], test: Callable[[int, list[int]], MeanTest]
) -> list[int]:
    """``selected`` with each change (``group``: the breaks of one change) moved to the break of the largest LR
    against the others refitted, until none moves. Each move raises the joint fit (the LR against the
    same others ranks the joint fits), so the loop ends; alone, a change already sits at its best break."""
    out = list(selected)
    moved = len(out) > 1
    while moved:
        moved = False
        for i, s in enumerate(out):
            if s not in group:
                continue
            others = out[:i] + out[i + 1 :]
            tried = {
                c: test(c, others).lr for c in group if group[c] == group[s] and c not in others
            }
            best = max(tried, key=lambda c: tried[c])
            if tried[best] > tried[s]:
                out[i], moved = best, True
    return out


def _change_profile(
    k: int,
    others: list[int],
    lrs: dict[int, float],
    group: dict[int, object],
    test: Callable[[int, list[int]], MeanTest],
) -> dict[int, float]:
    """The rivals of the selected change ``k``: every candidate's LR against ``others`` (``lrs``), its own breaks'
    profiled: at each break of ``k``'s change, the best joint fit over the breaks of each other selected
    change (one moved at a time), less the fit of ``others``. With the other change held at its break, a
    step on two axes at one turn had a profile that peaked where the other was put and excluded the turn."""
    rivals = dict(lrs)
    for o in (o for o in others if o in group):
        rest = [j for j in others if j != o]
        own = test(o, rest).lr
        for c in (c for c in group if group[c] == group[o] and c != o and c not in rest):
            # LRs add along a chain of nested fits: J(rest + c + j) − J(others) = LR(c | rest) − LR(o | rest) + LR(j | rest + c).
            shift = test(c, rest).lr - own
            for j in (j for j in rivals if group.get(j) == group.get(k) and j != c):
                rivals[j] = max(rivals[j], shift + test(j, [*rest, c]).lr)
    return rivals


def _swapped(
    selected: list[int],
    regs: dict[int, FloatArray],
    test: Callable[[int, list[int]], MeanTest],
    passes: Callable[[MeanTest], bool],
    margin: Callable[[int, MeanTest, list[int]], float],
) -> list[int]:
    """``selected`` with the one exchange of a selected effect for an unselected one that most raises the
    joint fit (:func:`forward_select`), or unchanged when none does: the new effect passes against the
    others, and its ``margin`` (the forward step's ranking) exceeds the old one's."""
    best, gain = None, 0.0
    for s in selected:
        others = [j for j in selected if j != s]
        own = margin(s, test(s, others), others)
        for c in regs:
            if c in selected:
                continue
            t = test(c, others)
            if passes(t) and margin(c, t, others) - own > gain:
                best, gain = (s, c), margin(c, t, others) - own
    if best is None:
        return selected
    return [best[1] if j == best[0] else j for j in selected]


def leverage_residual(design: FloatArray, data: FloatArray, sd: FloatArray) -> FloatArray:
    """Residual of ``data ≈ design θ`` (weights ``1/sd``), in data units, each over ``√(1 − h_kk)``.

    Dividing by the leverage keeps the fitted columns from passing for a
    deficit of variance in the variance-component fits that follow.
    """
    a = design / sd[:, None]
    z = data / sd
    q, _ = np.linalg.qr(a)
    coef, *_ = np.linalg.lstsq(a, z, rcond=None)
    h: FloatArray = np.einsum("ij,ij->i", q, q)
    return (z - a @ coef) * sd / np.sqrt(np.clip(1.0 - h, 1e-3, None))


def leverage_components(design: FloatArray, sd: FloatArray, weight: FloatArray) -> FloatArray:
    """(m, n) variance that per-datum excesses ``weight`` (m, n) leave in :func:`leverage_residual`'s output.

    The fit takes in part of an excess that varies between data: of ``e_j`` (variance ``w_j``) the residual
    ``k`` keeps ``Σ_j M_kj² w_j / sd_j²`` in weighted units (``M = I − H``), then the leverage scaling,
    ``sd_k² / (1 − h_kk)``. Without this a fitted excess on one column leaves a pattern another column fits.
    """
    q, _ = np.linalg.qr(design / sd[:, None])
    m = np.eye(sd.size) - q @ q.T
    kept: FloatArray = np.einsum("kj,ij->ik", m**2, weight / sd**2) * sd**2
    kept /= np.clip(np.diag(m), 1e-3, None)
    return kept


def _threshold(k: int, n_tests: int) -> float:
    from scipy.stats import chi2

    return float(chi2.isf(FAMILY_ALPHA / max(n_tests, 1), k))


def _threshold_mean(k: int, n: int, p: int, n_tests: int) -> float:
    """LR threshold of a mean effect: the exact F test (scale estimated from ``n − p − k`` dof) written as ``n ln(RSS0/RSS1)``."""
    from scipy.stats import f as f_dist

    dof = n - p - k
    if dof < 1:
        return float("inf")
    crit = float(f_dist.isf(FAMILY_ALPHA / max(n_tests, 1), k, dof))
    return float(n * np.log1p(k * crit / dof))


# --- variance components -----------------------------------------------------


@dataclass(frozen=True)
class VarianceData:
    """Vectors ``y_k ~ N(0, s0_k + Σ_j θ_j A_jk)`` for a variance-component fit.

    Attributes
    ----------
    y : (n, q) data (normalized units); s0 : (n, q, q) their known covariance;
    comps : (m, n, q, q) the component matrices ``A_jk`` (one per parameter ``θ_j``);
    rows : (n,) index of each datum in the position table;
    weight : (n,) each datum's share of one in the likelihood, or None (all 1): a fit's residuals over
        ``√(1 − h_kk)`` (:func:`leverage_residual`) are n numbers with ``n − p`` degrees of freedom, so each
        counts ``1 − h_kk`` — counted as n, the 3 residual degrees of freedom of 12 positions against nine
        parameters passed for 12, and a 1.7 % scatter (χ²₃ = 10.2) read as a wander at LR 23 (threshold 16).
    """

    y: FloatArray
    s0: FloatArray
    comps: FloatArray
    rows: IntArray
    weight: FloatArray | None = None

    @classmethod
    def finite(
        cls, y: FloatArray, s0: FloatArray, comps: FloatArray, weight: FloatArray | None = None
    ) -> VarianceData:
        """The rows of ``y`` (n, q), ``s0`` (n, q, q), ``comps`` (m, n, q, q) (and ``weight`` (n,)) whose data are finite."""
        ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(s0), axis=(1, 2))
        return cls(
            y[ok], s0[ok], comps[:, ok], np.flatnonzero(ok), None if weight is None else weight[ok]
        )

    @property
    def shares(self) -> FloatArray:
        """(n,) each datum's weight in the likelihood (ones when none was given)."""
        return np.ones(self.y.shape[0]) if self.weight is None else self.weight

    def subset(self, keep: BoolArray) -> VarianceData:
        """The same data with only the components ``keep`` (bool (m,))."""
        return VarianceData(
            self.y, self.s0, self.comps[np.asarray(keep, bool)], self.rows, self.weight
        )

    def with_fixed(self, theta: FloatArray, fixed: BoolArray) -> VarianceData:
        """Components ``fixed`` (bool (m,)) folded into ``s0`` at ``theta``; the rest stay free."""
        fixed = np.asarray(fixed, bool)
        s0 = self.s0 + np.einsum("j,jkab->kab", np.asarray(theta, float)[fixed], self.comps[fixed])
        return VarianceData(self.y, s0, self.comps[~fixed], self.rows, self.weight)

    def scaled(self, weight: FloatArray) -> VarianceData:
        """The single free component multiplied per position by ``weight`` (indexed by table row)."""
        return VarianceData(
            self.y,
            self.s0,
            self.comps * np.asarray(weight, float)[self.rows][None, :, None, None],
            self.rows,
            self.weight,
        )


def _nll_score(theta: FloatArray, data: list[VarianceData]) -> tuple[float, FloatArray, FloatArray]:
    """``½ Σ_k w_k [ln det S_k + y_kᵀ S_k⁻¹ y_k]`` over every dataset, its gradient in ``θ`` and the Fisher information.

    Gradient ``½ Σ_k w_k [tr(S⁻¹A_j) − yᵀS⁻¹A_jS⁻¹y]``; information ``½ Σ_k w_k tr(S⁻¹A_j S⁻¹A_l)``
    (``w_k`` :attr:`VarianceData.shares`).
    """
    m = theta.size
    nll, grad, info = 0.0, np.zeros(m), np.zeros((m, m))
    for d in data:
        w = d.shares
        s = d.s0 + np.einsum("j,jkab->kab", theta, d.comps)
        sol = np.linalg.solve(s, d.y[..., None])[..., 0]
        _, logdet = np.linalg.slogdet(s)
        nll += 0.5 * float(w @ (logdet + np.einsum("ka,ka->k", d.y, sol)))
        s_inv_a = np.linalg.solve(s[None], d.comps)
        grad += 0.5 * (
            np.einsum("k,jkaa->j", w, s_inv_a) - np.einsum("k,ka,jkab,kb->j", w, sol, d.comps, sol)
        )
        info += 0.5 * np.einsum("k,jkab,lkba->jl", w, s_inv_a, s_inv_a)
    return nll, grad, info


def fit_variance(data: list[VarianceData], *, max_iter: int = 100) -> tuple[FloatArray, float]:
    """Maximum-likelihood ``θ ≥ 0`` shared by ``data`` (:class:`VarianceData`), and the minimum negative log-likelihood.

    Projected Fisher scoring, the classic variance-component iteration: from
    ``θ = 0``, a Newton step with the Fisher information on the components not
    held at the bound (a component at 0 whose gradient pushes below 0 stays
    there), projected onto ``θ ≥ 0``, halved until the likelihood improves;
    stops when a step changes the likelihood by less than 1e-9.
    """
    m = data[0].comps.shape[0]
    theta = np.zeros(m)
    nll, grad, info = _nll_score(theta, data)
    for _ in range(max_iter if m else 0):
        free = (theta > 0.0) | (grad < 0.0)
        if not free.any():
            break
        step = np.zeros(m)
        f = np.flatnonzero(free)
        # A tiny ridge keeps a component the data cannot see (zero information) from a singular solve.
        sub = info[np.ix_(f, f)] + 1e-12 * np.trace(info) * np.eye(f.size) / m
        step[f] = np.linalg.solve(sub, -grad[f])
        t = 1.0
        while t > 1e-6:
            cand = np.maximum(theta + t * step, 0.0)
            c_nll, c_grad, c_info = _nll_score(cand, data)
            if c_nll <= nll:
                break
            t *= 0.5
        else:
            break
        done = nll - c_nll < 1e-9
        theta, nll, grad, info = cand, c_nll, c_grad, c_info
        if done:
            break
    return theta, nll


def variance_se_at_zero(d: VarianceData, j: int) -> float:
    """Fisher standard error of ``θ_j`` at ``θ = 0``: ``1/√(½ Σ_k w_k tr(S0⁻¹A_jk S0⁻¹A_jk))`` (the detection scale of a variance effect)."""
    m = np.linalg.solve(d.s0, d.comps[j])
    info = 0.5 * float(np.einsum("k,kab,kba->", d.shares, m, m))
    return float(1.0 / np.sqrt(info)) if info > 0 else float("inf")


# --- Gauss–Markov process behind a bias instability --------------------------


def mean_variance_factor(length_s: FloatArray, tau_s: float) -> FloatArray:
    """``V(L/τ) = 2(τ/L)²(L/τ − 1 + e^{−L/τ})``: variance of a length-L mean of a unit Gauss–Markov process."""
    x = np.asarray(length_s, float) / tau_s
    return np.where(x < 1e-6, 1.0, 2.0 / np.maximum(x, 1e-6) ** 2 * (x - 1.0 + np.exp(-x)))


def gauss_markov_moments(
    length_s: FloatArray, tau_s: float, batch_s: float
) -> tuple[FloatArray, FloatArray]:
    """Per unit variance of a Gauss–Markov bias (correlation time ``τ``): its excess over the chain's covariance.

    Returns (between, halves), each (n,):

    * between: variance of the position mean, ``V(L/τ)``;
    * halves: variance of the half-to-half difference,
      ``2 [V(h/τ) − (τ/h)² (1 − e^{−h/τ})²]`` with ``h = L/2``;

    both less what the noise reference (batch means of ``batch_s``,
    :func:`estimators.noise.batch_means_sd`) already holds of the process,
    ``[V(b/τ) − V(L/τ)] / (n_b − 1)`` for the mean (×4 for the halves).
    """
    length = np.asarray(length_s, float)
    half = 0.5 * length
    adjacent = (tau_s / half) ** 2 * (1.0 - np.exp(-half / tau_s)) ** 2
    nb = np.maximum(np.floor(length / batch_s), 2.0)
    held = np.clip(
        (
            mean_variance_factor(np.full_like(length, batch_s), tau_s)
            - mean_variance_factor(length, tau_s)
        )
        / (nb - 1.0),
        0.0,
        None,
    )
    between = np.clip(mean_variance_factor(length, tau_s) - held, 0.0, None)
    halves = np.clip(2.0 * (mean_variance_factor(half, tau_s) - adjacent) - 4.0 * held, 0.0, None)
    return between, halves


def batch_mean_covariance(n_batches: int, batch_s: float, tau_s: float) -> FloatArray:
    """(n_b, n_b) covariance of consecutive ``batch_s`` means of a unit-variance Gauss–Markov process (time constant ``τ``).

    ``V(b/τ)`` (:func:`mean_variance_factor`) on the diagonal; between batches ``d ≥ 1`` apart
    ``(τ/b)² (1 − e^{−b/τ})² e^{−(d−1) b/τ}`` (the double integral of ``e^{−|t−s|/τ}`` over two
    windows of length ``b``, ``d`` windows apart, over ``b²``).
    """
    d = np.abs(np.subtract.outer(np.arange(n_batches), np.arange(n_batches)))
    x = batch_s / tau_s
    off = (1.0 - np.exp(-x)) ** 2 / x**2 * np.exp(-(np.maximum(d, 1) - 1) * x)
    out: FloatArray = np.where(d == 0, mean_variance_factor(np.array(batch_s), tau_s), off)
    return out


@dataclass(frozen=True)
class BatchContrasts:
    """Within-position contrasts of one axis' batch means, the third datum on a wander's correlation time.

    Per group of positions with the same number of batches ``n_b``: an orthonormal basis ``Q`` (n_b, n_b − 2)
    of the contrasts orthogonal to the position's mean and to its half-to-half difference (those two are the
    other records' data), and the contrasts ``y = Qᵀ m`` (n, n_b − 2) of each position's batch means ``m``.
    Under the noise alone each contrast has the variance ``noise_var`` of one batch mean (the noise's
    correlation is far shorter than a batch); a Gauss–Markov bias of variance ``σ²`` adds
    ``σ² Qᵀ C(τ) Q`` (:func:`batch_mean_covariance`).
    """

    groups: tuple[tuple[FloatArray, FloatArray], ...]
    noise_var: float

    @classmethod
    def of_table(cls, tab: PositionTable, axis: int, rows: IntArray) -> BatchContrasts | None:
        """The contrasts of sensor axis ``axis`` over table ``rows`` (single-interval positions with ≥ 3 batches);
        None when ``tab`` carries no batch means or no position has a contrast."""
        by_size: dict[int, list[FloatArray]] = {}
        for k in rows if tab.batch_means else ():
            m = tab.batch_means[k][:, axis]
            if m.size >= 3 and np.isfinite(tab.halves[k, axis]):
                by_size.setdefault(m.size, []).append(m)
        if not by_size:
            return None
        groups = []
        for nb, means in sorted(by_size.items()):
            # The mean and the first-half-minus-second-half contrast (0 on an odd count's middle batch).
            kept = np.column_stack([np.ones(nb), np.sign(nb - 1 - 2 * np.arange(nb))])
            q = np.linalg.svd(kept, full_matrices=True)[0][:, 2:]
            groups.append((q, np.array(means) @ q))
        return cls(tuple(groups), float(tab.batch_var[axis]))

    def data(self, tau_s: float, batch_s: float) -> VarianceData:
        """The contrasts as independent scalars: in the eigenbasis ``U`` of each group's ``Qᵀ C(τ) Q`` (eigenvalues
        ``λ``) the rotated contrasts ``Uᵀ y`` have the variances ``noise_var + σ² λ`` and no correlation."""
        ys, weights = [], []
        for q, y in self.groups:
            lam, u = np.linalg.eigh(q.T @ batch_mean_covariance(q.shape[0], batch_s, tau_s) @ q)
            ys.append((y @ u).ravel())
            weights.append(np.tile(np.clip(lam, 0.0, None), y.shape[0]))
        z, w = np.concatenate(ys), np.concatenate(weights)
        return VarianceData(
            z[:, None],
            np.full((z.size, 1, 1), self.noise_var),
            w[None, :, None, None],
            np.arange(z.size),
        )


def fit_gauss_markov(
    between: VarianceData,
    halves: VarianceData,
    length_s: FloatArray,
    batch_s: float,
    batches: BatchContrasts | None = None,
) -> tuple[float, float]:
    """(σ², τ_s) of the Gauss–Markov bias of one axis that best explains the records.

    ``between`` and ``halves`` carry one free component each: the axis' weight
    per position for a unit excess that is the same at every position (the
    other components already folded into ``s0``). For a Gauss–Markov bias the
    excess of position ``k`` is ``σ²`` times :func:`gauss_markov_moments` of its
    length. Those two hardly tell the correlation time: a fast wander and a
    slower, larger one leave similar variances between positions and between
    their halves. ``batches`` (:class:`BatchContrasts`), the scatter of the
    noise windows' means inside the positions beyond the noise's own, does: a
    fast wander puts more of itself there. The likelihood is the sum over the
    records (a composite likelihood: each record's own law is exact, the
    correlation a wander induces between a position's records is left out).
    The time constant is profiled on a log grid from :data:`GM_MIN_TAU_WINDOWS`
    noise windows to 30 position lengths; σ² is the likelihood maximum at each.
    """
    best = (0.0, 1.0, np.inf)
    for tau in np.geomspace(GM_MIN_TAU_WINDOWS * batch_s, 30.0 * float(np.max(length_s)), 41):
        b_w, h_w = gauss_markov_moments(length_s, float(tau), batch_s)
        records = [between.scaled(b_w), halves.scaled(h_w)]
        if batches is not None:
            records.append(batches.data(float(tau), batch_s))
        theta, nll = fit_variance(records)
        if nll < best[2]:
            best = (float(theta[0]), float(tau), nll)
    return best[0], best[1]


LOADING_GRID = np.round(np.linspace(-1.0, 1.0, 81), 3)
"""Loadings a wander is profiled over (:func:`fit_loading`): a common wander as large on another axis as on
its own or larger would be that axis' wander."""


def fit_loading(halves: VarianceData, axis: int, other: int) -> tuple[float, float]:
    """(loading ``l``, likelihood ratio against ``l = 0``) of a wander of ``axis`` on sensor axis ``other``.

    ``halves`` is the half-to-half record with the wander's own component
    ``e_i e_iᵀ`` the one free component (the rest of the selected model in
    ``s0``). A wander common to both axes moves the bias along ``v = e_i + l e_j``:
    its component becomes ``v vᵀ``, whose off-diagonal ``l`` correlates the two
    axes' half-to-half differences and whose ``l²`` adds to the other axis'
    variance. ``l`` is profiled over :data:`LOADING_GRID`, the wander's
    variance refitted at each; one degree of freedom.
    """
    _, nll0 = fit_variance([halves])
    n = halves.y.shape[0]
    best_l, best = 0.0, nll0
    for lv in LOADING_GRID:
        v = np.eye(3)[axis] + lv * np.eye(3)[other]
        comp = np.broadcast_to(np.outer(v, v), (1, n, 3, 3))
        nll = fit_variance([VarianceData(halves.y, halves.s0, comp, halves.rows)])[1]
        if nll < best:
            best_l, best = float(lv), nll
    return best_l, 2.0 * (nll0 - best)


# --- structure of the residual -------------------------------------------------

WITHIN_ABSENT_LR = 3.84
"""Largest LR of an excess inside positions (any axis) for it to count as absent: χ²₁ at 5 %. Absence must
be shown, not merely not significant at the family-wise rate: a slow wander shows inside positions
weakly (LR 5–10), and the known scale it would make wrong names its between-position scatter deterministic."""


@dataclass(frozen=True)
class ResidualStructure:
    """Where a triad's scalar residual departs from the within-position noise: between positions, inside them.

    ``lr_between`` (3,): the LR of an excess on the baseline's scalar residuals along sensor axis ``i``
    (weights ``J_b_i²``), the within-position noise the known scale; ``lr_within`` (3,): of an excess of
    axis ``i`` on the half-to-half differences. ``structured``: the residual holds structure between
    positions (the largest ``lr_between`` beyond ``threshold``) and none inside them (every axis'
    ``lr_within`` below :data:`WITHIN_ABSENT_LR`) — the signature of a deterministic effect, not of wander, which shows inside
    positions too (on any axis, a wander makes the within-position noise too small a scale). ``axis``:
    the axis whose excess fits best (the scalar residual tells the axes apart only through the orientations). ``t_mid_s``, ``up`` (n, 3), ``residual_norm`` and ``sigma_norm``: the residual against
    time and orientation, for the plot; ``temp_c`` (None without a temperature), ``heating`` (+1 heating, −1
    cooling) and ``jac`` (n, 9) the scalar equation's Jacobian: the residual against temperature, per axis.
    """

    triad: Triad
    axis: str
    lr_between: FloatArray
    lr_within: FloatArray
    threshold: float
    structured: bool
    t_mid_s: FloatArray
    up: FloatArray
    residual_norm: FloatArray
    sigma_norm: FloatArray
    temp_c: FloatArray | None = None
    heating: FloatArray | None = None
    jac: FloatArray | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "triad": self.triad.value,
            "axis": self.axis,
            "structured": self.structured,
            "lr_between": [float(v) for v in self.lr_between],
            "lr_within": [float(v) for v in self.lr_within],
            "threshold": self.threshold,
        }

    @property
    def sentence(self) -> str:
        i = AXES.index(self.axis)
        return (
            f"structured_residual: the {self.triad.value} scalar residual is structured between positions along "
            f"{self.axis} (LR {self.lr_between[i]:.1f}, threshold {self.threshold:.1f}) and absent inside them "
            f"(LR at most {float(np.max(self.lr_within)):.1f}): a deterministic effect's signature; the deterministic "
            "candidates are tested on it at the within-position noise before any wander"
        )


def residual_structure(
    triad: Triad,
    tab: PositionTable,
    jac: FloatArray,
    residual: FloatArray,
    sigma: FloatArray,
    n_tests: int,
) -> ResidualStructure:
    """The structure test of one triad's baseline scalar residual (:class:`ResidualStructure`).

    Each axis' excess is one variance component (:func:`fit_variance`), the between record after the
    nine parameters' fit (:func:`leverage_residual`), the halves record at the baseline's noise; each
    LR against χ²₁ at the audit's family-wise rate over its tests (Bonferroni).
    """
    weight = jac[:, :3] ** 2
    between = VarianceData.finite(
        leverage_residual(jac, residual, sigma)[:, None],
        (sigma**2)[:, None, None],
        leverage_components(jac, sigma, weight.T)[:, :, None, None],
    )
    n = tab.t_mid_s.size
    halves = _halves_record(tab, np.zeros((n, 3)), np.zeros((n, 3, 3)))
    lr_b, lr_w = np.zeros(3), np.zeros(3)
    _, nll_b0 = fit_variance([between.subset(np.zeros(3, bool))])
    _, nll_w0 = fit_variance([halves.subset(np.zeros(4, bool))])
    for i in range(3):
        _, nll = fit_variance([between.subset(np.arange(3) == i)])
        lr_b[i] = max(2.0 * (nll_b0 - nll), 0.0)
        if halves.y.shape[0]:
            _, nll = fit_variance([halves.subset(np.arange(4) == i)])
            lr_w[i] = max(2.0 * (nll_w0 - nll), 0.0)
    thr = _threshold(1, n_tests)
    i = int(np.argmax(lr_b))
    u = tab.mean / np.linalg.norm(tab.mean, axis=1, keepdims=True)
    return ResidualStructure(
        triad,
        AXES[i],
        lr_b,
        lr_w,
        thr,
        bool(lr_b[i] > thr and np.all(lr_w < WITHIN_ABSENT_LR)),
        tab.t_mid_s,
        u,
        residual,
        sigma,
        tab.temp_c,
        None if temperature_reason(tab) is not None else heating_sign_of_positions(tab),
        jac,
    )


# --- clipping -------------------------------------------------------------------


def clipping_candidates(
    triad: Triad,
    x_si: FloatArray,
    spans: IntArray,
    sample_sd_si: FloatArray,
    step_si: FloatArray | None,
    n_tests: int,
) -> list[Candidate]:
    """``clipping`` per axis: static samples held on a rail, read from the samples themselves.

    The extreme values of an axis over the static samples (``spans`` (n, 2)), the highest and the lowest,
    are its rail candidates. Without a rail the samples at such a level besides the extreme itself are
    a Poisson count of mean ``E = Σ_k n_k P(level)``, each position's samples normal about its mean
    with the baseline's per-sample sd, the level one output step wide (the grid's, or float32's
    resolution off a grid): a clipped output stacks samples there that the noise would have spread
    beyond. ``LR = −2 ln p`` of the count, the larger of the two sides, against
    ``−2 ln(α/(tests·6))`` (two sides of three axes per triad): both are tried because symmetric rails
    clip both sides of an axis whose positions reach either (a gyro's Earth rate projects on an axis
    with either sign, so its extremes are alike in magnitude and the stack may be on the smaller
    one). A stack is a rail's only where a rail explains it: a rail there holds the level's samples and
    those the noise puts beyond it, ``B = Σ_k n_k P(beyond)``, so the ``c`` others are Poisson of mean
    ``E + B``. Either that does not reject the count (``−2 ln P(≥ c | E + B)`` within the threshold: a rail
    a few samples deep), or a rail beats none by the threshold, ``LR_rail = 2 (c ln(1 + B/E) − B)`` (a
    deep rail, whose clipped samples pull the means inward and so ``B`` below the count). A level far out
    in the tail (a turn's end at a position's edge held on a level for two samples) stacks beyond ``E``,
    but a rail there clips nothing the noise reaches (``B ≈ E``): it fails both. The rail is exact to half
    a step. On a grid coarser than the noise the
    levels' counts hang on where each mean falls between two levels: not identifiable there.
    """
    thr = float(-2.0 * np.log(FAMILY_ALPHA / (max(n_tests, 1) * 6)))
    out = []
    for i, ax in enumerate(AXES):
        if step_si is not None and step_si[i] > sample_sd_si[i]:
            out.append(
                not_identifiable(
                    "clipping",
                    triad,
                    ax,
                    f"not identifiable: the output grid ({step_si[i]:.3g} SI) is coarser than the noise "
                    f"({sample_sd_si[i]:.3g} SI): a position's samples stack on a level or two whatever the rail",
                )
            )
            continue
        pieces = [x_si[a:b, i] for a, b in spans]
        static = np.concatenate(pieces)
        step = 0.0 if step_si is None else float(step_si[i])
        sides = {
            r: _rail_level(static, pieces, float(sample_sd_si[i]), step, r, side)
            for r, side in ((float(static.max()), 1.0), (float(static.min()), -1.0))
        }
        rail = max(sides, key=lambda r: (sides[r][0], abs(r)))
        lr, width, count, expected, lr_rail, lr_fit = sides[rail]
        explained = lr_rail > thr or lr_fit <= thr
        touched = [
            k for k, piece in enumerate(pieces) if np.any(np.abs(piece - rail) <= 0.5 * width)
        ]
        out.append(
            Candidate(
                "clipping",
                triad,
                ax,
                True,
                lr,
                thr,
                1.0,
                {
                    "rail_si": rail,
                    "rail_se_si": 0.5 * step,
                    "samples_on_rail": count,
                    "expected_without_rail": expected,
                    "positions_on_rail": touched,
                },
                lr > thr and explained,
                f"{triad.value} {ax}: {count} static samples on {rail:.6g} SI, the extreme level "
                f"({expected:.2g} expected there without a rail; positions {', '.join(f'#{k}' for k in touched[:5])}"
                f"{', …' if len(touched) > 5 else ''}): LR {lr:.1f} (threshold {thr:.1f})"
                + (
                    f"; not a rail: one there would hold what the noise puts beyond it, too few to make the "
                    f"stack (LR of the stack against such a rail {lr_fit:.1f}, of a rail against none {lr_rail:.1f})"
                    if lr > thr and not explained
                    else ""
                ),
            )
        )
    return out


def _rail_level(
    static: FloatArray, pieces: list[FloatArray], sd: float, step: float, rail: float, side: float
) -> tuple[float, float, int, float, float, float]:
    """(LR, level width, count, expected count, LR of a rail there against none, LR of the count against such
    a rail) of the static samples on the level of ``rail``
    (:func:`clipping_candidates`); ``pieces`` are the positions' samples, ``sd`` their per-sample noise,
    ``side`` +1 for the highest extreme, −1 for the lowest.

    The level and what lies beyond it are read on the extreme's own side, not on the side of the rail's
    sign: the two differ when both extremes share a sign (a bias larger than the noise)."""
    from scipy.stats import norm, poisson

    width = max(step, 2.0 * float(np.spacing(np.float32(abs(rail)))))
    count = int(np.sum(np.abs(static - rail) <= 0.5 * width))
    means = np.array([p.mean() for p in pieces])
    n_k = np.array([p.size for p in pieces])
    z_hi = (side * (rail - means) + 0.5 * width) / sd
    z_lo = (side * (rail - means) - 0.5 * width) / sd
    expected = float(np.sum(n_k * (norm.sf(z_lo) - norm.sf(z_hi))))
    beyond = float(np.sum(n_k * norm.sf(z_hi)))
    # The extreme sample itself is on the level by construction: the count is of the others.
    others = max(count - 1, 0)
    p = float(poisson.sf(others - 1, expected)) if others else 1.0
    lr_rail = 2.0 * (others * float(np.log1p(beyond / max(expected, 1e-300))) - beyond)
    p_rail = float(poisson.sf(others - 1, expected + beyond)) if others else 1.0
    lr = float(-2.0 * np.log(max(p, 1e-300)))
    return lr, width, count, expected, lr_rail, float(-2.0 * np.log(max(p_rail, 1e-300)))


# --- spectral lines -------------------------------------------------------------

LINE_SEGMENT = 256
"""Longest periodogram segment of the line test, samples (shorter positions: the largest power of two they hold)."""
LINE_FLOOR_BINS = 17
"""Width of the running median that is the line test's noise floor, bins: wide against a line's three bins
(Hann window), narrow against the bend of a sensor filter's roll-off."""
LINE_SKIP_BINS = 3
"""Lowest bins left out of the line test: the mean, and the wander the segment's detrend leaves."""
LINE_CONCENTRATION = 0.8
"""Least share of a peak's excess (over ±4 bins) in its three central bins for a line: a sinusoid puts ≥ 98 %
there through the Hann window wherever it falls between bins; a resonance's narrowband noise spreads wider."""


def line_spectrum(
    x: FloatArray, spans: IntArray, rate_hz: float
) -> tuple[FloatArray, FloatArray, int]:
    """(frequencies (m,), one-sided PSD (m, 3) in SI²/Hz, segments averaged) of the static samples.

    Non-overlapping Hann segments of :data:`LINE_SEGMENT` samples (or the largest power of two every usable
    position holds, at least 32), each linearly detrended, averaged over every segment of every position:
    independent segments, so each bin is its level times ``χ²_ν/ν``, ``ν = 2 × segments``.
    """
    from scipy.signal import detrend

    lengths = np.array([b - a for a, b in spans])
    usable = lengths[lengths >= 32]
    if usable.size == 0:
        return np.zeros(0), np.zeros((0, 3)), 0
    nseg = int(min(LINE_SEGMENT, 2 ** int(np.floor(np.log2(np.median(usable))))))
    segs = [x[a + j * nseg : a + (j + 1) * nseg] for a, b in spans for j in range((b - a) // nseg)]
    if not segs:
        return np.zeros(0), np.zeros((0, 3)), 0
    w = np.hanning(nseg)
    y = detrend(np.stack(segs), axis=1) * w[None, :, None]
    psd = np.mean(np.abs(np.fft.rfft(y, axis=1)) ** 2, axis=0) / (rate_hz * np.sum(w**2))
    psd[1:-1] *= 2.0
    freq: FloatArray = np.fft.rfftfreq(nseg, 1.0 / rate_hz).astype(np.float64)
    return freq, np.asarray(psd, dtype=np.float64), len(segs)


def line_candidates(
    triad: Triad, x_si: FloatArray, spans: IntArray, rate_hz: float, n_tests: int
) -> list[Candidate]:
    """``spectral_line`` per axis: a peak of the static samples' spectrum above its noise floor (:func:`line_spectrum`).

    The floor is the running median over :data:`LINE_FLOOR_BINS` bins (a coloured noise, a sensor filter's
    roll-off, bends it; a line does not move it), corrected for the median of ``χ²_ν/ν``; the bins within
    half its window of either end are not tried (a line there is not seen: said in ``reason``). A bin is a line
    when ``P/floor`` lies beyond the ``F(ν, ν_floor)`` quantile (the floor's own scatter counted) at the
    audit's family-wise rate split over the tests,
    the three axes and the bins tried; ``LR = −2 ln p`` of the highest bin. The amplitude is ``√(2 Σ (P −
    floor) Δf)`` over the peak's three bins (the line's variance ``A²/2``), its frequency the bins' power
    centroid, good to a bin (``Δf``). A peak whose excess spreads beyond its three bins
    (:data:`LINE_CONCENTRATION`) is narrowband noise (a resonance), not a line: it is not named.
    """
    from scipy.ndimage import median_filter
    from scipy.stats import f as f_dist

    freq, psd, m = line_spectrum(x_si, spans, rate_hz)
    out = []
    edge = max(LINE_SKIP_BINS, LINE_FLOOR_BINS // 2)
    if m == 0 or freq.size <= 2 * edge + 1:
        return [
            not_identifiable(
                "spectral_line", triad, ax, "not identifiable: no position holds a spectrum segment"
            )
            for ax in AXES
        ]
    nu = 2 * m
    # The floor is itself an estimate: a median of the window's bins has the variance of a mean of
    # 2/π of them, so the ratio is F-distributed with the floor's degrees of freedom.
    nu_floor = nu * LINE_FLOOR_BINS * 2.0 / np.pi
    # Where the running median's window is cut by an end of the spectrum the floor is not a median of its
    # neighbours: those bins (near 0 and near Nyquist) are not tried.
    tried = slice(edge, freq.size - edge)
    n_bins = freq.size - 2 * edge
    alpha = FAMILY_ALPHA / (max(n_tests, 1) * 3 * n_bins)
    thr = float(-2.0 * np.log(alpha))
    df = float(freq[1] - freq[0])
    for i, ax in enumerate(AXES):
        p_i = psd[:, i]
        floor = (
            median_filter(p_i, size=LINE_FLOOR_BINS, mode="nearest") / (1.0 - 2.0 / (9.0 * nu)) ** 3
        )
        logp = f_dist.logsf(p_i[tried] / floor[tried], nu, nu_floor)
        k = edge + int(np.argmin(logp))
        lr = float(-2.0 * np.min(logp))
        near = slice(max(k - 1, 1), min(k + 2, freq.size))
        excess = np.clip(p_i[near] - floor[near], 0.0, None)
        wide = slice(max(k - 4, 1), min(k + 5, freq.size))
        share = float(
            np.sum(excess) / max(np.sum(np.clip(p_i[wide] - floor[wide], 0.0, None)), 1e-300)
        )
        amp = float(np.sqrt(2.0 * np.sum(excess) * df))
        f_line = (
            float(np.sum(freq[near] * excess) / np.sum(excess))
            if np.sum(excess) > 0
            else float(freq[k])
        )
        out.append(
            Candidate(
                "spectral_line",
                triad,
                ax,
                True,
                lr,
                thr,
                1.0,
                {
                    "freq_hz": f_line,
                    "freq_resolution_hz": df,
                    "amplitude_si": amp,
                    "peak_over_floor": float(p_i[k] / floor[k]),
                    "share_in_three_bins": share,
                    "segments": m,
                    "bins_tried": n_bins,
                    "band_tried_hz": [float(freq[edge]), float(freq[-edge - 1])],
                    "spectrum_freq_hz": [float(v) for v in freq],
                    "spectrum_psd_si2_per_hz": [float(v) for v in p_i],
                    "floor_psd_si2_per_hz": [float(v) for v in floor],
                },
                lr > thr and share >= LINE_CONCENTRATION,
                f"{triad.value} {ax}: the static spectrum peaks {p_i[k] / floor[k]:.3g}× its floor at {f_line:.4g} Hz "
                f"(±{df:.2g} Hz; amplitude {amp:.3g} SI, {m} segments; {freq[edge]:.3g}–{freq[-edge - 1]:.3g} Hz tried): "
                f"LR {lr:.1f} (threshold {thr:.1f})"
                + (
                    ""
                    if share >= LINE_CONCENTRATION
                    else f"; {100 * share:.0f} % of its excess in the three central bins: narrowband noise, not a line"
                ),
            )
        )
    return out


# --- noise colour: the firmware's low-pass ---------------------------------------


def lowpass_candidate(
    triad: Triad,
    x_si: FloatArray,
    spans: IntArray,
    rate_hz: float,
    segment: int,
    floor_var_si2: FloatArray,
    n_tests: int,
) -> Candidate:
    """``lowpass`` (noise colour, for the triad): the static noise went through a Butterworth low-pass of order
    ``n`` and cut-off ``f_c`` (:func:`estimators.noise.fit_lowpass` on ``segment``-sample pieces of the positions).

    A low-pass keeps the spectrum at 0 (the level of position means) and takes the rest: the per-sample
    variance is ``σ²∫|H|²``, below the means' level, and the Allan deviation at short τ falls under white
    noise's. LR against white noise, threshold χ² with two degrees of freedom (the cut-off and the filter's
    size) at the family-wise rate split over the tests and the orders tried. Named with the order, the
    cut-off and its 95 % profile interval, the orders the data cannot tell from it and the input's
    per-sample sd (what the simulation filters); ``floor_var_si2`` (3,) the output grid's rounding.
    """
    from scipy.stats import chi2

    records = [x_si[a:b] for a, b in spans if b - a >= segment]
    if not records:
        return not_identifiable(
            "lowpass", triad, None, f"not identifiable: no position holds {segment} samples"
        )
    thr = float(chi2.isf(FAMILY_ALPHA / (max(n_tests, 1) * len(LOWPASS_ORDERS)), 2))
    fit = fit_lowpass(records, rate_hz, segment, floor_var_si2, interval_above=thr)
    low, high = fit.cutoff_interval_hz
    orders = ", ".join(str(o) for o in fit.orders_consistent)
    return Candidate(
        "lowpass",
        triad,
        None,
        True,
        fit.lr,
        thr,
        1.0,
        {
            "order": fit.order,
            "cutoff_hz": fit.cutoff_hz,
            "cutoff_low_hz": low,
            "cutoff_high_hz": high,
            "orders_consistent": list(fit.orders_consistent),
            "lr_by_order": [float(v) for v in fit.lr_by_order],
            "input_sd_si": [float(v) for v in fit.input_sd_si],
            "band_tried_hz": [float(v) for v in fit.band_hz],
            "spectrum_freq_hz": [float(v) for v in fit.freq_hz],
            "spectrum_si2": [[float(v) for v in row] for row in fit.pgram_si2.T],
            "fitted_si2": [[float(v) for v in row] for row in fit.fitted_si2.T],
        },
        fit.lr > thr,
        f"{triad.value} noise colour: the static spectrum falls as a Butterworth low-pass of order {fit.order} "
        f"(orders {orders} within 95 %) at {fit.cutoff_hz:.3g} Hz (95 % {low:.3g}–{high:.3g} Hz; "
        f"{fit.band_hz[0]:.2g}–{fit.band_hz[1]:.3g} Hz tried): LR {fit.lr:.1f} against white noise "
        f"(threshold {thr:.1f})",
    )


# --- the candidates of each triad ---------------------------------------------


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


def count_tests(has_gyro: bool, temperature: bool, earth_rate: bool = False) -> int:
    """Candidates tried (the Bonferroni split): per accelerometer axis drift, non-linearity,
    bias step, instability (+ temperature bias, scale and hysteresis); the cross-axis term, a change
    of non-orthogonality and nonstatic positions; per gyro axis drift, g-sensitivity, bias step,
    instability (+ temperature bias and hysteresis, and temperature scale when the gyro resolves the
    Earth rate: ``earth_rate``); per triad clipping, a spectral line and a low-pass. A step profiled over the breaks counts once here; its own threshold splits
    its share over the breaks (:func:`forward_select`)."""
    accel = 3 * (4 + (3 if temperature else 0)) + 6
    gyro_temp = (3 if earth_rate else 2) if temperature else 0
    gyro = 3 * (4 + gyro_temp) + 3 if has_gyro else 0
    return accel + gyro


@dataclass(frozen=True)
class _MeanEffect:
    """A mean-structure candidate: its regressor on the position record and on the halves (per unit parameter)."""

    name: str
    axis: int
    keys: tuple[str, ...]
    reg: FloatArray  # (n, k) on the residual (accel) or the mean (gyro)
    halves: FloatArray  # (n, k) first-half minus second-half change of axis ``axis`` per unit physical parameter
    sign: float  # physical parameter = sign · regression coefficient
    after: int | None = (
        None  # a change between positions after - 1 and after (profiled over the breaks)
    )
    window_s: tuple[float, float] = (
        0.0,
        0.0,
    )  # the turn the change lies in: end of after - 1, start of after
    breaks: int = 1  # how many breaks the change is profiled over (its threshold's multiplicity)
    triad_level: bool = False  # named without an axis (the three columns are the triad's)


def _change_effects(
    tab: PositionTable,
    name: str,
    axis: int,
    keys: tuple[str, ...],
    columns: FloatArray,
    triad_level: bool = False,
    sign: float = -1.0,
) -> list[_MeanEffect]:
    """A change of the effect ``columns`` (n, k) between two positions, one candidate per break.

    Break ``b`` (1 … n − 1) lies in the turn before position ``b``: the regressor is the columns
    from position ``b`` on (the first positions are the reference). The halves do not see a change
    in a turn; a change inside a position (a knock) splits it, or leaves it for ``nonstatic_positions``.
    ``sign``: physical parameter over regression coefficient (−1 on a scalar residual, +1 on a gyro mean).
    """
    n, k = columns.shape
    end = tab.t_mid_s + 0.5 * tab.duration_s
    start = tab.t_mid_s - 0.5 * tab.duration_s
    return [
        _MeanEffect(
            name,
            axis,
            keys,
            columns * (np.arange(n) >= b)[:, None],
            np.zeros((n, k)),
            sign,
            after=b,
            window_s=(float(end[b - 1]), float(start[b])),
            breaks=n - 1,
            triad_level=triad_level,
        )
        for b in range(1, n)
    ]


def heating_sign_of_positions(tab: PositionTable) -> FloatArray:
    """(n,) +1 for a position the unit was heating in, −1 cooling (the temperature's slope through its neighbours)."""
    assert tab.temp_c is not None
    out: FloatArray = np.sign(np.gradient(tab.temp_c, tab.t_mid_s))
    return out


def hysteresis_effect(
    tab: PositionTable, axis: int, key: str, d_bias: FloatArray | None = None
) -> _MeanEffect:
    """``temperature_hysteresis`` of ``axis``: a bias ``±h`` heating and cooling, on the scalar residual through
    ``d_bias`` (n,) = ∂f/∂b_axis (sign −1: the baseline lacks it), or on a gyro mean (``None``: the bias itself)."""
    heating = heating_sign_of_positions(tab)[:, None]
    reg = heating if d_bias is None else d_bias[:, None] * heating
    return _MeanEffect(
        "temperature_hysteresis",
        axis,
        (key,),
        reg,
        np.zeros((tab.t_mid_s.size, 1)),
        1.0 if d_bias is None else -1.0,
    )


def cross_axis_effect(tab: PositionTable, jac: FloatArray) -> _MeanEffect:
    """The second-order cross-axis term ``y_i += Kc_i y_j y_k`` of the triad (normalized ``kc_norm = Σ Kc_i·g``).

    The scalar residual sees a bias of axis ``i`` through ``∂f/∂b_i ≈ u_i``: each axis' term enters as
    ``Kc_i u_x u_y u_z``, the same regressor for all three. The norm tells the sum, not the axis: one
    candidate for the triad, its regressor ``⅓ Σ_i J_b_i Π_{j≠i} ã_j`` (the exact Jacobian; ≈ ``u_x u_y u_z``
    whichever axis carries the term).
    """
    others = np.column_stack([np.prod(np.delete(tab.mean, i, axis=1), axis=1) for i in range(3)])
    n = tab.t_mid_s.size
    return _MeanEffect(
        "cross_axis_nonlinearity",
        0,
        ("kc_norm",),
        np.mean(jac[:, :3] * others, axis=1, keepdims=True),
        np.zeros((n, 1)),
        -1.0,
        triad_level=True,
    )


def accel_changes(tab: PositionTable, jac: FloatArray) -> list[_MeanEffect]:
    """The accelerometers' changes between positions: a bias step per axis and a change of the three cosines (a mounting slip)."""
    out = [
        e
        for i in range(3)
        for e in _change_effects(tab, "bias_step", i, ("step_norm",), jac[:, [i]])
    ]
    out.append(cross_axis_effect(tab, jac))
    out += _change_effects(
        tab,
        "nonorthogonality_change",
        0,
        tuple(f"d_{a}_change" for a in ("xy", "xz", "yz")),
        jac[:, 6:9],
        triad_level=True,
    )
    return out


TEMPERATURE_ORDERS = (1, 2, 3)
"""Polynomial orders of an accelerometer's temperature bias the held-out criterion compares (M3)."""


def temperature_bias_order(
    tab: PositionTable, jac: FloatArray, residual: FloatArray, sigma: FloatArray, axis: int
) -> int:
    """The order of axis ``axis``' temperature bias on the scalar residual, chosen as M3 chooses it
    (:func:`estimators.temperature.held_out_scores`: positions sorted by temperature, alternate halves
    predicting each other, the lowest order within one standard error of the best), next to the nine
    parameters. A quadratic left at first order is a structured residual the wander would take."""
    assert tab.temp_c is not None
    dtemp = tab.temp_c - tab.temp_c.mean()
    x = dtemp / max(float(np.max(np.abs(dtemp))), 1e-9)

    def design(n: int) -> FloatArray:
        return np.hstack([jac, jac[:, [axis]] * x[:, None] ** np.arange(1, n + 1)])

    scores = held_out_scores(
        tab.temp_c, design, residual[:, None], sigma[:, None], TEMPERATURE_ORDERS
    )
    return chosen_order(scores)[0].order if scores else 1


def _temperature_bias_keys(order: int) -> tuple[str, ...]:
    return ("coef_norm_per_c", *(f"coef{k}_norm_per_c{k}" for k in range(2, order + 1)))


def _mean_effects(
    tab: PositionTable,
    jac: FloatArray | None,
    f_b_mps2: FloatArray | None,
    axis: int,
    temperature_order: int = 1,
) -> list[_MeanEffect]:
    """Mean effects of one axis: accelerometer when ``jac`` is given (exact scalar residual), else gyro.

    ``temperature_order``: the accelerometer temperature bias' polynomial order (:func:`temperature_bias_order`)."""
    n = tab.t_mid_s.size
    dt = (tab.t_mid_s - tab.t_mid_s.mean())[:, None]
    drift_halves = -0.5 * tab.duration_s[:, None]
    dtemp: FloatArray | None = None
    th: FloatArray | None = None
    if temperature_reason(tab) is None:
        # An identifiable temperature has its values and its half-to-half changes.
        assert tab.temp_c is not None and tab.temp_halves_c is not None
        dtemp = (tab.temp_c - tab.temp_c.mean())[:, None]
        th = tab.temp_halves_c[:, None]
    i = axis
    if jac is not None:
        # The baseline residual is f ≈ J δp − J_θ θ for an effect θ that the model lacks: the sign flips.
        out = [
            _MeanEffect(
                "bias_drift", i, ("rate_norm_per_s",), jac[:, [i]] * dt, drift_halves, -1.0
            ),
            _MeanEffect(
                "scale_nonlinearity",
                i,
                ("k2_norm", "k3_norm"),
                jac[:, [3 + i]] * np.column_stack([tab.mean[:, i], tab.mean[:, i] ** 2]),
                np.zeros((n, 2)),
                -1.0,
            ),
        ]
        if dtemp is not None and th is not None:
            out += [
                hysteresis_effect(tab, i, "offset_norm", jac[:, i]),
                _MeanEffect(
                    "temperature_bias",
                    i,
                    _temperature_bias_keys(temperature_order),
                    jac[:, [i]] * dtemp ** np.arange(1, temperature_order + 1),
                    # d(ΔT^k) over a position's halves: k ΔT^(k−1) times the temperature's change.
                    np.arange(1, temperature_order + 1)
                    * dtemp ** np.arange(temperature_order)
                    * th,
                    -1.0,
                ),
                _MeanEffect(
                    "temperature_scale",
                    i,
                    ("coef_per_c",),
                    jac[:, [3 + i]] * dtemp,
                    tab.mean[:, [i]] * th,
                    -1.0,
                ),
            ]
        return out
    # Gyro keys are in SI (rad/s): the regression runs on means normalized by Ω.
    assert f_b_mps2 is not None  # the gyro form regresses on the specific force
    out = [
        _MeanEffect("bias_drift", i, ("rate_rps_per_s",), dt, drift_halves, 1.0),
        _MeanEffect(
            "g_sensitivity",
            i,
            tuple(f"g{a}_rps_per_mps2" for a in AXES),
            f_b_mps2,
            np.zeros((n, 3)),
            1.0,
        ),
    ]
    out += _change_effects(tab, "bias_step", i, ("step_rps",), np.ones((n, 1)), sign=1.0)
    if dtemp is not None and th is not None:
        out += [
            _MeanEffect("temperature_bias", i, ("coef_rps_per_c",), dtemp, th, 1.0),
            hysteresis_effect(tab, i, "offset_rps"),
        ]
    return out


def _select_means(
    effects: list[_MeanEffect],
    base: FloatArray,
    data: FloatArray,
    sd: FloatArray,
    n_tests: int,
    n_halves: int,
    known_scale: bool = False,
) -> tuple[dict[int, MeanTest], FloatArray, FloatArray]:
    """Forward selection (weights ``1/sd``); returns the tests, the chosen columns and the chosen effects' halves means (n, n_halves)."""
    w = 1.0 / sd
    tests = forward_select(
        base * w[:, None],
        data * w,
        {k: e.reg * w[:, None] for k, e in enumerate(effects)},
        n_tests,
        {k: e.breaks for k, e in enumerate(effects)},
        known_scale,
        {k: (e.name, e.axis) for k, e in enumerate(effects) if e.after is not None},
    )
    chosen = [effects[k].reg for k, t in tests.items() if t.selected]
    halves_mean = np.zeros((data.size, n_halves))
    for k, t in tests.items():
        if t.selected:
            e = effects[k]
            halves_mean[:, e.axis if n_halves == 3 else 0] += e.halves @ (e.sign * t.coef)
    return tests, (np.hstack(chosen) if chosen else np.zeros((data.size, 0))), halves_mean


MEAN_PASSES = 4
"""Most passes of the mean selection with re-fitted weights (:func:`_means_with_excess`)."""


def _means_with_excess(
    effects: list[_MeanEffect],
    base: FloatArray,
    data: FloatArray,
    var0: FloatArray,
    excess_weight: FloatArray,
    n_tests: int,
    n_halves: int,
    known_scale: bool = False,
) -> tuple[dict[int, MeanTest], FloatArray, FloatArray, FloatArray]:
    """Mean selection whose weights carry the variance excess left after the chosen effects, iterated to a fixed point.

    Unexplained scatter must not pass for structure (the weights carry the
    excess), and a mean effect must not pass for scatter (the excess is fitted
    after it): from white weights, select, fit the excess ``v`` (components
    ``excess_weight`` (m, n)) on what is left, reselect with
    ``sd² = var0 + vᵀ·excess_weight``; stop when the chosen set repeats.
    ``known_scale`` (:func:`forward_select`) for a residual whose structure is between positions only.
    Returns the tests, the chosen columns, their halves means and the final sd (n,).
    """
    comps = excess_weight[:, :, None, None]
    sd, seen = np.sqrt(var0), None
    for _ in range(MEAN_PASSES):
        tests, chosen, halves_mean = _select_means(
            effects, base, data, sd, n_tests, n_halves, known_scale
        )
        keys = frozenset(k for k, t in tests.items() if t.selected)
        r = leverage_residual(np.hstack([base, chosen]), data, sd)
        v, _ = fit_variance([VarianceData.finite(r[:, None], var0[:, None, None], comps)])
        sd = np.sqrt(var0 + v @ excess_weight)
        if keys == seen:
            break
        seen = keys
    return tests, chosen, halves_mean, sd


POWER_Z = 1.645
"""Standard normal quantile of the 95 % power the minimum detectable size is stated at."""


def min_detectable(se: float, threshold: float) -> float:
    """Size named with 95 % power on this session: ``se (√threshold + z₀.₉₅)`` (the LR of a one-parameter
    effect is about its size over its standard error, squared; a stated approximation for the F form
    and for a variance component, whose LR grows more slowly at large sizes)."""
    return float(abs(se) * (np.sqrt(max(threshold, 0.0)) + POWER_Z))


CHANGE_TIME_LR = 3.84
"""Profile-LR drop that bounds the time of a change (χ²₁ at 95 %)."""


def _mean_candidates(
    effects: list[_MeanEffect],
    tests: dict[int, MeanTest],
    triad: Triad,
    to_si: float,
    what: str,
    scalar_tests: int | None = None,
) -> list[Candidate]:
    """One candidate per mean effect; ``to_si`` turns the fitted coefficients into the units of their keys.

    ``scalar_tests`` (on a scalar residual: :func:`count_tests`): the minimum detectable sizes are stated at the
    known-scale threshold (:func:`detect_threshold`), else at each test's own.

    A change profiled over the breaks is one candidate: the break selected, else the one of the largest LR,
    with when it happened: from the first to the last turn whose break's profile LR is within
    :data:`CHANGE_TIME_LR` of the best (a 95 % profile-likelihood set; a break only positions blind to
    the axis lie next to is as likely as the best), its middle ± half its span. A selected change whose
    break another axis explains as well (its LR within :data:`CHANGE_TIME_LR` in the round it joined) is
    named for the triad, the axes in ``axes_alike`` and the one fitted in ``fitted_axis`` (:func:`alike_axes`);
    the extended model re-simulates it on ``simulated_axis`` at ``simulated_<key>``, the smallest (:func:`smallest_alike`).
    """
    shown: dict[tuple[str, int], int] = {}
    for k, t in tests.items():
        e = effects[k]
        key = (e.name, e.axis)
        if e.after is None or key not in shown:
            shown.setdefault(key, k)
            continue
        best = tests[shown[key]]
        if t.selected or (not best.selected and t.lr > best.lr):
            shown[key] = k
    out = []
    for k in shown.values():
        t, e = tests[k], effects[k]
        ax = None if e.triad_level else AXES[e.axis]
        changed = e.after is not None and not e.triad_level
        alike = alike_axes(effects, tests, k) if t.selected and changed else []
        fitted: CandidateParams = (
            {key: float(e.sign * c * to_si) for key, c in zip(e.keys, t.coef, strict=True)}
            | {f"{key}_se": float(s * to_si) for key, s in zip(e.keys, t.se, strict=True)}
            | {
                f"{key}_min_detectable": float(
                    min_detectable(s * to_si, detect_threshold(t, e, scalar_tests))
                )
                for key, s in zip(e.keys, t.se, strict=True)
            }
        )
        when = ""
        if e.after is not None:
            profile = t.rivals or {j: u.lr for j, u in tests.items()}
            near = [
                effects[j].window_s
                for j, lr in profile.items()
                if (effects[j].name, effects[j].axis) == (e.name, e.axis)
                and lr >= t.lr - CHANGE_TIME_LR
            ]
            lo, hi = min(w[0] for w in near), max(w[1] for w in near)
            fitted |= {
                "after_position": e.after,
                "t_change_s": 0.5 * (lo + hi),
                "t_change_se_s": 0.5 * (hi - lo),
                "breaks_tried": e.breaks,
            } | change_min_detectable(effects, tests, k, to_si, scalar_tests)
            when = f" in the turn before position {e.after} ({lo:.1f}–{hi:.1f} s; {e.breaks} breaks tried)"
        if len(alike) > 1:
            ax = None
            # Re-simulated on the alike axis of the smallest step (its own sizes stay the fitted axis').
            src = smallest_alike(effects, t, k, alike)
            coef = t.coef if src == k else t.rival_fits[src][0]
            fitted |= {
                "axes_alike": alike,
                "fitted_axis": AXES[e.axis],
                "simulated_axis": AXES[effects[src].axis],
            } | {
                f"simulated_{key}": float(e.sign * c * to_si)
                for key, c in zip(e.keys, coef, strict=True)
            }
            when += (
                f"; its axis is not identifiable: {', '.join(alike)} explain it alike (one position on "
                "one side of the turn, or their columns alike there)"
            )
        where = "the triad" if ax is None else f"axis {ax}"
        out.append(
            Candidate(
                e.name,
                triad,
                ax,
                True,
                t.lr,
                t.threshold,
                t.cv_ratio,
                fitted,
                t.selected,
                f"{what} of {where} follow the {e.name} regressor{when}: LR {t.lr:.1f} (threshold {t.threshold:.1f}), held-out ratio {t.cv_ratio:.3f}",
            )
        )
    return out


def detect_threshold(test: MeanTest, effect: _MeanEffect, scalar_tests: int | None) -> float:
    """The threshold a minimum detectable size is stated at. On a scalar residual an effect between positions
    makes it structured, and it is then tested at the known scale (χ²ₖ at the split, :func:`forward_select`);
    the effect-free session's own test (the F form, the scale estimated) stated sizes 1.2x too large there
    (a navigation gyro's step at 0.5x the stated size was named in 4 of 12 trials, its threshold 20.0
    against the 32.6 stated). Elsewhere (a MEMS gyro's means) the test's own."""
    if scalar_tests is None:
        return test.threshold
    return _threshold(len(effect.keys), scalar_tests * effect.breaks)


def change_min_detectable(
    effects: list[_MeanEffect],
    tests: dict[int, MeanTest],
    k: int,
    to_si: float,
    scalar_tests: int | None = None,
) -> dict[str, float]:
    """A change's ``*_min_detectable`` at the turn it is hardest to see in and ``*_min_detectable_best`` at the
    easiest, over the turns with two positions on each side (in the first or last turn no axis is told:
    :func:`alike_axes`). The standard error of a step at a turn next to the session's ends or to positions
    blind to the axis is several times that of a middle one: one break's size,
    stated for all, was too large for a middle turn (0.5x of it named in 6 of 10 trials) and too small for
    another (1.5x named in 1 of 10)."""
    e = effects[k]
    sizes = np.array(
        [
            [min_detectable(s * to_si, detect_threshold(u, effects[j], scalar_tests)) for s in u.se]
            for j, u in tests.items()
            if (effects[j].name, effects[j].axis) == (e.name, e.axis)
            and 2 <= (effects[j].after or 0) <= e.breaks - 1
        ]
    )
    return {f"{key}_min_detectable": float(sizes[:, c].max()) for c, key in enumerate(e.keys)} | {
        f"{key}_min_detectable_best": float(sizes[:, c].min()) for c, key in enumerate(e.keys)
    }


def alike_axes(effects: list[_MeanEffect], tests: dict[int, MeanTest], k: int) -> list[str]:
    """The axes whose change at the break of the selected ``effects[k]`` explained the data within
    :data:`CHANGE_TIME_LR` of it when it joined (its own first; an axis selected at that break too is
    named on its own: a knock that moved two axes). On a scalar residual a change in the first or last
    turn moves one position: one datum, which every axis' column explains alike once the baseline's bias
    is fitted (the LR does not depend on a column's scale), so which axis joined was a tie."""
    e, test = effects[k], tests[k]
    out = [AXES[e.axis]]
    for j, lr in test.rivals.items():
        o = effects[j]
        if (o.name, o.after) == (e.name, e.after) and o.axis != e.axis and not tests[j].selected:
            if lr >= test.lr - CHANGE_TIME_LR:
                out.append(AXES[o.axis])
    return out


def smallest_alike(effects: list[_MeanEffect], test: MeanTest, k: int, alike: list[str]) -> int:
    """Of the selected change ``effects[k]`` and its rivals at its break on the ``alike`` axes, the key of the
    smallest fitted change. The axes explain the data alike, so the step on each is the datum over that
    axis' column: the tie's winner (the first axis tried) could carry a column near zero and a step many
    times the others', which, re-simulated, shows on that axis' own statistics as unexplained excess; the
    smallest is the least change that explains what the data show."""
    e = effects[k]
    keys = [k] + [
        j
        for j in test.rival_fits
        if (effects[j].name, effects[j].after) == (e.name, e.after)
        and AXES[effects[j].axis] in alike
    ]
    size = {j: float(np.linalg.norm(test.coef if j == k else test.rival_fits[j][0])) for j in keys}
    return min(keys, key=lambda j: size[j])


@dataclass(frozen=True)
class VarianceEffect:
    """A variance candidate: the components ``(record, component)`` it frees in the records of :func:`select_variance`."""

    name: str
    triad: Triad
    axis: int | None
    comps: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class _VarianceTest:
    lrs: FloatArray  # (records,) the likelihood ratio each record contributes
    threshold: float
    thetas: tuple[FloatArray, ...]

    @property
    def lr(self) -> float:
        return float(self.lrs.sum())


def _fit_records(
    records: list[VarianceData], active: list[BoolArray]
) -> tuple[tuple[FloatArray, ...], FloatArray]:
    """Every record fitted on its own with only its ``active`` components free (the others at zero)."""
    thetas, nlls = [], []
    for rec, act in zip(records, active, strict=True):
        th = np.zeros(act.size)
        if rec.y.shape[0]:
            th[act], nll = fit_variance([rec.subset(act)])
        else:
            nll = 0.0
        thetas.append(th)
        nlls.append(nll)
    return tuple(thetas), np.array(nlls)


def select_variance(
    effects: list[VarianceEffect], records: list[VarianceData], n_tests: int
) -> tuple[dict[int, _VarianceTest], list[int], tuple[FloatArray, ...]]:
    """Forward selection of variance effects over independent ``records``.

    As for the mean effects: each remaining effect is tested (profile LR, χ²
    with one degree of freedom per component it frees) against the components
    already selected; the largest margin over its threshold joins; repeat. One
    at a time, because effects overlap: a sensor-axis wander and a motion
    perpendicular to gravity both load a horizontal axis; tested jointly, each
    could hide behind the other. Returns (tests by index, selected indices,
    final fitted components per record).
    """
    active = [np.zeros(r.comps.shape[0], bool) for r in records]
    thetas, nlls = _fit_records(records, active)
    tests: dict[int, _VarianceTest] = {}
    selected: list[int] = []
    remaining = list(range(len(effects)))
    while remaining:
        for k in remaining:
            trial = [a.copy() for a in active]
            for r, j in effects[k].comps:
                trial[r][j] = True
            th, nl = _fit_records(records, trial)
            dof = sum(1 for r, _ in effects[k].comps if records[r].y.shape[0])
            tests[k] = _VarianceTest(
                np.clip(2.0 * (nlls - nl), 0.0, None), _threshold(max(dof, 1), n_tests), th
            )
        passing = [k for k in remaining if tests[k].lr > tests[k].threshold]
        if not passing:
            break
        best = max(passing, key=lambda k: tests[k].lr - tests[k].threshold)
        selected.append(best)
        for r, j in effects[best].comps:
            active[r][j] = True
        thetas, nlls = tests[best].thetas, _fit_records(records, active)[1]
        remaining.remove(best)
    return tests, selected, thetas


def variance_candidates(
    effects: list[VarianceEffect],
    records: list[VarianceData],
    duration_s: FloatArray,
    n_tests: int,
    batch_s: float,
    gyro_to_si: float = EARTH_RATE_RPS,
    tables: dict[Triad, PositionTable] | None = None,
) -> tuple[list[Candidate], tuple[FloatArray, ...]]:
    """The variance candidates of :func:`select_variance`, with a Gauss–Markov fit for each selected ``bias_instability``,
    and the selected model's components per record.

    ``tables`` (by triad, the rows the records index) lend the fit their batch means
    (:class:`BatchContrasts`); without them it sees the two records alone.

    A ``bias_instability`` frees ``((between record, i), (halves record, i))``;
    ``nonstatic_positions`` the accelerometer halves' perpendicular component
    (and the gyro halves' isotropic one).
    """
    tests, selected, final = select_variance(effects, records, n_tests)
    wanders = [k for k in selected if effects[k].name == "bias_instability"]
    # The loadings tried are their own family, at the audit's family-wise rate (as the noise colour's terms).
    loading_threshold = _threshold(1, 2 * len(wanders))
    out = []
    for k, e in enumerate(effects):
        t = tests[k]
        th = final if k in selected else t.thetas
        if e.name == "nonstatic_positions":
            (ra, ja), *gyro = e.comps
            p = float(th[ra][ja])
            q = float(th[gyro[0][0]][gyro[0][1]]) if gyro else 0.0
            # A slow wobble of rms θ about each body axis moves each perpendicular half mean by ~θ, their difference by ~√2 θ.
            angle = float(np.sqrt(p / 2.0))
            out.append(
                Candidate(
                    e.name,
                    e.triad,
                    None,
                    True,
                    t.lr,
                    t.threshold,
                    1.0,
                    {
                        "perp_excess_sd_norm": float(np.sqrt(p)),
                        "gyro_excess_sd_rps": float(np.sqrt(q) * gyro_to_si),
                        "angle_rms_rad": angle,
                        "band_hz": list(wobble_band(duration_s)),
                    },
                    k in selected,
                    f"half-to-half differences perpendicular to gravity exceed the sensor-axis wander by sd {np.sqrt(p):.3g}"
                    f"{f' and the gyros turn by sd {np.sqrt(q) * gyro_to_si:.3g} rad/s' if gyro else ''}"
                    f" (~{angle:.2g} rad rms inside positions): LR {t.lr:.1f} (threshold {t.threshold:.1f})",
                )
            )
            continue
        (rb, i), (rh, _) = e.comps
        vb, vh = float(th[rb][i]), float(th[rh][i])
        params: CandidateParams = {
            "between_sd_norm": float(np.sqrt(vb)),
            "between_var_se_norm2": variance_se_at_zero(records[rb], i),
            "between_var_min_detectable_norm2": min_detectable(
                variance_se_at_zero(records[rb], i), t.threshold
            ),
            "within_halves_sd_norm": float(np.sqrt(vh)),
            "lr_between": float(t.lrs[rb]),
            "lr_within": float(t.lrs[rh]),
        }
        if k in selected:
            others_b = np.arange(final[rb].size) != i
            others_h = np.arange(final[rh].size) != i
            tab = (tables or {}).get(e.triad)
            var, tau = fit_gauss_markov(
                records[rb].with_fixed(final[rb], others_b),
                records[rh].with_fixed(final[rh], others_h),
                duration_s,
                batch_s,
                None if tab is None else BatchContrasts.of_table(tab, i, records[rh].rows),
            )
            params |= {"gm_sigma_norm": float(np.sqrt(var)), "gm_tau_s": tau}
            own_halves = records[rh].with_fixed(final[rh], others_h)
            loadings = {AXES[j]: fit_loading(own_halves, i, j) for j in range(3) if j != i}
            params |= {
                "gm_loading": {a: lv for a, (lv, lr) in loadings.items() if lr > loading_threshold},
                "gm_loading_lr": {a: lr for a, (_, lr) in loadings.items()},
                "gm_loading_threshold": loading_threshold,
            }
        ax = AXES[i]
        out.append(
            Candidate(
                e.name,
                e.triad,
                ax,
                True,
                t.lr,
                t.threshold,
                1.0,
                params,
                k in selected,
                f"{e.triad.value} {ax} bias wanders by sd {np.sqrt(vb):.3g} between positions (LR {t.lrs[rb]:.1f}) and adds sd {np.sqrt(vh):.3g} "
                f"to the half-to-half differences (LR {t.lrs[rh]:.1f}), beyond white noise: LR {t.lr:.1f} (threshold {t.threshold:.1f})"
                + "".join(
                    f"; it moves {a} by {lv:.2g} of itself (LR {params['gm_loading_lr'][a]:.1f}, threshold "
                    f"{params['gm_loading_threshold']:.1f})"
                    for a, lv in params.get("gm_loading", {}).items()
                ),
            )
        )
    return out, final


def halves_chi2(
    records: list[VarianceData], thetas: tuple[FloatArray, ...], n: int
) -> tuple[FloatArray, FloatArray]:
    """Per position (n table rows): χ² of its half-to-half differences under the fitted model, and its degrees of freedom.

    The halves records are every second one of :func:`variance_effects`' order (accel, gyro).
    """
    chi, dof = np.zeros(n), np.zeros(n)
    for rec, th in zip(records[1::2], thetas[1::2], strict=True):
        if rec.y.shape[0] == 0:
            continue
        cov = rec.s0 + np.einsum("j,jkab->kab", th, rec.comps)
        chi[rec.rows] += np.einsum(
            "ka,ka->k", rec.y, np.linalg.solve(cov, rec.y[..., None])[..., 0]
        )
        dof[rec.rows] += rec.y.shape[1]
    return chi, dof


def disturbed_positions(
    records: list[VarianceData],
    thetas: tuple[FloatArray, ...],
    n: int,
    n_tests: int,
    *,
    common_motion: bool = True,
) -> BoolArray:
    """Rows whose halves lie beyond the fitted model at the family-wise rate split over tests and positions (bool (n,)).

    Motion in a few positions (a hand on the unit, a knock) is not a wander of
    every position: its halves stand out against whatever the homogeneous
    components explain. ``common_motion=False`` leaves the motion component
    common to every position (the last of each halves record,
    :func:`_halves_record`) out of that model: the screening's first look,
    before a wobble fitted with the disturbed positions still in can take
    their motion for a wobble of all (:func:`estimators.audit.audit.find_candidates`
    then confirms each flagged position against the model of the others,
    wobble included). Bonferroni over :data:`FAMILY_ALPHA` / (tests × positions).
    """
    from scipy.stats import chi2

    if not common_motion:
        thetas = tuple(
            np.where(np.arange(th.size) == th.size - 1, 0.0, th) if k % 2 else th
            for k, th in enumerate(thetas)
        )
    chi, dof = halves_chi2(records, thetas, n)
    p = np.where(dof > 0, chi2.sf(chi, np.maximum(dof, 1)), 1.0)
    return p < FAMILY_ALPHA / (max(n_tests, 1) * n)


def wobble_band(duration_s: FloatArray) -> tuple[float, float]:
    """Band of a wobble the half-to-half differences resolve, Hz: periods from two position lengths to half of one."""
    length = float(np.median(duration_s))
    return 0.5 / length, 2.0 / length


@dataclass(frozen=True)
class TriadRecords:
    """One triad after its mean effects: their candidates, and the two records its variance effects are tested on.

    ``between`` (n, q): the scalar residual (accel, q = 1, components ``J_b_i²``) or the
    gyro means' residuals (q = 3, components ``e_i e_iᵀ``); ``halves`` (n, 3): the
    half-to-half differences less the selected mean effects' share, components
    ``e_i e_iᵀ`` and a motion component (accel: ``I − u uᵀ``; gyro: ``I``).
    """

    candidates: list[Candidate]
    between: VarianceData
    halves: VarianceData


def _halves_record(tab: PositionTable, halves_mean: FloatArray, motion: FloatArray) -> VarianceData:
    n = tab.t_mid_s.size
    comps = np.stack(
        [np.broadcast_to(np.diag(np.eye(3)[i]), (n, 3, 3)) for i in range(3)] + [motion]
    )
    return VarianceData.finite(tab.halves - halves_mean, 4.0 * tab.cov, comps)


def _scalar_records(
    tab: PositionTable,
    effects: list[_MeanEffect],
    jac: FloatArray,
    residual: FloatArray,
    sigma: FloatArray,
    n_tests: int,
    triad: Triad,
    to_si: float,
    motion: FloatArray,
) -> tuple[list[Candidate], VarianceData, VarianceData]:
    """Mean candidates on the exact scalar residual of one triad, then its two variance records.

    ``motion`` (n, 3, 3) is the halves' motion component (accel: perpendicular to gravity; gyro: isotropic).
    """
    var0 = sigma**2
    g_b2 = (
        jac[:, :3] ** 2
    )  # a bias wander of axis i moves f by ∂f/∂b_i (≈ −u_i for the accelerometers)
    # Structure between positions and none inside them: the within-position noise is the residual's scale,
    # and each deterministic candidate is tested on what it explains (several at once are found together).
    known = residual_structure(triad, tab, jac, residual, sigma, n_tests).structured
    tests, chosen, halves_mean, sd = _means_with_excess(
        effects, jac, residual, var0, g_b2.T, n_tests, 3, known
    )
    what = f"{triad.value} scalar residuals" + (
        " (structured between positions only: tested at the within-position noise)" if known else ""
    )
    out = _mean_candidates(effects, tests, triad, to_si, what, n_tests)
    # Variance last: after the selected mean effects, so a deterministic effect is not also named as instability.
    design = np.hstack([jac, chosen])
    q, _ = np.linalg.qr(design / sd[:, None])
    between = VarianceData.finite(
        leverage_residual(design, residual, sd)[:, None],
        var0[:, None, None],
        leverage_components(design, sd, g_b2.T)[:, :, None, None],
        1.0 - np.einsum("ij,ij->i", q, q),
    )
    return out, between, _halves_record(tab, halves_mean, motion)


def accel_records(
    tab: PositionTable, jac: FloatArray, residual: FloatArray, sigma: FloatArray, n_tests: int
) -> TriadRecords:
    """Accelerometer mean candidates and variance records (module docstring).

    Parameters
    ----------
    tab : the accelerometer :class:`PositionTable` (covariances from the baseline noise).
    jac : (n, 9) ∂f/∂params of the exact scalar equation at the baseline; residual : (n,) f; sigma : (n,) its predicted sd.
    n_tests : candidates tried (:func:`count_tests`).
    """
    tri = Triad.ACCEL
    orders = [
        1
        if temperature_reason(tab) is not None
        else temperature_bias_order(tab, jac, residual, sigma, i)
        for i in range(3)
    ]
    effects = [
        e for i in range(3) for e in _mean_effects(tab, jac, None, i, orders[i])
    ] + accel_changes(tab, jac)
    u = tab.mean / np.linalg.norm(tab.mean, axis=1, keepdims=True)
    perp = np.eye(3)[None] - np.einsum("ka,kb->kab", u, u)
    out, between, halves = _scalar_records(
        tab, effects, jac, residual, sigma, n_tests, tri, 1.0, perp
    )
    reason = temperature_reason(tab)
    if reason is not None:
        out += [
            not_identifiable(name, tri, ax, reason)
            for ax in AXES
            for name in ("temperature_bias", "temperature_scale", "temperature_hysteresis")
        ]
    out.append(
        not_identifiable(
            "gravity_mismatch",
            tri,
            None,
            "not identifiable: a wrong local g is a common scale error absorbed by ex, ey, ez; needs a passport (known scale factors)",
        )
    )
    return TriadRecords(out, between, halves)


def earth_rate_records(
    tab: PositionTable,
    jac: FloatArray,
    residual: FloatArray,
    sigma: FloatArray,
    f_b_mps2: FloatArray,
    n_tests: int,
) -> TriadRecords:
    """Gyro candidates of the navigation-grade path: the exact scalar equation ``|ω − b − G f| = Ω`` (M1, M4).

    When the position means resolve the Earth rate, its projection on each
    axis is a large, position-dependent signal whose horizontal part depends
    on the unknown heading: regressing the means on the specific force (the
    MEMS path) drowns a g-sensitivity in it. The norm of the compensated rate
    does not depend on the heading (one nuisance angle per position
    eliminated): each effect enters the baseline's scalar residual through
    ``∂f/∂b_i`` (the Earth rate's direction on axis ``i``) times its
    regressor — ``t`` (drift), ``f`` (g-sensitivity, three columns), ``ΔT``
    (temperature bias), ``sign(dT/dt)`` (temperature hysteresis), a step from a
    turn on (bias step, profiled over the breaks) — or through ``∂f/∂e_i·ΔT`` (temperature scale: the
    Earth rate is a known rate). Bias instability is the wander of the
    scalar residual along ``(∂f/∂b_i)²`` and of the half-to-half differences,
    as for the accelerometers. What this gives up: the component of an effect
    perpendicular to the Earth rate (the heading takes it in).

    Parameters
    ----------
    tab : the gyro :class:`PositionTable` normalized by Ω (covariances from the baseline noise).
    jac, residual, sigma : the gyro's exact scalar equation at its baseline (:func:`estimators.audit.statistics.scalar_residuals`).
    f_b_mps2 : (n, 3) specific force of each position (the accelerometer means), m/s².
    n_tests : candidates tried (:func:`count_tests`).
    """
    tri = Triad.GYRO
    effects = [e for i in range(3) for e in _earth_rate_effects(tab, jac, f_b_mps2, i)]
    n = tab.t_mid_s.size
    out, between, halves = _scalar_records(
        tab,
        effects,
        jac,
        residual,
        sigma,
        n_tests,
        tri,
        EARTH_RATE_RPS,
        np.broadcast_to(np.eye(3), (n, 3, 3)),
    )
    reason = temperature_reason(tab)
    for ax in AXES:
        if reason is not None:
            out += [
                not_identifiable(e, tri, ax, reason)
                for e in ("temperature_bias", "temperature_scale", "temperature_hysteresis")
            ]
        out.append(
            not_identifiable(
                "scale_nonlinearity",
                tri,
                ax,
                "not identifiable: static positions give the gyros only the Earth rate (one magnitude)",
            )
        )
    return TriadRecords(out, between, halves)


def _earth_rate_effects(
    tab: PositionTable, jac: FloatArray, f_b_mps2: FloatArray, i: int
) -> list[_MeanEffect]:
    """Mean effects of gyro axis ``i`` on the scalar residual (:func:`earth_rate_records`).

    The keys are SI (rad/s): the coefficients are normalized by Ω and turned
    into SI by ×Ω, so the dimensionless temperature scale enters with its
    regressor (and halves) multiplied by Ω.
    """
    n = tab.t_mid_s.size
    dt = (tab.t_mid_s - tab.t_mid_s.mean())[:, None]
    out = [
        _MeanEffect(
            "bias_drift",
            i,
            ("rate_rps_per_s",),
            jac[:, [i]] * dt,
            -0.5 * tab.duration_s[:, None],
            -1.0,
        ),
        _MeanEffect(
            "g_sensitivity",
            i,
            tuple(f"g{a}_rps_per_mps2" for a in AXES),
            jac[:, [i]] * f_b_mps2,
            np.zeros((n, 3)),
            -1.0,
        ),
        *_change_effects(tab, "bias_step", i, ("step_rps",), jac[:, [i]]),
    ]
    if temperature_reason(tab) is None:
        assert tab.temp_c is not None and tab.temp_halves_c is not None
        dtemp = (tab.temp_c - tab.temp_c.mean())[:, None]
        th = tab.temp_halves_c[:, None]
        out += [
            _MeanEffect("temperature_bias", i, ("coef_rps_per_c",), jac[:, [i]] * dtemp, th, -1.0),
            hysteresis_effect(tab, i, "offset_rps", jac[:, i]),
            _MeanEffect(
                "temperature_scale",
                i,
                ("coef_per_c",),
                jac[:, [3 + i]] * dtemp * EARTH_RATE_RPS,
                tab.mean[:, [i]] * th * EARTH_RATE_RPS,
                -1.0,
            ),
        ]
    return out


def gyro_records(tab: PositionTable, f_b_mps2: FloatArray, n_tests: int) -> TriadRecords:
    """Gyro mean candidates (M4, on the position means) and variance records; the Earth rate enters as :data:`EARTH_RATE_VAR_NORM`.

    ``f_b_mps2`` (n, 3) is the specific force of each position (the accelerometer means), m/s².
    """
    tri = Triad.GYRO
    out: list[Candidate] = []
    n = tab.t_mid_s.size
    reason = temperature_reason(tab)
    ones = np.ones((n, 1))
    resid, var0, halves_mean = np.empty((n, 3)), np.empty((n, 3)), np.zeros((n, 3))
    up = f_b_mps2 / np.linalg.norm(f_b_mps2, axis=1, keepdims=True)
    for i, ax in enumerate(AXES):
        var0[:, i] = tab.cov[:, i, i] + tab.grid_var[i] + EARTH_RATE_VAR_NORM
        y = tab.mean[:, i] - vertical_earth_rate(tab.mean[:, i], up[:, i], var0[:, i]) * up[:, i]
        effects = _mean_effects(tab, None, f_b_mps2, i)
        tests, chosen, hm, sd = _means_with_excess(
            effects, ones, y, var0[:, i], np.ones((1, n)), n_tests, 1
        )
        halves_mean[:, i] = hm[:, 0]
        resid[:, i] = leverage_residual(np.hstack([ones, chosen]), y, sd)
        out += _mean_candidates(effects, tests, tri, EARTH_RATE_RPS, f"gyro {ax} position means")
        if reason is not None:
            out += [
                not_identifiable(e, tri, ax, reason)
                for e in ("temperature_bias", "temperature_hysteresis")
            ]
        out.append(
            not_identifiable(
                "temperature_scale",
                tri,
                ax,
                "not identifiable: the gyro scale needs a known rate (the Earth rate is below a MEMS gyro's noise)",
            )
        )
        out.append(
            not_identifiable(
                "scale_nonlinearity",
                tri,
                ax,
                "not identifiable: static positions give the gyros only the Earth rate",
            )
        )
    diag = np.stack([np.broadcast_to(np.diag(np.eye(3)[i]), (n, 3, 3)) for i in range(3)])
    between = VarianceData.finite(resid, np.einsum("ki,ij->kij", var0, np.eye(3)), diag)
    return TriadRecords(
        out, between, _halves_record(tab, halves_mean, np.broadcast_to(np.eye(3), (n, 3, 3)))
    )


def vertical_earth_rate(mean_norm: FloatArray, up_i: FloatArray, var: FloatArray) -> float:
    """The vertical Earth rate's share ``c·u_i`` of one gyro axis' means, ``|c| ≤ 1`` (normalized by Ω).

    The Earth rate's vertical part ``Ω sin φ · u`` follows the gravity direction
    like a diagonal g-sensitivity of ``Ω sin φ / g``; the latitude is not known,
    so ``c = sin φ`` is fitted (weighted least squares with an intercept) and
    clipped to [−1, 1]: a diagonal g-sensitivity is named only beyond what the
    Earth rate could be.
    """
    a = np.column_stack([np.ones_like(up_i), up_i]) / np.sqrt(var)[:, None]
    coef, *_ = np.linalg.lstsq(a, mean_norm / np.sqrt(var), rcond=None)
    return float(np.clip(coef[1], -1.0, 1.0))


def variance_effects(has_gyro: bool) -> list[VarianceEffect]:
    """``bias_instability`` per axis of each triad and ``nonstatic_positions``, over the records
    ``[accel between, accel halves, gyro between, gyro halves]`` (the last two only with a gyro)."""
    out = [VarianceEffect("bias_instability", Triad.ACCEL, i, ((0, i), (1, i))) for i in range(3)]
    if has_gyro:
        out += [
            VarianceEffect("bias_instability", Triad.GYRO, i, ((2, i), (3, i))) for i in range(3)
        ]
    out.append(
        VarianceEffect(
            "nonstatic_positions", Triad.ACCEL, None, ((1, 3), (3, 3)) if has_gyro else ((1, 3),)
        )
    )
    return out
