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
With ``--json`` the last line of stdout, even when no event came, is one summary
object of type ``ins.health.coverage`` (:data:`COVERAGE_TYPE`, schema
:data:`COVERAGE_VERSION`: samples, what was left out, the counts of events and
findings, the coverage and the verdict), told from the events by its ``type``;
``--report`` writes it into the report. :func:`replay_log` is the replay as a
value (:class:`ReplayResult`), behind ``ins_health.replay``.

Exit status (:mod:`service.cli`): 0 tested, no fault; 1 a fault found; 2 an
unusable log, passport or option, or a log without IMU data (the message names
what the log holds); 3 not enough to test — a check that applies did not run, or
the pipeline failed on frames (a passport it cannot use, say: each kind of
failure is named once with the frames it cost, and those samples were not tested).
A fault outranks 3. A summary goes to stderr.

Memory: the pipeline's batches of up to :data:`REPLAY_GROUP_SAMPLES` make temporaries of a few MB
each. glibc's malloc maps each one larger than its threshold (128 kB at the start) from the
kernel and unmaps it when freed, so every batch faults its pages in afresh; the threshold rises
by itself only when the process happens to free a larger mapped block first. The command sets it
(:func:`keep_batch_temporaries_on_heap`): with glibc's start value held, the hour of ULog took 4.4
million page faults and about 8 s more of CPU (7.5 s in the kernel) than with it risen (42,000
faults), or set (31,000). Other C libraries are left as they are.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
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
from service.grades import SENSOR_CLASSES, grade_name
from service.method_args import add_gravity_options

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from estimators.coverage import ImuCoverage, Verdict
    from estimators.cross_imu_norm import NormBlock
    from estimators.nominal_passport import SensorClass
    from estimators.passport import Passport
    from protocols.events import Event
    from protocols.frames import SampleBatch
    from protocols.logs import LogReader
    from service.config import ServiceConfig
    from service.log_report import ImuF0
    from service.pipeline import FleetProcessor

