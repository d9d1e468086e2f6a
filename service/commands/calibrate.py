"""``ins-health calibrate SESSION --out PASSPORT.json``: a passport from a fault-free session (methods.md M1)."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from estimators.conventions import Grade, Triad, reference_magnitude
from service.cli import UsageError, add_output, progress_step, stderr_progress
from service.grades import FLOOR_GRADE, SENSOR_CLASSES, grade_name
from service.session_args import add_session_arguments, load_session_input, time_gap_line

if TYPE_CHECKING:
    from estimators.chain import ChainConfig, ChainResult
    from estimators.ninepar import Estimate
    from estimators.passport import Passport


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="fit both triads from a fault-free multi-position session and write a passport",
        description="Static positions → the 9 parameters of each triad (refined least squares) → a passport. "
        "Tolerances default to max(3σ of the calibration, a floor for the sensor grade) (estimators/passport.py).",
    )
    add_session_arguments(p)
    add_output(
        p, "--out", required=True, metavar="PASSPORT.json", help="where to write the passport"
    )
    p.add_argument("--unit-id", help="identity of the unit (default: the session file's name)")
    p.add_argument(
        "--sensor-model", default="unknown", help="sensor model name recorded in the passport"
    )
    p.add_argument(
        "--grade",
        type=grade_name,
        choices=SENSOR_CLASSES,
        default=SENSOR_CLASSES[0],
        help="sensor class for the tolerance floors (default consumer_mems; both MEMS classes take "
        "the MEMS floors; 'mems' is taken as consumer_mems)",
    )
    p.add_argument(
        "--json", action="store_true", help="also print the full chain result as JSON on stdout"
    )
    p.add_argument(
        "--audit",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="audit the white-noise model against the session first (docs/audit-xsens.md) and carry the bias "
        "instability that survives it into the passport, so the service's thresholds use the audited model "
        "(default: on; --no-audit keeps the white-noise model). The audit needs more positions than the nine "
        "parameters (a six-position session has too few): then it concludes nothing, says so, and the white-noise "
        "model is kept",
    )
    p.add_argument(
        "--turn-deg",
        type=float,
        default=360.0,
        metavar="DEG",
        help="angle of the turns about one axis between two rests that calibrate the gyros' scale factors and "
        "misalignment (default 360: full turns, as Ferraris-type sessions have)",
    )
    p.add_argument(
        "--replicas",
        type=int,
        default=20,
        metavar="N",
        help="Monte Carlo replicas of the audit (default 20)",
    )
    p.set_defaults(func=run)


def own_session_check(
    result: ChainResult, passport: Passport, config: ChainConfig, estimates: dict[Triad, Estimate]
) -> str | None:
    """Why ``passport`` must not be written, or None: F0 of its own session against it, as
    ``diagnose`` runs it, fails persistently (a fit its positions contradict: a six-position fit
    of a session's faces that its tilts do not obey, a session with a fault in it). Healthy
    data leave F0's false-alarm rate, not a persistent failure."""
    from service.commands.diagnose import f0_clear_below_bound, f0_faults, f0_report

    with progress_step("calibrate", "the passport against its own session"):
        # The usual answer, no persistent failure, is known from λ0's lower bound without scipy.
        if f0_clear_below_bound(result, passport, config):
            return None
        failed = f0_faults(f0_report(result, passport, config))
    if not failed:
        return None
    parts = []
    for f in failed:
        est = estimates[Triad(f["triad"])]
        methods = sorted(set(est.sources or (est.method.value,)))
        parts.append(
            f"F0 fails persistently on {f['failed']} of {f['tested']} static samples of the "
            f"{f['triad']} triad from {f['first_t_s']:.3f} s (worst |½(|ã|²−1)| {f['worst']:.3g} "
            f"against λ0 {f['tolerance']:.3g}) with its {' and '.join(methods)}"
        )
    return (
        "the passport contradicts its own session, not written: "
        + "; ".join(parts)
        + ": its parameters do not explain the session's positions (a fault in the session, or "
        "poses the fit does not hold; `diagnose` of the session says which)"
    )


def run(args: argparse.Namespace) -> int:
    from estimators.chain import ChainConfig, calibration_estimates, run_chain
    from estimators.conventions import N_PARAMS, PARAM_NAMES
    from estimators.ninepar import SOURCE_SCALAR, Verdict
    from estimators.passport import passport_from_estimates, per_sample_noise_std
    from protocols.passport_codec import write_passport_json

    with progress_step("calibrate", f"reading {Path(args.session).name}"):
        inp = load_session_input(args)
    config = ChainConfig(
        gravity_mps2=inp.gravity_mps2, detector=inp.detector,
        accel_limit_mps2=inp.accel_limit_mps2, gyro_limit_rps=inp.gyro_limit_rps,
    )  # fmt: skip
    with progress_step("calibrate", "static detection, positions and the fit"):
        result = white = run_chain(inp.session, config)
    instability = None
    if not (math.isfinite(args.turn_deg) and args.turn_deg > 0):
        raise UsageError(f"--turn-deg must be a positive angle, got {args.turn_deg!r}")
    if args.audit:
        import estimators.audit as model_audit  # its submodules (and the simulator) load on first use

        n_pos = len(white.positions)
        # The audit's own first check, on the same positions: too few, and it would only say so.
        why = [f"{n_pos} static positions, it needs ≥ {model_audit.MIN_POSITIONS}"]
        if n_pos >= model_audit.MIN_POSITIONS:
            with progress_step("calibrate", f"the audit ({args.replicas} replicas)"):
                audit = model_audit.run_audit(
                    inp.session,
                    model_audit.AuditConfig(chain=config, replicas=args.replicas),
                    progress=stderr_progress("calibrate: audit"),
                )
            why = [] if audit.replica_stats else audit.statements
            if audit.replica_stats:
                instability = {t: m.excess_sd_norm for t, m in audit.extended_model.items()}
                print(
                    f"calibrate: audit ({args.replicas} replicas) names {[c.effect for c in audit.named] or 'nothing'}",
                    file=sys.stderr,
                )
                with progress_step("calibrate", "the fit with the audited noise"):
                    result = run_chain(
                        inp.session, replace(config, bias_instability_std=instability)
                    )
        if why:
            print(
                f"calibrate: audit concluded nothing ({'; '.join(why)}); white-noise model kept",
                file=sys.stderr,
            )
    with progress_step("calibrate", "the passport's estimates"):
        cal = calibration_estimates(result, turn_rad=math.radians(args.turn_deg))
    estimates = cal.estimates
    if not estimates:
        reasons = "; ".join(f"{t.value}: {r.estimate.reason}" for t, r in result.triads.items())
        raise UsageError(
            f"no triad could be calibrated from {len(result.positions)} positions ({reasons})"
        )
    passport = passport_from_estimates(
        estimates,
        unit_id=args.unit_id or Path(args.session).stem,
        sensor_model=args.sensor_model,
        sensor_ids={},
        created=dt.date.today().isoformat(),
        # White noise from the positions before the audited wander is added to their covariances.
        noise_std={
            t: per_sample_noise_std(white.positions, t, reference_magnitude(t, inp.gravity_mps2))
            for t in estimates
        },
        # The validated samples' rate: a repeated or non-finite time stamp must not set it.
        sample_rate_hz=(result.session or inp.session).rate_hz,
        grade=Grade(FLOOR_GRADE[args.grade]),
        bias_instability_std=instability,
    )
    refusal = own_session_check(result, passport, config, estimates)
    if refusal is not None:
        raise UsageError(refusal)
    write_passport_json(passport, args.out)
    print(
        f"calibrate: {len(result.positions)} positions ({len(result.position_rejections)} intervals rejected or merged), g = {inp.gravity_mps2:.5f} m/s² ({inp.gravity_source})",
        file=sys.stderr,
    )
    if result.sample_rejections.total:
        print(f"  rejected samples: {result.sample_rejections.counts}", file=sys.stderr)
    if (gaps := time_gap_line(result.detection)) is not None:
        print(gaps, file=sys.stderr)
    if cal.turns:
        print(
            "  turns: "
            + ", ".join(
                f"{'+' if tr.sign > 0 else '-'}{'xyz'[tr.axis]} at {tr.t_start_s:.1f} s"
                for tr in cal.turns
            ),
            file=sys.stderr,
        )
    for triad in (Triad.ACCEL, Triad.GYRO):
        r = result.triads.get(triad)
        if r is None:
            continue
        est = r.estimate
        line = f"  {triad.value}: M1 fit {est.verdict.value}"
        exact_fit = r.residuals is not None and est.chi2_per_dof is None
        if r.residuals is not None:
            line += f", residual rms {float((r.residuals**2).mean() ** 0.5):.3g} (normalized), " + (
                "no chi2/dof (no redundancy)" if exact_fit else f"chi2/dof {est.chi2_per_dof:.2f}"
            )
        if est.verdict is not Verdict.OBSERVABLE:
            line += f" — {est.reason}"
        print(line, file=sys.stderr)
        if exact_fit:
            from estimators.audit import MIN_POSITIONS

            # As many equations as parameters: the fit passes through every position, so its
            # residuals are zero whatever the data, and a disturbed position would go unseen.
            print(
                f"calibrate: warning: the {triad.value} fit has {est.n_positions} positions for its {N_PARAMS} "
                "parameters, no redundancy: the residual check (chi2/dof) is impossible and a bad position "
                f"would go unnoticed; record more positions (at least {MIN_POSITIONS}) to check the calibration",
                file=sys.stderr,
            )
        written = estimates.get(triad)
        if written is None:
            print(
                f"  {triad.value}: not in the passport (no parameter observable)", file=sys.stderr
            )
        elif written.sources is not None and set(written.sources) != {SOURCE_SCALAR}:
            by_source: dict[str, list[str]] = {}
            for name, src, ok in zip(PARAM_NAMES, written.sources, written.observable, strict=True):
                by_source.setdefault(src, []).append(name if ok else f"{name} (not observable)")
            parts = "; ".join(f"{' '.join(v)} from {k}" for k, v in by_source.items())
            print(f"  {triad.value} in the passport: {parts}", file=sys.stderr)
    print(f"  passport written to {args.out}", file=sys.stderr)
    if args.json:
        json.dump(result.to_dict(), sys.stdout, indent=1)
        print()
    return 0
