"""The offline chain of methods.md M1 on a whole session.

Fig. 2 of M1, offline: static detection → positions → the 9 parameters of each
triad with covariance → predicates F1…F9 against the passport. Used by the
``calibrate`` and ``diagnose`` commands and by the audit; the streaming service
runs the same steps sample by sample (``service/pipeline/``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from estimators._typing import FloatArray
from estimators.conventions import DEFAULT_FALSE_ALARM_PROB, N_PARAMS, Triad, reference_magnitude
from estimators.ninepar import (
    SOURCE_SCALAR,
    SOURCE_VECTOR,
    Estimate,
    Method,
    Verdict,
    ellipsoid_residual,
    equation_sigma,
    estimate_refined,
    estimate_triad,
    judged_estimate,
    not_observable_estimate,
    position_arrays,
)
from estimators.passport import Passport
from estimators.positions import (
    Position,
    PositionConfig,
    PositionRejection,
    PositionsResult,
    build_positions,
)
from estimators.session import ImuSession, Rejections, validate_session
from estimators.sixpos import (
    FULL_TURN_RAD,
    FullTurn,
    face_directions,
    face_positions,
    find_full_turns,
    gyro_nine_from_turns,
    six_face_session,
    six_position_accel_fitter,
)
from estimators.static_detector import StaticDetection, StaticDetectorConfig, detect_static

if TYPE_CHECKING:  # the diagnosis loads when a passport is given: calibrate has none
    from estimators.diagnosis import Diagnosis, Finding

FOREIGN_PASSPORT_MIN_FAILED = 4
"""Failed predicates (and more than half of the evaluated ones) that suggest the passport is another unit's."""


@dataclass(frozen=True)
class ChainConfig:
    """Settings of the offline chain (all defaults documented in their classes).

    Attributes
    ----------
    gravity_mps2 : local gravity magnitude g, m/s² (the accelerometers' reference).
    detector : static / orientation-change detector thresholds.
    positions : trimming, minimum samples and covariance of the position means.
    method : 9-parameter estimator (refined by default: exact, efficient).
    false_alarm_prob : per-triad false-alarm probability of the diagnosis.
    accel_limit_mps2, gyro_limit_rps : full-scale ranges; samples at or beyond them are rejected.
    bias_instability_std : per triad, (3,) normalized bias wander that does not average
        down (the audited model, :attr:`TriadPassport.bias_instability_std`); added to each
        position's covariance. None: the passport's value when diagnosing, else white noise only.
    """

    gravity_mps2: float
    detector: StaticDetectorConfig = field(default_factory=StaticDetectorConfig)
    positions: PositionConfig = field(default_factory=PositionConfig)
    method: Method = Method.REFINED
    false_alarm_prob: float = DEFAULT_FALSE_ALARM_PROB
    accel_limit_mps2: float | None = None
    gyro_limit_rps: float | None = None
    bias_instability_std: dict[Triad, FloatArray] | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.gravity_mps2) or not 9.7 < self.gravity_mps2 < 9.9:
            raise ValueError(
                f"gravity_mps2 must be a local gravity value near 9.8 m/s², got {self.gravity_mps2!r}"
            )
        for name in ("accel_limit_mps2", "gyro_limit_rps"):
            limit = getattr(self, name)
            if limit is not None and not (np.isfinite(limit) and limit > 0.0):
                raise ValueError(
                    f"{name} must be a positive full-scale range or None, got {limit!r}"
                )


@dataclass(frozen=True)
class TriadResult:
    """One triad through the chain.

    Attributes
    ----------
    estimate : the 9 parameters with covariance and observability verdict.
    residuals : (n_positions,) exact scalar equation per position, normalized
        (dimensionless, a fraction of the reference), or None without an estimate.
    residual_sigma : (n_positions,) its predicted standard deviation from the noise.
    diagnosis : predicates F1…F9 against the passport, or None when the
        passport (or the passport of this triad) is missing.
    """

    estimate: Estimate
    residuals: FloatArray | None
    residual_sigma: FloatArray | None
    diagnosis: Diagnosis | None

    @property
    def diagnosed(self) -> bool:
        """At least one of F1…F9 was evaluated: the data allowed a diagnosis of this triad."""
        return self.diagnosis is not None and self.diagnosis.n_evaluated > 0

    @property
    def reason(self) -> str:
        """Why the triad was not diagnosed ("" when it was): no passport, or the estimate's reason
        (too few positions, geometry, noise against the reference), or nothing observable in both."""
        if self.diagnosed:
            return ""
        if self.diagnosis is None:
            return "no passport for this triad"
        if self.estimate.params is None:
            return self.estimate.reason
        return f"no parameter is resolved by both this session and the passport ({self.estimate.reason})"

    @property
    def suspect(self) -> bool:
        """The triad has a passport and positions that determine its parameters, but its fit left the
        physical domain (:attr:`~estimators.ninepar.Estimate.fit_left_domain`): not diagnosed, and not
        to be taken for "no fault" either (a gross fault, values in other units, another unit)."""
        return self.diagnosis is not None and self.estimate.fit_left_domain


