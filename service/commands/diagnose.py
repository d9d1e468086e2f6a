"""``ins-health diagnose SESSION --passport PASSPORT.json [--json]``: the offline chain of methods.md M1.

Exit status: 0 the session was diagnosed (with or without faults); 2 unusable
input (one line on stderr); 3 the data do not allow a diagnosis (no triad had
a predicate F1…F9 it could evaluate: too few positions, their geometry, or
noise against the reference), said as ``NOT DIAGNOSED: …`` with the reasons.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from service.cli import UsageError
from service.session_args import add_session_arguments, load_session_input, time_gap_line

if TYPE_CHECKING:
    from estimators.chain import ChainConfig, ChainResult
    from estimators.passport import Passport

DEFAULT_FALSE_ALARM_PROB = 1.0e-3
"""estimators.diagnosis.DEFAULT_FALSE_ALARM_PROB, stated here so that the parser does not load
scipy (tests/test_cli_startup.py checks they agree)."""

EXIT_NOT_DIAGNOSED = 3


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="static detection → positions → estimates → predicates F1…F9 against a passport",
        description="Exit status 0: diagnosed, with or without faults; 2: unusable input (one-line reason); "
        "3: the data do not allow a diagnosis (NOT DIAGNOSED and why), or a triad with a passport "
        "could not be fitted (SUSPECT: a gross fault, values in other units, another unit's session).",
    )
    add_session_arguments(p)
    p.add_argument("--passport", required=True, metavar="PASSPORT.json", help="the unit's passport")
    p.add_argument(
        "--false-alarm",
        type=float,
        default=DEFAULT_FALSE_ALARM_PROB,
        metavar="P",
        help=f"per-triad false-alarm probability of F1…F9 (default {DEFAULT_FALSE_ALARM_PROB})",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object (positions, estimates, predicates, faults, F0, diagnosed/reason)",
    )
    p.set_defaults(func=run)


def f0_report(
    result: ChainResult, passport: Passport, config: ChainConfig
) -> dict[str, dict[str, Any]]:
    """F0 on every static sample against the passport, as the service runs it (service.pipeline).

    Static as the service's detector sees it: its thresholds raised to the passport's noise
    (:func:`~service.pipeline.detector_config`), as ``replay`` runs it. The chain's detector, whose
    thresholds come from the session's own noise, took a flight's manoeuvres for rest (a fault-free
    flight: 225 samples 'leaving the shell' that replay did not test).

    Per triad: static samples tested, how many leave the shell, the first such
    time and the worst ``|½(|ã|²−1)|``; or why F0 is not run for the triad.
    """
    import numpy as np

    from estimators.scalar import f0_batch
    from estimators.static_detector import detect_static
    from service.pipeline import PipelineOptions, detector_config
    from service.pipeline.triad_check import f0_config

    clean = result.session
    if clean is None:
        raise ValueError("the chain result does not carry its session")
    options = PipelineOptions(gravity_mps2=config.gravity_mps2)
    static = detect_static(
        clean, config=detector_config(options.detector, passport, clean.rate_hz)
    ).static
    out: dict[str, dict[str, Any]] = {}
    for triad, tp in passport.triads.items():
        x = clean.accel_mps2 if triad.value == "accel" else clean.gyro_rps
        if x is None:
            continue
        cfg, lambda0, note = f0_config(tp, options, clean.rate_hz)
        if cfg is None:
            out[triad.value] = {"run": False, "lambda0": lambda0, "note": note}
            continue
        f0 = f0_batch(x, static, cfg)
        failed = np.flatnonzero(f0.state == 0)
        out[triad.value] = {
            "run": True,
            "lambda0": lambda0,
            "tested": f0.n_tests,
            "failed": int(failed.size),
            "first_fail_t_s": float(clean.t_s[failed[0]]) if failed.size else None,
            "worst": float(np.nanmax(np.abs(f0.residual[failed]))) if failed.size else None,
            "note": note,
        }
    return out


def run(args: argparse.Namespace) -> int:
    from estimators.chain import ChainConfig, run_chain
    from estimators.passport import PassportError, check_references
    from protocols.passport_codec import read_passport_json

    passport = read_passport_json(args.passport)
    inp = load_session_input(args)
    config = ChainConfig(
        gravity_mps2=inp.gravity_mps2, false_alarm_prob=args.false_alarm, detector=inp.detector,
        accel_limit_mps2=inp.accel_limit_mps2, gyro_limit_rps=inp.gyro_limit_rps,
    )  # fmt: skip
    # A reference in other units would be diagnosed as bias faults on every axis: refuse it instead.
    try:
        check_references(passport, gravity_mps2=inp.gravity_mps2)
    except PassportError as exc:
        raise UsageError(f"{args.passport}: {exc}") from None
    result = run_chain(inp.session, config, passport)
    f0 = f0_report(result, passport, config)
    status = 0 if result.diagnosed and not result.suspects else EXIT_NOT_DIAGNOSED
    if args.json:
        out = result.to_dict()
        out["unit_id"] = passport.unit_id
        out["gravity_source"] = inp.gravity_source
        out["f0"] = f0
        json.dump(out, sys.stdout, indent=1)
        print()
        return status
    print(
        f"{passport.unit_id}: {len(result.positions)} positions, g = {inp.gravity_mps2:.5f} m/s² ({inp.gravity_source})"
    )
    if result.sample_rejections.total:
        print(f"  rejected samples: {result.sample_rejections.counts}")
    if (gaps := time_gap_line(result.detection)) is not None:
        print(gaps)
    for triad, r in result.triads.items():
        state = "diagnosed" if r.diagnosed else f"NOT DIAGNOSED: {r.reason}"
        print(f"  {triad.value}: {r.estimate.verdict.value} — {r.estimate.reason}; {state}")
    for name, f in f0.items():
        if not f["run"]:
            print(f"  F0 {name}: not run ({f['note']})")
        elif f["failed"]:
            print(
                f"  F0 {name}: {f['failed']} of {f['tested']} static samples leave the shell (λ0 {f['lambda0']:.3g}); "
                f"first at {f['first_fail_t_s']:.3f} s, worst |½(|ã|²−1)| {f['worst']:.3g}"
            )
        else:
            print(
                f"  F0 {name}: {f['tested']} static samples inside the shell (λ0 {f['lambda0']:.3g})"
            )
    for triad in result.suspects:
        print(
            f"SUSPECT {triad.value}: its positions determine the nine parameters but the fit left the physical "
            "domain (above): a fault far beyond the scheme's, values in other units or another unit's session; "
            "not diagnosed, and not 'no fault'"
        )
    if not result.diagnosed:
        print(f"NOT DIAGNOSED: {result.reason}")
        return status
    undiagnosed = [t.value for t, r in result.triads.items() if not r.diagnosed]
    if not result.faults and not result.suspects:
        print("  no fault" + (f" (not diagnosed: {', '.join(undiagnosed)})" if undiagnosed else ""))
    for fault in result.faults:
        print(
            f"  FAULT {fault.predicate}: {fault.triad.value} {fault.axis} {fault.cause.value}: estimate {fault.estimate:.4g} "
            f"vs nominal {fault.nominal:.4g} ± {fault.tolerance:.3g} (σ {fault.sigma:.2g})"
        )
    if result.passport_of_another_unit:
        failed, evaluated = result.predicate_counts()
        print(
            f"  hint: {failed} of {evaluated} predicates fail at once: the passport is probably not this unit's "
            f"(passport of {passport.unit_id!r})"
        )
    return status
