"""Service configuration: TOML in, typed frozen dataclasses out, every default documented.

``ins-health run --config FILE.toml`` reads one file with the sections below;
every key is optional and an unknown key is an error (a typo must not silently
fall back to a default). Every key is checked for its type and range before
the service starts: :class:`ConfigError` carries one line per error (all type
errors of the file, or when the types are right all range errors), and
``ins-health run`` prints each and exits with status 2. Infinities and
non-positive periods are refused. ``deploy/ins-health.toml`` is a complete,
commented example, loaded by the tests.

Sections
--------
``[service]``      instance name, data and passport directories, periods.
``[site]``         local gravity (measured value, or latitude/height → WGS-84).
``[zenoh]``        session (mode, endpoints, TLS, access control), the key expression of this
                   instance's share of the fleet, event acknowledgement.
``[mavlink]``      link (device, identity, RAW_IMU scaling, signing), alert rate limit.
``[pipeline]``     queue capacity, F0 false-alarm probability, minimum positions.
``[validity]``     stream validity and cross-IMU consistency thresholds.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from pathlib import Path
from typing import Any

from estimators.conventions import STANDARD_GRAVITY_MPS2, normal_gravity_mps2
from estimators.nominal_passport import SensorClass
from estimators.stream_validity import ValidityLimits
from protocols._schema import MAX_IMU_INDEX, SchemaError, check_vehicle
from protocols.mavlink_settings import UDP_RCVBUF_MIN_BYTES, MavlinkSettings
from protocols.zenoh_settings import (
    ALL_FRAMES,
    AckMode,
    Mode,
    ZenohSettings,
    check_frames_selector,
    check_receiver_name,
    check_service_name,
)

NO_DEFAULT_GRADE = "none"
"""``[service] default_grade`` that gives a unit without a passport no nominal one (stream checks only)."""


class ConfigError(ValueError):
    """The configuration cannot be used; one line per error, each naming the key and the value."""

    def __init__(self, *lines: str) -> None:
        # A key from the file or a library's message may hold line breaks: each error stays one line.
        lines = tuple(_one_line(line) for line in lines)
        super().__init__("\n".join(lines))
        self.lines = lines


def _one_line(text: str) -> str:
    """``text`` with its control characters written as escapes (``\\n``), as ``repr`` writes them."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


_BYTE_ID = (0, 255)
_MAVLINK_LINK_KEYS: dict[str, tuple[type, tuple[int, int] | None]] = {
    "device": (str, None),
    "vehicle": (str, None),
    "baud": (int, (1, 10_000_000)),
    "source_system": (int, (1, 255)),
    "source_component": (int, (1, 255)),
    "autopilot_system": (int, (1, 255)),
    "signing_link_id": (int, _BYTE_ID),
    "accept_unsigned": (bool, None),
    "signing_key_hex": (str, None),
    "signing_key_file": (str, None),
    "messages": (list, None),
    "imu_index": (dict, None),
    "raw_scale": (dict, None),
    "udp_rcvbuf_bytes": (int, (UDP_RCVBUF_MIN_BYTES, 2**31 - 1)),
}
"""Type and range of each ``[mavlink]`` link key, checked before the link settings are built: a
value of the wrong type must be refused, not compared (a string ``autopilot_system`` matched no
system, so every IMU message was ignored)."""


