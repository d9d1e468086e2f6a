"""Command-line pieces shared by the commands that talk to a deployed daemon through its Zenoh router (``watch``, ``publish``)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from protocols.zenoh_adapter import Session

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
"""The router of ``deploy/ins-health.toml`` (``[zenoh] connect``)."""
DEFAULT_CONNECT_TIMEOUT_S = 10.0


def add_router_arguments(parser: argparse.ArgumentParser) -> None:
    """``--router ENDPOINT`` and ``--connect-timeout-s S``."""
    parser.add_argument(
        "--router",
        default=DEFAULT_ROUTER,
        metavar="ENDPOINT",
        help=f"the Zenoh router to connect to (default {DEFAULT_ROUTER})",
    )
    parser.add_argument(
        "--connect-timeout-s",
        type=float,
        default=DEFAULT_CONNECT_TIMEOUT_S,
        metavar="S",
        help=f"how long to wait for the router, s (default {DEFAULT_CONNECT_TIMEOUT_S:g})",
    )


def open_router_session(args: argparse.Namespace) -> Session:
    """A client session of ``args.router`` (a context manager); ``ConnectionError`` when it does not answer in time.

    A bad endpoint is a ``ValueError`` naming it (protocols.zenoh_adapter.ZenohSettings).
    """
    from protocols.zenoh_adapter import open_session

    if not args.connect_timeout_s > 0:
        raise ValueError(f"--connect-timeout-s must be positive, got {args.connect_timeout_s!r}")
    return open_session(
        {"mode": "client", "connect": [args.router], "connect_timeout_s": args.connect_timeout_s}
    )
