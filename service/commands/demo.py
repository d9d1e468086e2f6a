"""``ins-health demo``: router, simulated vehicle and service on 127.0.0.1; a fault found and named (service/demo.py).

Exit status 0 when the injected fault was detected and named, 1 otherwise.
"""

from __future__ import annotations

import argparse

DEFAULT_SPEED = 5.0
"""service.demo.DEFAULT_SPEED, stated here so that the parser does not load zenoh
(tests/test_cli_startup.py checks they agree)."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help="run the self-contained demo (in-process Zenoh router, simulated vehicle, the service)",
        description="A simulated vehicle goes through ground handling, a short flight and a fault; the service finds and names it.",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=DEFAULT_SPEED,
        help=f"simulated time per wall-clock second (default {DEFAULT_SPEED:g})",
    )
    p.add_argument("--seed", type=int, default=7, help="seed of the simulated session (default 7)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from service.demo import run_demo

    if not 0.5 <= args.speed <= 100:
        raise ValueError(f"--speed must be within 0.5..100, got {args.speed!r}")
    result = asyncio.run(run_demo(speed=args.speed, seed=args.seed))
    return 0 if result.detected and result.named else 1
