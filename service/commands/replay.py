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
replays at the logged rate (wall clock), ``fast`` (default) as fast as possible;
a step of the log's time between frames longer than :data:`PACE_MAX_STEP_S`, forward
or back, is not waited for: the pacing resumes from the frame after it, and the
summary counts these steps.

Passports: ``--passport FILE`` (a passport JSON, e.g. from ``ins-health
calibrate``) for every IMU of the log, or ``--passport-dir DIR`` (the service's
passport store, keyed by ``--vehicle`` and IMU). Without either — a real log
never comes with one — every IMU gets the nominal passport of its sensor class
(``--grade``, default ``consumer_mems``; :mod:`estimators.nominal_passport`),
given by the fleet as the daemon gives it (``[service] default_grade``) and from
the same rate (:data:`service.pipeline.options.NOMINAL_MIN_RATE_HZ`):
F0 runs on the samples at rest against the class's tolerances, and the
nine-parameter diagnosis where the log holds the positions.

``--report DIR`` writes the log's IMU health report (``report.json``,
``report.md``, plots; :mod:`service.log_report`). Replays that take longer
than a few seconds print a progress line on stderr every
:data:`PROGRESS_EVERY_S` seconds (at full speed and with ``--pace recorded``);
memory stays bounded whatever the log's length (the reader streams, the
pipeline and the report keep small per-IMU state). Options of a service configuration (``--config``: ``[site]``,
``[pipeline]``, ``[validity]``) apply as in the daemon; ``--gravity`` or ``--latitude``
(``--height``) override its site.

Coverage and verdict. After the log, every IMU's coverage
(:func:`service.pipeline.coverage.imu_coverage`: per triad F0 and F1…F9 with the
samples or positions they ran on and their minimum detectable fault, the stream
checks, cross-IMU; what did not run and why) goes to stderr, one line per check,
and the verdict after it: ``fault`` when a sensor finding was raised (F0…F9,
gross, stale; not a recovery), ``no fault`` only when every check that applies
ran, else ``no finding within coverage`` with what was not tested (a warning).
With ``--json`` the last line of stdout is the coverage as one JSON object of
type ``ins.health.coverage`` (:data:`COVERAGE_TYPE`), told from the events by
its ``type``; ``--report`` writes it into the report.

Exit status (:mod:`service.cli`): 0 tested, no fault; 1 a fault found; 2 an
unusable log, passport or option, or a log without IMU data (the message names
what the log holds); 3 not enough to test — a check that applies did not run, or
the pipeline failed on frames (a passport it cannot use, say: each kind of
failure is named once with the frames it cost, and those samples were not tested).
A fault outranks 3. A summary goes to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli import (
    EXIT_OF_VERDICT,
    EXIT_STATUS_HELP,
    PROGRESS_EVERY_S,
    UsageError,
    add_output,
)
from service.method_args import add_gravity_options

if TYPE_CHECKING:
    from collections.abc import Callable

    from estimators.coverage import ImuCoverage, Verdict
    from estimators.nominal_passport import SensorClass
    from estimators.passport import Passport
    from protocols.events import Event
    from protocols.frames import SampleBatch
    from protocols.logs import LogReader
    from service.config import ServiceConfig
    from service.log_report import ImuF0
    from service.pipeline import FleetProcessor

