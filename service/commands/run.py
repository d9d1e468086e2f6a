"""``ins-health run --config FILE.toml``: the daemon (service/daemon.py).

Runs until SIGTERM or SIGINT (SIGHUP is logged and ignored: there is no reload), then drains: stops taking frames, processes what
was received, writes the checkpoints and keeps delivering events for a few
seconds; whatever is still undelivered is sent by the next start. SIGTERM or SIGINT
ends it within :data:`STOP_BOUND_S` in every state (connecting to an unreachable router
included); past that bound it logs why and exits with :data:`EXIT_STOP_TIMEOUT`. Exit status
0 after a clean stop, 2 for an unusable configuration (a ``data_dir`` this user cannot create or
write included: one line naming the setting and the fix, not a restart loop under
``Restart=on-failure``), 1 for a failure outside the tasks
(logged with its traceback), 70 when a task kept failing or the router stayed out of reach
beyond ``connect_timeout_s`` (:mod:`service.supervisor`), 74 when storage stayed away beyond
``storage_timeout_s`` or events held in memory could not be stored before the exit
(:data:`service.daemon.EXIT_STORAGE`), so that systemd starts it afresh.

The log goes to stderr through :mod:`service.log_setup` (one line per record; under
journald without time stamps and with syslog priorities); ``--log-level`` sets its
threshold. ``--data-dir DIR`` stands for the configuration's ``[service] data_dir`` (a trial as a normal
user with the deploy's configuration, whose data lives in ``/var/lib/ins-health``). Once an input is
connected (the Zenoh router, the MAVLink link) it says ``ins-health: NAME running``; until then
``NAME waiting for …`` naming the inputs it waits for (:meth:`service.daemon.Service.run`).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import getpass
import importlib
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli import UsageError
from service.log_setup import LEVELS, logger, logging_to

if TYPE_CHECKING:
    from service.config import ServiceConfig
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
        "--data-dir",
        help="folder of the outbox and checkpoints, instead of the configuration's [service] data_dir",
    )
    p.add_argument(
        "--log-level",
        choices=LEVELS,
        default="info",
        help="least severe log records written to stderr (default: %(default)s)",
    )
    p.set_defaults(func=run)


STOP_BOUND_S = 15.0
"""The longest a stop may take, from SIGTERM to exit: the drain's delivery time
(``service.daemon.DRAIN_TIMEOUT_S``, 5 s), a Zenoh connection attempt under way
(``CONNECT_ATTEMPT_S``, 3 s), an acknowledgement under way (``ack_timeout_s``, 1 s by
default), the queued frames and the last checkpoint; below the unit's ``TimeoutStopSec``.
A MAVLink open under way is not waited for (it runs in a thread of its own, left behind)."""
EXIT_FAILED = 1
"""Exit status when the daemon fails outside its supervised tasks (at start, or in the drain)."""
EXIT_STOP_TIMEOUT = 75
"""Exit status when a stop overran :data:`STOP_BOUND_S` (EX_TEMPFAIL of sysexits.h)."""


async def serve(service: Service) -> int:
    """Run ``service`` until SIGTERM or SIGINT (or a fatal failure); its exit status."""
    import asyncio
    import os

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    # SIGHUP (a closed terminal or ssh session, or an operator expecting a reload) killed the daemon
    # with no drain and no last checkpoint. There is no reload: it is said and otherwise ignored, so a
    # stop stays SIGTERM's and systemd's Restart= keeps its meaning.
    loop.add_signal_handler(
        signal.SIGHUP,
        lambda: logger("run").warning(
            "SIGHUP ignored: the configuration is read at start (restart the service to read it "
            "again); SIGTERM or SIGINT stops it"
        ),
    )
    runner = asyncio.create_task(service.run(stop))
    await asyncio.wait(
        [runner, asyncio.create_task(stop.wait())], return_when=asyncio.FIRST_COMPLETED
    )
    done, _ = await asyncio.wait([runner], timeout=STOP_BOUND_S)
    if not done:
        logger("run").critical(
            "the stop took longer than %.0f s; exiting with status %d without finishing it",
            STOP_BOUND_S, EXIT_STOP_TIMEOUT,
        )  # fmt: skip
        # The outbox and checkpoints are SQLite in WAL mode: as safe as after kill -9.
        os._exit(EXIT_STOP_TIMEOUT)
    return runner.result()


SWITCH_INTERVAL_S = 0.001
"""Python's thread switch interval for the daemon (default 5 ms). The transport threads (Zenoh
callbacks, the MAVLink reader, event delivery) wait for the interpreter lock while the loop runs a
pipeline; a 1 ms interval bounds that wait, which is most of the fault-to-event latency's tail."""


def freeze_imports() -> None:
    """Keep what the imports made (modules, numpy's, scipy's, zenoh's and pymavlink's tables: it lives as
    long as the process) out of the cyclic collector's full passes.

    A full pass walks every tracked object and stops every thread meanwhile, and an event delivered
    during one comes that much later. The modules a pipeline loads on its first frame
    (:data:`service.pipeline.PIPELINE_IMPORTS`) are loaded here first, so they are frozen with the rest: loaded
    after the freeze, they were 44,000 of the 44,300 objects the full passes walked in the daemon
    under the MAVLink latency benchmark (passes of 13–47 ms; 330 objects after). The daemon
    starts 0.8 s later and its first unit's first frame no longer waits for them. Objects made
    later are collected as before.
    """
    from service.pipeline import PIPELINE_IMPORTS

    for name in PIPELINE_IMPORTS:
        importlib.import_module(name)
    gc.collect()
    gc.freeze()


def with_data_dir(config: ServiceConfig, args: argparse.Namespace) -> ServiceConfig:
    """``config`` with ``--data-dir`` in place of its ``data_dir``, the folder made and checked writable.

    A folder this user may not make or write ended the start in a traceback on one log line
    (``PermissionError: '/var/lib/ins-health'``), exit 1, which ``Restart=on-failure`` repeats;
    now it is a configuration error naming the setting and the fix.
    """
    if args.data_dir is not None:
        service = dataclasses.replace(config.service, data_dir=Path(args.data_dir).resolve())
        config = dataclasses.replace(config, service=service)
        where = "--data-dir"
    else:
        where = f"[service] data_dir of {args.config}"
    folder = config.service.data_dir
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(f"Permission denied: {str(folder)!r}")
    except OSError as exc:
        raise UsageError(
            f"{where} = {str(folder)!r} cannot be used by user {getpass.getuser()} "
            f"({exc.strerror or exc}): give --data-dir DIR (a folder of yours, e.g. "
            f"~/.local/share/ins-health) or set data_dir to a folder this user may write"
        ) from None
    return config


def run(args: argparse.Namespace) -> int:
    import asyncio

    from service.config import load_config
    from service.daemon import Service
    from service.outbox import OutboxError

    config = with_data_dir(load_config(args.config), args)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    freeze_imports()
    with logging_to(sys.stderr, level=args.log_level):
        try:
            return asyncio.run(serve(Service(config)))
        except OutboxError as exc:
            # The outbox's own words say what is wrong and what to do; a traceback would bury them.
            logger("run").critical("the daemon cannot start: %s", exc)
            return EXIT_FAILED
        except Exception:
            # A failure outside the supervised tasks (a link that cannot be opened, a state
            # file that cannot be read): one log record with its traceback, then status 1.
            logger("run").critical("the daemon failed", exc_info=True)
            return EXIT_FAILED
