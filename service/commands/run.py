"""``ins-health run --config FILE.toml``: the daemon (service/daemon.py).

Runs until SIGTERM or SIGINT, then drains: stops taking frames, processes what
was received, writes the checkpoints and keeps delivering events for a few
seconds; whatever is still undelivered is sent by the next start. Exit status
0 after a clean stop, 2 for an unusable configuration.

The log goes to stderr through :mod:`service.log_setup` (one line per record; under
journald without time stamps and with syslog priorities); ``--log-level`` sets its
threshold. Once frames are accepted it says ``ins-health: NAME running``.
"""

from __future__ import annotations

import argparse
import signal
import sys
from typing import TYPE_CHECKING

from service.log_setup import LEVELS, logger, logging_to

if TYPE_CHECKING:
    from service.daemon import Service


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the health-monitor daemon",
        description="Run the ins-health daemon: IMU frames in (Zenoh, MAVLink), fault events out (durable outbox).",
    )
    p.add_argument(
        "--config", required=True, help="service configuration, TOML (see deploy/ins-health.toml)"
    )
    p.add_argument(
        "--log-level",
        choices=LEVELS,
        default="info",
        help="least severe log records written to stderr (default: %(default)s)",
    )
    p.set_defaults(func=run)


async def serve(service: Service) -> None:
    """Run ``service`` until SIGTERM or SIGINT."""
    import asyncio

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    ready = asyncio.Event()
    runner = asyncio.create_task(service.run(stop, ready=ready))
    await asyncio.wait(
        [runner, asyncio.create_task(ready.wait())], return_when=asyncio.FIRST_COMPLETED
    )
    if ready.is_set():
        logger("run").info("%s running", service.config.service.name)
    await runner


SWITCH_INTERVAL_S = 0.001
"""Python's thread switch interval for the daemon (default 5 ms). The transport threads (Zenoh
callbacks, the MAVLink reader, event delivery) wait for the interpreter lock while the loop runs a
pipeline; a 1 ms interval bounds that wait, which is most of the fault-to-event latency's tail."""


def run(args: argparse.Namespace) -> int:
    import asyncio

    from service.config import load_config
    from service.daemon import Service

    config = load_config(args.config)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    with logging_to(sys.stderr, level=args.log_level):
        asyncio.run(serve(Service(config)))
    return 0
