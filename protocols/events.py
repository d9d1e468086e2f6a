"""Fault events and service status: typed values and their versioned schemas.

An :class:`Event` is what the service reports: one failed predicate of one IMU
(F0 of methods.md M1 on a sample, F1…F9 of the M1 diagnosis against the
passport, or a stream-validity check). It travels to the durable outbox, to
Zenoh (msgpack), to MAVLink (STATUSTEXT) and to replay output (JSON lines).

Event id
--------
``event_id`` is 32 lowercase hex digits: the first 16 bytes of BLAKE2b over the
msgpack encoding of ``[tag, vehicle, imu, predicate, triad, axis, cause, t_s]``
where ``t_s`` is the *data* time (seconds, the time stamp of the sample that
completed the detection, packed as float64) — never a wall clock — followed by
``epoch`` when it is not 0. The same detection therefore gets the same id in a
retry, after a restart, and in a replay of the same log; the outbox and every
receiver deduplicate by it.

``epoch`` counts the source's new runs as the pipeline detects them (a reboot of the vehicle:
its time since boot or its ``seq`` went back; a new run id of the publisher), checkpointed with
the unit's state. A time since boot repeats across reboots: without the epoch the same fault at
the same uptime after a reboot had the id of the first and was dropped as already delivered.
Epoch 0 (a stream's first run, every replay of a log without a restart) leaves the id as it was.

Wire schema, version 2 (msgpack map; JSON lines use the same map)
-----------------------------------------------------------------
``type`` = ``"ins.health.event"``, ``v`` = 1 or 2, ``id`` (str, 32 hex), ``vehicle``
(str), ``imu`` (int 0..255), ``t_s`` (float, s), ``predicate`` (str,
:class:`Predicate`), ``triad`` (str :class:`~estimators.conventions.Triad` or
nil), ``axis`` (``x y z xy xz yz`` or nil), ``cause`` (str, a
:class:`~estimators.conventions.Cause` or :class:`StreamCause` value),
``estimate``, ``nominal``, ``tolerance``, ``sigma`` (finite float or nil),
``unit`` (str, unit of those four numbers: ``"1"`` dimensionless, ``"s"``,
``"m/s^2"``, ``"rad/s"``, ``"count"``, ``"degC"``), ``severity`` (str, lower-case
:class:`Severity` name), ``text`` (str, ≤ :data:`MAX_TEXT_CHARS`).

Version 3 adds ``epoch`` (int ≥ 1, present only then: an event of epoch 0 is written at version
1 or 2 as before). Version 2 adds the predicates ``gross`` (gross plausibility at rest,
:mod:`estimators.gross`), ``thrust_axis`` (in flight against GNSS, :mod:`estimators.thrust_gnss`)
the cause ``gravity_magnitude``, and the predicate ``cross_imu_norm`` (two IMUs' norms compared
in flight, :mod:`estimators.cross_imu_norm`); nothing else changed. An event is written with the lowest version that
holds it (:func:`event_version`): a version-1 reader keeps reading every other event, and is told a
gross event is of a newer schema rather than given an unknown predicate. All three versions are
read; a map naming what only a later version has is refused.

Status schema, version 2: ``type`` = ``"ins.health.status"``, ``v`` = 2,
``vehicle``, ``service`` (instance name), ``t_s`` (service clock, s since the
Unix epoch), ``counters`` (map str → int ≥ 0), ``imus`` (array of maps
``{imu, state, samples, last_t_s, positions, detail, coverage}``), ``coverage``
an array of maps, one per check of the IMU
(:meth:`estimators.coverage.CheckCoverage.to_dict`: what ran, on how much, its
minimum detectable fault, and why a check did not run). Version 1 (no
``coverage``) is still read, with no coverage. A coverage entry whose ``check`` is a name this
reader does not know is a newer writer's check (new checks are added within version 2): it is
kept as read in ``ImuStatus.unknown_coverage`` and written back unchanged, and the rest of the
status is read; any other unusable entry refuses the status.

Service status schema, version 1: ``type`` = ``"ins.health.service_status"``, ``v`` = 1, ``service``
(instance name), ``t_s`` (s since the Unix epoch), ``vehicles`` (array of the vehicle ids it
serves, possibly empty), ``counters`` (map str → int ≥ 0, the instance's ``service.*`` counters):
what an instance says of itself from its start, before any vehicle and whatever their number.
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from enum import Enum, StrEnum
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from estimators.conventions import AXES, Cause, Triad
from estimators.coverage import Check, CheckCoverage
from protocols._schema import (
    MAX_MESSAGE_BYTES,
    Reason,
    check_header,
    check_imu,
    check_vehicle,
    enum_field,
    field,
    first_enum,
    float_field,
    pack,
    unpack_map,
)
from protocols.event_kinds import EventError as EventError
from protocols.event_kinds import Predicate as Predicate
from protocols.event_kinds import Severity as Severity
from protocols.event_kinds import StreamCause as StreamCause

if TYPE_CHECKING:  # the diagnosis pulls in scipy.stats: too heavy an import for a wire schema
    from estimators.diagnosis import Finding

EVENT_TYPE = "ins.health.event"
EVENT_VERSION = 3
SUPPORTED_EVENT_VERSIONS = (1, 2, 3)
MAX_EPOCH = 2**32 - 1
STATUS_TYPE = "ins.health.status"
STATUS_VERSION = 2
SUPPORTED_STATUS_VERSIONS = (1, 2)
SERVICE_STATUS_TYPE = "ins.health.service_status"
SERVICE_STATUS_VERSION = 1
MAX_EVENT_BYTES = 64 * 1024
MAX_STATUS_BYTES = MAX_MESSAGE_BYTES
MAX_TEXT_CHARS = 1000
EVENT_AXES = (*AXES, "xy", "xz", "yz")
"""Valid ``axis`` values: one sensor axis, or an axis pair for non-orthogonality (conventions.PARAM_AXIS)."""


_V2_ONLY: frozenset[Enum] = frozenset(
    {
        Predicate.GROSS,
        Predicate.THRUST_AXIS,
        StreamCause.GRAVITY_MAGNITUDE,
        Predicate.CROSS_IMU_NORM,
    }
)
"""What only schema version 2 holds (module docstring)."""

EventCause = Cause | StreamCause


@dataclass(frozen=True)
class Event:
    """One detection. Build with :func:`make_event` or :func:`event_from_finding` (they derive the id).

    Attributes
    ----------
    event_id : 32 hex digits, stable across retries and replays (module docstring).
    vehicle, imu : the IMU.
    t_s : data time of the sample that completed the detection, s.
    predicate, triad, axis, cause : what failed and why.
    estimate, nominal, tolerance, sigma : the number behind it, the passport value,
        the allowed deviation and the estimate's standard deviation, in ``unit``.
    unit : unit of those four numbers.
    severity : :class:`Severity` (MAV_SEVERITY values).
    text : one human sentence.
    epoch : the source's run (module docstring; 0: its first).
    """

    event_id: str
    vehicle: str
    imu: int
    t_s: float
    predicate: Predicate
    triad: Triad | None
    axis: str | None
    cause: EventCause
    estimate: float | None
    nominal: float | None
    tolerance: float | None
    sigma: float | None
    unit: str
    severity: Severity
    text: str
    epoch: int = 0

    def __post_init__(self) -> None:
        check_vehicle(self.vehicle, error=EventError)
        if type(self.epoch) is not int or not 0 <= self.epoch <= MAX_EPOCH:
            raise EventError(
                Reason.BAD_VALUE, f"epoch must be an int in [0, {MAX_EPOCH}], got {self.epoch!r}"
            )
        check_imu(self.imu, error=EventError)
        if not (
            isinstance(self.event_id, str)
            and len(self.event_id) == 32
            and all(c in "0123456789abcdef" for c in self.event_id)
        ):
            raise EventError(
                Reason.BAD_VALUE,
                f"event id must be 32 lower-case hex digits, got {self.event_id!r}",
            )
        if (
            isinstance(self.t_s, bool)
            or not isinstance(self.t_s, (int, float))
            or not math.isfinite(self.t_s)
        ):
            raise EventError(Reason.BAD_VALUE, f"t_s must be a finite number, got {self.t_s!r}")
        object.__setattr__(self, "t_s", float(self.t_s))
        object.__setattr__(self, "predicate", Predicate.parse(self.predicate))
        object.__setattr__(self, "cause", _parse_cause(self.cause))
        object.__setattr__(self, "severity", _parse_severity(self.severity))
        if self.triad is not None:
            object.__setattr__(self, "triad", Triad(self.triad))
        if self.axis is not None and self.axis not in EVENT_AXES:
            raise EventError(
                Reason.BAD_VALUE, f"axis must be one of {EVENT_AXES} or None, got {self.axis!r}"
            )
        for name in ("estimate", "nominal", "tolerance", "sigma"):
            value = getattr(self, name)
            if value is None:
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
            ):
                raise EventError(
                    Reason.NON_FINITE if isinstance(value, float) else Reason.WRONG_TYPE,
                    f"{name} must be a finite number or None, got {value!r}",
                )
            object.__setattr__(self, name, float(value))
        if not isinstance(self.text, str) or len(self.text) > MAX_TEXT_CHARS:
            raise EventError(
                Reason.BAD_VALUE, f"text must be a str of at most {MAX_TEXT_CHARS} characters"
            )
        if not isinstance(self.unit, str) or len(self.unit) > 16:
            raise EventError(Reason.BAD_VALUE, f"unit must be a short str, got {self.unit!r}")

    @property
    def sensor(self) -> str | None:
        """``"accel"`` or ``"gyro"`` (None when the event is about the whole IMU)."""
        return None if self.triad is None else self.triad.value


def event_id(
    *,
    vehicle: str,
    imu: int,
    predicate: Predicate,
    triad: Triad | None,
    axis: str | None,
    cause: EventCause,
    t_s: float,
    epoch: int = 0,
) -> str:
    """The stable id of a detection (module docstring): 32 hex digits."""
    fields = [
        EVENT_TYPE,
        vehicle,
        int(imu),
        Predicate.parse(predicate).value,
        None if triad is None else Triad(triad).value,
        axis,
        _parse_cause(cause).value,
        struct.pack("<d", float(t_s)),
    ]
    key = pack([*fields, int(epoch)] if epoch else fields)
    return hashlib.blake2b(key, digest_size=16).hexdigest()


def make_event(
    *,
    vehicle: str,
    imu: int,
    t_s: float,
    predicate: Predicate | str | int,
    cause: EventCause | str,
    severity: Severity | int,
    triad: Triad | str | None = None,
    axis: str | None = None,
    estimate: float | None = None,
    nominal: float | None = None,
    tolerance: float | None = None,
    sigma: float | None = None,
    unit: str = "1",
    text: str | None = None,
    epoch: int = 0,
) -> Event:
    """The generic constructor: any predicate (F0, stream validity, cross-IMU, …), id derived, text defaulted.

    ``t_s`` is the data time of the sample that completed the detection and ``epoch`` the
    source's run (both enter the id); ``text`` defaults to :func:`describe` of the event.
    """
    predicate = Predicate.parse(predicate)
    cause = _parse_cause(cause)
    triad = None if triad is None else Triad(triad)
    eid = event_id(
        vehicle=vehicle,
        imu=imu,
        predicate=predicate,
        triad=triad,
        axis=axis,
        cause=cause,
        t_s=t_s,
        epoch=epoch,
    )
    event = Event(
        eid,
        vehicle,
        imu,
        t_s,
        predicate,
        triad,
        axis,
        cause,
        estimate,
        nominal,
        tolerance,
        sigma,
        unit,
        Severity(severity),
        text or "",
        epoch,
    )
    return event if text is not None else replace(event, text=describe(event))


def event_from_finding(
    finding: Finding,
    *,
    vehicle: str,
    imu: int,
    t_s: float,
    severity: Severity = Severity.ERROR,
    epoch: int = 0,
) -> Event:
    """An event for a failed predicate F1…F9 of the M1 diagnosis (``estimators.diagnosis.Finding``).

    The numbers of a finding are normalized parameters (dimensionless, methods.md
    M1: zero signal ``b = bias/g`` or ``bias/Ω``, scale-factor error ``e``,
    non-orthogonality ``δ``), so the unit is ``"1"``.
    """
    return make_event(
        vehicle=vehicle,
        imu=imu,
        t_s=t_s,
        predicate=finding.predicate,
        cause=finding.cause,
        severity=severity,
        triad=finding.triad,
        axis=finding.axis,
        estimate=finding.estimate,
        nominal=finding.nominal,
        tolerance=finding.tolerance,
        sigma=finding.sigma,
        unit="1",
        epoch=epoch,
    )


_CAUSE_WORDS = {
    Cause.ZERO_SIGNAL: "zero signal",
    Cause.SCALE_FACTOR: "scale factor error",
    Cause.NON_ORTHOGONALITY: "non-orthogonality",
    StreamCause.OUT_OF_SHELL: "output off the unit sphere",
    StreamCause.NO_DATA: "no samples",
    StreamCause.STUCK_VALUE: "stuck value",
    StreamCause.REJECTED_SAMPLES: "rejected samples",
    StreamCause.DISAGREEMENT: "disagrees with the other IMUs",
    StreamCause.TEMPERATURE_RANGE: "temperature outside the passport range",
    StreamCause.RECOVERED: "recovered",
    StreamCause.GRAVITY_MAGNITUDE: "|a| − g at rest",
}
_TRIAD_WORDS = {Triad.ACCEL: "accelerometer", Triad.GYRO: "gyro"}


def cause_words(cause: EventCause) -> str:
    """The cause in a few plain words."""
    return _CAUSE_WORDS[_parse_cause(cause)]


def describe(event: Event) -> str:
    """One human sentence naming vehicle, instance, sensor, cause and the number, e.g.

    ``"v1 IMU0 accelerometer y: scale factor error 2.1e-03 (nominal 0, tolerance 1e-03, sigma 1e-04) [F5]"``.
    """
    where = f"{event.vehicle} IMU{event.imu}"
    if event.triad is not None:
        where += f" {_TRIAD_WORDS[event.triad]}"
    if event.axis is not None:
        where += f" {event.axis}"
    unit = "" if event.unit == "1" else f" {event.unit}"
    what = cause_words(event.cause)
    if event.estimate is not None:
        what += f" {event.estimate:.3g}{unit}"
    extra = [
        f"{name} {value:.3g}"
        for name, value in (
            ("nominal", event.nominal),
            ("tolerance", event.tolerance),
            ("sigma", event.sigma),
        )
        if value is not None
    ]
    if extra:
        what += f" ({', '.join(extra)})"
    return f"{where}: {what} [{event.predicate.value}]"


def event_version(event: Event) -> int:
    """The lowest schema version that holds ``event`` (module docstring)."""
    if event.epoch:
        return 3
    return 2 if event.predicate in _V2_ONLY or event.cause in _V2_ONLY else 1


def event_to_dict(event: Event) -> dict[str, Any]:
    """The schema map (module docstring) of an event, at :func:`event_version`."""
    out = {
        "type": EVENT_TYPE,
        "v": event_version(event),
        "id": event.event_id,
        "vehicle": event.vehicle,
        "imu": event.imu,
        "t_s": event.t_s,
        "predicate": event.predicate.value,
        "triad": None if event.triad is None else event.triad.value,
        "axis": event.axis,
        "cause": event.cause.value,
        "estimate": event.estimate,
        "nominal": event.nominal,
        "tolerance": event.tolerance,
        "sigma": event.sigma,
        "unit": event.unit,
        "severity": event.severity.name.lower(),
        "text": event.text,
    }
    if event.epoch:
        out["epoch"] = event.epoch
    return out


def event_from_dict(obj: Mapping[str, Any]) -> Event:
    """Validate a schema map and build the :class:`Event`; raises :class:`EventError`.

    The id is checked against the fields: a map whose id does not match its
    content is rejected (``bad_value``), so a corrupted or forged id cannot
    break deduplication.
    """
    if not isinstance(obj, Mapping):
        raise EventError(Reason.NOT_A_MAP, f"an event must be a map, got {type(obj).__name__}")
    obj = dict(obj)
    version = check_header(
        obj, type_tag=EVENT_TYPE, versions=SUPPORTED_EVENT_VERSIONS, error=EventError
    )
    severity_name = field(obj, "severity", str, error=EventError)
    if severity_name.upper() not in Severity.__members__ or severity_name != severity_name.lower():
        raise EventError(
            Reason.BAD_VALUE,
            f"severity {severity_name!r} is not one of {[s.name.lower() for s in Severity]}",
        )
    axis = field(obj, "axis", str, optional=True, error=EventError)
    if axis is not None and axis not in EVENT_AXES:
        raise EventError(Reason.BAD_VALUE, f"axis {axis!r} is not one of {EVENT_AXES}")
    event = Event(
        event_id=field(obj, "id", str, error=EventError),
        vehicle=check_vehicle(field(obj, "vehicle", str, error=EventError), error=EventError),
        imu=check_imu(field(obj, "imu", int, error=EventError), error=EventError),
        t_s=float_field(obj, "t_s", error=EventError),
        predicate=enum_field(obj, "predicate", (Predicate,), error=EventError),
        triad=enum_field(obj, "triad", (Triad,), optional=True, error=EventError),
        axis=axis,
        cause=enum_field(obj, "cause", (Cause, StreamCause), error=EventError),
        estimate=float_field(obj, "estimate", optional=True, error=EventError),
        nominal=float_field(obj, "nominal", optional=True, error=EventError),
        tolerance=float_field(obj, "tolerance", optional=True, error=EventError),
        sigma=float_field(obj, "sigma", optional=True, error=EventError),
        unit=field(obj, "unit", str, error=EventError),
        severity=Severity[severity_name.upper()],
        text=field(obj, "text", str, error=EventError),
        epoch=field(obj, "epoch", int, error=EventError) if version >= 3 else 0,
    )
    if version >= 3 and event.epoch == 0:
        raise EventError(Reason.BAD_VALUE, "an event of schema version 3 has an epoch >= 1")
    expected = event_id(
        vehicle=event.vehicle,
        imu=event.imu,
        predicate=event.predicate,
        triad=event.triad,
        axis=event.axis,
        cause=event.cause,
        t_s=event.t_s,
        epoch=event.epoch,
    )
    if event.event_id != expected:
        raise EventError(
            Reason.BAD_VALUE,
            f"event id {event.event_id} does not match its fields (expected {expected})",
        )
    if version < event_version(event):
        raise EventError(
            Reason.BAD_VALUE,
            f"predicate {event.predicate.value!r} with cause {event.cause.value!r} needs event schema "
            f"version {event_version(event)}, the map says {version}",
        )
    return event


def encode_event(event: Event) -> bytes:
    """msgpack bytes of an event (schema version :func:`event_version`)."""
    return pack(event_to_dict(event))


def decode_event(data: bytes, *, max_bytes: int = MAX_EVENT_BYTES) -> Event:
    """Decode and validate msgpack bytes; raises :class:`EventError` with a reason."""
    return event_from_dict(unpack_map(data, error=EventError, max_bytes=max_bytes))


def event_to_json(event: Event) -> str:
    """One JSON line (no newline), keys sorted: the same map as msgpack."""
    return json.dumps(event_to_dict(event), sort_keys=True, separators=(",", ":"), allow_nan=False)


def event_from_json(text: str) -> Event:
    """Parse one JSON line; raises :class:`EventError` with a reason."""
    if not isinstance(text, str):
        raise EventError(Reason.WRONG_TYPE, f"expected str, got {type(text).__name__}")
    if len(text) > MAX_EVENT_BYTES:
        raise EventError(
            Reason.TOO_LARGE, f"{len(text)} characters exceeds the limit of {MAX_EVENT_BYTES}"
        )
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except EventError:
        raise
    except ValueError as exc:
        raise EventError(Reason.MALFORMED, f"not valid JSON ({exc})") from None
    return event_from_dict(obj)


def _reject_constant(name: str) -> float:
    raise EventError(Reason.NON_FINITE, f"JSON constant {name} is not allowed")


def _parse_cause(value: Any) -> EventCause:
    cause = first_enum(value, (Cause, StreamCause))
    if cause is None:
        raise EventError(Reason.BAD_VALUE, f"unknown cause {value!r}")
    return cause


def _parse_severity(value: Any) -> Severity:
    try:
        return Severity(value)
    except ValueError:
        raise EventError(
            Reason.BAD_VALUE, f"severity must be a MAV_SEVERITY value 0..7, got {value!r}"
        ) from None


# --------------------------------------------------------------------------- status


class ImuState(StrEnum):
    """Health state of one IMU as the status topic reports it."""

    STARTING = "starting"
    OK = "ok"
    WARNING = "warning"
    FAULT = "fault"
    NO_DATA = "no_data"
    NO_PASSPORT = "no_passport"


@dataclass(frozen=True)
class ImuStatus:
    """Per-IMU part of a status message.

    Attributes
    ----------
    imu : IMU index.
    state : :class:`ImuState`.
    samples : samples accepted so far.
    last_t_s : data time of the last accepted sample, s (None before the first).
    positions : static positions accumulated for the diagnosis.
    detail : short free text (e.g. the last failed predicate).
    coverage : what each check of the IMU tested so far (empty from a version-1 status).
    unknown_coverage : coverage entries of checks this reader does not know, as read (a newer
        writer's: each names its ``check``; module docstring).
    """

    imu: int
    state: ImuState
    samples: int = 0
    last_t_s: float | None = None
    positions: int = 0
    detail: str = ""
    coverage: tuple[CheckCoverage, ...] = ()
    unknown_coverage: tuple[dict[str, Any], ...] = ()

    def __post_init__(self) -> None:
        check_imu(self.imu, error=EventError)
        object.__setattr__(self, "state", ImuState(self.state))
        for name in ("samples", "positions"):
            value = getattr(self, name)
            if type(value) is not int or value < 0:
                raise EventError(Reason.BAD_VALUE, f"{name} must be an int >= 0, got {value!r}")


@dataclass(frozen=True)
class Status:
    """The periodic status of one vehicle as seen by one service instance.

    Attributes
    ----------
    vehicle : vehicle id.
    service : name of the service instance that publishes it.
    t_s : service clock at publication, s since the Unix epoch.
    counters : name → count (accepted frames, rejections by reason, drops, events, …).
    imus : per-IMU state.
    """

    vehicle: str
    service: str
    t_s: float
    counters: Mapping[str, int] = dc_field(default_factory=dict)
    imus: tuple[ImuStatus, ...] = ()

    def __post_init__(self) -> None:
        check_vehicle(self.vehicle, error=EventError)
        if not isinstance(self.service, str) or not self.service:
            raise EventError(
                Reason.BAD_VALUE, f"service must be a non-empty str, got {self.service!r}"
            )
        for name, value in self.counters.items():
            if not isinstance(name, str) or type(value) is not int or value < 0:
                raise EventError(
                    Reason.BAD_VALUE,
                    f"counter {name!r} must be a str name with an int >= 0, got {value!r}",
                )
        object.__setattr__(self, "counters", MappingProxyType(dict(self.counters)))
        object.__setattr__(self, "imus", tuple(self.imus))


def status_to_dict(status: Status) -> dict[str, Any]:
    """The schema map of a status message (what :func:`encode_status` packs)."""
    return {
        "type": STATUS_TYPE,
        "v": STATUS_VERSION,
        "vehicle": status.vehicle,
        "service": status.service,
        "t_s": float(status.t_s),
        "counters": dict(status.counters),
        "imus": [
            {
                "imu": s.imu,
                "state": s.state.value,
                "samples": s.samples,
                "last_t_s": s.last_t_s,
                "positions": s.positions,
                "detail": s.detail,
                "coverage": [c.to_dict() for c in s.coverage] + list(s.unknown_coverage),
            }
            for s in status.imus
        ],
    }


def encode_status(status: Status) -> bytes:
    """msgpack bytes of a status message (schema version :data:`STATUS_VERSION`)."""
    return pack(status_to_dict(status))


def decode_status(data: bytes, *, max_bytes: int = MAX_STATUS_BYTES) -> Status:
    """Decode and validate a status message; raises :class:`EventError` with a reason."""
    obj = unpack_map(data, max_bytes=max_bytes, error=EventError)
    version = check_header(
        obj, type_tag=STATUS_TYPE, versions=SUPPORTED_STATUS_VERSIONS, error=EventError
    )
    imus = []
    for item in field(obj, "imus", list, error=EventError):
        if not isinstance(item, dict):
            raise EventError(
                Reason.WRONG_TYPE, f"each imus entry must be a map, got {type(item).__name__}"
            )
        known, unknown = (
            ((), ()) if version < 2 else _coverage(field(item, "coverage", list, error=EventError))
        )
        imus.append(
            ImuStatus(
                imu=field(item, "imu", int, error=EventError),
                state=enum_field(item, "state", (ImuState,), error=EventError),
                samples=field(item, "samples", int, error=EventError),
                last_t_s=float_field(item, "last_t_s", optional=True, error=EventError),
                positions=field(item, "positions", int, error=EventError),
                detail=field(item, "detail", str, error=EventError),
                coverage=known,
                unknown_coverage=unknown,
            )
        )
    return Status(
        vehicle=field(obj, "vehicle", str, error=EventError),
        service=field(obj, "service", str, error=EventError),
        t_s=float_field(obj, "t_s", error=EventError),
        counters=field(obj, "counters", dict, error=EventError),
        imus=tuple(imus),
    )


_CHECKS = frozenset(c.value for c in Check)


def _coverage(
    items: list[Any],
) -> tuple[tuple[CheckCoverage, ...], tuple[dict[str, Any], ...]]:
    """The ``coverage`` of a version-2 status IMU entry: the entries of known checks, and those of
    checks a newer writer added, as read; :class:`EventError` for an entry it cannot read."""
    known: list[CheckCoverage] = []
    unknown: list[dict[str, Any]] = []
    for c in items:
        if isinstance(c, dict) and isinstance(c.get("check"), str) and c["check"] not in _CHECKS:
            unknown.append(c)
            continue
        try:
            known.append(CheckCoverage.from_dict(c))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise EventError(Reason.BAD_VALUE, f"unusable coverage entry: {exc!r}") from None
    return tuple(known), tuple(unknown)


@dataclass(frozen=True)
class ServiceStatus:
    """The periodic status of one service instance, vehicles or none (module docstring).

    Attributes
    ----------
    service : instance name.
    t_s : service clock at publication, s since the Unix epoch.
    vehicles : the vehicles it serves now.
    counters : the instance's counters (``service.*``).
    """

    service: str
    t_s: float
    vehicles: tuple[str, ...] = ()
    counters: Mapping[str, int] = dc_field(default_factory=dict)

    def __post_init__(self) -> None:
        for vehicle in self.vehicles:
            check_vehicle(vehicle, error=EventError)
        object.__setattr__(self, "vehicles", tuple(self.vehicles))
        # The same rule as a vehicle's status counters.
        Status(vehicle=self.service, service=self.service, t_s=self.t_s, counters=self.counters)
        object.__setattr__(self, "counters", MappingProxyType(dict(self.counters)))


def encode_service_status(status: ServiceStatus) -> bytes:
    """msgpack bytes of a service status (schema version :data:`SERVICE_STATUS_VERSION`)."""
    return pack(
        {
            "type": SERVICE_STATUS_TYPE,
            "v": SERVICE_STATUS_VERSION,
            "service": status.service,
            "t_s": float(status.t_s),
            "vehicles": list(status.vehicles),
            "counters": dict(status.counters),
        }
    )


def decode_service_status(data: bytes, *, max_bytes: int = MAX_STATUS_BYTES) -> ServiceStatus:
    """Decode and validate a service status; raises :class:`EventError` with a reason."""
    obj = unpack_map(data, max_bytes=max_bytes, error=EventError)
    check_header(obj, type_tag=SERVICE_STATUS_TYPE, versions=(1,), error=EventError)
    vehicles = field(obj, "vehicles", list, error=EventError)
    if not all(isinstance(v, str) for v in vehicles):
        raise EventError(Reason.WRONG_TYPE, "vehicles must be an array of str")
    return ServiceStatus(
        service=field(obj, "service", str, error=EventError),
        t_s=float_field(obj, "t_s", error=EventError),
        vehicles=tuple(vehicles),
        counters=field(obj, "counters", dict, error=EventError),
    )