@dataclass(frozen=True)
class ServiceSection:
    """``[service]``.

    name : instance name, shown on the status topic (default ``"ins-health"``).
    data_dir : directory of ``outbox.sqlite`` and ``checkpoints.sqlite`` (default ``"./ins-health-data"``; a default
        is relative to the working directory, a configured relative path to the configuration file).
    passport_dir : directory of the passport store (default ``"./passports"``).
    status_period_s : period of the status publication and of the timeout checks, s (default 1.0;
        this and the other periods at least :data:`PERIOD_MIN_S`).
    checkpoint_period_s : period of the estimator-state checkpoints, s (default 30.0);
        SIGTERM always writes a last one.
    delivery_retry_s : delay before a sink retries events its transport did not accept, s (default 0.5).
    outbox_max_mb : the largest the outbox file may grow, MB (default 0: as large as the disk allows);
        beyond it the outbox is full as on a full disk (:mod:`service.outbox_writer`).
    outbox_max_pending : events each sink (Zenoh, MAVLink) may have waiting in the outbox
        (default 100000, at most :data:`OUTBOX_MAX_PENDING_MAX`); beyond it that sink gives up its
        oldest (logged, counted as ``outbox.given_up.<sink>``), the other sinks still deliver them.
        With ``outbox_max_mb`` set, keep the backlogs within it (an event takes about 1 KB of the
        file): a file full of one sink's backlog holds the new events in memory (delivered from
        there to the other sinks) and, past ``storage_timeout_s``, ends the daemon.
    max_held_events : events held in memory while the outbox cannot take them, delivered from there
        (default 10000, at most :data:`MAX_HELD_EVENTS_MAX`; :mod:`service.outbox_writer`).
    storage_timeout_s : how long the outbox or the checkpoints may refuse writes (or the data
        directory be gone) before the daemon stops feeding the watchdog and exits with status 74
        for the service manager to restart it, s (default 300, in [1, 86400]).
    vehicles : vehicle ids served; empty (default) serves every vehicle the key expression delivers.
        A frame of a vehicle outside a non-empty list is counted as ``frames.rejected.unknown_vehicle``; the
        passport of IMU 0 of each listed vehicle is checked at startup.
    default_grade : sensor class (:class:`estimators.nominal_passport.SensorClass`: ``consumer_mems``,
        ``industrial_mems``, ``tactical``, ``navigation``) whose nominal passport a unit runs on
        when the store has no usable entry for it (none, or one refused: it stays reported as
        refused), so that F0 and the diagnosis run against the class's datasheet limits
        (default ``consumer_mems``, the drone-autopilot IMU); ``"none"``: such a unit runs
        the stream validity checks only.
    """

    name: str = "ins-health"
    data_dir: Path = Path("./ins-health-data")
    passport_dir: Path = Path("./passports")
    status_period_s: float = 1.0
    checkpoint_period_s: float = 30.0
    delivery_retry_s: float = 0.5
    outbox_max_mb: float = 0.0
    outbox_max_pending: int = 100_000
    max_held_events: int = 10_000
    storage_timeout_s: float = 300.0
    vehicles: tuple[str, ...] = ()
    default_grade: str = SensorClass.CONSUMER_MEMS.value

    @property
    def nominal_class(self) -> SensorClass | None:
        """The class of ``default_grade`` (None: ``"none"``; :func:`load_config` refuses any other value)."""
        return None if self.default_grade == NO_DEFAULT_GRADE else SensorClass(self.default_grade)

    @property
    def outbox_max_bytes(self) -> int | None:
        """``outbox_max_mb`` in bytes (None: unbounded)."""
        return int(self.outbox_max_mb * 1e6) if self.outbox_max_mb > 0 else None


@dataclass(frozen=True)
class SiteSection:
    """``[site]``: the local gravity magnitude, the accelerometers' scalar reference (M1).

    gravity_mps2 : a measured local value, m/s² (takes precedence when given).
    latitude_deg, height_m : else WGS-84 normal gravity at this place
        (:func:`estimators.conventions.normal_gravity_mps2`).
    With neither, standard gravity 9.80665 m/s² is used (an error up to 0.3 %, which
    widens F0's shell accordingly: configure the site).
    """

    gravity_mps2: float | None = None
    latitude_deg: float | None = None
    height_m: float = 0.0

    @property
    def local_gravity_mps2(self) -> float:
        if self.gravity_mps2 is not None:
            return float(self.gravity_mps2)
        if self.latitude_deg is not None:
            return normal_gravity_mps2(self.latitude_deg, self.height_m)
        return STANDARD_GRAVITY_MPS2


DEFAULT_ZENOH_SESSION = ZenohSettings(mode=Mode.CLIENT, connect=("tcp/127.0.0.1:7447",))


@dataclass(frozen=True)
class ZenohSection:
    """``[zenoh]``.

    enabled : subscribe to frames and publish events/status over Zenoh (default true).
    frames_key : key expression of the frames this instance handles (default ``"ins/*/imu/*"``);
        split a fleet across instances by giving each its own (e.g. ``"ins/alpha-$*/imu/*"``).
    event_ack : ``"receiver"`` (default: an event is delivered once a receiving application
        acknowledged it, :class:`protocols.zenoh_settings.AckMode`) or ``"matched"`` (once the
        reliable put found a subscriber).
    ack_timeout_s : how long one delivery waits for acknowledgements (default 1.0 s).
    min_acks : distinct receivers whose acknowledgements an event needs (default 1; one receiver
        answering twice, or under two names, counts once:
        :func:`protocols.zenoh_adapter.distinct_receivers`).
    ack_from : the names of the receivers (ground stations, ``ins-health watch --receiver NAME``)
        whose acknowledgements count (default empty: any receiver's); another's answer is refused,
        counted (``service.zenoh.acks_refused``) and logged. Under the deploy's access control a
        name is bound to a ground station's certificate (``deploy/zenoh-router.json5``).
    session : the session itself, from the other keys of the table, read by
        :meth:`protocols.zenoh_settings.ZenohSettings.from_dict`: ``mode`` (default ``"client"``),
        ``connect`` (default ``["tcp/127.0.0.1:7447"]`` in client mode), ``listen``,
        ``multicast_scouting`` (default false), ``connect_timeout_s`` (default: wait for the
        router), ``tls`` and ``access_control`` (tables passed to Zenoh), ``extra``.
    """

    enabled: bool = True
    frames_key: str = ALL_FRAMES
    event_ack: AckMode = AckMode.RECEIVER
    ack_timeout_s: float = 1.0
    min_acks: int = 1
    ack_from: tuple[str, ...] = ()
    session: ZenohSettings = DEFAULT_ZENOH_SESSION


