"""``ins-health diagnose SESSION --passport PASSPORT.json [--json]``: the offline chain of methods.md M1."""

from __future__ import annotations

import argparse
import json
import sys

from service.session_args import add_session_arguments, load_session_input

DEFAULT_FALSE_ALARM_PROB = 1.0e-3
"""estimators.diagnosis.DEFAULT_FALSE_ALARM_PROB, stated here so that the parser does not load
scipy (tests/test_cli_startup.py checks they agree)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="static detection → positions → estimates → predicates F1…F9 against a passport",
        description="Exit status 0 with or without faults; 2 with a one-line reason for unusable input.",
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
        help="print one JSON object (positions, estimates, predicates, faults)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimators.chain import ChainConfig, run_chain
    from protocols.passport_codec import read_passport_json

    passport = read_passport_json(args.passport)
    inp = load_session_input(args)
    config = ChainConfig(
        gravity_mps2=inp.gravity_mps2, false_alarm_prob=args.false_alarm, detector=inp.detector,
        accel_limit_mps2=inp.accel_limit_mps2, gyro_limit_rps=inp.gyro_limit_rps,
    )  # fmt: skip
    result = run_chain(inp.session, config, passport)
    if args.json:
        out = result.to_dict()
        out["unit_id"] = passport.unit_id
        out["gravity_source"] = inp.gravity_source
        json.dump(out, sys.stdout, indent=1)
        print()
        return 0
    print(
        f"{passport.unit_id}: {len(result.positions)} positions, g = {inp.gravity_mps2:.5f} m/s² ({inp.gravity_source})"
    )
    if result.sample_rejections.total:
        print(f"  rejected samples: {result.sample_rejections.counts}")
    for triad, r in result.triads.items():
        note = "" if r.diagnosis is not None else " (no passport for this triad: not diagnosed)"
        print(f"  {triad.value}: {r.estimate.verdict.value} — {r.estimate.reason}{note}")
    if not result.faults:
        print("  no fault")
    for f in result.faults:
        print(
            f"  FAULT {f.predicate}: {f.triad.value} {f.axis} {f.cause.value}: estimate {f.estimate:.4g} vs nominal {f.nominal:.4g} ± {f.tolerance:.3g} (σ {f.sigma:.2g})"
        )
    return 0