REPLAY_BATCH_SAMPLES = 100
REPLAY_MAX_IMUS = 16
COVERAGE_TYPE = "ins.health.coverage"
COVERAGE_VERSION = 1
"""Schema of the ``--json`` coverage line: ``type``, ``v``, ``vehicle``, ``verdict`` (a
:class:`estimators.coverage.Verdict` value), ``exit_status``, ``untested`` (lines), ``imus``
(:meth:`estimators.coverage.ImuCoverage.to_dict` each)."""
PACE_MAX_STEP_S = 60.0
"""Longest step of log time between frames that ``--pace recorded`` waits through, s. A frame of
:data:`REPLAY_BATCH_SAMPLES` samples of a 4 Hz telemetry stream spans 25 s; a longer step is a
logging pause or a corrupt time stamp (one a year ahead, or past what a sleep takes), not worth
the wait."""
SENSOR_CLASSES = ("consumer_mems", "industrial_mems", "tactical", "navigation")
"""The values of :class:`estimators.nominal_passport.SensorClass`, the default first (stated here:
building the parser must not import scipy, service.cli)."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay",
        help="run a logged flight (.tlog, DataFlash .bin/.log, PX4 .ulg) through the pipeline and print the events",
        description="Replay a log through the same pipeline as the daemon; the same log always gives the same events. "
        "After them: what each check tested (its minimum detectable fault) and what it could not, and the verdict.",
        epilog=EXIT_STATUS_HELP,
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
        "--grade",
        choices=SENSOR_CLASSES,
        default=SENSOR_CLASSES[0],
        help="sensor class of the nominal passport used without --passport/--passport-dir (default consumer_mems)",
    )
    add_output(
        p,
        "--report",
        metavar="DIR",
        help="write the IMU health report (report.json, report.md, plots) into DIR (created; its parent must exist)",
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


def _lookup(args: argparse.Namespace) -> tuple[Any, SensorClass | None, dict[str, Any]]:
    """The passport lookup, the class whose nominal passport the fleet gives a unit without one
    (:class:`~service.pipeline.FleetProcessor`, as the daemon's ``[service] default_grade``), and
    what the report says about them."""
    from estimators.nominal_passport import SensorClass, describe_class
    from protocols.passport_codec import read_passport_json
    from service.passport_store import PassportStore

    if args.passport is not None:
        passport: Passport = read_passport_json(args.passport)
        info = {"kind": "file", "unit_id": passport.unit_id, "sensor_model": passport.sensor_model}
        return (lambda vehicle, imu: passport), None, info
    if args.passport_dir is not None:
        return PassportStore(args.passport_dir).get, None, {"kind": "store"}
    return (
        (lambda vehicle, imu: None),
        SensorClass(args.grade),
        {"kind": "nominal", **describe_class(args.grade)},
    )


def replay_events(
    log: Path,
    *,
    fleet: FleetProcessor,
    vehicle: str,
    pace_recorded: bool = False,
    on_event: Callable[[Event], None] | None = None,
    on_batch: Callable[[SampleBatch], None] | None = None,
    progress: Callable[[str], None] | None = None,
    on_pace_step: Callable[[float], None] | None = None,
) -> tuple[list[Event], LogReader]:
    """Run a log through ``fleet``; returns every event in order and the reader (with its statistics).

    Each frame is stamped with its last sample time as its arrival (the log's own clock).
    ``on_batch`` sees every frame the reader gives; ``progress`` gets a line every
    :data:`PROGRESS_EVERY_S` seconds of wall time; ``on_pace_step`` each step of log time (s)
    that ``pace_recorded`` does not wait through (module docstring).
    """
    from protocols.logs import LogReader

    reader = LogReader(log, vehicle=vehicle, batch_samples=REPLAY_BATCH_SAMPLES)
    events: list[Event] = []

    def emit(event: Event) -> None:
        events.append(event)
        if on_event is not None:
            on_event(event)

    wall0 = time.monotonic()
    data0: float | None = None
    next_note = wall0 + PROGRESS_EVERY_S
    samples = 0
    paced_t, due = 0.0, wall0  # the latest log time paced, and when it was due on the wall clock
    for batch in reader:
        t_last = float(batch.t_s[-1])
        if data0 is None:
            data0 = paced_t = float(batch.t_s[0])
        if pace_recorded:
            step = t_last - paced_t
            if abs(step) > PACE_MAX_STEP_S:
                paced_t = t_last
                if on_pace_step is not None:
                    on_pace_step(step)
            elif step > 0:
                paced_t, due = t_last, due + step
                if (delay := due - time.monotonic()) > 0:
                    time.sleep(delay)
        samples += batch.n_samples
        if on_batch is not None:
            on_batch(batch)
        for e in fleet.process(batch, arrival_s=t_last):
            emit(e)
        now = time.monotonic()
        if progress is not None and now >= next_note:
            next_note = now + PROGRESS_EVERY_S
            progress(
                f"{100.0 * reader.fraction_read:3.0f} % of {log.name} read, {samples:,} samples, "
                f"{t_last - data0:.0f} s of log in {now - wall0:.0f} s"
            )
    for e in fleet.finish():
        emit(e)
    return events, reader


def human(event: Event) -> str:
    return f"t={event.t_s:10.3f} s  {event.severity.name:<8s} {event.text}"


def run(args: argparse.Namespace) -> int:
    import json

    from estimators.coverage import Verdict, untested_lines, verdict
    from estimators.log_health import HealthConfig, ImuHealthAccumulator, pair_differences
    from protocols.events import StreamCause, event_to_json
    from service.daemon import pipeline_options
    from service.pipeline import FleetProcessor, detector_config
    from service.pipeline.coverage import FAULT_PREDICATES, imu_coverage

    config = _config(args)
    options = pipeline_options(config)
    errors: list[str] = []
    failed: dict[
        tuple[str, int, str], list[Any]
    ] = {}  # (vehicle, imu, kind) -> [frames, first message]
    pace_steps: list[float] = []

    def pipeline_error(vehicle: str, imu: int, message: str) -> None:
        failed.setdefault((vehicle, imu, message.split(":", 1)[0]), [0, message])[0] += 1

    lookup, nominal, passport_info = _lookup(args)
    fleet = FleetProcessor(
        passports=lookup,
        nominal=nominal,
        options=options,
        # A log's IMUs are all wanted (a ULog numbers its instances up to 8, protocols.ulog).
        max_imus_per_vehicle=max(config.pipeline.max_imus_per_vehicle, REPLAY_MAX_IMUS),
        on_passport_error=lambda v, i, msg: errors.append(f"{v} IMU{i}: {msg}"),
        on_pipeline_error=pipeline_error,
    )
    printer = (
        (lambda e: print(event_to_json(e), flush=True))
        if args.json
        else (lambda e: print(human(e), flush=True))
    )
    health: dict[int, ImuHealthAccumulator] = {}
    health_config = HealthConfig()

    def observe(batch: SampleBatch) -> None:
        if args.report is None:
            return
        acc = health.get(batch.imu)
        if acc is None:
            # Rest as the pipeline's static detector sees it: its thresholds raised to the passport's noise.
            pipe = fleet.admit(batch.vehicle, batch.imu)
            det = detector_config(
                options,
                None if pipe is None else pipe.passport_at(_rate(batch)),
                _rate(batch),
            )
            acc = health[batch.imu] = ImuHealthAccumulator(
                dataclasses.replace(
                    health_config,
                    accel_rest_mps2=det.accel_std_mps2,
                    gyro_rest_rps=det.gyro_std_rps,
                )
            )
        acc.update(batch.t_s, batch.accel_mps2, batch.gyro_rps, batch.temp_c)

    events, reader = replay_events(
        args.log,
        fleet=fleet,
        vehicle=args.vehicle,
        pace_recorded=args.pace == "recorded",
        on_event=printer,
        on_batch=observe,
        progress=lambda line: print(f"ins-health replay: {line}", file=sys.stderr, flush=True),
        on_pace_step=pace_steps.append,
    )
    errors += [
        f"{v} IMU{i}: {pipe.nominal_too_slow}"
        for (v, i), pipe in sorted(fleet.pipelines.items())
        if pipe.nominal_too_slow
    ]
    for line in errors:
        print(f"ins-health replay: {line}; stream checks only", file=sys.stderr)
    for (vehicle, imu, _), (frames, message) in sorted(failed.items()):
        print(
            f"ins-health replay: {vehicle} IMU{imu}: the pipeline failed on {frames} frame(s) ({message}); "
            "their samples were not tested",
            file=sys.stderr,
        )
    if passport_info["kind"] == "nominal":
        print(
            f"ins-health replay: no passport: nominal passport of class {passport_info['class']} ({passport_info['source']})",
            file=sys.stderr,
        )
    if pace_steps:
        longest = max(pace_steps, key=abs)
        print(
            f"ins-health replay: --pace recorded: {len(pace_steps)} steps of log time over {PACE_MAX_STEP_S:g} s "
            f"not waited for (longest {longest:+.6g} s); the pacing resumed after each",
            file=sys.stderr,
        )
    for key, why in sorted(reader.stats.skipped.items()):
        print(f"ins-health replay: not replayed: {key} {why}", file=sys.stderr)
    if cut := reader.stats.cut():
        print(f"ins-health replay: {args.log.name} is {cut}: read up to there", file=sys.stderr)
    for said in (reader.stats.logger(), reader.stats.clock()):
        if said:
            print(f"ins-health replay: {args.log.name}: {said}", file=sys.stderr)
    samples = ", ".join(f"IMU{i} {n}" for i, n in sorted(reader.stats.samples.items())) or "none"
    print(
        f"ins-health replay: {args.log.name} ({reader.format.value}): samples {samples}; left out {reader.stats.left_out()}; {len(events)} events",
        file=sys.stderr,
    )
    for vehicle in fleet.vehicles():
        counters = fleet.status(vehicle, service="replay", now_unix_s=0.0).counters
        print(
            "ins-health replay: counters "
            + ", ".join(f"{k} {n}" for k, n in sorted(counters.items())),
            file=sys.stderr,
        )
    pipes = [p for (v, _), p in sorted(fleet.pipelines.items()) if v == args.vehicle]
    coverages = [imu_coverage(p, imus_on_vehicle=len(pipes)) for p in pipes]
    found = [
        e
        for e in events
        if e.predicate.value in FAULT_PREDICATES and e.cause != StreamCause.RECOVERED
    ]
    said = verdict(bool(found), coverages)
    untested = untested_lines(coverages) + [
        f"IMU{imu}: the pipeline failed on {frames} frame(s)"
        for (_, imu, _), (frames, _) in sorted(failed.items())
    ]
    if failed and said is Verdict.NO_FAULT:
        said = Verdict.NO_FINDING
    status = EXIT_OF_VERDICT[said.value]
    for cov in coverages:
        for line in cov.lines():
            print(f"ins-health replay: coverage {line}", file=sys.stderr)
    print(f"ins-health replay: {_verdict_line(said, len(found), untested)}", file=sys.stderr)
    if args.json:
        print(
            json.dumps(_coverage_map(args.vehicle, said, status, untested, coverages)), flush=True
        )
    if args.report is not None:
        from service.log_report import build_report, write_report

        healths = {imu: acc.result(options.gravity_mps2) for imu, acc in sorted(health.items())}
        pairs = pair_differences({i: h.blocks for i, h in healths.items()}, health_config.block_s)
        report = build_report(
            log_name=args.log.name,
            log_format=reader.format.value,
            stats=reader.stats,
            system=reader.system,
            passport=passport_info,
            gravity_mps2=options.gravity_mps2,
            config=health_config,
            healths=healths,
            f0={imu: _f0_summary(fleet, args.vehicle, imu) for imu in healths},
            pairs=pairs,
            events=events,
            coverage=_coverage_map(args.vehicle, said, status, untested, coverages),
        )
        md = write_report(report, healths, pairs, args.report)
        print(f"ins-health replay: report {md}", file=sys.stderr)
    return status


def _verdict_line(said: Verdict, n_found: int, untested: list[str]) -> str:
    """The verdict as a person reads it: the findings, or what was not tested (a warning)."""
    from estimators.coverage import Verdict

    if said is Verdict.FAULT:
        return f"ERROR    verdict: fault ({n_found} finding event(s) above)"
    if said is Verdict.NO_FINDING:
        return "WARNING  verdict: no finding within coverage; not tested: " + "; ".join(untested)
    return "INFO     verdict: no fault (every check that applies ran)"


def _coverage_map(
    vehicle: str, said: Verdict, status: int, untested: list[str], coverages: list[ImuCoverage]
) -> dict[str, Any]:
    """The coverage line of ``--json`` and of the report (:data:`COVERAGE_VERSION`)."""
    return {
        "type": COVERAGE_TYPE,
        "v": COVERAGE_VERSION,
        "vehicle": vehicle,
        "verdict": said.value,
        "exit_status": status,
        "untested": untested,
        "imus": [c.to_dict() for c in coverages],
    }


def _rate(batch: SampleBatch) -> float:
    """The rate a frame was sampled at (median interval), Hz; 1 Hz for a one-sample frame."""
    import numpy as np

    return float(1.0 / np.median(np.diff(batch.t_s))) if batch.n_samples > 1 else 1.0


def _f0_summary(fleet: FleetProcessor, vehicle: str, imu: int) -> ImuF0 | None:
    """What F0 did on an IMU's accelerometers (shell and counts), from its pipeline."""
    from estimators.conventions import Triad
    from service.log_report import ImuF0

    pipe = fleet.pipelines.get((vehicle, imu))
    check = None if pipe is None else pipe.checks.get(Triad.ACCEL)
    if pipe is None or check is None:
        return None
    return ImuF0(
        lambda0=check.lambda0 if check.f0 is not None else None,
        tests=pipe.counters.get("f0.accel.tests", 0),
        fails=pipe.counters.get("f0.accel.fail", 0),
    )