REPLAY_BATCH_SAMPLES = 100
"""Samples per frame the log is read in: the frames the cross-IMU checks see, in the order the log
holds them, as a live stream's (at full speed the reader joins an IMU's frames that come in a row:
an IMU alone on its vehicle takes them joined, :func:`_taken`)."""
REPLAY_GROUP_SAMPLES = 16384
"""Samples of consecutive frames taken together at full speed
(:meth:`~service.pipeline.FleetProcessor.process_queued`, as the daemon takes queued frames): their
IMU's pipeline takes them as one batch (its cost is mostly per batch: about 1 ms, 56,000
samples/s in frames of 100; 20 minutes at 1 kHz replayed 0.3 s faster in groups of 16,384 than of
4,096, none faster in groups of 32,768; peak memory 19 MB more than at 4,096, 5 MB at 8,192), and
its events and the report do not depend on how the samples are batched
(``tests/test_replay_framing.py``). Only frames of IMUs each alone on its vehicle so far are taken
together (:func:`_take`); the reader joins up to as many (:func:`replay_events`)."""
REPLAY_MAX_IMUS = 16
HEAP_MMAP_THRESHOLD_BYTES = 16 << 20
"""Blocks glibc's malloc takes from its heap, not from fresh kernel mappings, in a replay (module
docstring: a batch's temporaries are a few MB; freed, the heap keeps them for the next batch)."""
HEAP_TRIM_THRESHOLD_BYTES = 32 << 20
"""Free memory at the top of the heap glibc keeps rather than gives back (its rule: twice the
mapping threshold, as when the threshold rises by itself)."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
USER_MALLOC_SETTINGS = (
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_TOP_PAD_",
    "MALLOC_MMAP_MAX_",
)
"""glibc's environment variables for the thresholds a replay would set: set by the user, they stand."""
"""mallopt's parameter numbers (glibc's ``malloc.h``)."""
COVERAGE_TYPE = "ins.health.coverage"
COVERAGE_VERSION = 2
"""Schema of the ``--json`` summary line, the last of stdout even when no event came: ``type``
(:data:`COVERAGE_TYPE`), ``v``, ``vehicle``, ``log`` (the file's name), ``start_t_s`` (its first
sample's time on its clock, or null), ``verdict`` (a
:class:`estimators.coverage.Verdict` value), ``exit_status``, ``untested`` (lines), ``samples``
(read per IMU, keys the IMU index as text), ``left_out`` (by reason), ``events`` and
``findings`` (counts), ``imus`` (:meth:`estimators.coverage.ImuCoverage.to_dict` each).
Version 1 had neither ``log``, ``start_t_s``, ``samples``, ``left_out``, ``events`` nor ``findings``."""
PACE_MAX_STEP_S = 60.0
"""Longest step of log time between frames that ``--pace recorded`` waits through, s. A frame of
:data:`REPLAY_BATCH_SAMPLES` samples of a 4 Hz telemetry stream spans 25 s; a longer step is a
logging pause or a corrupt time stamp (one a year ahead, or past what a sleep takes), not worth
the wait."""


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
        type=grade_name,
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
    on_batch: Callable[[SampleBatch, int], None] | None = None,
    progress: Callable[[str], None] | None = None,
    on_pace_step: Callable[[float], None] | None = None,
) -> tuple[list[Event], LogReader]:
    """Run a log through ``fleet``; returns every event in order and the reader (with its statistics).

    Each frame is stamped with its last sample time as its arrival (the log's own clock). At full
    speed the reader joins an IMU's frames that come one after the other, up to
    :data:`REPLAY_GROUP_SAMPLES` (:class:`~protocols.logs.LogReader`'s ``join_frames``): those of
    an IMU alone on its vehicle go through as they are, the others are taken frame by frame.
    ``on_batch`` sees every batch so taken and the frames it joins; ``progress`` gets a line every
    :data:`PROGRESS_EVERY_S` seconds of wall time; ``on_pace_step`` each step of log time (s)
    that ``pace_recorded`` does not wait through (module docstring).
    """
    from protocols.logs import LogReader

    join = 1 if pace_recorded else -(-REPLAY_GROUP_SAMPLES // REPLAY_BATCH_SAMPLES)
    reader = LogReader(log, vehicle=vehicle, batch_samples=REPLAY_BATCH_SAMPLES, join_frames=join)
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
    group: list[tuple[SampleBatch, int]] = []
    queued = 0
    for batch, frames in (taken for joined in reader for taken in _taken(fleet, reader, joined)):
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
        # Judged before on_batch, which may admit the frame's IMU (the report's rest thresholds).
        together = not pace_recorded and _alone(fleet, batch)
        if not together:
            for e in _take(fleet, group):
                emit(e)
            group, queued = [], 0
        if on_batch is not None:
            on_batch(batch, frames)
        if not together:
            for e in fleet.process(batch, arrival_s=t_last):
                emit(e)
        else:
            group.append((batch, frames))
            queued += batch.n_samples
            if queued >= REPLAY_GROUP_SAMPLES:
                for e in _take(fleet, group):
                    emit(e)
                group, queued = [], 0
        now = time.monotonic()
        if progress is not None and now >= next_note:
            next_note = now + PROGRESS_EVERY_S
            progress(
                f"{100.0 * reader.fraction_read:3.0f} % of {log.name} read, {samples:,} samples, "
                f"{t_last - data0:.0f} s of log in {now - wall0:.0f} s"
            )
    for e in _take(fleet, group) + fleet.finish():
        emit(e)
    return events, reader


def _taken(
    fleet: FleetProcessor, reader: LogReader, batch: SampleBatch
) -> Iterator[tuple[SampleBatch, int]]:
    """A batch of the reader as the replay takes it, with the frames each part joins: whole when
    its IMU is alone on its vehicle (:func:`_alone`), else frame by frame (each judged when its
    turn comes: the first frame of an IMU admits it)."""
    from service.pipeline.imu_pipeline import split_batch

    frames = reader.frames_of(batch)
    if frames == 1 or _alone(fleet, batch):
        yield batch, frames
        return
    for frame in split_batch(batch, frames):
        yield frame, 1


def _alone(fleet: FleetProcessor, batch: SampleBatch) -> bool:
    """Whether a frame may wait for the next ones (:data:`REPLAY_GROUP_SAMPLES`): its IMU is served
    already and is its vehicle's only one so far.

    A vehicle's second IMU takes every frame one by one as it comes: the cross-IMU checks pair
    the IMUs frame by frame (the second IMU's first frame starts them, the clock offsets are
    bounded per frame), and a disagreement names the scalar checks' state and the run at its frame.
    """
    key = (batch.vehicle, batch.imu)
    return key in fleet.pipelines and sum(v == batch.vehicle for v, _ in fleet.pipelines) == 1


def _take(fleet: FleetProcessor, group: list[tuple[SampleBatch, int]]) -> list[Event]:
    """Frames of IMUs alone on their vehicles (batches with the frames each joins), through the
    fleet together (:meth:`~service.pipeline.FleetProcessor.process_queued`: each IMU's
    consecutive frames as one batch); arriving at the last sample's time (the log's own clock)."""
    if len(group) == 1 and group[0][1] == 1:
        return fleet.process(group[0][0], arrival_s=float(group[0][0].t_s[-1]))
    if not group:
        return []
    batches = [b for b, _ in group]
    return fleet.process_queued(
        batches, arrival_s=float(batches[-1].t_s[-1]), frames=[f for _, f in group]
    )


def human(event: Event, start_t_s: float) -> str:
    """An event as a person reads it, its time from the log's start (``start_t_s``, s of its clock)."""
    return f"t={event.t_s - start_t_s:10.3f} s  {event.severity.name:<8s} {event.text}"


UNIX_TIME_FROM_S, UNIX_TIME_TO_S = 946_684_800.0, 4_102_444_800.0
"""Log times in [2000-01-01, 2100-01-01) are taken for Unix times (and dated when said)."""


def log_start(t_s: float | None, clock: str = "the log's clock") -> str:
    """A log's first sample time as said once: seconds of its clock, and the UTC date when the
    clock is a Unix time (a telemetry log's; a DataFlash log counts from the autopilot's boot)."""
    import datetime as dt

    if t_s is None:
        return "no sample"
    said = f"{t_s:.3f} s of {clock}"
    if UNIX_TIME_FROM_S <= t_s < UNIX_TIME_TO_S:
        utc = dt.datetime.fromtimestamp(t_s, dt.UTC).isoformat(timespec="milliseconds")
        said += f", {utc.replace('+00:00', ' UTC')}"
    return said


@dataclasses.dataclass(frozen=True)
class ReplayResult:
    """What a replay found (:func:`replay_log`; ``ins_health.replay``).

    ``events``: every event in order; ``coverage``: each IMU's coverage; ``verdict`` and
    ``exit_status`` as the command's (module docstring); ``untested``: what applies and was not
    tested, why; ``start_t_s``: the log's first sample time on its clock (None: no sample; event
    times are on that clock, an IMU's on another clock on its own); ``samples``: samples read per IMU; ``left_out``: what the reader left out, by
    reason (``skipped_bytes`` among them); ``notes``: what the command says on stderr besides
    progress (passports, the reader's notes, counters, coverage, the verdict), in order.
    """

    log: Path
    format: str
    vehicle: str
    events: tuple[Event, ...]
    coverage: tuple[ImuCoverage, ...]
    verdict: Verdict
    exit_status: int
    untested: tuple[str, ...]
    start_t_s: float | None
    samples: dict[int, int]
    left_out: dict[str, int]
    notes: tuple[str, ...]

    @property
    def findings(self) -> tuple[Event, ...]:
        """The events that name a sensor fault (F0…F9, gross, stale; not a recovery)."""
        from protocols.events import StreamCause
        from service.pipeline.coverage import FAULT_PREDICATES

        return tuple(
            e
            for e in self.events
            if e.predicate.value in FAULT_PREDICATES and e.cause != StreamCause.RECOVERED
        )

    def summary(self) -> dict[str, Any]:
        """The last line of ``--json`` (:data:`COVERAGE_VERSION`)."""
        return _coverage_map(self)


def keep_batch_temporaries_on_heap() -> bool:
    """Where the C library is glibc, set its malloc's mapping and trim thresholds for a replay's
    batches (:data:`HEAP_MMAP_THRESHOLD_BYTES`, module docstring); True when set. Other C libraries
    (musl, macOS, Windows) are left as they are: this is glibc's policy and glibc's call. So are
    thresholds the user set for the process (``MALLOC_*_`` or ``glibc.malloc.*`` in
    ``GLIBC_TUNABLES``, :data:`USER_MALLOC_SETTINGS`): a device short of memory may ask for eager
    trimming, and gets it."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(name in os.environ for name in USER_MALLOC_SETTINGS) or "glibc.malloc." in tunables:
        return False
    try:
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return False
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (ValueError, OSError, AttributeError):  # no such confstr name, library or symbol
        return False
    return bool(
        mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD_BYTES)
        and mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_THRESHOLD_BYTES)
    )


def freeze_imports(*, report: bool) -> None:
    """Load what a replay loads on first use (the pipeline's λ0, the report's matplotlib with
    ``report``) and keep every object made so far out of the cyclic collector's passes (``gc.freeze``).

    What the imports make lives as long as the process, and a full pass walks all of it: in a
    five-minute replay one during the imports (17-24 ms of CPU), one at the report's first figure
    (48 ms) and the interpreter's last at exit (45 ms), and 260 young passes (30 ms) most of them
    during the imports. With the collector off while they run and their objects frozen, no full
    pass runs before the exit's, which walks what the replay made (5 ms), and 70 young ones (10 ms).
    The daemon freezes its imports too (:func:`service.commands.run.freeze_imports`). The command
    calls it as its own process only (``service.cli.main(own_process=True)``: the console script);
    called within a process (the tests, a library user) it leaves the collector as it is, as
    :func:`replay_log` does.
    """
    import contextlib
    import gc
    import importlib

    from service.pipeline import PIPELINE_IMPORTS

    was_enabled = gc.isenabled()  # a process that runs without the collector keeps it off
    gc.disable()  # the collector's passes over the imports' objects would find nothing to free
    try:
        for name in PIPELINE_IMPORTS + (("service.log_report",) if report else ()):
            # One that cannot load (no matplotlib for the report) fails where the replay uses it,
            # after the events and the verdict, as without this preload.
            with contextlib.suppress(ImportError):
                importlib.import_module(name)
    finally:
        gc.freeze()
        if was_enabled:
            gc.enable()


def run(args: argparse.Namespace) -> int:
    import json

    from protocols.events import event_to_json

    if args.own_process:
        keep_batch_temporaries_on_heap()
        freeze_imports(report=args.report is not None)
    starts: dict[int, float] = {}
    printer = (
        (lambda e: print(event_to_json(e), flush=True))
        if args.json
        else (lambda e: print(human(e, starts.get(e.imu, 0.0)), flush=True))
    )
    result = replay_log(
        args,
        on_event=printer,
        on_start=starts.__setitem__,
        say=lambda line: print(f"ins-health replay: {line}", file=sys.stderr, flush=True),
    )
    if args.json:
        print(json.dumps(result.summary()), flush=True)
    return result.exit_status


def replay_log(
    args: argparse.Namespace,
    *,
    on_event: Callable[[Event], None] | None = None,
    on_start: Callable[[int, float], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> ReplayResult:
    """The replay of ``args`` (this command's options): events to ``on_event`` as they come, each
    IMU's start (the log's first sample time, or the IMU's own on another clock) to ``on_start``
    before its events, progress and notes to ``say``; the report written when ``args.report`` is set."""
    from estimators.coverage import Verdict, untested_lines, verdict
    from estimators.log_health import HealthConfig, ImuHealthAccumulator, pair_differences
    from estimators.stream_validity import CLOCK_BASE_MIN_S
    from service.pipeline import FleetProcessor, detector_config
    from service.pipeline.coverage import imu_coverage
    from service.pipeline.imu_pipeline import split_batch
    from service.pipeline.options import pipeline_options
    from service.pipeline.thrust_axis import ThrustAxisReplay

    notes: list[str] = []

    def note(line: str) -> None:
        notes.append(line)
        if say is not None:
            say(line)

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
    norm_blocks: list[NormBlock] = []

    def norm_block(vehicle: str, _pair: tuple[int, int], block: NormBlock) -> None:
        if args.report is not None and vehicle == args.vehicle:
            norm_blocks.append(block)

    fleet = FleetProcessor(
        on_norm_block=norm_block,
        passports=lookup,
        nominal=nominal,
        options=options,
        # A log's IMUs are all wanted (a ULog numbers its instances up to 8, protocols.ulog).
        max_imus_per_vehicle=max(config.pipeline.max_imus_per_vehicle, REPLAY_MAX_IMUS),
        on_passport_error=lambda v, i, msg: errors.append(f"{v} IMU{i}: {msg}"),
        on_pipeline_error=pipeline_error,
    )
    health: dict[int, ImuHealthAccumulator] = {}
    # IMU -> why its figures cannot be drawn (a finite sample whose square overflows): the replay
    # goes on to its verdict, the report is refused after it.
    unreportable: dict[int, str] = {}
    health_config = HealthConfig()
    start_t_s: list[float] = []
    thrust = ThrustAxisReplay(args.log, args.vehicle, on_event)

    starts: dict[int, float] = {}

    def observe(batch: SampleBatch, frames: int) -> None:
        # The thrust-axis check takes the GNSS epochs up to each frame's end: frame by frame.
        # (An IMU's first batch is one frame: the log's GNSS is read by then.)
        for frame in [batch] if frames == 1 or thrust.track is None else split_batch(batch, frames):
            thrust.batch(frame)
        if batch.imu not in starts:
            first = float(batch.t_s[0])
            if not start_t_s:
                start_t_s.append(first)
                note(f"{args.log.name} starts at {log_start(first)}: times count from there")
            elif abs(first - start_t_s[0]) > CLOCK_BASE_MIN_S:
                # One IMU on Unix time, one since boot: each time from the log's start would be
                # 1.7e9 s off.
                note(
                    f"IMU{batch.imu} stamps another clock (or started late): it starts at "
                    f"{log_start(first, 'its clock')}: its times count from there"
                )
            else:
                first = start_t_s[0]
            starts[batch.imu] = first
            if on_start is not None:
                on_start(batch.imu, first)
        if args.report is None or batch.imu in unreportable:
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
        try:
            acc.update(batch.t_s, batch.accel_mps2, batch.gyro_rps, batch.temp_c)
        except ValueError as exc:
            unreportable[batch.imu] = str(exc)

    events, reader = replay_events(
        args.log,
        fleet=fleet,
        vehicle=args.vehicle,
        pace_recorded=args.pace == "recorded",
        on_event=on_event,
        on_batch=observe,
        progress=say,
        on_pace_step=pace_steps.append,
    )
    events = thrust.merged(events)
    errors += [
        f"{v} IMU{i}: {pipe.nominal_too_slow}"
        for (v, i), pipe in sorted(fleet.pipelines.items())
        if pipe.nominal_too_slow
    ]
    for line in errors:
        note(f"{line}; stream checks only")
    for (vehicle, imu, _), (frames, message) in sorted(failed.items()):
        note(
            f"{vehicle} IMU{imu}: the pipeline failed on {frames} frame(s) ({message}); "
            "their samples were not tested"
        )
    if passport_info["kind"] == "nominal":
        note(
            f"no passport: nominal passport of class {passport_info['class']} ({passport_info['source']})"
        )
    if pace_steps:
        longest = max(pace_steps, key=abs)
        note(
            f"--pace recorded: {len(pace_steps)} steps of log time over {PACE_MAX_STEP_S:g} s "
            f"not waited for (longest {longest:+.6g} s); the pacing resumed after each"
        )
    for key, why in sorted(reader.stats.skipped.items()):
        note(f"not replayed: {key} {why}")
    if cut := reader.stats.cut():
        note(f"{args.log.name} is {cut}: read up to there")
    for said_by_reader in (reader.stats.logger(), reader.stats.clock()):
        if said_by_reader:
            note(f"{args.log.name}: {said_by_reader}")
    samples = ", ".join(f"IMU{i} {n}" for i, n in sorted(reader.stats.samples.items())) or "none"
    note(
        f"{args.log.name} ({reader.format.value}): samples {samples}; left out {reader.stats.left_out()}; {len(events)} events"
    )
    for vehicle in fleet.vehicles():
        counters = fleet.status(vehicle, service="replay", now_unix_s=0.0).counters
        note("counters " + ", ".join(f"{k} {n}" for k, n in sorted(counters.items())))
    pipes = [p for (v, _), p in sorted(fleet.pipelines.items()) if v == args.vehicle]
    coverages = [
        thrust.covered(
            imu_coverage(
                p,
                imus_on_vehicle=len(pipes),
                cross_not_running=fleet.cross_not_running(p.vehicle, p.imu),
                vehicle_checks=fleet.norm_coverage(args.vehicle, p.imu),
            )
        )
        for p in pipes
    ]
    for line in thrust.notes:
        note(line)
    untested = untested_lines(coverages) + [
        f"IMU{imu}: the pipeline failed on {frames} frame(s)"
        for (_, imu, _), (frames, _) in sorted(failed.items())
    ]
    result = ReplayResult(
        log=args.log,
        format=reader.format.value,
        vehicle=args.vehicle,
        events=tuple(events),
        coverage=tuple(coverages),
        verdict=Verdict.NO_FAULT,
        exit_status=EXIT_OF_VERDICT[Verdict.NO_FAULT.value],
        untested=tuple(untested),
        start_t_s=start_t_s[0] if start_t_s else None,
        samples=dict(sorted(reader.stats.samples.items())),
        left_out=_left_out(reader),
        notes=(),
    )
    said = verdict(bool(result.findings), coverages)
    if failed and said is Verdict.NO_FAULT:
        said = Verdict.NO_FINDING
    status = EXIT_OF_VERDICT[said.value]
    result = dataclasses.replace(result, verdict=said, exit_status=status)
    for cov in coverages:
        for line in cov.lines():
            note(f"coverage {line}")
    note(_verdict_line(said, len(result.findings), untested))
    if args.report is not None:
        from protocols.firmware_health import read_firmware_health
        from service.log_report import build_report, norm_summary, write_report

        firmware = read_firmware_health(args.log, reader.format, reader.stats.held)
        if firmware.unread:
            note(f"{args.log.name}: the firmware's own health data not read ({firmware.unread})")
        healths = {}
        for imu, acc in sorted(health.items()):
            try:
                healths[imu] = acc.result(options.gravity_mps2)
            except ValueError as exc:
                unreportable.setdefault(imu, str(exc))
        if unreportable:
            raise ValueError(
                "report not written: "
                + "; ".join(
                    f"IMU{imu}'s figures: {why}" for imu, why in sorted(unreportable.items())
                )
            )
        pairs = pair_differences({i: h.blocks for i, h in healths.items()}, health_config.block_s)
        report = build_report(
            log_name=args.log.name,
            log_format=reader.format.value,
            stats=reader.stats,
            system=reader.system,
            passport={**passport_info, "not_applied": errors},
            gravity_mps2=options.gravity_mps2,
            config=health_config,
            healths=healths,
            f0={imu: _f0_summary(fleet, args.vehicle, imu) for imu in healths},
            pairs=pairs,
            events=events,
            coverage=_coverage_map(result),
            start_t_s=result.start_t_s,
            firmware=firmware,
            cross_imu_norm=norm_summary(fleet.norms.get(args.vehicle)),
        )
        md = write_report(
            report,
            healths,
            pairs,
            args.report,
            firmware,
            thrust=thrust.statistics(),
            norm_blocks=norm_blocks,
        )
        note(f"report {md}")
    return dataclasses.replace(result, notes=tuple(notes))


def _left_out(reader: LogReader) -> dict[str, int]:
    """What the reader left out, by reason, the bytes it skipped among them."""
    out = dict(sorted(reader.stats.dropped.items()))
    if reader.stats.skipped_bytes:
        out["skipped_bytes"] = reader.stats.skipped_bytes
    return out


def _verdict_line(said: Verdict, n_found: int, untested: list[str]) -> str:
    """The verdict as a person reads it: the findings, or what was not tested (a warning)."""
    from estimators.coverage import Verdict

    if said is Verdict.FAULT:
        return f"ERROR    verdict: fault ({n_found} finding event(s) above)"
    if said is Verdict.NO_FINDING:
        return "WARNING  verdict: no finding within coverage; not tested: " + "; ".join(untested)
    return "INFO     verdict: no fault (every check that applies ran)"


def _coverage_map(result: ReplayResult) -> dict[str, Any]:
    """The summary line of ``--json`` and the report's coverage (:data:`COVERAGE_VERSION`)."""
    return {
        "type": COVERAGE_TYPE,
        "v": COVERAGE_VERSION,
        "vehicle": result.vehicle,
        "log": result.log.name,
        "verdict": result.verdict.value,
        "exit_status": result.exit_status,
        "untested": list(result.untested),
        "start_t_s": result.start_t_s,
        "samples": {str(imu): n for imu, n in result.samples.items()},
        "left_out": result.left_out,
        "events": len(result.events),
        "findings": len(result.findings),
        "imus": [c.to_dict() for c in result.coverage],
    }


def _rate(batch: SampleBatch) -> float:
    """The rate an IMU's first frame was sampled at (the median interval of its first
    :data:`~estimators.log_health.RUN_START_SAMPLES`, as the report's filters take it, whatever
    the frame's size), Hz; 1 Hz for a one-sample frame."""
    import numpy as np

    from estimators.log_health import RUN_START_SAMPLES

    head = batch.t_s[:RUN_START_SAMPLES]
    return float(1.0 / np.median(np.diff(head))) if head.size > 1 else 1.0


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
