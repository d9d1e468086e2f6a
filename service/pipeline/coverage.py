"""What an IMU's pipeline tested so far (:mod:`estimators.coverage`): per triad F0, F1…F9 and the
gross test with their minimum detectable fault, the stream checks and the cross-IMU check, and why any did not run.

Read from the pipeline's own state (F0's test counter ``f0.<triad>.tests``, its λ0 and the gravity
directions it saw, the diagnosis's estimator), so ``replay``, the daemon's status and ``watch`` state
the same coverage."""

from __future__ import annotations

from typing import TYPE_CHECKING

from estimators.conventions import EARTH_RATE_RPS, Triad
from estimators.coverage import (
    Check,
    CheckCoverage,
    ImuCoverage,
    f0_mdf,
    ninepar_coverage,
    tolerance_triples,
)
from estimators.gross import tolerance_passports
from estimators.scalar import derive_lambda0
from service.pipeline.options import F0_SHELL_LIMIT, TRIAD_WORD
from service.pipeline.triad_check import TriadCheck, f0_threshold

if TYPE_CHECKING:
    from service.pipeline.imu_pipeline import ImuPipeline

FAULT_PREDICATES = frozenset(
    {"F0", *(f"F{j}" for j in range(1, 10)), "stale", "gross", "thrust_axis", "cross_imu_norm"}
)
"""Predicates whose (not recovered) event is a sensor finding: the verdict is then a fault."""


def imu_coverage(
    pipe: ImuPipeline,
    *,
    imus_on_vehicle: int | None = None,
    cross_not_running: str | None = None,
    vehicle_checks: tuple[CheckCoverage, ...] = (),
) -> ImuCoverage:
    """The coverage of one IMU's pipeline; ``imus_on_vehicle``: IMUs its vehicle streams, for the
    cross-IMU check (None: left out, a check of the vehicle rather than of this IMU);
    ``cross_not_running``: why the cross-IMU check does not compare this IMU now
    (:meth:`estimators.stream_validity.CrossImuMonitor.not_compared`);
    ``vehicle_checks``: the vehicle's checks this IMU takes part in (the cross-IMU norm,
    :meth:`~service.pipeline.FleetProcessor.norm_coverage`), added at the end."""
    checks: list[CheckCoverage] = []
    for triad in (Triad.ACCEL, Triad.GYRO):
        check = pipe.checks.get(triad)
        if check is None:
            blind = _blind_gyro(pipe, triad)
            if blind is not None:
                checks.append(
                    CheckCoverage(Check.F0, triad, ran=False, applies=False, reason=blind)
                )
                checks.append(
                    CheckCoverage(Check.F1_F9, triad, ran=False, applies=False, reason=blind)
                )
                continue
            why = _no_check(pipe, triad)
            checks.append(CheckCoverage(Check.F0, triad, ran=False, reason=why))
            checks.append(CheckCoverage(Check.F1_F9, triad, ran=False, reason=why))
            continue
        checks.append(_f0(pipe, triad, check))
        checks.append(_ninepar(pipe, triad, check))
    checks += [_gross(pipe, triad) for triad in (Triad.ACCEL, Triad.GYRO)]
    checks.append(
        CheckCoverage(Check.STREAM, None, ran=True, samples=pipe.n_samples)
        if pipe.n_samples
        else CheckCoverage(Check.STREAM, None, ran=False, reason="no sample accepted")
    )
    if imus_on_vehicle is not None:
        checks.append(
            CheckCoverage(Check.CROSS_IMU, None, ran=False, reason=cross_not_running)
            if imus_on_vehicle >= 2 and cross_not_running is not None
            else CheckCoverage(Check.CROSS_IMU, None, ran=True, samples=pipe.n_samples)
            if imus_on_vehicle >= 2
            else CheckCoverage(
                Check.CROSS_IMU,
                None,
                ran=False,
                applies=False,
                reason="one IMU: nothing to compare",
            )
        )
    if pipe.thrust is not None:
        checks.append(pipe.thrust.coverage())
    return ImuCoverage(pipe.imu, (*checks, *vehicle_checks))


def _no_check(pipe: ImuPipeline, triad: Triad) -> str:
    if pipe.passport is None:
        return pipe.passport_note or "no passport"
    if pipe.nominal_too_slow:
        return pipe.nominal_too_slow
    if triad in pipe.passport.triads:  # the checks are set up with the sample rate
        return _not_running(pipe) or "not set up"
    return f"the passport has no {TRIAD_WORD[triad]} triad"


