"""The scalar check F0 of a triad on every sample (methods.md M1).

Normalization
-------------
A triad's output is divided by its scalar reference (:func:`estimators.conventions.reference_magnitude`):
``ã = a / g`` for the accelerometers, ``ω̃ = ω / Ω`` for the gyros. ``g`` is the
local gravity magnitude, either configured or from WGS-84 normal gravity
(:func:`triad_reference`).

Optionally the passport's nominal errors are compensated first, so the shell is
centred on the *calibrated* output: with the triad model of
:mod:`estimators.conventions` (``ã = A u + b``) the compensated output is
``u' = A⁻¹ (ã − b)``, which has unit norm for a static unit whose errors equal
the passport's.

The predicate
-------------
``s = ½(|ã|² − 1)`` (the left side of M1's scalar calibration equation) and::

    F0 = OK    if |s| ≤ λ0      (the paper's accelerometer form, two-sided)
         FAIL  otherwise
         NOT_APPLICABLE  while the unit is not static (the scalar relation does
                         not hold there: F0 then says nothing, it never "fails")

With ``n_avg > 1`` the test is applied to the mean of ``n_avg`` consecutive
static samples (non-overlapping windows aligned at the start of each static
run); every sample then carries the outcome of the last completed window of its
run, and ``NOT_APPLICABLE`` until the first window of the run completes.

λ0 is derived, not chosen: :func:`derive_lambda0`.

Persistence
-----------
λ0 bounds the white noise of a resting unit. A knock on a resting vehicle (a
hand on a hand-held unit, a door, a wheel chock) rings for a few milliseconds
far outside any noise bound, while every sensor fault of M1's model (a zero
signal, a scale factor or an axis that moved) stays. A failure is therefore
declared where ``persist`` consecutive samples fail
(:func:`persistent_failure`), dated at its first failing sample; ``persist = 1``
is the bare predicate.
"""

from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import BoolArray, FloatArray, IntArray, StateArray
from estimators.conventions import Triad, normal_gravity_mps2, reference_magnitude


class F0State(IntEnum):
    """Outcome of F0 for one sample (the paper's F0 = 1 / 0, plus "not applicable")."""

    OK = 1
    FAIL = 0
    NOT_APPLICABLE = -1


_OK = F0State.OK
_FAIL = F0State.FAIL
_NA = F0State.NOT_APPLICABLE


def triad_reference(
    triad: Triad,
    *,
    gravity_mps2: float | None = None,
    latitude_deg: float | None = None,
    height_m: float = 0.0,
) -> float:
    """The scalar reference of a triad in its SI unit (g in m/s², Ω in rad/s).

    For accelerometers exactly one of ``gravity_mps2`` (a configured, e.g.
    measured, value) or ``latitude_deg`` (WGS-84 normal gravity at
    ``height_m``) must be given; gyros always use the Earth rate.
    """
    triad = Triad(triad)
    if triad is Triad.GYRO:
        return reference_magnitude(triad, math.nan)
    if (gravity_mps2 is None) == (latitude_deg is None):
        raise ValueError(
            "give exactly one of gravity_mps2 or latitude_deg for the accelerometer reference"
        )
    if gravity_mps2 is not None:
        if not (math.isfinite(gravity_mps2) and 9.7 < gravity_mps2 < 9.9):
            raise ValueError(
                f"gravity_mps2 must be a surface gravity within (9.7, 9.9), got {gravity_mps2!r}"
            )
        return reference_magnitude(triad, gravity_mps2)
    assert latitude_deg is not None  # exactly one of the two is given (checked above)
    return reference_magnitude(triad, normal_gravity_mps2(latitude_deg, height_m))


def normalize(x_si: FloatArray, reference: float) -> FloatArray:
    """``x / reference`` as a new array (never in place): (N, 3) SI → (N, 3) dimensionless."""
    if not (math.isfinite(reference) and reference > 0.0):
        raise ValueError(f"reference must be finite and > 0, got {reference!r}")
    return np.asarray(x_si, dtype=float) / reference


