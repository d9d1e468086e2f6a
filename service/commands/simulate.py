"""``ins-health simulate``: write a simulated IMU session as a CSV session file.

Options come from the command line or a TOML file (``--config``); command-line
options win. The TOML keys (each option's destination; the tables hold what
does not fit on one line)::

    seed = 7
    rate_hz = 100.0
    grade = "consumer_mems"   # consumer_mems | navigation ("mems": consumer_mems)
    random_errors = false     # draw the errors from the grade instead of its fixed preset
    quantization = true
    latitude_deg = 45.0
    height_m = 0.0
    # gravity_mps2 = 9.80665  # assumed local gravity (default: WGS-84 normal gravity)

    [profile]
    kind = "multiposition"    # multiposition | static | flight
    positions = 18
    orientations = "eighteen" # eighteen | random
    static_s = 20.0
    transition_s = 4.0
    first_static_s = 60.0
    heading_deg = 0.0
    duration_s = 600.0        # static and flight
    rest_s = 10.0             # flight

    [temperature]             # constant | ramp | warmup | cycle, with that profile's fields
    kind = "cycle"
    base_c = 20.0
    peak_c = 40.0
    period_s = 300.0

    [[faults]]                # kind step|ramp|stuck|noise_burst|saturation; index: 0-8 or bx..d3 / x,y,z
    kind = "step"
    triad = "accel"
    index = "bx"
    t_start_s = 200.0
    magnitude = 0.01
    duration_s = 100.0

    [[effects]]               # any effect of estimators.sim by name, with its parameters
    name = "bias_instability"
    triad = "gyro"
    gm_sigma_si = [1e-3, 1e-3, 1e-3]
    gm_tau_s = [60.0, 60.0, 60.0]

On the command line a fault is ``KIND:TRIAD:INDEX:T_START_S:MAGNITUDE[:DURATION_S]``
and a temperature profile ``KIND[:key=value,...]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimators.conventions import PARAM_NAMES, Grade, Triad
from service.cli import UsageError, add_output
from service.grades import FLOOR_GRADE, SIMULATED, grade_name

if TYPE_CHECKING:
    from estimators.sim import Fault, FaultKind

PROFILES = ("multiposition", "static", "flight")
# The simulator's names the parser shows, stated here so that it does not load scipy
# (tests/test_cli_startup.py checks they agree with estimators.sim).
TEMPERATURE_KINDS = ("constant", "ramp", "warmup", "cycle")
ORIENTATIONS = ("eighteen", "random")
"""The values of estimators.sim.OrientationScheme."""
# Command-line options that are keys of the [profile] table.
PROFILE_KEYS = (
    "positions",
    "orientations",
    "static_s",
    "transition_s",
    "first_static_s",
    "heading_deg",
    "duration_s",
    "rest_s",
)
_DURATIONS = ("static_s", "transition_s", "first_static_s", "duration_s", "rest_s", "rate_hz")
"""Settings that must be positive and finite (seconds, or Hz)."""
TOP_KEYS = (
    "seed",
    "rate_hz",
    "grade",
    "random_errors",
    "quantization",
    "latitude_deg",
    "height_m",
    "gravity_mps2",
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="write a simulated IMU session (CSV)",
        description="Simulate an IMU session with known errors and faults and write it as a CSV session file.",
    )
    add_output(p, "--out", required=True, metavar="SESSION.csv", help="CSV session file to write")
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE.toml",
        help="TOML file with the options (command-line options win)",
    )
    add_output(
        p,
        "--truth",
        metavar="FILE.json",
        help="also write the truth (parameters, positions, faults) as JSON",
    )
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--profile", choices=PROFILES, help="motion (default multiposition)")
    p.add_argument("--positions", type=int, help="number of static positions (default 18)")
    p.add_argument(
        "--orientations",
        choices=ORIENTATIONS,
        help="position scheme (default eighteen)",
    )
    p.add_argument(
        "--static-s", dest="static_s", type=float, help="length of each position, s (default 20)"
    )
    p.add_argument(
        "--transition-s", dest="transition_s", type=float, help="length of each turn, s (default 4)"
    )
    p.add_argument(
        "--first-static-s",
        dest="first_static_s",
        type=float,
        help="length of the first position, s",
    )
    p.add_argument(
        "--heading-deg", dest="heading_deg", type=float, help="heading of the positions, degrees"
    )
    p.add_argument(
        "--duration-s",
        dest="duration_s",
        type=float,
        help="length of a static or flight profile, s",
    )
    p.add_argument(
        "--rest-s", dest="rest_s", type=float, help="rest before and after a flight, s (default 10)"
    )
    p.add_argument("--rate-hz", dest="rate_hz", type=float, help="sample rate, Hz (default 100)")
    p.add_argument(
        "--grade",
        type=grade_name,
        choices=SIMULATED,
        help="sensor class of the error preset (default consumer_mems; 'mems' is taken as consumer_mems)",
    )
    p.add_argument(
        "--random-errors",
        dest="random_errors",
        action="store_const",
        const=True,
        help="draw the errors from the grade",
    )
    p.add_argument(
        "--no-quantization",
        dest="quantization",
        action="store_const",
        const=False,
        help="no output quantization",
    )
    p.add_argument(
        "--latitude", dest="latitude_deg", type=float, help="latitude, degrees (default 45)"
    )
    p.add_argument(
        "--height", dest="height_m", type=float, help="height above the ellipsoid, m (default 0)"
    )
    p.add_argument(
        "--gravity",
        dest="gravity_mps2",
        type=float,
        help="assumed local gravity, m/s² (default WGS-84)",
    )
    p.add_argument(
        "--temperature",
        help="temperature profile KIND[:key=value,...], KIND in " + ", ".join(TEMPERATURE_KINDS),
    )
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        help="KIND:TRIAD:INDEX:T_START_S:MAGNITUDE[:DURATION_S] (repeatable)",
    )
    p.set_defaults(func=run)


# --- settings ----------------------------------------------------------------


def _load_config(path: Path | None) -> dict:
    if path is None:
        return {}
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"{path}: not valid TOML: {exc}") from None


def _parse_kv(text: str, what: str) -> dict:
    out = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise UsageError(f"{what}: expected key=value, got {item!r}")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise UsageError(f"{what}: {key.strip()} must be a number, got {value!r}") from None
    return out


def _temperature_table(text: str) -> dict:
    kind, _, rest = text.partition(":")
    return {"kind": kind.strip(), **_parse_kv(rest, f"--temperature {text}")}


def _fault_table(text: str) -> dict:
    parts = text.split(":")
    if len(parts) not in (5, 6):
        raise UsageError(
            f"--fault {text}: expected KIND:TRIAD:INDEX:T_START_S:MAGNITUDE[:DURATION_S]"
        )
    keys = ("kind", "triad", "index", "t_start_s", "magnitude", "duration_s")
    table: dict[str, str | float] = dict(zip(keys[: len(parts)], parts, strict=True))
    try:
        for k in ("t_start_s", "magnitude", "duration_s"):
            if k in table:
                table[k] = float(table[k])
    except ValueError:
        raise UsageError(f"--fault {text}: times and magnitude must be numbers") from None
    return table


def settings_from(args: argparse.Namespace) -> dict:
    """The TOML settings of ``--config`` with the command-line options applied over them."""
    cfg = _load_config(args.config)
    cfg.setdefault("profile", {})
    if args.profile is not None:
        cfg["profile"]["kind"] = args.profile
    for key in PROFILE_KEYS:
        if getattr(args, key) is not None:
            cfg["profile"][key] = getattr(args, key)
    for key in TOP_KEYS:
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)
    if args.temperature is not None:
        cfg["temperature"] = _temperature_table(args.temperature)
    cfg["faults"] = list(cfg.get("faults", [])) + [_fault_table(f) for f in args.fault]
    return cfg


# --- settings → spec ---------------------------------------------------------


def _choice(value, enum, what):
    try:
        return enum(value)
    except ValueError:
        raise UsageError(
            f"{what} must be one of {[e.value for e in enum]}, got {value!r}"
        ) from None


def _temperature(table: dict | None):
    from estimators.sim import (
        ConstantTemperature,
        CycleTemperature,
        RampTemperature,
        WarmupTemperature,
    )

    if table is None:
        return None
    table = dict(table)
    kind = table.pop("kind", None)
    profiles = dict(
        zip(
            TEMPERATURE_KINDS,
            (ConstantTemperature, RampTemperature, WarmupTemperature, CycleTemperature),
            strict=True,
        )
    )
    if kind not in profiles:
        raise UsageError(f"temperature kind must be one of {list(profiles)}, got {kind!r}")
    try:
        return profiles[kind](**table)
    except TypeError as exc:
        raise UsageError(f"temperature {kind}: {exc}") from None


def _fault_index(kind: FaultKind, index) -> int:
    from estimators.sim.faults import PARAMETER_FAULTS

    if isinstance(index, int):
        return index
    names = PARAM_NAMES if kind in PARAMETER_FAULTS else ("x", "y", "z")
    s = str(index).strip().lower()
    if s.isdigit():
        return int(s)
    if s not in names:
        raise UsageError(
            f"fault index for {kind.value} must be 0-{len(names) - 1} or one of {list(names)}, got {index!r}"
        )
    return names.index(s)


def _fault(table: dict) -> Fault:
    from estimators.sim import Fault, FaultKind

    kind = _choice(table.get("kind"), FaultKind, "fault kind")
    try:
        return Fault(
            kind=kind,
            triad=_choice(table.get("triad"), Triad, "fault triad"),
            index=_fault_index(kind, table.get("index")),
            t_start_s=float(table["t_start_s"]),
            magnitude=float(table["magnitude"]),
            duration_s=float(table.get("duration_s", math.inf)),
        )
    except KeyError as exc:
        raise UsageError(f"fault {table!r}: missing {exc.args[0]}") from None


def _model(cfg: dict, seed: int):
    from estimators.sim import EnvironmentEffect, grade_error_model, make_effect

    name = grade_name(str(cfg.get("grade", SIMULATED[0])), what="grade")
    if name not in SIMULATED:
        raise UsageError(f"grade must be one of {list(SIMULATED)}, got {name!r}")
    grade = Grade(FLOOR_GRADE[name])
    rng = np.random.default_rng([seed, 1]) if cfg.get("random_errors", False) else None
    model = grade_error_model(grade, rng=rng, quantization=bool(cfg.get("quantization", True)))
    for table in cfg.get("effects", []):
        table = dict(table)
        name = table.pop("name", None)
        triad = table.pop("triad", None)
        effect = make_effect(name, table)
        if not isinstance(effect, EnvironmentEffect):
            triad = _choice(triad, Triad, f"effect {name} triad")
        model = model.with_effect(effect, triad)
    return name, model


def spec_from_settings(cfg: dict):
    """(SessionSpec, seed, grade) from the merged settings."""
    from estimators.sim import Fly, OrientationScheme, flight_spec, multi_position_spec, static_spec

    seed = int(cfg.get("seed", 0))
    if seed < 0:
        raise UsageError(f"seed must be non-negative, got {seed}")
    grade, model = _model(cfg, seed)
    prof = dict(cfg.get("profile", {}))
    kind = prof.pop("kind", "multiposition")
    # Said in the option's words: the simulator's own check named its internal segment (Hold(...)).
    for key, value in [*prof.items(), ("rate_hz", cfg.get("rate_hz"))]:
        if key not in _DURATIONS or value is None:
            continue
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not (number and 0.0 < float(value) < math.inf):
            raise UsageError(
                f"--{key.replace('_', '-')} (setting {key}) must be a positive finite number, got {value!r}"
            )
    common = dict(
        model=model,
        rate_hz=float(cfg.get("rate_hz", 100.0)),
        latitude_deg=float(cfg.get("latitude_deg", 45.0)),
        height_m=float(cfg.get("height_m", 0.0)),
        gravity_mps2=None if cfg.get("gravity_mps2") is None else float(cfg["gravity_mps2"]),
        temperature=_temperature(cfg.get("temperature")),
        faults=tuple(_fault(f) for f in cfg.get("faults", [])),
    )
    if kind == "multiposition":
        scheme = _choice(prof.get("orientations", "eighteen"), OrientationScheme, "orientations")
        spec = multi_position_spec(
            n_positions=int(prof.get("positions", 18)),
            scheme=scheme,
            orientation_rng=np.random.default_rng([seed, 2]),
            heading_rad=math.radians(float(prof.get("heading_deg", 0.0))),
            static_s=float(prof.get("static_s", 20.0)),
            transition_s=float(prof.get("transition_s", 4.0)),
            first_static_s=None
            if prof.get("first_static_s") is None
            else float(prof["first_static_s"]),
            **common,
        )
    elif kind == "static":
        spec = static_spec(duration_s=float(prof.get("duration_s", 600.0)), **common)
    elif kind == "flight":
        spec = flight_spec(
            fly=Fly(float(prof.get("duration_s", 120.0))),
            rest_s=float(prof.get("rest_s", 10.0)),
            **common,
        )
    else:
        raise UsageError(f"profile kind must be one of {list(PROFILES)}, got {kind!r}")
    return spec, seed, grade


def truth_json(result, seed: int) -> dict:
    """The truth of a simulation as plain JSON types."""
    tr = result.truth

    def params(p):
        return dict(zip(PARAM_NAMES, map(float, p), strict=True))

    return {
        "seed": seed,
        "rate_hz": result.spec.rate_hz,
        "gravity_mps2": tr.gravity_mps2,
        "gravity_true_mps2": tr.gravity_true_mps2,
        "latitude_deg": tr.latitude_deg,
        "accel_params": params(tr.accel_params),
        "gyro_params": params(tr.gyro_params),
        "static_intervals_s": tr.static_intervals_s.tolist(),
        "effects": {
            "accel": list(tr.model.accel.names),
            "gyro": list(tr.model.gyro.names),
            "environment": [e.name for e in tr.model.environment],
        },
        "faults": [
            {
                **asdict(f),
                "kind": f.kind.value,
                "triad": f.triad.value,
                "target": f.target,
                "duration_s": None if math.isinf(f.duration_s) else f.duration_s,
            }
            for f in tr.faults
        ],
    }


def run(args: argparse.Namespace) -> int:
    from estimators.sim import simulate
    from protocols.session_file import write_csv_session

    spec, seed, grade = spec_from_settings(settings_from(args))
    result = simulate(spec, seed)
    s = result.session
    write_csv_session(
        args.out,
        s,
        metadata={
            "gravity_mps2": repr(result.truth.gravity_mps2),
            "latitude_deg": spec.latitude_deg,
            "height_m": spec.height_m,
            "rate_hz": spec.rate_hz,
            "grade": grade,
            "seed": seed,
        },
        comments=("simulated by ins-health simulate",),
    )
    if args.truth is not None:
        args.truth.write_text(
            json.dumps(truth_json(result, seed), indent=2) + "\n", encoding="utf-8"
        )
    n_pos = len(result.truth.static_intervals_s)
    print(
        f"simulate: wrote {args.out}: {s.n_samples} samples, {s.t_s[-1] - s.t_s[0]:.1f} s at {spec.rate_hz:g} Hz, "
        f"{n_pos} static interval(s), grade {grade}, seed {seed}, {len(spec.faults)} fault(s)",
        file=sys.stderr,
    )
    return 0