DEFAULT_MAVLINK_VEHICLE = "mavlink.autopilot"
"""The vehicle id of the MAVLink link's IMUs when ``[mavlink] vehicle`` is not set. It was ``"mav1"``,
a plausible fleet name and so a Zenoh frame key any local process could feed (such frames are now
refused once the link has fed the vehicle, ``other_source``); a configuration that relied on it and keeps
passports or history under ``mav1`` sets ``vehicle = "mav1"``."""
DEFAULT_MAVLINK_LINK = MavlinkSettings(
    device="udpin:127.0.0.1:14550", vehicle=DEFAULT_MAVLINK_VEHICLE
)


class MavlinkReader(StrEnum):
    """Where the MAVLink link is read and parsed."""

    PROCESS = "process"
    """A child process of its own (:class:`protocols.mavlink_process.MavlinkProcessLink`): pymavlink's
    parse runs beside the pipeline, on another core (≥ 50 k messages/s of one sample each)."""
    THREAD = "thread"
    """A thread of the service's process (one process less; the parse shares the pipeline's
    interpreter: about 30 k messages/s of one sample each, fewer as the pipeline's work grows)."""


@dataclass(frozen=True)
class MavlinkSection:
    """``[mavlink]``.

    enabled : read IMU messages and send alerts over MAVLink (default false).
    alert_min_interval_s : a repeat of the same alert (vehicle, IMU, predicate, sensor, axis,
        cause) within this interval is suppressed (default 10 s; :class:`service.alert_policy.AlertPolicy`).
    alert_max_per_s : distinct alerts are paced to at most this many per second (default 1);
        they wait in the outbox, none is dropped. The Zenoh event stream stays complete whatever
        these say.
    heartbeat_period_s : HEARTBEAT period of the onboard-computer component (default 1.0 s).
    reader : ``"process"`` (default) or ``"thread"``: where the link is read and parsed
        (:class:`MavlinkReader`).
    link : the link itself, from the other keys of the table, read by
        :meth:`protocols.mavlink_settings.MavlinkSettings.from_dict`: ``device`` (pymavlink
        connection string, default ``"udpin:127.0.0.1:14550"``; ``tcp:…``, or a serial device
        with ``baud``), ``vehicle`` (vehicle id of this link's IMUs, default :data:`DEFAULT_MAVLINK_VEHICLE`; Zenoh
        frames under the same id are refused once the link has fed it IMU samples),
        ``source_system``, ``source_component`` (default 191, MAV_COMP_ID_ONBOARD_COMPUTER),
        ``autopilot_system`` (the one system whose IMU messages are read; unset, the first
        heard: other systems' are counted as ``service.mavlink.rejected.other_system`` and each
        logged once), ``messages``, ``imu_index``, ``raw_scale`` (RAW_IMU counts → SI,
        default ArduPilot's mG, mrad/s, cdegC), ``signing_key_hex`` or ``signing_key_file``
        (a file holding the 64 hex digits, relative to the configuration file; MAVLink 2 signing:
        what is sent is signed, IMU messages unsigned or signed with another key are refused and
        counted as ``service.mavlink.rejected.unsigned`` / ``.bad_signature``),
        ``signing_link_id``, ``accept_unsigned`` (default false: read unsigned IMU messages anyway),
        ``udp_rcvbuf_bytes`` (a UDP link's receive buffer, default 4 MiB: the backlog held
        before the kernel drops datagrams, counted as ``service.mavlink.dropped_kernel``).
    """

    enabled: bool = False
    alert_min_interval_s: float = 10.0
    alert_max_per_s: float = 1.0
    heartbeat_period_s: float = 1.0
    reader: MavlinkReader = MavlinkReader.PROCESS
    link: MavlinkSettings = DEFAULT_MAVLINK_LINK


