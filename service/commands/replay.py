"""``ins-health replay LOG [--json] [--pace recorded|fast] [--passport FILE | --passport-dir DIR]``.

Reads a MAVLink telemetry log (``.tlog``), an ArduPilot DataFlash log (binary
``.bin`` or text ``.log`` as the firmware writes it; IMU/IMU2/IMU3 with
temperature) or a PX4 ULog (``sensor_combined`` and the per-instance IMU topics
logged at a useful rate), recognised by content, with
:class:`protocols.logs.LogReader` and runs it through the daemon's pipeline
(:class:`service.pipeline.FleetProcessor`), printing the events: as a person
reads them, or with ``--json`` one JSON object per line
(:func:`protocols.events.event_to_json`). The same log always gives the same
events, ids included: everything runs on the log's own time. The timeout check
is a live one (no sample for ``timeout_s`` on the arrival clock) and is not run
on a log; a gap in a log is counted as a time jump (the summary on stderr lists
the counters) and ends the static interval it falls in. ``--pace recorded``
replays at the logged rate (wall clock), ``fast`` (default) as fast as possible.

Passports: ``--passport FILE`` (a passport JSON, e.g. from ``ins-health
calibrate``) for every IMU of the log, or ``--passport-dir DIR`` (the service's
passport store, keyed by ``--vehicle`` and IMU). Without either the stream
checks run alone. Options of a service configuration (``--config``: ``[site]``,
``[pipeline]``, ``[validity]``) apply as in the daemon; ``--gravity`` or ``--latitude``
(``--height``) override its site.

Exit status 0 whatever the events; 2 for an unusable log, passport or option, and
for a log without IMU data (the message names what the log holds).
A summary goes to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli import UsageError
from service.method_args import add_gravity_options

if TYPE_CHECKING:
    from estimators.passport import Passport
    from protocols.events import Event
    from protocols.logs import LogReader
    from service.config import ServiceConfig
    from service.pipeline import FleetProcessor

REPLAY_BATCH_SAMPLES = 100
REPLAY_MAX_IMUS = 16


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay",
        help="run a logged flight (.tlog, DataFlash .bin/.log, PX4 .ulg) through the pipeline and print the events",
        description="Replay a log through the same pipeline as the daemon; the same log always gives the same events.",
    )
    p.add_argument(
        "log", type=Path, metavar="LOG", help="a .tlog, DataFlash .bin/.log or ULog .ulg file"
    )
    p.add_argument("--json", action="store_true", help="one JSON event per line (the event schema)")
    p.add_argument(
        "--pace",
        choices=("fast", "recorded"),
        default="fast",
        help="as fast as possible (default) or at the recorded rate",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--passport", type=Path, metavar="FILE", help="passport JSON for every IMU of the log"
    )
    src.add_argument(
        "--passport-dir",
        type=Path,
        metavar="DIR",
        help="passport store (<vehicle>/imu<n>.passport.json)",
    )
    p.add_argument(
        "--vehicle", default="replay", help="vehicle id given to the log's IMUs (default 'replay')"
    )
    p.add_argument(
        "--config",
        type=Path,
        help="service configuration whose [site], [pipeline] and [validity] apply",
    )
    add_gravity_options(p)
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> ServiceConfig:
    from service.config import ServiceConfig, SiteSection, load_config

    config = load_config(args.config) if args.config else ServiceConfig()
    if args.gravity_mps2 is not None or args.latitude_deg is not None:
        site = SiteSection(
            gravity_mps2=args.gravity_mps2, latitude_deg=args.latitude_deg, height_m=args.height_m
        )
        if not 9.7 < site.local_gravity_mps2 < 9.9:
            raise UsageError(
                f"local gravity {site.local_gravity_mps2!r} m/s² is not a value on the Earth's surface"
            )
        config = dataclasses.replace(config, site=site)
    return config


def _lookup(args: argparse.Namespace):
    from protocols.passport_codec import read_passport_json
    from service.passport_store import PassportStore

    if args.passport is not None:
        passport: Passport = read_passport_json(args.passport)
        return lambda vehicle, imu: passport
    if args.passport_dir is not None:
        return PassportStore(args.passport_dir).get

    def none(vehicle: str, imu: int) -> Passport:
        raise ValueError("no passport given (--passport or --passport-dir)")

    return none


def replay_events(
    log: Path, *, fleet: FleetProcessor, vehicle: str, pace_recorded: bool = False, on_event=None
) -> tuple[list[Event], LogReader]:
    """Run a log through ``fleet``; returns every event in order and the reader (with its statistics).

    Each frame is stamped with its last sample time as its arrival (the log's own clock).
    """
    from protocols.logs import LogReader

    reader = LogReader(log, vehicle=vehicle, batch_samples=REPLAY_BATCH_SAMPLES)
    events: list[Event] = []

    def emit(event: Event) -> None:
        events.append(event)
        if on_event is not None:
            on_event(event)

    start: tuple[float, float] | None = None  # (wall clock, data time) at the first frame
    for batch in reader:
        t_last = float(batch.t_s[-1])
        if pace_recorded:
            if start is None:
                start = time.monotonic(), float(batch.t_s[0])
            wall0, data0 = start
            delay = (t_last - data0) - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
        for e in fleet.process(batch, arrival_s=t_last):
            emit(e)
    for e in fleet.finish():
        emit(e)
    return events, reader


def human(event: Event) -> str:
    return f"t={event.t_s:10.3f} s  {event.severity.name:<8s} {event.text}"


def run(args: argparse.Namespace) -> int:
    from protocols.events import event_to_json
    from service.daemon import pipeline_options
    from service.pipeline import FleetProcessor

    config = _config(args)
    errors: list[str] = []
    fleet = FleetProcessor(
        passports=_lookup(args),
        options=pipeline_options(config),
        # A log's IMUs are all wanted (a ULog numbers its instances up to 8, protocols.ulog).
        max_imus_per_vehicle=max(config.pipeline.max_imus_per_vehicle, REPLAY_MAX_IMUS),
        on_passport_error=lambda v, i, msg: errors.append(f"{v} IMU{i}: {msg}"),
    )
    printer = (
        (lambda e: print(event_to_json(e), flush=True))
        if args.json
        else (lambda e: print(human(e), flush=True))
    )
    events, reader = replay_events(
        args.log,
        fleet=fleet,
        vehicle=args.vehicle,
        pace_recorded=args.pace == "recorded",
        on_event=printer,
    )
    for line in errors:
        print(f"ins-health replay: {line}; stream checks only", file=sys.stderr)
    samples = ", ".join(f"IMU{i} {n}" for i, n in sorted(reader.stats.samples.items())) or "none"
    dropped = ", ".join(f"{k} {n}" for k, n in sorted(reader.stats.dropped.items())) or "none"
    print(
        f"ins-health replay: {args.log.name} ({reader.format.value}): samples {samples}; left out {dropped}; {len(events)} events",
        file=sys.stderr,
    )
    for vehicle in fleet.vehicles():
        counters = fleet.status(vehicle, service="replay", now_unix_s=0.0).counters
        print(
            "ins-health replay: counters "
            + ", ".join(f"{k} {n}" for k, n in sorted(counters.items())),
            file=sys.stderr,
        )
    return 0