def scalar_residual(x_norm: FloatArray) -> FloatArray:
    """``½(|x|² − 1)`` per row: (N, 3) normalized outputs → (N,) (methods.md M1, left side)."""
    x = np.asarray(x_norm, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x_norm must have shape (N, 3), got {x.shape}")
    norm2: FloatArray = np.einsum("ij,ij->i", x, x)
    return 0.5 * (norm2 - 1.0)


def compensate(x_norm: FloatArray, bias_norm: FloatArray, matrix: FloatArray) -> FloatArray:
    """``A⁻¹ (x − b)`` per row: the output with the passport's nominal errors removed.

    ``matrix`` is ``A`` of :func:`estimators.conventions.triad_matrix`; solved, not inverted.
    """
    x = np.asarray(x_norm, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x_norm must have shape (N, 3), got {x.shape}")
    return np.linalg.solve(np.asarray(matrix, float), (x - np.asarray(bias_norm, float)).T).T


@dataclass(frozen=True)
class F0Config:
    """What F0 needs for one triad.

    Attributes
    ----------
    lambda0 : half thickness of the shell in ``s = ½(|ã|²−1)`` (dimensionless), from :func:`derive_lambda0`.
    reference : the triad's scalar reference in its SI unit (g in m/s², Ω in rad/s).
    bias_norm : (3,) nominal normalized zero signals to compensate (default none).
    matrix : (3, 3) nominal ``A`` of :func:`estimators.conventions.triad_matrix` (default identity).
    n_avg : samples per tested window mean (default 1: every sample is tested).
    """

    lambda0: float
    reference: float
    bias_norm: ArrayLike = (0.0, 0.0, 0.0)
    matrix: ArrayLike = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    n_avg: int = 1
    _affine: tuple[FloatArray, FloatArray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lambda0) and self.lambda0 > 0.0):
            raise ValueError(f"lambda0 must be finite and > 0, got {self.lambda0!r}")
        if not (math.isfinite(self.reference) and self.reference > 0.0):
            raise ValueError(f"reference must be finite and > 0, got {self.reference!r}")
        b = np.asarray(self.bias_norm, dtype=float)
        a = np.asarray(self.matrix, dtype=float)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ValueError(f"bias_norm must be 3 finite numbers, got {self.bias_norm!r}")
        if a.shape != (3, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"matrix must be a finite 3x3 matrix, got {self.matrix!r}")
        if np.linalg.cond(a) > 1e6:
            raise ValueError(f"matrix is singular or nearly so (condition {np.linalg.cond(a):.3g})")
        if (
            isinstance(self.n_avg, bool)
            or not isinstance(self.n_avg, (int, np.integer))
            or self.n_avg < 1
        ):
            raise ValueError(f"n_avg must be an integer >= 1, got {self.n_avg!r}")
        object.__setattr__(self, "bias_norm", tuple(float(v) for v in b))
        object.__setattr__(self, "matrix", tuple(tuple(float(v) for v in row) for row in a))
        object.__setattr__(self, "n_avg", int(self.n_avg))
        # Solved here, once: a stream's F0 uses them on every frame (two 3×3 solves were
        # 7 % of a 5-sample frame's cost in the pipeline).
        m = np.linalg.solve(a, np.eye(3)) / self.reference
        c = np.linalg.solve(a, b)
        m.flags.writeable = c.flags.writeable = False
        object.__setattr__(self, "_affine", (m, c))

    @property
    def is_uncompensated(self) -> bool:
        """No nominal errors to remove (zero bias, identity matrix)."""
        return self.bias_norm == (0.0, 0.0, 0.0) and self.matrix == (
            (1.0, 0.0, 0.0),
            (0.0, 1.0, 0.0),
            (0.0, 0.0, 1.0),
        )

    def affine(self) -> tuple[FloatArray, FloatArray]:
        """``(M, c)`` with ``u' = M x_si − c``: ``M = A⁻¹ / reference``, ``c = A⁻¹ b`` (read-only).

        The 3×3 ``A`` is solved against the identity and against ``b`` when the
        config is made; folding ``1/reference`` into ``M`` lets the per-sample path
        work on raw SI floats.
        """
        return self._affine


@dataclass(frozen=True)
class F0Result:
    """F0 over a batch of N samples.

    Attributes
    ----------
    state : (N,) int8, values of :class:`F0State`.
    residual : (N,) the tested statistic ``s`` (of the sample, or of its window mean
        when ``n_avg > 1``); NaN where the state is NOT_APPLICABLE.
    n_tests : number of shell tests made (samples, or windows when ``n_avg > 1``).
    n_fail : tests that failed.
    n_rejected : non-finite samples (counted, never tested).
    """

    state: StateArray
    residual: FloatArray
    n_tests: int
    n_fail: int
    n_rejected: int


def f0_batch(x_si: FloatArray, static: BoolArray, config: F0Config) -> F0Result:
    """F0 on N samples at once (methods.md M1, the predicate F0).

    Parameters
    ----------
    x_si : (N, 3) triad output in its SI unit (m/s² or rad/s), sensor axes.
    static : (N,) bool, True where the unit is static (e.g. from
        :func:`estimators.static_detector.detect_static`).
    config : threshold, reference, nominal compensation, window length.

    Gives the same states as feeding the rows one by one to :class:`F0Monitor`.
    """
    x = np.asarray(x_si, dtype=float)
    st = np.asarray(static)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x_si must have shape (N, 3), got {x.shape}")
    if st.shape != (x.shape[0],) or st.dtype != bool:
        raise ValueError(
            f"static must be a bool array of shape ({x.shape[0]},), got {st.dtype} {st.shape}"
        )
    m, c = config.affine()
    if config.n_avg == 1 and config.is_uncompensated:
        # Nothing to compensate: |x|²/ref² directly, without an (N, 3) temporary.
        s = np.einsum("ij,ij->i", x, x)
        s *= 0.5 / config.reference**2
        s -= 0.5
    else:
        with np.errstate(invalid="ignore"):  # NaN rows are expected: counted below
            u = x @ m.T
        u -= c
        s = scalar_residual(u)
    finite = np.isfinite(s)
    n_rejected = int(x.shape[0] - np.count_nonzero(finite))
    if config.n_avg != 1:
        return _f0_windows(u, st, finite, config, n_rejected)
    tested = st & finite
    ok = tested & (np.abs(s) <= config.lambda0)
    # OK = 1, FAIL = 0, NOT_APPLICABLE = -1 from two boolean masks: ok + (tested − 1).
    state = ok.view(np.int8) + (tested.view(np.int8) - np.int8(1))
    residual = np.where(tested, s, np.nan)
    n_tests = int(np.count_nonzero(tested))
    return F0Result(state, residual, n_tests, int(n_tests - np.count_nonzero(ok)), n_rejected)


def persistent_failure(state: StateArray, run_in: int, persist: int) -> tuple[int, int]:
    """Where F0's failure becomes persistent (module docstring, Persistence).

    Parameters
    ----------
    state : (N,) :class:`F0State` values of consecutive samples (any other state breaks a run).
    run_in : failing samples in a row just before these (carried across batches).
    persist : failing samples in a row that make a failure (≥ 1).

    Returns ``(k, run_out)``: the index of the sample that completes the first
    run of ``persist`` failing samples (−1 if none; the run began at
    ``k − persist + 1``, before this batch when that is negative), and the
    failing samples in a row at the end of the batch. Cutting the samples into
    batches anywhere gives the same failures.
    """
    if persist < 1 or run_in < 0:
        raise ValueError(f"persist must be >= 1 and run_in >= 0, got {persist!r}, {run_in!r}")
    fail = np.asarray(state) == _FAIL
    n = fail.size
    if n == 0:
        return -1, int(run_in)
    if not fail.any():  # the usual batch: no run, nothing carried
        return -1, 0
    idx = np.arange(n)
    last_break = np.maximum.accumulate(np.where(fail, -1, idx))
    run = np.where(last_break < 0, idx + 1 + run_in, idx - last_break)
    hits = np.flatnonzero(run >= persist)
    return (int(hits[0]) if hits.size else -1), int(run[-1])


def persistence_samples(persistence_s: float, rate_hz: float) -> int:
    """Failing samples in a row that make a persistent F0 failure: ``persistence_s`` at ``rate_hz``,
    at least one (module docstring, Persistence)."""
    return max(1, round(persistence_s * rate_hz))


@dataclass(frozen=True)
class F0Session:
    """F0 over a whole session, its failures split into persistent ones and knocks (module docstring).

    Attributes
    ----------
    tested, failed : shell tests made and failed.
    persist : failing samples in a row that make a failure.
    runs : runs of failing samples in a row (a sample not failing, tested or not, ends a run).
    persistent_runs : those of at least ``persist`` samples; the others are knocks.
    first_fail_t_s : time of the first failing sample, s (None without failures).
    worst : largest ``|s|`` of a failing sample (None without failures).
    onset_t_s : first sample of the first persistent run, s (None without one): when the
        failure began, as the service dates its F0 event.
    onset_residual : ``s`` of that sample.
    persistent_failed : failing samples inside persistent runs.
    persistent_worst : largest ``|s|`` inside persistent runs (None without one).
    """

    tested: int
    failed: int
    persist: int
    runs: int
    persistent_runs: int
    first_fail_t_s: float | None
    worst: float | None
    onset_t_s: float | None
    onset_residual: float | None
    persistent_failed: int
    persistent_worst: float | None

    @property
    def persistent(self) -> bool:
        """F0 failed persistently: a finding, not a knock."""
        return self.persistent_runs > 0

    @property
    def knocks(self) -> int:
        """Failing runs shorter than the persistence: counted, not a finding."""
        return self.runs - self.persistent_runs


def f0_session(
    t_s: FloatArray, x_si: FloatArray, static: BoolArray, config: F0Config, persist: int
) -> F0Session:
    """F0 on every static sample of a session (:func:`f0_batch`) with the persistence rule of
    :func:`persistent_failure` applied to the whole of it: ``persist`` failing samples in a row
    are a failure, dated at their first; shorter runs are knocks."""
    if persist < 1:
        raise ValueError(f"persist must be >= 1, got {persist!r}")
    t = np.asarray(t_s, dtype=float)
    res = f0_batch(x_si, static, config)
    if t.shape != res.state.shape:
        raise ValueError(f"t_s must have shape {res.state.shape}, got {t.shape}")
    fail = res.state == _FAIL
    edges = np.diff(np.concatenate([[0], fail.view(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    long = stops - starts >= persist
    inside = np.zeros(fail.size, dtype=bool)
    for a, b in zip(starts[long], stops[long], strict=True):
        inside[a:b] = True
    failed = np.flatnonzero(fail)
    onset = int(starts[long][0]) if long.any() else None

    def worst(idx: IntArray) -> float | None:
        return float(np.max(np.abs(res.residual[idx]))) if idx.size else None

    return F0Session(
        tested=res.n_tests,
        failed=res.n_fail,
        persist=persist,
        runs=int(starts.size),
        persistent_runs=int(np.count_nonzero(long)),
        first_fail_t_s=float(t[failed[0]]) if failed.size else None,
        worst=worst(failed),
        onset_t_s=None if onset is None else float(t[onset]),
        onset_residual=None if onset is None else float(res.residual[onset]),
        persistent_failed=int(np.count_nonzero(inside)),
        persistent_worst=worst(np.flatnonzero(inside)),
    )


def _f0_windows(
    u: FloatArray, static: BoolArray, finite: BoolArray, config: F0Config, n_rejected: int
) -> F0Result:
    """The ``n_avg > 1`` form of :func:`f0_batch` (non-finite rows are skipped, not run breaks)."""
    n = u.shape[0]
    n_avg = config.n_avg
    rows = np.flatnonzero(finite)
    st = static[rows]
    k = np.arange(rows.size)
    # Position inside the current static run (valid rows only): runs restart after any non-static row.
    run_start = np.maximum.accumulate(np.where(st & ~np.concatenate([[False], st[:-1]]), k, 0))
    pos = k - run_start
    done = st & ((pos + 1) % n_avg == 0)
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(u[rows], axis=0)])
    ends = np.flatnonzero(done)
    wmean = (csum[ends + 1] - csum[ends + 1 - n_avg]) / n_avg
    ws = scalar_residual(wmean)
    wok = np.abs(ws) <= config.lambda0
    # Each static row carries the last completed window of its own run.
    last = np.maximum.accumulate(np.where(done, k, -1))
    has = st & (last >= run_start)
    widx = np.searchsorted(ends, last[has])
    state_v = np.full(rows.size, np.int8(_NA), dtype=np.int8)
    state_v[has] = np.where(wok[widx], np.int8(_OK), np.int8(_FAIL))
    res_v = np.full(rows.size, np.nan)
    res_v[has] = ws[widx]
    state = np.full(n, np.int8(_NA), dtype=np.int8)
    residual = np.full(n, np.nan)
    state[rows] = state_v
    residual[rows] = res_v
    return F0Result(
        state, residual, int(ends.size), int(ends.size - np.count_nonzero(wok)), n_rejected
    )


class F0Monitor:
    """F0 one sample at a time: O(1), plain floats, no array allocation per sample.

    ``check(x, y, z, static)`` takes one triad sample in its SI unit and whether
    the unit is static at that sample; it returns an :class:`F0State`. A
    non-finite sample is counted in ``n_rejected``, returns NOT_APPLICABLE and
    leaves the state untouched. Same decisions as :func:`f0_batch`.
    """

    __slots__ = (
        "_c",
        "_count",
        "_lam",
        "_last",
        "_m",
        "_n_avg",
        "_sx",
        "_sy",
        "_sz",
        "config",
        "last_residual",
        "n_fail",
        "n_not_applicable",
        "n_rejected",
        "n_tests",
    )

    def __init__(self, config: F0Config) -> None:
        self.config = config
        m, c = config.affine()
        self._m = tuple(float(v) for v in m.ravel())
        self._c = tuple(float(v) for v in c)
        self._lam = config.lambda0
        self._n_avg = config.n_avg
        self._sx = self._sy = self._sz = 0.0
        self._count = 0
        self._last = _NA
        self.last_residual = math.nan
        self.n_tests = 0
        self.n_fail = 0
        self.n_not_applicable = 0
        self.n_rejected = 0

    def check(self, x: float, y: float, z: float, static: bool) -> F0State:
        m00, m01, m02, m10, m11, m12, m20, m21, m22 = self._m
        c0, c1, c2 = self._c
        u = m00 * x + m01 * y + m02 * z - c0
        v = m10 * x + m11 * y + m12 * z - c1
        w = m20 * x + m21 * y + m22 * z - c2
        s = 0.5 * (u * u + v * v + w * w - 1.0)
        # Any NaN/Inf input makes s non-finite (0·inf is NaN too): one test covers all axes.
        if not math.isfinite(s):
            self.n_rejected += 1
            return _NA
        if not static:
            self._count = 0
            self._sx = self._sy = self._sz = 0.0
            self._last = _NA
            self.n_not_applicable += 1
            return _NA
        if self._n_avg != 1:
            return self._window(u, v, w)
        self.last_residual = s
        self.n_tests += 1
        if -self._lam <= s <= self._lam:
            return _OK
        self.n_fail += 1
        return _FAIL

    def _window(self, u: float, v: float, w: float) -> F0State:
        self._sx += u
        self._sy += v
        self._sz += w
        self._count += 1
        if self._count == self._n_avg:
            k = 1.0 / self._n_avg
            mu, mv, mw = self._sx * k, self._sy * k, self._sz * k
            s = 0.5 * (mu * mu + mv * mv + mw * mw - 1.0)
            self._count = 0
            self._sx = self._sy = self._sz = 0.0
            self.last_residual = s
            self.n_tests += 1
            if -self._lam <= s <= self._lam:
                self._last = _OK
            else:
                self.n_fail += 1
                self._last = _FAIL
        if self._last is _NA:
            self.n_not_applicable += 1
        return self._last

    def state_dict(self) -> dict[str, Any]:
        """Plain JSON-able state (counters and the open window) for checkpoints."""
        return {
            "window_sum": [self._sx, self._sy, self._sz],
            "window_count": self._count,
            "last_state": int(self._last),
            "last_residual": None if math.isnan(self.last_residual) else self.last_residual,
            "n_tests": self.n_tests,
            "n_fail": self.n_fail,
            "n_not_applicable": self.n_not_applicable,
            "n_rejected": self.n_rejected,
        }

    @classmethod
    def from_state_dict(cls, config: F0Config, state: dict[str, Any]) -> F0Monitor:
        mon = cls(config)
        try:
            mon._sx, mon._sy, mon._sz = (float(v) for v in state["window_sum"])
            mon._count = int(state["window_count"])
            mon._last = F0State(int(state["last_state"]))
            lr = state["last_residual"]
            mon.last_residual = math.nan if lr is None else float(lr)
            for name in ("n_tests", "n_fail", "n_not_applicable", "n_rejected"):
                setattr(mon, name, int(state[name]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid F0Monitor state: {exc}") from None
        if not 0 <= mon._count < config.n_avg:
            raise ValueError(
                f"invalid F0Monitor state: window_count {mon._count} outside [0, {config.n_avg})"
            )
        return mon


@dataclass(frozen=True)
class Lambda0:
    """The derived F0 threshold and what it is made of (all dimensionless, in units of ``s``).

    ``lambda0 = noise_threshold + tolerance_first_order + tolerance_second_order + reference_offset``.

    Attributes
    ----------
    lambda0 : the threshold.
    noise_threshold : ``x`` with ``P(|s_noise| > x) = false_alarm_prob`` for a unit exactly at its nominal.
    noise_std : per-test standard deviation of the normalized output used (worst axis, after averaging).
    quadratic_mean : ``E[½|n|²]`` of that noise (the second-order noise term's offset).
    tolerance_first_order : max over orientations of M1's linear error terms with every
        parameter at its tolerance and the worst signs.
    tolerance_second_order : what the exact worst case over orientations and units within
        tolerance (:func:`tolerance_extremes`) adds to the first-order term (the terms
        the linear equation drops, at the worst unit; negative where they reduce it).
    reference_offset : offset from the relative error of the reference (g or Ω).
    false_alarm_prob : stated probability per test (two-sided).
    n_avg : samples per test.
    """

    lambda0: float
    noise_threshold: float
    noise_std: float
    quadratic_mean: float
    tolerance_first_order: float
    tolerance_second_order: float
    reference_offset: float
    false_alarm_prob: float
    n_avg: int


_NCX2_MIN_SIGMA = 1e-4
"""Below this normalized noise scipy's non-central χ² loses accuracy (its non-centrality
1/σ² exceeds 1e8); the Gaussian with the exact two moments is then exact to O(σ)."""


def _ncx2_tails() -> tuple[Any, Any]:
    """The non-central χ² survival function and CDF ``(sf, cdf)(x, df, nc)`` that scipy.stats' ``ncx2`` evaluates.

    Its ``sf`` is the ufunc ``scipy.special._ufuncs._ncx2_sf`` (Boost's), its ``cdf``
    ``scipy.special.chndtr``: called directly they give its values bit for bit
    (tests/test_scalar.py holds them to ``scipy.stats``), and scipy.special loads in a
    fraction of the time scipy.stats takes (benchmarks/bench_sixpos_calibrate.py). A scipy
    without that private ufunc gets scipy.stats' own.
    """
    from scipy import special

    sf = getattr(special._ufuncs, "_ncx2_sf", None)
    if sf is None:
        from scipy import stats

        return stats.ncx2.sf, stats.ncx2.cdf
    return sf, special.chndtr


def _noise_tail(x: float, sigma: float) -> float:
    """``P(|s| > x)`` for ``s = ½(|u + n|² − 1)``, ``|u| = 1``, ``n ~ N(0, σ² I₃)``."""
    from scipy import special  # loaded when λ0 is derived, not with the module

    if sigma >= _NCX2_MIN_SIGMA:
        nc = 1.0 / (sigma * sigma)
        sf, cdf = _ncx2_tails()
        with np.errstate(over="ignore"):  # as scipy.stats calls them (its gh-17432)
            up = sf((1.0 + 2.0 * x) * nc, 3, nc)
            lo = cdf((1.0 - 2.0 * x) * nc, 3, nc) if 2.0 * x < 1.0 else 0.0
        return float(up + lo)
    mean = 1.5 * sigma**2
    sd = math.sqrt(sigma**2 + 1.5 * sigma**4)
    # The normal's sf(z) and cdf(z) as scipy.stats.norm takes them: ndtr(−z) and ndtr(z).
    return float(special.ndtr(-((x - mean) / sd)) + special.ndtr((-x - mean) / sd))


def _worst_first_order(tol: FloatArray) -> float:
    """``max_{|u|=1} Σ tb_i|u_i| + Σ te_i u_i² + td1|u_x u_y| + td2|u_x u_z| + td3|u_y u_z|``.

    With free signs of the nine errors the worst ``|s|`` is this sum of absolute
    terms, whose maximum lies in the positive octant: a grid over the octant's
    two angles, refined by a bounded quasi-Newton step from the best node.
    """
    tb, te, td = tol[:3], tol[3:6], tol[6:]

    def value(angles: FloatArray) -> FloatArray:
        th, ph = angles[..., 0], angles[..., 1]
        ux, uy, uz = np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)
        worst: FloatArray = (
            tb[0] * ux
            + tb[1] * uy
            + tb[2] * uz
            + te[0] * ux**2
            + te[1] * uy**2
            + te[2] * uz**2
            + td[0] * ux * uy
            + td[1] * ux * uz
            + td[2] * uy * uz
        )
        return worst

    g = np.linspace(0.0, 0.5 * np.pi, 61)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1)
    vals = value(grid)
    best = np.unravel_index(np.argmax(vals), vals.shape)
    from scipy import optimize  # loaded when λ0 is derived, not with the module

    res = optimize.minimize(
        lambda a: -value(a), grid[best], method="L-BFGS-B", bounds=[(0.0, 0.5 * np.pi)] * 2
    )
    return float(max(vals[best], -res.fun))


_SPHERE_POINTS = 2000
"""Directions of the sphere grid that seeds the exact worst case (about 4.6° apart); the bounded
refinement from the best node makes the result exact to the optimizer's tolerance."""


def _model_matrices(params: FloatArray) -> FloatArray:
    """The matrices ``A = diag(1 + e) R`` (M, 3, 3) of :func:`_static_residual` for parameter rows ``params`` (M, 9)."""
    d = params[:, 6:]
    c = np.empty((params.shape[0], 3, 3))
    c[:, 0, 0] = c[:, 1, 1] = c[:, 2, 2] = 1.0
    c[:, 0, 1] = c[:, 1, 0] = d[:, 0]
    c[:, 0, 2] = c[:, 2, 0] = d[:, 1]
    c[:, 1, 2] = c[:, 2, 1] = d[:, 2]
    w, v = np.linalg.eigh(c)
    root = np.einsum("mij,mj,mkj->mik", v, np.sqrt(np.maximum(w, 0.0)), v)
    a: FloatArray = (1.0 + params[:, 3:6])[:, :, None] * root
    return a


def _static_residual(params: FloatArray, u: FloatArray) -> FloatArray:
    """``s = ½(|A u + b|² − 1)`` (M, K) of the conventions model for parameter rows ``params`` (M, 9) and directions ``u`` (K, 3).

    ``A = diag(1 + e) R`` with ``R Rᵀ`` the matrix of the cosines δ: every ``A`` with the same
    ``A Aᵀ`` maps the unit sphere onto the same ellipsoid, so the symmetric square root is as good
    as the sensor axes themselves. A cosine matrix that is not positive semi-definite (axes that no
    real triad has) is clipped to the nearest one that is.
    """
    return _residual_of(_model_matrices(params), params[:, :3], u)


def _residual_of(a: FloatArray, b: FloatArray, u: FloatArray) -> FloatArray:
    """``½(|A u + b|² − 1)`` (M, K) for matrices ``a`` (M, 3, 3), offsets ``b`` (M, 3) and directions ``u`` (K, 3)."""
    out = np.einsum("mij,kj->mki", a, u) + b[:, None, :]
    res: FloatArray = 0.5 * (np.einsum("mki,mki->mk", out, out) - 1.0)
    return res


def tolerance_extremes(tolerance_norm: ArrayLike) -> tuple[float, float]:
    """The least and the largest ``s = ½(|ã|² − 1)`` a static unit within ``tolerance_norm`` reads (methods.md M1).

    Exact over every orientation and every unit of the conventions model
    (:mod:`estimators.conventions`: ``ãᵢ = (1 + eᵢ) sᵢ·u + bᵢ``, ``sᵢ·sⱼ = δ``) whose nine
    parameters lie anywhere within ± ``tolerance_norm`` (order ``[bx by bz ex ey ez d1 d2 d3]``,
    normalized), without noise: the tolerance part of F0's shell, no first-order expansion
    and no bound on the terms it drops. A sphere grid at every corner of the parameter box
    seeds a bounded search over the two angles and the nine parameters, from the best node
    for each side. Returns ``(s_min, s_max)``; both 0 for zero tolerances.
    """
    tol = np.asarray(tolerance_norm, dtype=float).reshape(-1)
    if tol.shape != (9,) or not np.all(np.isfinite(tol)) or np.any(tol < 0):
        raise ValueError(f"tolerance_norm must be 9 finite numbers >= 0, got {tolerance_norm!r}")
    # The search costs about 0.1 s and every pipeline, F0 and gross configuration asks for the
    # same few passports' tolerances again: the answer depends on the nine numbers alone.
    return _tolerance_extremes(tuple(float(t) for t in tol))


@functools.lru_cache(maxsize=256)
def _tolerance_extremes(tolerance: tuple[float, ...]) -> tuple[float, float]:
    tol = np.asarray(tolerance)
    if not np.any(tol):
        return 0.0, 0.0
    from scipy import optimize  # loaded when λ0 is derived, not with the module

    corners, u = _search_grid(tol)
    seeds = _grid_extremes(corners, u)

    def residual(x: FloatArray) -> float:
        th, phi = x[0], x[1]
        d = np.array([[np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)]])
        return float(_static_residual(x[2:][None, :], d)[0, 0])

    bounds = [(-np.pi, 2.0 * np.pi)] * 2 + [(-t, t) for t in tol]
    extremes = []
    for sign, (m, j, s_node) in zip((1.0, -1.0), seeds, strict=True):
        start = np.r_[
            np.arccos(np.clip(u[j, 2], -1.0, 1.0)), np.arctan2(u[j, 1], u[j, 0]), corners[m]
        ]
        res = optimize.minimize(
            lambda x, sg=sign: -sg * residual(x),
            start,
            method="L-BFGS-B",
            bounds=bounds,
            options={"ftol": 1e-15, "gtol": 1e-12},
        )
        extremes.append(sign * max(sign * s_node, -float(res.fun)))
    return extremes[1], extremes[0]


def _search_grid(tol: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The nodes that seed :func:`tolerance_extremes`' search: the corners (M, 9) of the box ± ``tol``
    (9,) and :data:`_SPHERE_POINTS` directions (K, 3) spread evenly over the sphere (a Fibonacci lattice)."""
    # (u, b) and (−u, −b) read the same |ã|: the corners with b_x ≥ 0 and the whole sphere suffice.
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 9, indexing="ij")).reshape(9, -1).T
    corners = np.unique(signs[signs[:, 0] > 0] * tol, axis=0)
    k = np.arange(_SPHERE_POINTS) + 0.5
    z = 1.0 - 2.0 * k / _SPHERE_POINTS
    ph = np.pi * (1.0 + 5.0**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return corners, np.stack([r * np.cos(ph), r * np.sin(ph), z], axis=1)


def _grid_extremes(corners: FloatArray, u: FloatArray) -> list[tuple[int, int, float]]:
    """The largest and the least node of ``s = _static_residual(corners, u)``: ``(m, k, s[m, k])`` each,
    the first in ``s``'s row-major order among equals (``np.argmax``/``np.argmin``), the same bits.

    Only the rows that can hold either are evaluated. Over the whole sphere a row's values lie
    between ``½(max(σ_min − |b|, |b| − σ_max, 0)² − 1)`` and ``½((σ_max + |b|)² − 1)``, ``σ`` the
    singular values of its ``A``; every tenth direction of every row bounds the extremes from
    within, and rows whose bounds cannot reach them are left out: for the consumer-MEMS
    tolerances about 30 rows of the 256 corners are evaluated, in a quarter of the whole grid's
    time. The matrices ``A`` are computed for all rows at once, as the whole grid computes them,
    and each kept row's values are those of the whole grid (numpy's einsum computes a row alike
    in a stack of any height; tests/test_scalar.py holds the nodes to the whole grid's).
    """
    a = _model_matrices(corners)
    b = corners[:, :3]
    rows = np.arange(corners.shape[0])
    # Tolerances near 1e300 overflow A: LAPACK's SVD refuses inf (printing on stdout) and NaN
    # nodes order by argmax's rule, not by bounds. The whole grid then, as before the cut.
    if np.all(np.isfinite(a)):
        sv = np.linalg.svd(a, compute_uv=False)
        norm_b = np.sqrt(np.einsum("mi,mi->m", b, b))
        high = 0.5 * ((sv[:, 0] + norm_b) ** 2 - 1.0)
        low = 0.5 * (np.maximum(np.maximum(sv[:, 2] - norm_b, norm_b - sv[:, 0]), 0.0) ** 2 - 1.0)
        # Far above the rounding of the bounds and of the nodes, far below the gaps they leave.
        slack = 1e-9 * (sv[:, 0] + norm_b) ** 2 + 1e-12
        if np.all(np.isfinite(high)):
            # Every node is then finite (|A u + b| <= σ_max + |b|), the bounds order them.
            coarse = _residual_of(a, b, u[::10])
            rows = rows[(high + slack >= coarse.max()) | (low - slack <= coarse.min())]
    s = _residual_of(a[rows], b[rows], u)
    nodes = []
    for flat in (int(np.argmax(s)), int(np.argmin(s))):
        m, k = divmod(flat, u.shape[0])
        nodes.append((int(rows[m]), k, float(s[m, k])))
    return nodes


def derive_lambda0(
    *,
    noise_std_norm: ArrayLike,
    false_alarm_prob: float,
    quantization_norm: ArrayLike | None = None,
    n_avg: int = 1,
    tolerance_norm: ArrayLike | None = None,
    reference_rel_err: float = 0.0,
) -> Lambda0:
    """Derive F0's threshold λ0 from noise, tolerances and a false-alarm probability (methods.md M1).

    Model. For a static unit the tested output is ``ã = P v + b + n`` with
    ``|v| = 1`` (``P = I + D`` symmetric: the triad matrix up to a rotation,
    which does not change the norm), ``b`` the residual zero signals and ``n``
    the noise. Then exactly::

        s = ½(|ã|² − 1) = [v·Dv + b·v] + ½|Dv + b|² + (v + Dv + b)·n + ½|n|²

    1. **Noise.** With the deterministic errors at zero, ``s = v·n + ½|n|²``.
       Taking every axis at the worst variance ``σ² = maxᵢ(σᵢ² + qᵢ²/12) / n_avg``
       (white noise plus uniform quantization of step ``qᵢ``; dividing by
       ``n_avg`` assumes independent samples, which holds for the quantization
       error when the noise is at least about half a step) makes ``|ã|²/σ²`` a
       non-central χ² with 3 degrees of freedom and non-centrality ``1/σ²``: the
       ``½|n|²`` term (mean ``3σ²/2``) is included exactly, not dropped.
       ``noise_threshold`` solves ``P(s > x) + P(s < −x) = p`` (two-sided, as
       the paper's ``|s| ≤ λ0``). For σ < 1e-4 the Gaussian with the exact mean
       ``3σ²/2`` and variance ``σ² + 3σ⁴/2`` is used (skewness O(σ)). The worst
       axis is the worst orientation of the linear term ``v·n`` and
       overestimates ``½|n|²`` for unequal axes: conservative.
    2. **Tolerances, first order.** ``v·Dv + b·v`` is M1's right side
       ``Σ bᵢvᵢ + Σ eᵢvᵢ² + δ1 vxvy + δ2 vxvz + δ3 vyvz``. With each parameter
       anywhere within ± its tolerance the worst ``|s|`` over all orientations
       is the maximum over the unit sphere of the sum of absolute terms
       (:func:`_worst_first_order`).
    3. **Tolerances, exact.** The shell's tolerance part is the largest
       ``|s|`` a noise-free unit within tolerance reads in any orientation,
       computed without expansion (:func:`tolerance_extremes`); what it adds to
       the first-order term (``½|Dv + b|²`` and the second-order part of ``P``
       at the worst unit) is reported as ``tolerance_second_order``. A bound
       on those terms instead (``½(‖D‖ + |b|)²`` and the like) overstates
       them (0.0185 against 0.0158 for the consumer-MEMS tolerances), and F0
       then passes what the tolerances exclude.
    4. **Reference.** A relative error ``r`` of the reference (g or Ω) scales
       ``|ã|`` by ``1 ± r``: an offset of at most ``r + r²/2``.

    ``λ0`` is the sum: the false-alarm probability is ``p`` for a unit exactly
    at the values the monitor compensates and at most ``p`` for any unit within
    tolerance. The noise cross term ``(Dv + b)·n`` changes the noise variance by
    a relative O(tolerance) and is neglected.

    Parameters
    ----------
    noise_std_norm : (3,) per-sample white-noise standard deviation of each axis,
        normalized (SI value / reference).
    false_alarm_prob : stated probability of a FAIL per test for a healthy static unit, in (0, 1).
    quantization_norm : (3,) converter step of each axis, normalized, or None. Its error
        is taken as zero-mean (rounding to nearest); a truncating converter (M2's
        Entier) reads low by half a step on average: compensate that in ``bias_norm``
        of :class:`F0Config` (M2's half-pulse correction) or add it to the
        zero-signal tolerances.
    n_avg : samples per tested window mean (:class:`F0Config`).
    tolerance_norm : (9,) bound of each parameter's deviation from the values
        the monitor compensates, order ``[bx by bz ex ey ez d1 d2 d3]``,
        normalized: the passport tolerances when the monitor compensates the
        passport's nominal values, ``|nominal| + tolerance`` when it does not.
        None: zero.
    reference_rel_err : bound of the relative error of the reference, ≥ 0.
    """
    # A service derives each unit's λ0 more than once (the static detector's gyro bound, F0's
    # configuration, its coverage): the answer depends on these numbers alone.
    return _lambda0(
        *_lambda0_inputs(
            noise_std_norm,
            false_alarm_prob,
            quantization_norm,
            n_avg,
            tolerance_norm,
            reference_rel_err,
        )
    )


def lambda0_lower_bound(**inputs: Any) -> float:
    """A lower bound of :func:`derive_lambda0`'s λ0 for the same keyword arguments, without scipy (methods.md M1).

    ``σ·Φ⁻¹(1 − p)·(1 − 1e-9) + r + r²/2``, with σ the worst axis as λ0 takes it and ``r`` the
    reference's relative error. Whoever needs to know only that no statistic exceeds λ0, or
    that λ0 exceeds a limit, learns it from this bound when it holds, in microseconds, and
    needs the exact λ0 (scipy's χ² tails, root finding and the tolerances' worst case, a
    few hundred ms in a fresh process) only when it does not.

    Proof, term by term of λ0 = x_p + T + (r + r²/2) (:func:`derive_lambda0`):

    * **Noise.** ``x_p`` solves ``P(|s| > x) = p`` for ``s = ½(|u + n|² − 1)``, ``|u| = 1``,
      ``n ~ N(0, σ² I₃)`` (M1's equation with the deterministic errors at zero). Split
      ``n = n₁u + n⊥`` (``n₁ ~ N(0, σ²)``, ``n⊥ ⊥ u``): ``|u + n|² = (1 + n₁)² + |n⊥|² ≥
      (1 + n₁)²``, so ``s ≥ n₁ + ½n₁²``, and for ``x ≥ 0`` every ``n₁ > x`` makes ``s > x``:
      ``P(|s| > x) ≥ P(s > x) ≥ P(n₁ > x) = 1 − Φ(x/σ)``. At ``x = σΦ⁻¹(1 − p)`` the tail is
      thus at least ``p``; it falls with ``x``, so its root ``x_p`` lies at or beyond. The
      Gaussian λ0 takes below σ = 1e-4 (mean ``3σ²/2 ≥ 0``, standard deviation ``≥ σ``)
      obeys the same: its upper tail at ``σΦ⁻¹(1 − p)`` is at least ``p`` too. The factor
      ``1 − 1e-9`` leaves room for the root finder's tolerance (relative 1e-12) and the
      tails' rounding; for ``p ≥ ½`` the noise term is bounded by 0.
    * **Tolerances.** ``T = max(s_max, −s_min)`` of :func:`tolerance_extremes`, and
      ``s_max ≥ s_min`` (both are the extremes of one set of values, the search's start
      included), so ``T ≥ (s_max − s_min)/2 ≥ 0``: bounded by 0.
    * **Reference.** The same closed form as λ0's.

    tests/test_scalar.py holds the bound below the exact λ0 on random inputs (both tail paths,
    quantization, averaging, tolerances).
    """
    # derive_lambda0's own checks and defaults, so that both read the same inputs alike.
    args = inspect.signature(derive_lambda0).bind(**inputs)
    args.apply_defaults()
    sigma, p, _, ref_err, _ = _lambda0_inputs(**args.arguments)
    from statistics import NormalDist  # the standard library's, not scipy's: the point of it

    noise = max(0.0, sigma * NormalDist().inv_cdf(1.0 - p) * (1.0 - 1e-9))
    return noise + ref_err + 0.5 * ref_err**2


def _lambda0_inputs(
    noise_std_norm: ArrayLike,
    false_alarm_prob: float,
    quantization_norm: ArrayLike | None,
    n_avg: int,
    tolerance_norm: ArrayLike | None,
    reference_rel_err: float,
) -> tuple[float, float, tuple[float, ...], float, int]:
    """:func:`derive_lambda0`'s inputs checked, as :func:`_lambda0` takes them: σ of the worst
    axis after quantization and averaging, p, the nine tolerances, the reference's error, n_avg."""
    sig = np.asarray(noise_std_norm, dtype=float).reshape(-1)
    if sig.shape != (3,) or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError(
            f"noise_std_norm must be 3 finite positive numbers, got {noise_std_norm!r}"
        )
    if not (0.0 < false_alarm_prob < 1.0):
        raise ValueError(f"false_alarm_prob must be in (0, 1), got {false_alarm_prob!r}")
    if isinstance(n_avg, bool) or not isinstance(n_avg, (int, np.integer)) or n_avg < 1:
        raise ValueError(f"n_avg must be an integer >= 1, got {n_avg!r}")
    var = sig**2
    if quantization_norm is not None:
        q = np.asarray(quantization_norm, dtype=float).reshape(-1)
        if q.shape != (3,) or not np.all(np.isfinite(q)) or np.any(q < 0):
            raise ValueError(
                f"quantization_norm must be 3 finite numbers >= 0, got {quantization_norm!r}"
            )
        var = var + q**2 / 12.0
    tol = (
        np.zeros(9)
        if tolerance_norm is None
        else np.asarray(tolerance_norm, dtype=float).reshape(-1)
    )
    if tol.shape != (9,) or not np.all(np.isfinite(tol)) or np.any(tol < 0):
        raise ValueError(f"tolerance_norm must be 9 finite numbers >= 0, got {tolerance_norm!r}")
    if not (math.isfinite(reference_rel_err) and 0.0 <= reference_rel_err < 1.0):
        raise ValueError(f"reference_rel_err must be in [0, 1), got {reference_rel_err!r}")

    sigma = math.sqrt(float(var.max()) / n_avg)
    return (
        sigma,
        float(false_alarm_prob),
        tuple(float(t) for t in tol),
        float(reference_rel_err),
        int(n_avg),
    )


@functools.lru_cache(maxsize=256)
def _lambda0(
    sigma: float,
    false_alarm_prob: float,
    tolerance: tuple[float, ...],
    reference_rel_err: float,
    n_avg: int,
) -> Lambda0:
    tol = np.asarray(tolerance)
    hi = 10.0 * sigma + sigma**2
    while _noise_tail(hi, sigma) > false_alarm_prob:
        hi *= 2.0
    from scipy import optimize

    x_p = optimize.brentq(
        lambda x: _noise_tail(x, sigma) - false_alarm_prob, 0.0, hi, xtol=1e-15, rtol=1e-12
    )

    first = _worst_first_order(tol) if np.any(tol) else 0.0
    s_min, s_max = tolerance_extremes(tol)
    second = max(s_max, -s_min) - first
    ref = reference_rel_err + 0.5 * reference_rel_err**2
    return Lambda0(
        lambda0=float(x_p + first + second + ref),
        noise_threshold=float(x_p),
        noise_std=sigma,
        quadratic_mean=1.5 * sigma**2,
        tolerance_first_order=first,
        tolerance_second_order=second,
        reference_offset=ref,
        false_alarm_prob=false_alarm_prob,
        n_avg=n_avg,
    )