@dataclass(frozen=True)
class PipelineSection:
    """``[pipeline]``.

    queue_capacity : frames queued per (vehicle, IMU) before new frames are dropped and counted (default 256).
    instance_queue_capacity : frames queued for all units of the instance together (default 4096); when
        full, a unit holding less than its fair share (this over the units with frames queued) takes
        the place of the newest frame of the longest queue, and one holding its share or more has its
        new frame dropped (:class:`protocols._handoff.FairQueues`; deploy/SCALING.md).
    false_alarm_probability : per-sample false-alarm probability of F0 from which λ0 is derived
        with the passport's noise and tolerances (default 1e-9: at 1 kHz about one false alarm
        in 11 days of static data; :func:`estimators.scalar.derive_lambda0`).
    f0_persistence_s : F0 is declared failed only after failing this long without a break (default
        0.02 s, at least one sample): a knock on a resting vehicle rings for a few ms, a sensor fault
        stays (:func:`estimators.scalar.persistent_failure`).
    min_positions : static positions needed before the nine-parameter diagnosis runs (default 9, M1).
    max_imus_per_vehicle : pipelines created per vehicle at most (default 4); more IMU indices are
        counted as ``unknown_imu`` (a flood of fake indices cannot exhaust memory).
    max_vehicles : vehicles served at most (default 256), for the same reason.
    """

    queue_capacity: int = 256
    instance_queue_capacity: int = 4096
    false_alarm_probability: float = 1e-9
    f0_persistence_s: float = 0.02
    min_positions: int = 9
    max_imus_per_vehicle: int = 4
    max_vehicles: int = 256


@dataclass(frozen=True)
class ServiceConfig:
    """The whole configuration (see the module docstring for the sections)."""

    service: ServiceSection = field(default_factory=ServiceSection)
    site: SiteSection = field(default_factory=SiteSection)
    zenoh: ZenohSection = field(default_factory=ZenohSection)
    mavlink: MavlinkSection = field(default_factory=MavlinkSection)
    pipeline: PipelineSection = field(default_factory=PipelineSection)
    validity: ValidityLimits = field(default_factory=ValidityLimits)

    @property
    def outbox_path(self) -> Path:
        return self.service.data_dir / "outbox.sqlite"

    @property
    def checkpoint_path(self) -> Path:
        return self.service.data_dir / "checkpoints.sqlite"


_SECTIONS: dict[str, type] = {
    "service": ServiceSection,
    "site": SiteSection,
    "zenoh": ZenohSection,
    "mavlink": MavlinkSection,
    "pipeline": PipelineSection,
    "validity": ValidityLimits,
}


ACK_TIMEOUT_MAX_S = 86_400.0
"""Longest wait for acknowledgements of one delivery, s ([zenoh] ack_timeout_s)."""


def _path(where: str, value: str, base_dir: Path) -> Path:
    """``value`` as a path: ``~`` expanded, relative to ``base_dir`` (the configuration's folder)."""
    if "\0" in value:
        raise ConfigError(f"{where} holds a NUL character: {value!r}")
    try:
        path = Path(value).expanduser()
    except RuntimeError as exc:  # ~user of no user, or no home directory
        raise ConfigError(f"{where}: {value!r}: {exc}") from None
    return path if path.is_absolute() else (base_dir / path)


def _coerce(where: str, kind: Any, value: Any, base_dir: Path) -> Any:
    args = typing.get_args(kind)
    if type(None) in args:
        if value is None:
            return None
        kind = next(a for a in args if a is not type(None))
    if typing.get_origin(kind) is tuple:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where} must be a list of strings, got {value!r}")
        return tuple(value)
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if kind is Path:
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{where} must be a non-empty path string, got {value!r}")
        return _path(where, value, base_dir)
    if isinstance(kind, type) and issubclass(kind, Enum):
        try:
            return kind(value)
        except ValueError:
            raise ConfigError(
                f"{where} must be one of {[m.value for m in kind]}, got {value!r}"
            ) from None
    raise ConfigError(f"{where}: unsupported option type {kind!r}")


def _split_section(
    name: str,
    cls: type,
    raw: Any,
    base_dir: Path,
    nested: str,
    parse: Callable[[dict[str, Any]], object],
    defaults: dict[str, Any],
    check: Callable[[dict[str, Any]], list[str]],
) -> Any:
    """A section whose own keys are fields of ``cls`` and whose other keys configure a transport (``nested``)."""
    if not isinstance(raw, dict):
        raise ConfigError(f"[{name}] must be a table, got {raw!r}")
    own = {f.name for f in dataclasses.fields(cls)} - {nested}
    rest = {**defaults, **{k: v for k, v in raw.items() if k not in own}}
    errors = list(check(rest))
    settings = None
    if not errors:
        try:
            settings = parse(rest)
        except (ValueError, TypeError) as exc:
            errors.append(f"[{name}] {exc}")
    try:
        section = _build_section(name, cls, {k: v for k, v in raw.items() if k in own}, base_dir)
    except ConfigError as exc:
        errors += exc.lines
    if errors:
        raise ConfigError(*errors)
    return dataclasses.replace(section, **{nested: settings})


