"""Command-line arguments shared by the commands that read a session file."""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from estimators.conventions import normal_gravity_mps2
from estimators.session import ImuSession
from estimators.static_detector import StaticDetection, StaticDetectorConfig
from protocols.session_file import (
    UNIT_KEYS,
    AccelUnit,
    GyroUnit,
    LoadedSession,
    SessionFileError,
    SessionUnits,
    TimeUnit,
    UnitsError,
    check_units,
    load_session,
    parse_scale,
)
from service.cli import UsageError

DEFAULT_LATITUDE_DEG = 45.0


@dataclass(frozen=True)
class SessionInput:
    """A session read from the command line and the settings that go with it.

    Attributes
    ----------
    session : the samples, SI.
    gravity_mps2, gravity_source : local gravity, m/s², and where it came from.
    accel_limit_mps2, gyro_limit_rps : full-scale ranges (saturation check), or None.
    detector : static-detector thresholds (from the stated noise, else from the session's own).
    """

    session: ImuSession
    gravity_mps2: float
    gravity_source: str
    accel_limit_mps2: float | None = None
    gyro_limit_rps: float | None = None
    detector: StaticDetectorConfig = StaticDetectorConfig()


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """SESSION (CSV file, Xsens raw-count pair or its folder) and the local gravity."""
    parser.add_argument(
        "session",
        metavar="SESSION",
        help="CSV session file (t,ax,ay,az,gx,gy,gz[,temp]), or the accelerometer file / folder of an Xsens raw-count pair",
    )
    parser.add_argument(
        "--gyro-file",
        metavar="PATH",
        help="gyro file of an Xsens raw-count pair (SESSION is then its accelerometer file)",
    )
    parser.add_argument(
        "--sidecar",
        metavar="TOML",
        help="nominal scale (SI per count) and offset (counts) of a raw-count pair (default: the packaged Xsens MTi "
        "sidecar), or what a CSV session does not say: accel_scale, gyro_scale, the units, fs (protocols/session_file.py)",
    )
    add_unit_arguments(parser)
    g = parser.add_argument_group(
        "local gravity (first that applies: --gravity, --latitude/--height, the file's own value, WGS-84 at 45°)"
    )
    g.add_argument("--gravity", type=float, metavar="MPS2", help="local gravity magnitude, m/s²")
    g.add_argument(
        "--latitude",
        type=float,
        metavar="DEG",
        help="geodetic latitude, degrees (WGS-84 normal gravity)",
    )
    g.add_argument(
        "--height",
        type=float,
        default=0.0,
        metavar="M",
        help="height above the ellipsoid, metres (default 0)",
    )
    r = parser.add_argument_group(
        "full-scale ranges (a sample with any axis at or beyond its range is saturated: rejected and counted)"
    )
    r.add_argument(
        "--accel-range",
        type=float,
        metavar="MPS2",
        help="accelerometer full scale, m/s² (default: not checked)",
    )
    r.add_argument(
        "--gyro-range",
        type=float,
        metavar="RPS",
        help="gyro full scale, rad/s (default: not checked)",
    )
    n = parser.add_argument_group(
        "static detection (default: thresholds from the session's own noise, estimators/static_detector.py; "
        "a stated noise overrides its triad's)"
    )
    n.add_argument(
        "--accel-noise",
        type=float,
        metavar="MPS2",
        help="per-sample white noise of each accelerometer, m/s²: threshold at 3× its window spread",
    )
    n.add_argument(
        "--gyro-noise",
        type=float,
        metavar="RPS",
        help="per-sample white noise of each gyro, rad/s (navigation-grade gyros need it): threshold at 3× its window spread",
    )


def add_unit_arguments(parser: argparse.ArgumentParser) -> None:
    """--accel-unit, --gyro-unit, --time-unit: the units of a CSV session's columns."""
    u = parser.add_argument_group(
        "units of a CSV session's columns (default: the file's '# accel_unit = g' style comments, else SI); "
        "values implausible in their units are refused with the unit they look like"
    )
    for name, kind, what in (
        ("accel", AccelUnit, "specific force"),
        ("gyro", GyroUnit, "angular rate"),
        ("time", TimeUnit, "time stamps"),
    ):
        u.add_argument(
            f"--{name}-unit",
            choices=[k.value for k in kind],
            metavar="UNIT",
            help=f"unit of the {what} columns ({', '.join(k.value for k in kind)})",
        )
    for name, example in (
        ("accel", "1/16384 with --accel-unit g"),
        ("gyro", "1/131 with --gyro-unit deg/s"),
    ):
        u.add_argument(
            f"--{name}-scale",
            type=_scale,
            metavar="SIZE",
            help=f"the columns hold raw counts of this size in the {name} unit, a number or a "
            f"fraction (MPU-6050 ±2 g / ±250 °/s: {example}); whole numbers implausible as SI "
            "without a scale are refused",
        )


