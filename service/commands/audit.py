"""``ins-health audit SESSION [--json] [--report DIR] [--replicas N] [--seed S]``: the model audit (issue 4)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from service.cli import UsageError, progress_step, stderr_progress
from service.session_args import add_session_arguments, load_session_input

DEFAULT_REPLICAS = 20
"""estimators.audit.DEFAULT_REPLICAS, stated here so that the parser does not load scipy
(tests/test_cli_startup.py checks they agree)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "audit",
        help="measured statistics against the simulation of the same session: named causes, extended model, gain",
        description="Exit status 0; 2 with a one-line reason for unusable input.",
    )
    add_session_arguments(p)
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object (grade_paths, baseline, candidates, named_causes, extended, gain)",
    )
    p.add_argument("--report", metavar="DIR", help="write audit.md and PNG plots into DIR")
    p.add_argument(
        "--replicas",
        type=int,
        default=DEFAULT_REPLICAS,
        metavar="N",
        help=f"Monte Carlo replicas (default {DEFAULT_REPLICAS})",
    )
    p.add_argument(
        "--seed", type=int, default=0, metavar="S", help="seed of the replicas (default 0)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimators.audit import AuditConfig, run_audit
    from estimators.chain import ChainConfig

    if args.replicas < 5:
        raise UsageError(f"--replicas must be at least 5, got {args.replicas}")
    with progress_step("audit", f"reading {Path(args.session).name}"):
        inp = load_session_input(args)
    chain = ChainConfig(
        gravity_mps2=inp.gravity_mps2,
        detector=inp.detector,
        accel_limit_mps2=inp.accel_limit_mps2,
        gyro_limit_rps=inp.gyro_limit_rps,
    )
    with progress_step("audit", f"the audit ({args.replicas} replicas)"):
        result = run_audit(
            inp.session,
            AuditConfig(chain, replicas=args.replicas, seed=args.seed),
            progress=stderr_progress("audit"),
        )
    if args.report:
        from service.audit_report import write_report

        with progress_step("audit", f"the report in {args.report}"):
            write_report(result, args.report, title=args.session)
    data = result.to_dict()
    if args.json:
        json.dump(data, sys.stdout, indent=1)
        print()
        return 0
    print(
        f"{result.n_positions} positions, {result.replicas} replicas, g = {inp.gravity_mps2:.5f} m/s² ({inp.gravity_source})"
    )
    for s in result.statements:
        print(f"  {s}")
    for triad, path in data["grade_paths"].items():
        print(f"  {triad} path {path['path']}: {path['reason']}")
    if data["baseline"]["ratio"] is not None:
        print(
            f"  headline χ²/dof ratio: baseline {data['baseline']['ratio']:.2f} (tail {data['baseline']['tail_prob']:.2f}), extended {data['extended']['ratio']:.2f} (tail {data['extended']['tail_prob']:.2f})"
        )
    if result.left_out:
        print(f"  extended comparison: {result.left_out_reason}")
    for c in data["named_causes"]:
        print(f"  CAUSE {c['effect']} {c['triad']} {c['axis'] or ''}: {c['evidence']}")
    if not data["named_causes"]:
        print("  no cause named")
    return 0
