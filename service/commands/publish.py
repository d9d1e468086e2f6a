"""``ins-health publish SESSION|LOG --vehicle V [--imu N] [--pace recorded|max] [--router ENDPOINT]``: stream a recording as IMU frames, to bench-test a deployed daemon.

SESSION is a session file (a CSV file, or an Xsens raw-count pair or its
folder: :mod:`protocols.session_file`), published as IMU ``N`` (default 0) of
vehicle ``V``. LOG is a MAVLink ``.tlog``, a DataFlash ``.bin``/``.log`` or a
PX4 ULog ``.ulg`` (:class:`protocols.logs.LogReader`; a file is taken for a
log when its content is one), each of its IMUs published as itself, or only
IMU ``N`` with ``--imu``. Frames of ``--batch`` samples (:mod:`protocols.frames`) go through
the router to the daemon's frame subscription; publishing starts once the
daemon subscribes to each IMU's frames (waiting up to ``--wait-s``). Every frame
carries one run id drawn at the start (:mod:`protocols.frames` version 2): publishing
again is a new run for the daemon, whose positions and diagnosis start afresh.

``--pace recorded`` (default) publishes each frame when its last sample's time
has come, as the vehicle did; ``--pace max`` as fast as the link takes them.
Unlike a vehicle's frames, which a congested link may shed, these are sent
reliably (Zenoh ``CongestionControl.BLOCK``): a bench test must know that the
daemon was offered every sample. Progress goes to stderr every few seconds; a
summary line (frames, samples, seconds of data, seconds taken, and the samples
left out: a session's unusable ones, which the daemon would refuse with their
whole frame, or what the log reader left out) ends the output. Before it ends,
publish waits for the router to confirm that it holds the last frames (:meth:`protocols.zenoh_adapter.FramePublisher.drain`),
then asks the daemon for the vehicle's status until it has taken every frame
sent (``imu<n>.frames.received`` and ``…queued``, waiting up to ``--wait-s``)
and says the frames it dropped, its queue of the IMU full
(``imu<n>.frames.dropped_overload``, counted from publish's start). Exit status
0 when the daemon took every frame; 1 when it dropped any (named on stderr) or
the router did not confirm the last ones; 3 when the daemon did not account for
them within ``--wait-s`` (a daemon older than this command does not answer);
2 for an unusable file or option, an unreachable router or no subscriber; 130
when interrupted (Ctrl-C, SIGTERM).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli import UsageError
from service.router_args import add_router_arguments, open_router_session
from service.session_args import add_unit_arguments, load_units_checked

if TYPE_CHECKING:
    from protocols.frames import SampleBatch
    from protocols.zenoh_adapter import FramePublisher, Session

DEFAULT_BATCH_SAMPLES = 100
PROGRESS_PERIOD_S = 5.0
STATUS_POLL_S = 0.2
"""How often the daemon's status is asked for at the end (it publishes one every status period, 1 s)."""
EXIT_DROPPED = 1
EXIT_UNACCOUNTED = 3


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "publish",
        help="stream a session file or a flight log as IMU frames to a deployed daemon (bench test)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "recording",
        type=Path,
        metavar="SESSION|LOG",
        help="a session file (CSV, Xsens pair folder) or a .tlog/.bin/.log/.ulg flight log",
    )
    p.add_argument("--vehicle", required=True, metavar="V", help="vehicle id of the frames")
    p.add_argument(
        "--imu",
        type=int,
        metavar="N",
        help="IMU index of a session's frames (default 0); of a log, the only IMU to publish (default all)",
    )
    p.add_argument(
        "--pace",
        choices=("recorded", "max"),
        default="recorded",
        help="at the recorded rate (default) or as fast as possible",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=DEFAULT_BATCH_SAMPLES,
        metavar="SAMPLES",
        help=f"samples per frame (default {DEFAULT_BATCH_SAMPLES})",
    )
    p.add_argument(
        "--wait-s",
        type=float,
        default=10.0,
        metavar="S",
        help="how long to wait for the daemon to subscribe to an IMU's frames, s (default 10)",
    )
    add_unit_arguments(p)
    add_router_arguments(p)
    p.set_defaults(func=run)


def _is_log(path: Path) -> bool:
    from protocols.logs import detect_format

    if not path.is_file():
        return False
    try:
        detect_format(path)
    except ValueError:
        return False
    return True