def _scale(text: str) -> float:
    try:
        return parse_scale(text)
    except SessionFileError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def load_units_checked(
    path: str,
    gyro_file: str | None,
    sidecar: str | None,
    args: argparse.Namespace,
    *,
    faulty_accel_ok: bool = False,
) -> LoadedSession:
    """The session in SI, refused with one line when its values are implausible in their units;
    ``faulty_accel_ok``: a verdict's, whose accelerometer no unit fits is tested as read
    (:func:`protocols.session_file.check_units`, said on stderr)."""
    declared = SessionUnits(
        args.accel_unit,
        args.gyro_unit,
        args.time_unit,
        args.accel_scale,
        args.gyro_scale,
    )
    loaded = load_session(path, gyro_file, sidecar=sidecar, units=declared)
    for said in loaded.notes:
        print(f"ins-health: {path}: {said}", file=sys.stderr)
    if "format" in loaded.metadata:
        u = loaded.units
        print(
            f"ins-health: {path} read as {loaded.metadata['format']} "
            f"(time {u.time}, accelerometer {u.accel}, gyro {u.gyro})",
            file=sys.stderr,
        )
    try:
        note = check_units(
            loaded.session,
            loaded.units,
            time_declared=declared.time is not None or UNIT_KEYS["time"] in loaded.metadata,
            faulty_accel_ok=faulty_accel_ok,
        )
    except UnitsError as exc:
        if exc.kind == "time" or (gyro_file is None and not Path(path).is_dir()):
            raise
        # Units cannot be declared for a raw-count pair: the check's advice (--accel-unit ...) would
        # be refused. What goes wrong with a pair is the files or the sidecar.
        raise UnitsError(
            f"{str(exc).split(' (')[0]}: this raw-count pair is converted by its sidecar, so the "
            "accelerometer and gyro files may be swapped (the accelerometer's first, the gyro's with "
            "--gyro-file) or the sidecar's scale factors may not be this unit's",
            exc.kind,
        ) from None
    if note is not None:
        print(f"ins-health: {path}: {note}", file=sys.stderr)
    return loaded


def load_session_input(args: argparse.Namespace, *, faulty_accel_ok: bool = False) -> SessionInput:
    """Read the session and settle the local gravity (the rule in the argument group's title);
    ``faulty_accel_ok`` as :func:`load_units_checked`'s."""
    loaded = load_units_checked(
        args.session, args.gyro_file, args.sidecar, args, faulty_accel_ok=faulty_accel_ok
    )
    if args.gravity is not None:
        gravity, source = args.gravity, "--gravity"
    elif args.latitude is not None:
        gravity, source = (
            normal_gravity_mps2(args.latitude, args.height),
            f"WGS-84 at {args.latitude}° {args.height} m",
        )
    elif loaded.gravity_mps2 is not None:
        gravity, source = loaded.gravity_mps2, "session file"
    else:
        gravity, source = (
            normal_gravity_mps2(DEFAULT_LATITUDE_DEG, 0.0),
            f"WGS-84 at {DEFAULT_LATITUDE_DEG}° (default)",
        )
    for name, noise in (("--accel-noise", args.accel_noise), ("--gyro-noise", args.gyro_noise)):
        if noise is not None and not (math.isfinite(noise) and noise > 0.0):
            raise UsageError(f"{name} must be a positive noise level, got {noise!r}")
    detector = StaticDetectorConfig.from_noise(
        accel_noise_mps2=args.accel_noise,
        gyro_noise_rps=args.gyro_noise,
        base=StaticDetectorConfig.from_session(loaded.session),
    )
    return SessionInput(
        loaded.session, float(gravity), source, args.accel_range, args.gyro_range, detector
    )


def time_gap_line(detection: StaticDetection) -> str | None:
    """What the session's time gaps cost the static detection, for the report; None without gaps."""
    if not detection.gaps:
        return None
    limit_s = detection.config.gap_limit_s(detection.rate_hz)
    line = (
        f"  time gaps: {detection.gaps} step(s) between samples longer than {limit_s:.3g} s "
        f"(longest {detection.longest_gap_s:.4g} s, at {detection.rate_hz:.4g} Hz median rate)"
    )
    if detection.untested_samples:
        line += (
            f"; {detection.untested_samples} samples lie between gaps closer than one "
            f"{detection.config.window_s:g} s window and were never tested for rest "
            "(a sample rate that changes in the session?)"
        )
    return line