def _zenoh_keys(table: dict[str, Any]) -> list[str]:
    timeout = table.get("connect_timeout_s")
    if isinstance(timeout, float) and not math.isfinite(timeout):
        # "wait forever" is the absent key; an infinity reads like a number and hangs the start.
        return [
            f"[zenoh] connect_timeout_s must be a finite number >= 0 or absent, got {timeout!r}"
        ]
    return []


def _mavlink_keys(table: dict[str, Any]) -> list[str]:
    errors = []
    for key, value in table.items():
        if key not in _MAVLINK_LINK_KEYS:
            continue  # unknown keys: the link settings name them
        kind, bounds = _MAVLINK_LINK_KEYS[key]
        wrong = isinstance(value, bool) != (kind is bool) or not isinstance(value, kind)
        if wrong:
            errors.append(f"[mavlink] {key} must be {kind.__name__}, got {value!r}")
        elif bounds is not None and not bounds[0] <= value <= bounds[1]:
            errors.append(f"[mavlink] {key} must be in {bounds[0]}..{bounds[1]}, got {value!r}")
    scale = table.get("raw_scale")
    if isinstance(scale, dict):
        for key, value in scale.items():
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and value > 0):
                errors.append(
                    f"[mavlink] raw_scale.{key} must be a finite number > 0, got {value!r}"
                )
    index = table.get("imu_index")
    if isinstance(index, dict):
        for key, value in index.items():
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
                errors.append(
                    f"[mavlink] imu_index.{key} must be an integer in 0..255, got {value!r}"
                )
    return errors


def _zenoh_section(raw: Any, base_dir: Path) -> ZenohSection:
    mode = raw.get("mode", Mode.CLIENT.value) if isinstance(raw, dict) else None
    defaults: dict[str, Any] = {"mode": Mode.CLIENT.value}
    if mode == Mode.CLIENT.value:
        defaults["connect"] = list(DEFAULT_ZENOH_SESSION.connect)
    return _split_section(
        "zenoh",
        ZenohSection,
        raw,
        base_dir,
        "session",
        ZenohSettings.from_dict,
        defaults,
        _zenoh_keys,
    )


def _mavlink_section(raw: Any, base_dir: Path) -> MavlinkSection:
    defaults = {"device": DEFAULT_MAVLINK_LINK.device, "vehicle": DEFAULT_MAVLINK_LINK.vehicle}

    def settings(table: dict[str, Any]) -> MavlinkSettings:
        key_file = table.get("signing_key_file")
        if isinstance(key_file, str) and key_file:
            table = {
                **table,
                "signing_key_file": str(_path("[mavlink] signing_key_file", key_file, base_dir)),
            }
        return MavlinkSettings.from_dict(table)

    return _split_section(
        "mavlink",
        MavlinkSection,
        raw,
        base_dir,
        "link",
        settings,
        defaults,
        _mavlink_keys,
    )


_NESTED = {"zenoh": _zenoh_section, "mavlink": _mavlink_section}


def _build_section(section: str, cls: type, raw: Any, base_dir: Path) -> Any:
    if not isinstance(raw, dict):
        raise ConfigError(f"[{section}] must be a table, got {raw!r}")
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(raw) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ConfigError(f"[{section}] has unknown keys {unknown}; known: {sorted(hints)}")
    values: dict[str, Any] = {}
    errors: list[str] = []
    for name, value in raw.items():
        try:
            values[name] = _coerce(f"[{section}] {name}", hints[name], value, base_dir)
        except ConfigError as exc:
            errors += exc.lines
    if errors:
        raise ConfigError(*errors)
    try:
        return cls(**values)
    except ValueError as exc:
        raise ConfigError(f"[{section}] {exc}") from None


def config_from_dict(raw: dict[str, Any], *, base_dir: Path | None = None) -> ServiceConfig:
    """A :class:`ServiceConfig` from a parsed TOML document; relative paths resolve against ``base_dir``."""
    base = Path.cwd() if base_dir is None else Path(base_dir)
    unknown = sorted(set(raw) - set(_SECTIONS))
    if unknown:
        raise ConfigError(f"unknown sections {unknown}; known: {sorted(_SECTIONS)}")
    parts: dict[str, Any] = {}
    errors: list[str] = []
    for name, cls in _SECTIONS.items():
        if name not in raw:
            continue
        try:
            parts[name] = (
                _NESTED[name](raw[name], base)
                if name in _NESTED
                else _build_section(name, cls, raw[name], base)
            )
        except ConfigError as exc:
            errors += exc.lines
    if errors:
        raise ConfigError(*errors)
    cfg = ServiceConfig(**parts)
    errors = _check(cfg)
    if errors:
        raise ConfigError(*errors)
    return cfg