def _log_batches(args: argparse.Namespace) -> tuple[Iterator[SampleBatch], Callable[[], str]]:
    """The log's frames, and what reading it left out (known once they are all read)."""
    from protocols.logs import LogReader

    reader = LogReader(args.recording, vehicle=args.vehicle, batch_samples=args.batch)

    def left_out() -> str:
        stats = reader.stats
        return "; ".join(
            p for p in (stats.left_out(), stats.cut(), stats.logger(), stats.clock()) if p
        )

    return (b for b in reader if args.imu is None or b.imu == args.imu), left_out


def _session_batches(args: argparse.Namespace) -> tuple[Iterator[SampleBatch], Callable[[], str]]:
    """The session's usable samples as frames, and what validation left out.

    A frame holding one unusable sample (NaN, a duplicate time stamp) is refused whole by the
    daemon's decoder: those samples are left out here and said, not sent to cost their frame.
    """
    from estimators.session import SessionError, validate_session
    from protocols.frames import split_session

    session = load_units_checked(
        str(args.recording), None, None, args, faulty_accel_ok=True
    ).session
    try:
        session, rejected = validate_session(session)
    except SessionError as exc:
        raise UsageError(f"{args.recording}: {exc}") from None
    imu = 0 if args.imu is None else args.imu
    left_out = ", ".join(f"{k} {n}" for k, n in sorted(rejected.counts.items())) or "none"
    batches = split_session(session, vehicle=args.vehicle, imu=imu, batch_samples=args.batch)
    return batches, lambda: left_out


def _publisher(session: Session, batch: SampleBatch, wait_s: float) -> FramePublisher:
    """A lossless publisher of ``batch``'s IMU, once the daemon subscribes to its frames."""
    from protocols.zenoh_adapter import CongestionControl, FramePublisher

    pub = FramePublisher(
        session, batch.vehicle, batch.imu, congestion_control=CongestionControl.BLOCK
    )
    deadline = time.monotonic() + wait_s
    while not pub.matched:
        if time.monotonic() > deadline:
            pub.close()
            raise UsageError(
                f"nothing subscribes to the frames of {batch.vehicle} IMU{batch.imu} after {wait_s:g} s: "
                "is the daemon running and is this vehicle in its [zenoh] frames_key?"
            )
        time.sleep(0.05)
    return pub


def _unit_frames(session: Session, vehicle: str) -> dict[str, int] | None:
    """The daemon's ``imu<n>.frames.*`` counters of ``vehicle`` (summed over the instances that
    answer); None when none answers."""
    from protocols.zenoh_adapter import query_status

    statuses = query_status(session, vehicle, timeout_s=STATUS_POLL_S * 5)
    if not statuses:
        return None
    out: dict[str, int] = {}
    for status in statuses:
        for name, n in status.counters.items():
            if ".frames." in name and name.startswith("imu"):
                out[name] = out.get(name, 0) + n
    return out


def _daemon_account(
    session: Session, vehicle: str, sent: dict[int, int], before: dict[str, int], wait_s: float
) -> dict[int, int] | None:
    """IMU → frames the daemon dropped of those ``sent`` (IMU → frames), once its status shows them
    all received and none queued; None when it does not within ``wait_s``."""
    deadline = time.monotonic() + wait_s
    while True:
        now = _unit_frames(session, vehicle)
        if now is not None:

            def gained(imu: int, what: str, now: dict[str, int] = now) -> int:
                name = f"imu{imu}.frames.{what}"
                return now.get(name, 0) - before.get(name, 0)

            if all(
                gained(imu, "received") >= n and now.get(f"imu{imu}.frames.queued", 0) == 0
                for imu, n in sent.items()
            ):
                return {imu: gained(imu, "dropped_overload") for imu in sent}
        if time.monotonic() > deadline:
            return None
        time.sleep(STATUS_POLL_S)


class _RecordedPace:
    """Holds each frame back until its last sample's time has come, counted from the first frame."""

    def __init__(self) -> None:
        self._origin: tuple[float, float] | None = None

    def wait(self, batch: SampleBatch) -> None:
        if self._origin is None:
            self._origin = (time.monotonic(), float(batch.t_s[0]))
        wall0, data0 = self._origin
        time.sleep(max(0.0, (float(batch.t_s[-1]) - data0) - (time.monotonic() - wall0)))


