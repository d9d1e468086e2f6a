"""Command-line pieces shared by the bench-method commands (``passport``, ``sixpos``).

Local gravity, session loading, angle lists, passport identity, and the
report output (text or one JSON object). Kept out of ``service/commands`` so
the command discovery sees only commands.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimators.conventions import normal_gravity_mps2
from estimators.session import ImuSession, Rejections, validate_session
from protocols.session_file import LoadedSession
from service.cli import UsageError, add_output
from service.session_args import load_units_checked

if TYPE_CHECKING:
    from estimators.passport import Passport, TriadPassport


def add_method_command(subparsers, name: str, *, help: str, doc: str, dest: str, metavar: str):
    """Add the command ``name`` (described by the first paragraph of ``doc``) and return the
    subparsers of its required sub-command (the method or test), stored as ``args.<dest>``."""
    p = subparsers.add_parser(name, help=help, description=doc.split("\n\n")[0])
    return p.add_subparsers(dest=dest, metavar=metavar, required=True)


def add_gravity_options(p: argparse.ArgumentParser) -> None:
    """Local gravity, with the option names of the other session commands (``calibrate``, ``simulate``)."""
    g = p.add_argument_group(
        "local gravity (first that applies: --gravity, --latitude/--height, the file's gravity_mps2)"
    )
    g.add_argument(
        "--gravity",
        dest="gravity_mps2",
        type=float,
        metavar="MPS2",
        help="local gravity magnitude, m/s²",
    )
    g.add_argument(
        "--latitude",
        dest="latitude_deg",
        type=float,
        metavar="DEG",
        help="geodetic latitude of the bench, degrees (WGS-84 normal gravity)",
    )
    g.add_argument(
        "--height",
        dest="height_m",
        type=float,
        default=0.0,
        metavar="M",
        help="height above the ellipsoid, m (default 0)",
    )


def gravity_from(
    args: argparse.Namespace,
    *,
    file_gravity_mps2: float | None = None,
    default_mps2: float | None = None,
) -> float:
    """Local gravity: ``--gravity``, else normal gravity at ``--latitude``, else the file's, else ``default``.

    Without any of them the command refuses: M4's point is that the standard
    9.80665 m/s² instead of the local value is a 0.2 % scale error.
    """
    if args.gravity_mps2 is not None:
        if not (math.isfinite(args.gravity_mps2) and 9.7 < args.gravity_mps2 < 9.9):
            raise UsageError(
                f"--gravity must be a local gravity near 9.8 m/s², got {args.gravity_mps2!r}"
            )
        return float(args.gravity_mps2)
    if args.latitude_deg is not None:
        return normal_gravity_mps2(args.latitude_deg, args.height_m)
    if file_gravity_mps2 is not None:
        return float(file_gravity_mps2)
    if default_mps2 is not None:
        return float(default_mps2)
    raise UsageError(
        "the method needs the local gravity: give --latitude (and --height) or --gravity"
    )


def load_valid(
    path: Path, args: argparse.Namespace
) -> tuple[LoadedSession, ImuSession, Rejections]:
    """A session file in SI (its units from ``args``' unit options or the file, refused when
    implausible), and its samples after validation (non-finite values and repeated or backward
    times dropped, counted)."""
    loaded = load_units_checked(str(path), None, None, args)
    clean, rejected = validate_session(loaded.session)
    return loaded, clean, rejected


def add_rejections(total: dict[str, int], rejections: Rejections) -> None:
    """Add a file's validation counts to ``total`` (reason → samples)."""
    for reason, n in rejections.counts.items():
        total[reason] = total.get(reason, 0) + n


def rejected_text(rejected: dict[str, int]) -> str:
    """A report line with the samples validation dropped, or nothing when none were."""
    if not rejected:
        return ""
    return "\nsamples rejected by validation: " + ", ".join(
        f"{reason} {n}" for reason, n in sorted(rejected.items())
    )


def parse_angles_deg(text: str) -> np.ndarray:
    """``START:STOP:STEP`` (inclusive) or a comma list, degrees → (M,) degrees."""
    try:
        if ":" in text:
            start, stop, step = (float(v) for v in text.split(":"))
            if step == 0 or (stop - start) / step < 0:
                raise ValueError
            n = math.floor((stop - start) / step + 1e-9) + 1
            return start + step * np.arange(n)
        return np.array([float(v) for v in text.split(",") if v.strip()])
    except ValueError:
        raise UsageError(
            f"--angles-deg must be START:STOP:STEP or a comma list of degrees, got {text!r}"
        ) from None


def axis_index(name: str) -> int:
    return "xyz".index(name)


def add_passport_options(p: argparse.ArgumentParser) -> None:
    add_output(p, "--out", help="passport JSON file to write")
    add_output(p, "--report", help="also write the full report as JSON")
    p.add_argument(
        "--unit-id", default="unit", help="identity of the unit in the passport (default 'unit')"
    )
    p.add_argument("--sensor-model", default="", help="sensor model name for the passport")
    p.add_argument(
        "--json", action="store_true", help="print the report as one JSON object instead of text"
    )


def write_passport(args: argparse.Namespace, triad_passport: TriadPassport) -> Passport:
    """Wrap one triad passport with the identity options and write it to ``--out`` (if given)."""
    # Imported here, as the commands' heavy modules are: the CLI parser loads this module.
    from estimators.passport import Passport
    from protocols.passport_codec import write_passport_json

    passport = Passport(
        unit_id=args.unit_id,
        sensor_model=args.sensor_model,
        sensor_ids={},
        created=dt.date.today().isoformat(),
        triads={triad_passport.triad: triad_passport},
    )
    if args.out is not None:
        write_passport_json(passport, args.out)
    return passport


def plain(value: Any) -> Any:
    """JSON-ready copy: arrays to lists, numpy scalars to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    return value


def emit(args: argparse.Namespace, report: dict, text: str) -> None:
    """Print the report (``--json``: one object, else ``text``) and write ``--report`` if asked."""
    obj = plain(report)
    if getattr(args, "report", None) is not None:
        args.report.write_text(json.dumps(obj, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(obj) if args.json else text)