def _blind_gyro(pipe: ImuPipeline, triad: Triad) -> str | None:
    """Why the gyro's F0 and F1…F9 cannot apply when the passport left its gyro out, or None.

    ``calibrate`` leaves out a gyro whose session resolved no parameter (a MEMS gyro cannot see the
    Earth rate); the nominal passport of a MEMS class says the same with λ0 > 1. The passport alone
    cannot tell such a gyro from a navigation-grade one left out by mistake; the noise the stream
    shows can: when F0's shell from that noise alone exceeds :data:`F0_SHELL_LIMIT`, neither check
    could run with any passport, and a verdict must not wait for them."""
    p = pipe.passport
    if triad is not Triad.GYRO or p is None or triad in p.triads or pipe.gross is None:
        return None
    noise = pipe.gross.sample_noise_si(triad)
    if noise is None:
        return None
    lam = derive_lambda0(
        noise_std_norm=noise / EARTH_RATE_RPS,
        false_alarm_prob=pipe.options.false_alarm_probability,
    ).lambda0
    if lam <= F0_SHELL_LIMIT:
        return None
    return (
        f"the passport has no gyro triad, and the gyro's own noise ({noise.max():.2g} rad/s per "
        f"sample, {noise.max() / EARTH_RATE_RPS:.3g} Ω) cannot see the Earth rate: F0's shell "
        f"from it alone, λ0 {lam:.3g}, exceeds {F0_SHELL_LIMIT:g}"
    )


def _not_running(pipe: ImuPipeline) -> str | None:
    """Why the chain has not started on this IMU (None once it has)."""
    if pipe.detection is not None:
        return None
    if pipe.counters.get("samples.rejected.implausible_rate"):
        return "sample rate implausible: the chain never started"
    return "too few samples to measure the sample rate"


def _f0(pipe: ImuPipeline, triad: Triad, check: TriadCheck) -> CheckCoverage:
    tp, options = check.passport, pipe.options
    if check.f0 is None:
        # λ0 beyond the unit sphere: a MEMS gyro's noise and bias dwarf the Earth rate it is normalized by.
        # A gyro's is a limit of the method; an accelerometer's, of a passport too loose to test it.
        gyro = triad is Triad.GYRO
        what = (
            "gyro cannot see the Earth rate" if gyro else "the passport's tolerances are too wide"
        )
        return CheckCoverage(
            Check.F0, triad, ran=False, applies=not gyro,
            reason=f"{what}: the F0 shell λ0 {check.lambda0:.3g} exceeds 1",
        )  # fmt: skip
    why = _not_running(pipe)
    tests = pipe.counters.get(f"f0.{triad.value}.tests", 0)
    if why is None and not tests:
        why = f"no rest: the {TRIAD_WORD[triad]} was never static"
    if why is not None:
        return CheckCoverage(Check.F0, triad, ran=False, reason=why)
    assert pipe.detection is not None
    rate_hz = pipe.detection.rate_hz
    if check.f0_noise_at is None or check.f0_noise_at[0] != rate_hz:
        check.f0_noise_at = (rate_hz, f0_threshold(tp, options, rate_hz).noise_std)
    bias, scale = f0_mdf(
        lambda0=check.lambda0,
        noise_std=check.f0_noise_at[1],
        persist=pipe.f0_persist,
        max_abs_u=check.f0_max_abs_u,
        reference=options.reference(triad),
    )
    tol_bias, tol_scale = tolerance_triples(tp.tolerance, tp.reference)
    return CheckCoverage(
        Check.F0,
        triad,
        ran=True,
        samples=tests,
        mdf_bias_si=bias,
        mdf_scale=scale,
        tolerance_bias_si=tol_bias,
        tolerance_scale=tol_scale,
        false_alarm_prob=options.false_alarm_probability,
    )


def _ninepar(pipe: ImuPipeline, triad: Triad, check: TriadCheck) -> CheckCoverage:
    from estimators.diagnosis import diagnose

    est, options = check.estimator, pipe.options
    if est is None:
        reason = "the passport resolves no parameter"
        if triad is Triad.GYRO:
            reason = f"gyro cannot see the Earth rate: {reason}"
        return CheckCoverage(Check.F1_F9, triad, ran=False, applies=False, reason=reason)
    why = _not_running(pipe)
    n = est.n_positions
    if why is None and n < options.min_positions:
        since = "" if check.f0_fail_t_s is None else " since F0 failed"
        why = f"{n} position{'s' * (n != 1)} at rest{since}, {options.min_positions} needed"
    if why is not None:
        return CheckCoverage(Check.F1_F9, triad, ran=False, positions=n, reason=why)
    diag = diagnose(
        est.estimate(), check.passport, false_alarm_prob=options.diagnosis_false_alarm_probability
    )
    return ninepar_coverage(
        diag,
        positions=n,
        reference=options.reference(triad),
        passport_observable=check.passport.observable,
    )


def _gross(pipe: ImuPipeline, triad: Triad) -> CheckCoverage:
    """The gross test of one triad: run whatever the rate and the passport (:mod:`estimators.gross`)."""
    if pipe.gross is None:
        reason = _not_running(pipe) or "not set up"
        return CheckCoverage(Check.GROSS, triad, ran=False, reason=reason)
    tps, _ = tolerance_passports(pipe.passport, gravity_mps2=pipe.options.gravity_mps2)
    return pipe.gross.coverage()[triad].check(
        tps[triad], gravity_mps2=pipe.options.gravity_mps2, total_windows=pipe.gross.windows
    )