@dataclass(frozen=True)
class ChainResult:
    """Everything the offline chain found on a session."""

    n_samples: int
    sample_rejections: Rejections
    detection: StaticDetection
    positions: tuple[Position, ...]
    position_rejections: tuple[PositionRejection, ...]
    triads: dict[Triad, TriadResult]
    gravity_mps2: float
    session: ImuSession | None = None
    """The validated samples the chain ran on."""
    onset: Onset | None = None
    """Where a fault began mid-session (:func:`split_at_onset`); ``triads`` are then the fits
    of the positions after it, ``onset.before`` those of the positions before."""

    @property
    def faults(self) -> tuple[Finding, ...]:
        """The failed predicates of ``triads`` (after the onset, when there is one)."""
        return _findings(self.triads)

    @property
    def faults_before(self) -> tuple[Finding, ...]:
        """The failed predicates of the positions before the onset (none without one)."""
        return () if self.onset is None else _findings(self.onset.before)

    @property
    def diagnosed(self) -> bool:
        """Some triad was diagnosed: "no fault" then means the data were looked at."""
        return any(r.diagnosed for r in self.triads.values())

    @property
    def suspects(self) -> tuple[Triad, ...]:
        """The triads with a passport whose fit left the physical domain (:attr:`TriadResult.suspect`)."""
        return tuple(t for t, r in self.triads.items() if r.suspect)

    @property
    def reason(self) -> str:
        """Why nothing was diagnosed, per triad ("" when something was)."""
        if self.diagnosed:
            return ""
        return "; ".join(f"{t.value}: {r.reason}" for t, r in self.triads.items())

    def predicate_counts(self) -> tuple[int, int]:
        """(failed, evaluated) predicates over all triads."""
        diags = [r.diagnosis for r in self.triads.values() if r.diagnosis is not None]
        return sum(len(d.findings) for d in diags), sum(d.n_evaluated for d in diags)

    @property
    def passport_of_another_unit(self) -> bool:
        """Most predicates fail at once (:data:`FOREIGN_PASSPORT_MIN_FAILED`, more than half of
        those evaluated): a unit rarely breaks that way, a passport of another unit always does.

        Never after an :attr:`onset`: the unit changed within the session (one set of parameters
        did not explain its positions), which another unit's passport, constant over the session,
        does not make; a second change after it makes the later fit fail broadly instead."""
        if self.onset is not None:
            return False
        failed, evaluated = self.predicate_counts()
        return failed >= FOREIGN_PASSPORT_MIN_FAILED and 2 * failed > evaluated

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: positions, estimates with standard deviations, predicates, faults."""
        return {
            "n_samples": self.n_samples,
            "gravity_mps2": self.gravity_mps2,
            "rejected_samples": dict(self.sample_rejections.counts),
            "static_intervals": len(self.detection.intervals),
            "positions": [p.to_dict() for p in self.positions],
            "position_rejections": [r.to_dict() for r in self.position_rejections],
            "triads": _triads_dict(self.triads),
            "faults": [f.to_dict() for f in self.faults],
            "diagnosed": self.diagnosed,
            "reason": self.reason,
            "passport_of_another_unit": self.passport_of_another_unit,
            "onset": None if self.onset is None else self.onset.to_dict(),
        }


@dataclass(frozen=True)
class Onset:
    """A fault that began mid-session: the positions before and after it, fitted apart (:func:`split_at_onset`).

    Attributes
    ----------
    t_s : when it began (the first sample of F0's first persistent failure), s.
    before : per triad, the fit of the positions that ended before ``t_s``, against the passport.
    n_before, n_after : positions wholly before and wholly after ``t_s``.
    n_straddling : positions that held ``t_s`` (in neither set).
    changed_after : the fit of the positions after ``t_s`` does not explain them either (the
        test of :func:`split_at_onset`): the unit changed again, or the fault came and went, and
        that fit's estimates mix the states it held.
    """

    t_s: float
    before: dict[Triad, TriadResult]
    n_before: int
    n_after: int
    n_straddling: int
    changed_after: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "t_s": self.t_s,
            "n_before": self.n_before,
            "n_after": self.n_after,
            "n_straddling": self.n_straddling,
            "changed_after": self.changed_after,
            "before": _triads_dict(self.before),
            "faults_before": [f.to_dict() for f in _findings(self.before)],
        }


def _findings(triads: dict[Triad, TriadResult]) -> tuple[Finding, ...]:
    return tuple(
        f for r in triads.values() if r.diagnosis is not None for f in r.diagnosis.findings
    )


def _triads_dict(triads: dict[Triad, TriadResult]) -> dict[str, Any]:
    return {
        t.value: {
            "estimate": r.estimate.to_dict(),
            "residuals": None if r.residuals is None else [float(v) for v in r.residuals],
            "residual_sigma": None
            if r.residual_sigma is None
            else [float(v) for v in r.residual_sigma],
            "residual_rms": None
            if r.residuals is None
            else float(np.sqrt(np.mean(r.residuals**2))),
            "predicates": None if r.diagnosis is None else r.diagnosis.to_dict(),
            "diagnosed": r.diagnosed,
            "reason": r.reason,
            "suspect": r.suspect,
        }
        for t, r in triads.items()
    }


def present_triads(session: ImuSession) -> tuple[Triad, ...]:
    """The triads a session carries, accelerometers first."""
    return tuple(
        t
        for t, a in ((Triad.ACCEL, session.accel_mps2), (Triad.GYRO, session.gyro_rps))
        if a is not None
    )


def run_chain(
    session: ImuSession, config: ChainConfig, passport: Passport | None = None
) -> ChainResult:
    """Static detection → positions → estimates → diagnosis (module docstring).

    Raises ``ValueError`` (a :class:`~estimators.session.SessionError`) when the
    session has no usable samples, and without a passport when a triad's positions
    cannot be fitted (a channel without spread); a session without enough positions
    is not an error: its estimates say "not observable yet" and no predicate is
    evaluated. With a passport, a triad that cannot be fitted is not diagnosed, and why.
    A triad with a passport that M1's geometry does not resolve is diagnosed by
    the M4 fits that make a six-position passport (:func:`m4_estimate`), where
    the session holds their geometry.
    """
    clean, rejected = validate_session(
        session, accel_limit_mps2=config.accel_limit_mps2, gyro_limit_rps=config.gyro_limit_rps
    )
    detection = detect_static(clean, config=config.detector)
    found: PositionsResult = build_positions(clean, detection, config=config.positions)
    instability = config.bias_instability_std
    if instability is None and passport is not None:
        instability = {t: tp.bias_instability_std for t, tp in passport.triads.items()}
    positions = _with_bias_instability(found.positions, instability or {}, config.gravity_mps2)
    turns = _diagnosis_turns(clean, detection, positions, passport)
    return ChainResult(
        session.n_samples,
        rejected,
        detection,
        positions,
        found.rejections,
        _fit_triads(positions, turns, present_triads(clean), config, passport),
        config.gravity_mps2,
        clean,
    )


def split_at_onset(
    result: ChainResult, t_s: float, triad: Triad, config: ChainConfig, passport: Passport
) -> ChainResult:
    """The chain's fits redone apart on the positions before and after the onset ``t_s`` of a
    fault F0 found in ``triad``, when the unit changed there.

    One fit of positions taken before and after a fault began estimates neither the
    old nor the new parameters (M1 restarts its estimation when F0 fails, Fig. 2).
    But F0 sees a fault only in the orientations it moves ``½(|ã|²−1)`` in (a scale
    error of axis ``i`` by ``e·u_i²``): a fault present from the start first fails
    F0 wherever its axis first points along gravity. The unit changed at ``t_s``
    when one set of parameters does not explain all its positions: the largest
    normalized residual of the session's fit ``|r_k|/σ_k`` exceeds the two-sided
    Bonferroni bound at ``config.false_alarm_prob`` over the ``n`` positions
    (:func:`~estimators.diagnosis.critical_z`).

    Positions that ended by ``t_s`` are then fitted as one set, those that began
    at or after it as another, each against the passport (a set with too few
    positions says so); a position holding ``t_s`` is in neither. ``result`` is
    returned unchanged when no position ended before ``t_s`` (the fault was there
    from the start), when the session's fit explains every position, or when it
    has no fit to judge by (too few positions; or a fit that left the physical
    domain, which a fault there from the start also gives).
    """
    if result.session is None:
        raise ValueError("the chain result does not carry its session")
    before = tuple(p for p in result.positions if p.t_end_s <= t_s)
    whole = result.triads.get(triad)
    if not before or whole is None or not _changed(whole, config.false_alarm_prob):
        return result
    after = tuple(p for p in result.positions if p.t_start_s >= t_s)
    turns = _diagnosis_turns(result.session, result.detection, result.positions, passport)
    present = tuple(result.triads)
    later = _fit_triads(
        after, tuple(tr for tr in turns if tr.t_start_s >= t_s), present, config, passport
    )
    return replace(
        result,
        triads=later,
        onset=Onset(
            t_s,
            _fit_triads(
                before, tuple(tr for tr in turns if tr.t_end_s <= t_s), present, config, passport
            ),
            len(before),
            len(after),
            len(result.positions) - len(before) - len(after),
            _changed(later[triad], config.false_alarm_prob),
        ),
    )


def _diagnosis_turns(
    session: ImuSession,
    detection: StaticDetection,
    positions: tuple[Position, ...],
    passport: Passport | None,
) -> tuple[FullTurn, ...]:
    """The full turns a gyro with a passport is diagnosed by (:func:`m4_estimate`): only in a
    session holding the six faces, the calibration of the Ferraris type whose turns they are.

    A turn's scale factor is its integral against exactly ``2π``; the detector accepts any
    stretch between rests within 10 % of it about one axis. In a flight a manoeuvre between its
    rests can integrate to that (about a fixed axis or not): taken for a turn it gave a healthy
    navigation-grade unit a scale error of -0.025 against a tolerance of 0.0045.
    """
    if passport is None or Triad.GYRO not in passport.triads or face_positions(positions) is None:
        return ()
    return find_full_turns(session, detection.intervals)


def _changed(whole: TriadResult, false_alarm_prob: float) -> bool:
    """The session's fit of a triad does not explain all its positions (:func:`split_at_onset`)."""
    if whole.residuals is None or whole.residual_sigma is None:
        return False
    z = np.abs(whole.residuals) / whole.residual_sigma
    from estimators.diagnosis import critical_z

    return bool(np.max(z) > critical_z(false_alarm_prob, z.size))


def _fit_triads(
    positions: tuple[Position, ...],
    turns: tuple[FullTurn, ...],
    triads: tuple[Triad, ...],
    config: ChainConfig,
    passport: Passport | None,
) -> dict[Triad, TriadResult]:
    """Estimate and (with a passport) diagnose each triad from ``positions`` (and ``turns``).

    Positions a triad cannot be fitted from (a channel without spread: stuck, or clipped at its
    range) make a passport impossible: an error without one. Against a passport they are that
    triad's finding to make, not the session's end: the triad is not diagnosed, the reason
    said, and the other triad and F0 still judge the samples.
    """
    out = {}
    for triad in triads:
        reference = reference_magnitude(triad, config.gravity_mps2)
        fitted = True
        try:
            est = estimate_triad(positions, triad, reference, method=config.method)
        except ValueError as exc:
            if passport is None:
                raise ValueError(f"{triad.value}: {exc}") from None
            est = not_observable_estimate(
                triad,
                config.method,
                f"its positions cannot be fitted: {exc}",
                len(positions),
                reference,
            )
            fitted = False
        tp = None if passport is None else passport.triads.get(triad)
        # A fit that left the physical domain is not a geometry M4 completes: it stays SUSPECT.
        if (
            fitted
            and tp is not None
            and est.verdict is not Verdict.OBSERVABLE
            and not est.fit_left_domain
        ):
            alt = m4_estimate(triad, est, positions, turns, config.gravity_mps2)
            if alt is not None and alt.params is not None and np.any(alt.observable):
                est = alt
        residuals = sigma = None
        if est.params is not None:
            mean, cov = position_arrays(positions, triad, reference)
            residuals = ellipsoid_residual(est.params, mean)[0]
            sigma = equation_sigma(est.params, mean, cov)
        diag = None
        if tp is not None:
            from estimators.diagnosis import diagnose

            diag = diagnose(est, tp, false_alarm_prob=config.false_alarm_prob)
        out[triad] = TriadResult(est, residuals, sigma, diag)
    return out


def _with_bias_instability(
    positions: tuple[Position, ...], std_norm: dict[Triad, FloatArray], gravity_mps2: float
) -> tuple[Position, ...]:
    """Positions whose mean covariances also carry the bias wander (it does not average down)."""
    extra = {
        t: np.diag((np.asarray(s, float) * reference_magnitude(t, gravity_mps2)) ** 2)
        for t, s in std_norm.items()
        if np.any(s)
    }
    if not extra:
        return positions
    out = []
    for p in positions:
        accel_cov, gyro_cov = p.accel_cov_mps2, p.gyro_cov_rps
        if Triad.ACCEL in extra and accel_cov is not None:
            accel_cov = accel_cov + extra[Triad.ACCEL]
        if Triad.GYRO in extra and gyro_cov is not None:
            gyro_cov = gyro_cov + extra[Triad.GYRO]
        out.append(replace(p, accel_cov_mps2=accel_cov, gyro_cov_rps=gyro_cov))
    return tuple(out)


# --------------------------------------------------------------------------- the best passport


@dataclass(frozen=True)
class Calibration:
    """What ``calibrate`` puts in a passport (:func:`calibration_estimates`).

    Attributes
    ----------
    estimates : per triad with at least one observable parameter, the estimate
        (``sources`` says how each parameter was obtained).
    turns : the full turns found (and used for the gyros).
    """

    estimates: dict[Triad, Estimate]
    turns: tuple[FullTurn, ...]


def calibration_estimates(result: ChainResult, *, turn_rad: float = FULL_TURN_RAD) -> Calibration:
    """The best estimate of each triad the session allows (docs/methods.md, "M4 into the passport").

    M1's fit where it resolves all nine parameters. Otherwise the six-position
    vector fit (accelerometers, when the positions are the six faces) or the
    static means and full turns of ``turn_rad`` (gyros) supply what it does not:
    alone when M1's geometry fails, else for the parameters M1 leaves
    unobservable, M1's value kept for the others. A triad with no observable
    parameter is left out.
    """
    if result.session is None:
        raise ValueError("the chain result does not carry its session")
    turns = find_full_turns(result.session, result.detection.intervals, turn_rad=turn_rad)
    out: dict[Triad, Estimate] = {}
    for triad, r in result.triads.items():
        est = r.estimate
        if est.verdict is Verdict.OBSERVABLE:
            out[triad] = replace(est, sources=(SOURCE_SCALAR,) * N_PARAMS)
            continue
        alt = m4_estimate(triad, est, result.positions, turns, result.gravity_mps2, turn_rad)
        best = est if alt is None else alt
        if best.params is not None and np.any(best.observable):
            out[triad] = (
                best
                if best.sources is not None
                else replace(best, sources=(SOURCE_SCALAR,) * N_PARAMS)
            )
    return Calibration(out, turns)


def m4_estimate(
    triad: Triad,
    scalar: Estimate,
    positions: tuple[Position, ...],
    turns: tuple[FullTurn, ...],
    gravity_mps2: float,
    turn_rad: float = FULL_TURN_RAD,
) -> Estimate | None:
    """M1's estimate ``scalar`` of ``triad`` completed (or replaced) by M4 (docs/methods.md, "M4 into
    the passport"): the six-position vector fit for the accelerometers, the full turns of
    ``turn_rad`` and the static means for the gyros; None when the session holds neither.
    ``sources`` names the method of each parameter."""
    if triad is Triad.ACCEL:
        return _accel_vector(positions, scalar, gravity_mps2)
    return _gyro_turns(turns, positions, scalar, reference_magnitude(triad, gravity_mps2), turn_rad)


def _accel_vector(
    positions: tuple[Position, ...], scalar: Estimate, gravity_mps2: float
) -> Estimate | None:
    """M1's estimate completed (or replaced) by the six-position vector fit, one covariance.

    The combination ``θ(m)`` (M1's refined fit for the parameters it resolves, the
    vector fit for the rest) is a function of the position means ``m``; its
    covariance is ``Σ_k J_k P_k J_kᵀ`` with ``J_k`` its Jacobian by central
    differences and ``P_k`` the covariance of mean ``k`` (the two fits share data,
    so their cross-covariance is in it). Only in a session of six faces
    (:func:`~estimators.sixpos.six_face_session`).
    """
    faces = six_face_session(positions)
    if faces is None:
        return None
    index = [positions.index(p) for p in faces]
    mean, cov = position_arrays(positions, Triad.ACCEL, gravity_mps2)
    keep = (
        np.zeros(N_PARAMS, dtype=bool)
        if scalar.params is None
        else np.asarray(scalar.observable, dtype=bool)
    )

    # The faces of the means: a step of a tenth of a mean's σ turns no position 20° (a Jacobian
    # of the fit at its faces), so the three designs are factored once for all its fits.
    fit_faces = six_position_accel_fitter(
        face_directions(mean[index] * gravity_mps2),
        gravity_mps2=gravity_mps2,
        accel_cov_mps2=cov[index] * gravity_mps2**2,
        quadratic=False,
    )

    def combined(m: FloatArray) -> FloatArray:
        fit = fit_faces(m[index] * gravity_mps2)
        vector = fit.nine_params()
        if not keep.any():
            return vector
        refined = estimate_refined(m, cov, Triad.ACCEL, reference=gravity_mps2)
        if refined.params is None:
            raise ValueError(f"M1's fit failed under a perturbation of the means: {refined.reason}")
        return np.where(keep, refined.params, vector)

    params = combined(mean)
    used = positions if keep.any() else faces
    rows = range(len(positions)) if keep.any() else index
    total = np.zeros((N_PARAMS, N_PARAMS))
    for k in rows:
        jac = np.zeros((N_PARAMS, 3))
        for a in range(3):
            h = 0.1 * float(np.sqrt(cov[k, a, a]))
            step = np.zeros_like(mean)
            step[k, a] = h
            jac[:, a] = (combined(mean + step) - combined(mean - step)) / (2.0 * h)
        total += jac @ cov[k] @ jac.T
    sources = tuple(SOURCE_SCALAR if keep[j] else SOURCE_VECTOR for j in range(N_PARAMS))
    return judged_estimate(
        Triad.ACCEL,
        Method.COMBINED if keep.any() else Method.SIX_POSITION,
        params,
        0.5 * (total + total.T),
        n_positions=len(used),
        reference=gravity_mps2,
        sources=sources,
    )


def _gyro_turns(
    turns: tuple[FullTurn, ...],
    positions: tuple[Position, ...],
    scalar: Estimate,
    reference: float,
    turn_rad: float,
) -> Estimate | None:
    """M1's gyro estimate completed (or replaced) by the full turns and the static means.

    The turns' integrals and the static means M1 uses are different data, so the
    two blocks of the covariance are taken as independent.
    """
    if not turns:
        return None
    params, cov, known, sources = gyro_nine_from_turns(
        turns, positions, turn_rad=turn_rad, reference_rps=reference
    )
    keep = (
        np.zeros(N_PARAMS, dtype=bool)
        if scalar.params is None or scalar.cov is None
        else np.asarray(scalar.observable, dtype=bool)
    )
    if keep.any() and scalar.params is not None and scalar.cov is not None:
        params = np.where(keep, scalar.params, params)
        cov = np.where(np.outer(keep, keep), scalar.cov, np.where(np.outer(~keep, ~keep), cov, 0.0))
        known = known | keep
        sources = tuple(SOURCE_SCALAR if keep[j] else sources[j] for j in range(N_PARAMS))
    return judged_estimate(
        Triad.GYRO,
        Method.COMBINED if keep.any() else Method.SIX_POSITION,
        params,
        cov,
        n_positions=len(positions),
        reference=reference,
        sources=sources,
        known=known,
    )