class _Progress:
    """Frames, samples and data time published so far; a line on stderr every :data:`PROGRESS_PERIOD_S`."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.frames = self.samples = 0
        self.by_imu: dict[int, int] = {}
        self.first_t_s: float | None = None
        self.last_t_s = 0.0
        self.start = self._shown = time.monotonic()

    def add(self, batch: SampleBatch) -> None:
        self.frames += 1
        self.by_imu[batch.imu] = self.by_imu.get(batch.imu, 0) + 1
        self.samples += batch.n_samples
        if self.first_t_s is None:
            self.first_t_s = float(batch.t_s[0])
        self.last_t_s = float(batch.t_s[-1])
        if time.monotonic() - self._shown >= PROGRESS_PERIOD_S:
            self._shown = time.monotonic()
            print(f"ins-health publish: {self.summary()}", file=sys.stderr, flush=True)

    def summary(self) -> str:
        data_s = 0.0 if self.first_t_s is None else self.last_t_s - self.first_t_s
        return (
            f"{self.name}: {self.frames} frames, {self.samples} samples, "
            f"{data_s:.1f} s of data in {time.monotonic() - self.start:.1f} s"
        )


def run(args: argparse.Namespace) -> int:
    import secrets  # here, not with the parser every command builds: it brings hmac and hashlib
    import signal

    if args.batch < 1:
        raise UsageError(f"--batch must be at least 1, got {args.batch}")
    if not args.wait_s >= 0:
        raise UsageError(f"--wait-s must be >= 0, got {args.wait_s!r}")
    if not args.recording.exists():
        raise UsageError(f"{args.recording}: no such file or folder")
    batches, left_out = _log_batches(args) if _is_log(args.recording) else _session_batches(args)
    progress = _Progress(args.recording.name)

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    publishers: dict[int, FramePublisher] = {}
    dropped: dict[int, int] | None = None
    run_id = secrets.randbits(63)
    try:
        with open_router_session(args) as session:
            before = _unit_frames(session, args.vehicle) or {}
            try:
                pace = _RecordedPace() if args.pace == "recorded" else None
                for batch in batches:
                    if pace is not None:
                        pace.wait(batch)
                    if batch.imu not in publishers:
                        publishers[batch.imu] = _publisher(session, batch, args.wait_s)
                    # A log whose clock started again inside (a reboot) numbers its runs from 0:
                    # each is a new run for the daemon too.
                    run = run_id + (batch.run or 0)
                    publishers[batch.imu].publish(dataclasses.replace(batch, run=run))
                    progress.add(batch)
            finally:
                for pub in publishers.values():
                    pub.close()
            dropped = _daemon_account(session, args.vehicle, progress.by_imu, before, args.wait_s)
    except KeyboardInterrupt:
        print(f"ins-health publish: interrupted: {progress.summary()}", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(f"{progress.summary()}; left out: {left_out()}")
    unconfirmed = sorted(imu for imu, pub in publishers.items() if not pub.confirmed)
    if unconfirmed:
        print(
            f"ins-health publish: the router did not confirm the last frames of IMU "
            f"{', '.join(map(str, unconfirmed))} (the link to it is lost): some may not have reached it",
            file=sys.stderr,
        )
        return 1
    if dropped is None:
        print(
            f"ins-health publish: the daemon did not account for the frames of {args.vehicle} within "
            f"--wait-s {args.wait_s:g} s (its status shows them neither received nor dropped): "
            "whether it took them all is unknown",
            file=sys.stderr,
        )
        return EXIT_UNACCOUNTED
    if lost := {imu: n for imu, n in dropped.items() if n}:
        print(
            "ins-health publish: the daemon dropped "
            + ", ".join(
                f"{n} of {progress.by_imu[imu]} frames of {args.vehicle} IMU{imu}"
                for imu, n in sorted(lost.items())
            )
            + " (its queue of the IMU full: the service was behind; "
            "imu<n>.frames.dropped_overload on the status topic)",
            file=sys.stderr,
        )
        return EXIT_DROPPED
    print(f"ins-health publish: the daemon took all {progress.frames} frames", file=sys.stderr)
    return 0
