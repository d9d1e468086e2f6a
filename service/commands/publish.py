"""``ins-health publish SESSION|LOG --vehicle V [--imu N] [--pace recorded|max] [--router ENDPOINT]``: stream a recording as IMU frames, to bench-test a deployed daemon.

SESSION is a session file (a CSV file, or an Xsens raw-count pair or its
folder: :mod:`protocols.session_file`), published as IMU ``N`` (default 0) of
vehicle ``V``. LOG is a MAVLink ``.tlog``, a DataFlash ``.bin``/``.log`` or a
PX4 ULog ``.ulg`` (:class:`protocols.logs.LogReader`; a file is taken for a
log when its content is one), each of its IMUs published as itself, or only
IMU ``N`` with ``--imu``. Frames of ``--batch`` samples (:mod:`protocols.frames`) go through
the router to the daemon's frame subscription; publishing starts once the
daemon subscribes to each IMU's frames (waiting up to ``--wait-s``).

``--pace recorded`` (default) publishes each frame when its last sample's time
has come, as the vehicle did; ``--pace max`` as fast as the link takes them.
Unlike a vehicle's frames, which a congested link may shed, these are sent
reliably (Zenoh ``CongestionControl.BLOCK``): a bench test must know that the
daemon was offered every sample. Progress goes to stderr every few seconds; a
summary line (frames, samples, seconds of data, seconds taken, and the samples
left out: a session's unusable ones, which the daemon would refuse with their
whole frame, or what the log reader left out) ends the output. Before it ends,
publish waits for the router to confirm that it holds the last frames (:meth:`protocols.zenoh_adapter.FramePublisher.drain`). Exit status 0;
1 when the router did not confirm them; 2 for an unusable file or option, an
unreachable router or no subscriber; 130 when interrupted (Ctrl-C, SIGTERM).
"""

from __future__ import annotations

import argparse
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
        self.first_t_s: float | None = None
        self.last_t_s = 0.0
        self.start = self._shown = time.monotonic()

    def add(self, batch: SampleBatch) -> None:
        self.frames += 1
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
    try:
        with open_router_session(args) as session:
            try:
                pace = _RecordedPace() if args.pace == "recorded" else None
                for batch in batches:
                    if pace is not None:
                        pace.wait(batch)
                    if batch.imu not in publishers:
                        publishers[batch.imu] = _publisher(session, batch, args.wait_s)
                    publishers[batch.imu].publish(batch)
                    progress.add(batch)
            finally:
                for pub in publishers.values():
                    pub.close()
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
    return 0
