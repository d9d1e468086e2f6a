"""Command-line arguments shared by the commands that read a session file."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from estimators.conventions import normal_gravity_mps2
from estimators.session import ImuSession
from protocols.session_file import load_session

DEFAULT_LATITUDE_DEG = 45.0


@dataclass(frozen=True)
class SessionInput:
    """A session read from the command line, with its local gravity and where that came from."""

    session: ImuSession
    gravity_mps2: float
    gravity_source: str


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """SESSION (CSV file, Xsens raw-count pair or its folder) and the local gravity."""
    parser.add_argument("session", metavar="SESSION", help="CSV session file (t,ax,ay,az,gx,gy,gz[,temp]), or the accelerometer file / folder of an Xsens raw-count pair")
    parser.add_argument("--gyro-file", metavar="PATH", help="gyro file of an Xsens raw-count pair (SESSION is then its accelerometer file)")
    parser.add_argument("--sidecar", metavar="TOML", help="nominal scale (SI per count) and offset (counts) of a raw-count pair; default: the packaged Xsens MTi sidecar")
    g = parser.add_argument_group("local gravity (first that applies: --gravity, --latitude/--height, the file's own value, WGS-84 at 45°)")
    g.add_argument("--gravity", type=float, metavar="MPS2", help="local gravity magnitude, m/s²")
    g.add_argument("--latitude", type=float, metavar="DEG", help="geodetic latitude, degrees (WGS-84 normal gravity)")
    g.add_argument("--height", type=float, default=0.0, metavar="M", help="height above the ellipsoid, metres (default 0)")


def load_session_input(args: argparse.Namespace) -> SessionInput:
    """Read the session and settle the local gravity (the rule in the argument group's title)."""
    loaded = load_session(args.session, args.gyro_file, sidecar=args.sidecar)
    if args.gravity is not None:
        gravity, source = args.gravity, "--gravity"
    elif args.latitude is not None:
        gravity, source = normal_gravity_mps2(args.latitude, args.height), f"WGS-84 at {args.latitude}° {args.height} m"
    elif loaded.gravity_mps2 is not None:
        gravity, source = loaded.gravity_mps2, "session file"
    else:
        gravity, source = normal_gravity_mps2(DEFAULT_LATITUDE_DEG, 0.0), f"WGS-84 at {DEFAULT_LATITUDE_DEG}° (default)"
    return SessionInput(loaded.session, float(gravity), source)