def load_config(path: str | Path) -> ServiceConfig:
    """Read and validate a TOML configuration file (relative paths are relative to the file)."""
    path = Path(path)
    try:
        # utf-8-sig: a byte-order mark (a Windows editor's) made tomllib say "Invalid statement".
        raw = tomllib.loads(path.read_bytes().decode("utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # TOML is UTF-8
        raise ConfigError(f"{path}: not UTF-8 text (TOML is): {exc}") from None
    return config_from_dict(raw, base_dir=path.resolve().parent)


def _positive(errors: list[str], where: str, value: float) -> None:
    if not value > 0:
        errors.append(f"{where} must be > 0, got {value!r}")


OUTBOX_MAX_PENDING_MAX = 10_000_000
"""A sink's backlog at most: with events of about 1 KB, 10 GB of outbox."""
MAX_HELD_EVENTS_MAX = 1_000_000
"""Events held in memory at most: about 1.5 KB each (``benchmarks/bench_delivery.py``), 1.5 GB."""

PERIOD_MIN_S = 0.01
"""The shortest period of a task's loop (status, checkpoints, delivery retries, heartbeat): 1e-300 s
passed as > 0, and the task then ran at every turn of the event loop, the frames' loop."""


def _period(errors: list[str], where: str, value: float) -> None:
    if not PERIOD_MIN_S <= value:
        errors.append(f"{where} must be at least {PERIOD_MIN_S} s, got {value!r}")


SQLITE_MAX_MB = 4_294_967_294 * 4096 / 1e6
"""The largest SQLite database of 4 KiB pages, MB (its largest page count times the page size): an
``outbox_max_mb`` above it bounds nothing."""
UNITS_MAX = 16_384
"""Pipelines at most (``max_vehicles`` × ``max_imus_per_vehicle``): a unit's pipeline held 0.22 MB
after 120 s at 200 Hz (deploy/SCALING.md, "Memory": 144 MB with one IMU, 158 MB with 64), so this
many fill 3.6 GB, the whole memory of the smaller companion computers (4 GB)."""
QUEUE_FRAMES_MAX = 65_536
"""Frames queued at most (``queue_capacity``, ``instance_queue_capacity``): 65,536 frames of 100
samples (5.6 KB each, deploy/SCALING.md) are 367 MB, more than the unit's MemoryMax (320M)."""

_UPPER_BOUNDS: dict[tuple[str, str], tuple[float, str]] = {
    # The periods: a task run less than hourly is not a periodic task an operator can watch.
    ("service", "status_period_s"): (
        3_600.0,
        "an hour: the status is how a silent vehicle is told",
    ),
    ("service", "delivery_retry_s"): (3_600.0, "an hour between tries of an undelivered event"),
    # A checkpoint older than REVIVE_MAX_AGE_S is not revived at start (service.daemon): a longer
    # period would make every restart start afresh.
    ("service", "checkpoint_period_s"): (
        7 * 86_400.0,
        "7 days: older checkpoints are not revived (REVIVE_MAX_AGE_S)",
    ),
    ("service", "outbox_max_mb"): (SQLITE_MAX_MB, "the largest SQLite file of 4 KiB pages"),
    ("site", "height_m"): (
        50_000.0,
        "50 km: above any vehicle's flight and the normal-gravity model",
    ),
    # Latitude is an angle from the equator: past a pole it names no place (the normal-gravity
    # model raised ValueError there, ending the start without the key's section or other errors).
    ("site", "latitude_deg"): (90.0, "the north pole"),
    ("zenoh", "min_acks"): (256, "256 ground stations, each answering every event"),
    # Past it the daemon exits for systemd to restart it (storage_timeout_s's role for the disk, and
    # its bound): a router away longer is the absent key, waiting for it; 1e300 s overflowed the
    # milliseconds Zenoh takes.
    ("zenoh", "connect_timeout_s"): (
        86_400.0,
        "a day, as storage_timeout_s: omit the key to wait for the router",
    ),
    ("mavlink", "alert_min_interval_s"): (86_400.0, "a day: a repeat later than that is news"),
    # STATUSTEXT is 59 bytes with its header: a 115,200-baud link carries about 195 a second.
    ("mavlink", "alert_max_per_s"): (200.0, "a 115200-baud link carries about 195 STATUSTEXT/s"),
    # Ground stations call a component lost after a few missed HEARTBEATs (QGroundControl, 3.5 s).
    ("mavlink", "heartbeat_period_s"): (60.0, "a minute: ground stations call it lost long before"),
    ("pipeline", "queue_capacity"): (QUEUE_FRAMES_MAX, "QUEUE_FRAMES_MAX: 367 MB of frames"),
    ("pipeline", "instance_queue_capacity"): (
        QUEUE_FRAMES_MAX,
        "QUEUE_FRAMES_MAX: 367 MB of frames",
    ),
    # Positions are kept until the fit runs; a session holds tens, a calibration 12 to 24.
    ("pipeline", "min_positions"): (1_000, "1000 positions: no session holds so many at rest"),
    ("pipeline", "max_imus_per_vehicle"): (MAX_IMU_INDEX + 1, "IMU indices are 0..255"),
    ("pipeline", "max_vehicles"): (UNITS_MAX, "UNITS_MAX pipelines: 3.6 GB"),
    ("validity", "timeout_s"): (3_600.0, "an hour: a stream silent longer is long timed out"),
    # A stale run is counted, not buffered: bounded by meaning, an hour at the highest rate.
    ("validity", "stale_run_samples"): (36_000_000, "an hour at 10 kHz"),
    # The error window is a ring of flags (1 B a sample, checkpointed) and a running sum of int64s
    # over it and a batch at each frame (8 B a sample): 9 B a sample of transient memory per IMU.
    # A minute at the highest rate, 600,000 samples, is 5.4 MB: 4e8 took 1.3-1.7 GB, 1e12 failed.
    ("validity", "error_window_samples"): (600_000, "a minute at 10 kHz, 5.4 MB per IMU"),
    # A limit beyond twice the widest range of an autopilot IMU (±32 g, ±4000 °/s) is never
    # exceeded: it turns the comparison off.
    ("validity", "cross_imu_accel_mps2"): (628.0, "twice a ±32 g accelerometer's range"),
    ("validity", "cross_imu_gyro_rps"): (139.6, "twice a ±4000 °/s gyro's range"),
    ("validity", "cross_imu_window_s"): (60.0, "a minute: the bins are means over it"),
    ("validity", "cross_imu_persist_windows"): (7_200, "an hour of 0.5 s bins before a report"),
    # Detector windows and position buffers are sized in samples from the rate.
    ("validity", "max_rate_hz"): (100_000.0, "100 kHz: no IMU samples faster"),
}
"""The largest value of each numeric key and why (memory, or where a larger value means nothing or
turns a check off); checked at start with the other range errors (exit 2)."""


def _upper_bounds(cfg: ServiceConfig) -> list[str]:
    errors = []
    for (section, key), (bound, why) in _UPPER_BOUNDS.items():
        table = getattr(cfg, section)
        # [zenoh]'s session keys are read into its ZenohSettings.
        value = getattr(table, key) if hasattr(table, key) else getattr(table.session, key)
        if isinstance(value, (int, float)) and value > bound:
            errors.append(f"[{section}] {key} must be at most {bound:g} ({why}), got {value!r}")
    v = cfg.validity
    if v.cross_imu_window_s * v.cross_imu_persist_windows > 3_600.0:
        errors.append(
            "[validity] cross_imu_window_s x cross_imu_persist_windows must be at most 3600 s (a "
            f"disagreement reported an hour late is no check), got {v.cross_imu_window_s!r} x "
            f"{v.cross_imu_persist_windows!r}"
        )
    p = cfg.pipeline
    if p.max_vehicles * p.max_imus_per_vehicle > UNITS_MAX:
        errors.append(
            f"[pipeline] max_vehicles x max_imus_per_vehicle must be at most {UNITS_MAX} (0.22 MB a "
            f"pipeline: UNITS_MAX), got {p.max_vehicles} x {p.max_imus_per_vehicle}"
        )
    return errors


def _check(cfg: ServiceConfig) -> list[str]:
    """Every range error of a typed configuration, one line each."""
    errors: list[str] = []
    s, p, m, z = cfg.service, cfg.pipeline, cfg.mavlink, cfg.zenoh
    for vehicle in s.vehicles:
        try:
            check_vehicle(vehicle, error=SchemaError)
        except SchemaError as exc:
            errors.append(f"[service] vehicles: {exc}")
    try:
        # The name is a key chunk of the instance's liveliness token and service status.
        check_service_name(s.name)
    except ValueError as exc:
        errors.append(f"[service] name: {exc}")
    for name in ("data_dir", "passport_dir"):
        folder = getattr(s, name)
        # A file there ended the start in a traceback (FileExistsError) from the outbox's mkdir.
        # os.path: False where the caller may not look (Path.exists raised PermissionError, and a
        # command that reads the configuration for its site only, replay --config, then failed).
        if folder is not None and os.path.isfile(folder):
            errors.append(f"[service] {name} {str(folder)!r} is a file, not a folder")
    for name in ("status_period_s", "checkpoint_period_s", "delivery_retry_s"):
        _period(errors, f"[service] {name}", getattr(s, name))
    grades = [c.value for c in SensorClass] + [NO_DEFAULT_GRADE]
    if s.default_grade not in grades:
        errors.append(f"[service] default_grade must be one of {grades}, got {s.default_grade!r}")
    if not (math.isfinite(s.outbox_max_mb) and s.outbox_max_mb >= 0):
        errors.append(
            f"[service] outbox_max_mb must be a finite number >= 0, got {s.outbox_max_mb!r}"
        )
    for name, top in (
        ("outbox_max_pending", OUTBOX_MAX_PENDING_MAX),
        ("max_held_events", MAX_HELD_EVENTS_MAX),
    ):
        value = getattr(s, name)
        if not (type(value) is int and 1 <= value <= top):
            errors.append(f"[service] {name} must be an integer in [1, {top}], got {value!r}")
    if not (math.isfinite(s.storage_timeout_s) and 1.0 <= s.storage_timeout_s <= 86_400.0):
        errors.append(
            f"[service] storage_timeout_s must be in [1, 86400] s, got {s.storage_timeout_s!r}"
        )
    for name in (
        "queue_capacity",
        "instance_queue_capacity",
        "max_imus_per_vehicle",
        "max_vehicles",
    ):
        _positive(errors, f"[pipeline] {name}", getattr(p, name))
    if not 0.0 < p.false_alarm_probability < 0.5:
        errors.append(
            f"[pipeline] false_alarm_probability must be in (0, 0.5), got {p.false_alarm_probability!r}"
        )
    if not (math.isfinite(p.f0_persistence_s) and 0.0 <= p.f0_persistence_s <= 1.0):
        errors.append(
            f"[pipeline] f0_persistence_s must be in [0, 1] s, got {p.f0_persistence_s!r}"
        )
    if p.min_positions < 9:
        errors.append(
            f"[pipeline] min_positions must be >= 9 (nine parameters, M1), got {p.min_positions}"
        )
    site = cfg.site
    latitude = 0.0 if site.latitude_deg is None else site.latitude_deg
    if latitude < -90.0:
        errors.append(
            f"[site] latitude_deg must be at least -90 (the south pole), got {latitude!r}"
        )
    if site.height_m <= -10_000.0:
        errors.append(
            f"[site] height_m must be above -10000 (below any ground), got {site.height_m!r}"
        )
    # Normal gravity is defined there only; beyond, the bounds said the key (it raised ValueError,
    # which ended the start without its section nor the other errors).
    if (
        abs(latitude) <= 90.0
        and -10_000.0 < site.height_m <= _UPPER_BOUNDS[("site", "height_m")][0]
    ):
        g = site.local_gravity_mps2
        if not 9.7 < g < 9.9:
            errors.append(
                f"[site] gravity {g!r} m/s² is not a value on the Earth's surface (9.7..9.9)"
            )
    for name in ("alert_min_interval_s", "alert_max_per_s"):
        _positive(errors, f"[mavlink] {name}", getattr(m, name))
    _period(errors, "[mavlink] heartbeat_period_s", m.heartbeat_period_s)
    try:
        check_vehicle(m.link.vehicle, error=SchemaError)
    except SchemaError as exc:
        errors.append(f"[mavlink] vehicle: {exc}")
    if m.enabled and not m.link.messages:
        errors.append("[mavlink] messages is empty: the link would read no IMU message")
    if not z.enabled and not m.enabled:
        errors.append("neither [zenoh] nor [mavlink] is enabled: the service would have no input")
    if z.enabled:
        try:
            check_frames_selector(z.frames_key)
        except ValueError as exc:
            errors.append(f"[zenoh] frames_key {exc}")
    # Zenoh takes the timeout in whole milliseconds: beyond a day it overflowed ("negative timeout")
    # and every delivery failed.
    if not 0 < z.ack_timeout_s <= ACK_TIMEOUT_MAX_S or z.min_acks < 1:
        errors.append(
            f"[zenoh] needs 0 < ack_timeout_s <= {ACK_TIMEOUT_MAX_S:g} and min_acks >= 1, got "
            f"{z.ack_timeout_s!r} and {z.min_acks!r}"
        )
    errors += _upper_bounds(cfg)
    for name in z.ack_from:
        try:
            check_receiver_name(name)
        except ValueError as exc:
            errors.append(f"[zenoh] ack_from: {exc}")
    if z.ack_from and z.event_ack is not AckMode.RECEIVER:
        errors.append('[zenoh] ack_from names receivers: it needs event_ack = "receiver"')
    if z.ack_from and len(set(z.ack_from)) < z.min_acks:
        errors.append(
            f"[zenoh] min_acks {z.min_acks} cannot be met by the {len(set(z.ack_from))} "
            f"receiver(s) of ack_from {list(z.ack_from)}"
        )
    return errors
