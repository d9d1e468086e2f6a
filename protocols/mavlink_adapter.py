"""MAVLink transport (pymavlink): IMU messages in as SI batches; HEARTBEAT and STATUSTEXT alerts out.

Input messages and their units (converted once, here, to the SI of
:mod:`estimators.conventions`)
=================  ============  ==================  ==================  ===================
message            time          accel               gyro                temperature
=================  ============  ==================  ==================  ===================
``RAW_IMU``        time_usec µs  raw × scale          raw × scale          raw × scale (0: none)
``SCALED_IMU[23]`` time_boot_ms  mG (1e-3 g0)         mrad/s              cdegC (0: none)
``HIGHRES_IMU``    time_usec µs  m/s²                rad/s               °C if fields_updated has bit 4096
=================  ============  ==================  ==================  ===================

``RAW_IMU`` carries raw sensor counts whose scale the standard leaves to the
sender; :data:`RAW_IMU_ARDUPILOT` (the default) is what ArduPilot sends: mG,
mrad/s and cdegC, the same as ``SCALED_IMU``. Configure :class:`ImuScale` for
other senders. ``g0`` is :data:`~estimators.conventions.STANDARD_GRAVITY_MPS2`
(a unit, as in ArduPilot's ``GRAVITY_MSS``). Axes and signs are passed through:
MAVLink's body frame is FRD and its accelerations are specific force, which is
the convention of this project (a level unit reads −g on z: +g along *up*).
Time is the sender's boot clock; ``time_boot_ms`` wraps after 49.7 days.

Each message type maps to an IMU index (:data:`DEFAULT_IMU_INDEX`); for
``RAW_IMU`` and ``HIGHRES_IMU`` the message's own ``id`` field is added. An
autopilot that sends two types for the same IMU (PX4 may send HIGHRES_IMU and
SCALED_IMU) should have one of them left out of ``messages``.

pymavlink global state
----------------------
pymavlink chooses its wire protocol and dialect through environment variables
read at import (``MAVLINK20``, ``MAVLINK_DIALECT``) and switches them *globally*
(``os.environ`` and ``mavutil.mavlink``) when it first sees a MAVLink 2 byte.
This module never relies on that: it imports the MAVLink 2 ``ardupilotmega``
dialect module explicitly, gives every connection its own parser/encoder of
that dialect, and marks the connection as already MAVLink 2 so pymavlink's
auto-switch never runs. A MAVLink 2 parser also reads MAVLink 1 packets.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Any, Literal, Protocol, TypeAlias

import numpy as np
from numpy.typing import ArrayLike
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from estimators.conventions import Cause, Triad
from protocols._handoff import ThreadToAsyncRing
from protocols.events import Event, Predicate, Severity, StreamCause
from protocols.frames import BatchSource, FrameError, SampleBatch
from protocols.log_rate import LogRate
from protocols.mavlink_settings import (
    DEFAULT_IMU_INDEX,
    GPS_RAW_INT_FIELDS,
    MILLI_UNITS,
    RAW_IMU_ARDUPILOT,
    ImuMessage,
    ImuScale,
    LinkRejection,
    MavlinkSettings,
)

STATUSTEXT_MAX_CHARS = 50
"""Characters of one STATUSTEXT (the MAVLink field; ground stations show one message per line)."""


MavlinkMessage: TypeAlias = mavlink2.MAVLink_message
"""Any message of the dialect (pymavlink ships no type stubs: to mypy this is ``Any``)."""

_HIGHRES_TEMPERATURE_BIT = mavlink2.HIGHRES_IMU_UPDATED_TEMPERATURE
_HIGHRES_TRIADS_BITS = (
    mavlink2.HIGHRES_IMU_UPDATED_XACC
    | mavlink2.HIGHRES_IMU_UPDATED_YACC
    | mavlink2.HIGHRES_IMU_UPDATED_ZACC
    | mavlink2.HIGHRES_IMU_UPDATED_XGYRO
    | mavlink2.HIGHRES_IMU_UPDATED_YGYRO
    | mavlink2.HIGHRES_IMU_UPDATED_ZGYRO
)
"""HIGHRES_IMU ``fields_updated`` bits of the accelerometer and gyro fields."""
# A child of the daemon's logger (service.log_setup.LOGGER_NAME), so its lines take the daemon's format.
_log = logging.getLogger("ins_health.mavlink")


# --------------------------------------------------------------------------- in


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample decoded from a MAVLink message, SI units (before it becomes a batch)."""

    imu: int
    t_s: float
    accel_mps2: tuple[float, float, float]
    gyro_rps: tuple[float, float, float]
    temp_c: float | None


def highres_triads_updated(msg: MavlinkMessage) -> bool:
    """False for a HIGHRES_IMU message whose ``fields_updated`` leaves out an accelerometer or gyro
    field (no new measurement there: :attr:`LinkRejection.FIELDS_NOT_UPDATED`); True otherwise."""
    return msg.get_type() != "HIGHRES_IMU" or bool(_triads_updated(msg.fields_updated))


def _triads_updated(fields_updated: Any) -> Any:
    """Whether ``fields_updated`` (an int, or an integer array) flags all six triad fields."""
    return fields_updated & _HIGHRES_TRIADS_BITS == _HIGHRES_TRIADS_BITS


def decode_imu_message(
    msg: MavlinkMessage,
    *,
    raw_scale: ImuScale = RAW_IMU_ARDUPILOT,
    imu_index: Mapping[ImuMessage, int] = DEFAULT_IMU_INDEX,
) -> ImuSample | None:
    """SI sample of a RAW_IMU / SCALED_IMU* / HIGHRES_IMU message; ``None`` for other messages.

    ``msg`` is a pymavlink message object (live link or log). Units: module table.
    """
    try:
        kind = ImuMessage(msg.get_type())
    except ValueError:
        return None
    base = imu_index.get(kind)
    if base is None:
        return None
    if kind is ImuMessage.HIGHRES_IMU:
        temp = float(msg.temperature) if msg.fields_updated & _HIGHRES_TEMPERATURE_BIT else None
        return ImuSample(
            base + int(getattr(msg, "id", 0)),
            msg.time_usec * 1e-6,
            (float(msg.xacc), float(msg.yacc), float(msg.zacc)),
            (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro)),
            temp,
        )
    if kind is ImuMessage.RAW_IMU:
        scale, t_s, imu = raw_scale, msg.time_usec * 1e-6, base + int(getattr(msg, "id", 0))
    else:
        scale, t_s, imu = MILLI_UNITS, msg.time_boot_ms * 1e-3, base
    # The temperature extension field is 0 when the sender has none (MAVLink spec; a real 0 °C is sent as 1).
    raw_temp = int(getattr(msg, "temperature", 0))
    ka, kg = scale.accel_mps2_per_lsb, scale.gyro_rps_per_lsb
    return ImuSample(
        imu,
        t_s,
        (msg.xacc * ka, msg.yacc * ka, msg.zacc * ka),
        (msg.xgyro * kg, msg.ygyro * kg, msg.zgyro * kg),
        raw_temp * scale.temp_c_per_lsb if raw_temp else None,
    )


# --------------------------------------------------------------------------- out: typed builders


def imu_message(
    kind: ImuMessage,
    *,
    t_s: float,
    accel_mps2: ArrayLike,
    gyro_rps: ArrayLike,
    temp_c: float | None = None,
    imu_id: int = 0,
    raw_scale: ImuScale = RAW_IMU_ARDUPILOT,
) -> MavlinkMessage:
    """Build an IMU message from SI values (the inverse of :func:`decode_imu_message`; a simulated autopilot).

    Integer messages round to the nearest count; ``imu_id`` goes into the
    ``id`` field of RAW_IMU and HIGHRES_IMU (the SCALED_IMU* number is the IMU).
    """
    kind = ImuMessage(kind)
    a = [float(v) for v in np.asarray(accel_mps2, float).reshape(3)]
    g = [float(v) for v in np.asarray(gyro_rps, float).reshape(3)]
    if kind is ImuMessage.HIGHRES_IMU:
        return mavlink2.MAVLink_highres_imu_message(
            time_usec=round(t_s * 1e6),
            xacc=a[0],
            yacc=a[1],
            zacc=a[2],
            xgyro=g[0],
            ygyro=g[1],
            zgyro=g[2],
            xmag=0.0,
            ymag=0.0,
            zmag=0.0,
            abs_pressure=0.0,
            diff_pressure=0.0,
            pressure_alt=0.0,
            temperature=0.0 if temp_c is None else float(temp_c),
            fields_updated=0b111111 | (0 if temp_c is None else _HIGHRES_TEMPERATURE_BIT),
            id=int(imu_id),
        )
    scale = raw_scale if kind is ImuMessage.RAW_IMU else MILLI_UNITS
    ia = [_count(v / scale.accel_mps2_per_lsb) for v in a]
    ig = [_count(v / scale.gyro_rps_per_lsb) for v in g]
    it = 0 if temp_c is None else (_count(temp_c / scale.temp_c_per_lsb) or 1)
    common = dict(
        xacc=ia[0],
        yacc=ia[1],
        zacc=ia[2],
        xgyro=ig[0],
        ygyro=ig[1],
        zgyro=ig[2],
        xmag=0,
        ymag=0,
        zmag=0,
        temperature=it,
    )
    if kind is ImuMessage.RAW_IMU:
        return mavlink2.MAVLink_raw_imu_message(
            time_usec=round(t_s * 1e6), id=int(imu_id), **common
        )
    cls = {
        ImuMessage.SCALED_IMU: mavlink2.MAVLink_scaled_imu_message,
        ImuMessage.SCALED_IMU2: mavlink2.MAVLink_scaled_imu2_message,
        ImuMessage.SCALED_IMU3: mavlink2.MAVLink_scaled_imu3_message,
    }[kind]
    return cls(time_boot_ms=round(t_s * 1e3), **common)


def _count(value: float) -> int:
    """Nearest int16 count; out of range is an error (a saturated field would lie)."""
    n = round(value)
    if not -32768 <= n <= 32767:
        raise ValueError(f"{value:.1f} counts do not fit the int16 field of the message")
    return n


def heartbeat_message(*, system_status: int = mavlink2.MAV_STATE_ACTIVE) -> MavlinkMessage:
    """HEARTBEAT of an onboard computer component (MAV_TYPE_ONBOARD_CONTROLLER, no autopilot)."""
    return mavlink2.MAVLink_heartbeat_message(
        type=mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot=mavlink2.MAV_AUTOPILOT_INVALID,
        base_mode=0,
        custom_mode=0,
        system_status=int(system_status),
        mavlink_version=3,
    )


def statustext_messages(
    text: str, *, severity: Severity, chunk_id: int = 0
) -> list[MavlinkMessage]:
    """STATUSTEXT message(s) for ``text`` (ASCII; other characters become ``?``).

    Up to 50 characters: one message with ``id`` 0 (the MAVLink rule for a
    single chunk). Longer: 50-character chunks sharing ``chunk_id`` (1..65535)
    with ``chunk_seq`` 0, 1, …; a final shorter (possibly empty) chunk marks
    the end, so ground stations that reassemble MAVLink 2 chunks show the whole text.
    """
    data = text.encode("ascii", "replace")
    if len(data) <= STATUSTEXT_MAX_CHARS:
        return [
            mavlink2.MAVLink_statustext_message(
                severity=int(Severity(severity)), text=data, id=0, chunk_seq=0
            )
        ]
    if not 1 <= chunk_id <= 65535:
        raise ValueError(f"a long text needs a chunk_id in 1..65535, got {chunk_id}")
    pieces = [data[i : i + STATUSTEXT_MAX_CHARS] for i in range(0, len(data), STATUSTEXT_MAX_CHARS)]
    if len(pieces[-1]) == STATUSTEXT_MAX_CHARS:
        pieces.append(b"")
    if len(pieces) > 256:
        raise ValueError(f"text of {len(data)} characters needs more than 256 chunks")
    return [
        mavlink2.MAVLink_statustext_message(
            severity=int(Severity(severity)), text=p, id=chunk_id, chunk_seq=i
        )
        for i, p in enumerate(pieces)
    ]


_SENSOR_ABBREV = {Triad.ACCEL: "ACC", Triad.GYRO: "GYR"}
_CAUSE_ABBREV = {
    Cause.ZERO_SIGNAL: "bias",
    Cause.SCALE_FACTOR: "scale",
    Cause.NON_ORTHOGONALITY: "nonorth",
    StreamCause.OUT_OF_SHELL: "off-sphere",
    StreamCause.NO_DATA: "no data",
    StreamCause.STUCK_VALUE: "stuck",
    StreamCause.REJECTED_SAMPLES: "rejects",
    StreamCause.DISAGREEMENT: "disagree",
    StreamCause.TEMPERATURE_RANGE: "temp range",
    StreamCause.RECOVERED: "recovered",
    StreamCause.GRAVITY_MAGNITUDE: "|a|-g",
}
_UNIT_ABBREV = {"1": "", "s": "s", "m/s^2": "m/s2", "rad/s": "rad/s", "count": "", "degC": "C"}


def alert_text(event: Event) -> str:
    """The ≤ 50-character STATUSTEXT line of an event.

    Rule: ``IMU<n> <SENSOR> <AXIS> <cause> <estimate>[unit] lim <tolerance> <predicate>``,
    e.g. ``"IMU1 ACC Y scale 0.0021 lim 0.001 F5"``. Instance, sensor, cause and
    the estimate are always kept; when the line is too long the predicate is
    dropped first, then the limit, then the estimate loses digits. (The vehicle
    is the MAVLink system itself, so it is not repeated.)
    """
    head = f"IMU{event.imu}"
    if event.triad is not None:
        head += f" {_SENSOR_ABBREV[event.triad]}"
    if event.axis is not None:
        head += f" {event.axis.upper()}"
    head += f" {_CAUSE_ABBREV[event.cause]}"
    unit = _UNIT_ABBREV.get(event.unit, event.unit)
    for digits in (3, 2, 1):
        number = "" if event.estimate is None else f" {event.estimate:.{digits}g}{unit}"
        limit = "" if event.tolerance is None else f" lim {event.tolerance:.{digits}g}"
        for candidate in (
            f"{head}{number}{limit} {event.predicate.value}",
            f"{head}{number}{limit}",
            f"{head}{number}",
        ):
            if len(candidate) <= STATUSTEXT_MAX_CHARS:
                return candidate
    return f"{head}{number}"[:STATUSTEXT_MAX_CHARS]


class AlertRateLimiter:
    """Rate limit for STATUSTEXT alerts: the Zenoh event stream stays complete, the GCS is not flooded.

    At most one alert per ``min_interval_s`` for the same (imu, predicate,
    triad, axis), and at most ``max_per_s`` alerts per second overall (token
    bucket, burst ``max_per_s``). Time comes from the caller (``now_s``,
    any monotonic clock), so the rule is deterministic in tests and replays.
    """

    def __init__(self, *, min_interval_s: float = 10.0, max_per_s: float = 1.0):
        if min_interval_s < 0 or max_per_s <= 0:
            raise ValueError(
                f"need min_interval_s >= 0 and max_per_s > 0, got {min_interval_s}, {max_per_s}"
            )
        self._interval_s = float(min_interval_s)
        self._rate = float(max_per_s)
        self._tokens = float(max_per_s)
        self._last_s: float | None = None
        self._last_by_key: dict[tuple[str, int, Predicate, Triad | None, str | None], float] = {}
        self.suppressed = 0

    def allow(self, event: Event, now_s: float) -> bool:
        """True if an alert for ``event`` may be sent at ``now_s`` (and counts it as sent)."""
        if self._last_s is not None:
            self._tokens = min(self._rate, self._tokens + (now_s - self._last_s) * self._rate)
        self._last_s = now_s
        key = (event.vehicle, event.imu, event.predicate, event.triad, event.axis)
        last = self._last_by_key.get(key)
        if (last is not None and now_s - last < self._interval_s) or self._tokens < 1.0:
            self.suppressed += 1
            return False
        self._tokens -= 1.0
        self._last_by_key[key] = now_s
        return True


# --------------------------------------------------------------------------- the link

_SENT_LOCK = threading.Lock()
"""Guards the links' counts of what they sent (:meth:`LinkCounters.count_sent`)."""


@dataclass
class LinkCounters:
    """What a :class:`MavlinkLink` saw and sent.

    The reader thread writes these; other threads read them with ``dict(...)``
    snapshots (one C-level copy, never a dict changing size under an iterator).
    """

    messages: int = 0
    imu_samples: dict[str, int] = field(default_factory=dict)
    ignored_systems: dict[int, int] = field(default_factory=dict)
    """IMU messages of a system other than :attr:`imu_system`, not read, by the system that sent
    them (:attr:`ignored_system` in all)."""
    imu_system: int | None = None
    """The system id whose IMU messages are read: ``autopilot_system``, or when that is unset the
    system of the first IMU message read (None until then)."""
    dropped_kernel: int = 0
    """Datagrams the kernel dropped at a UDP link's socket before they were read: its receive
    buffer was full, the reader behind its input (:class:`KernelDrops`; 0 on other links)."""
    rejected: dict[str, int] = field(default_factory=dict)
    signing_stale: int = 0
    """IMU and other packets signed with the key but refused for their time stamp (counted in
    ``rejected`` too): replays, or an autopilot whose clock went back (:func:`keep_replay_window`)."""
    gnss_messages: int = 0
    """GPS_RAW_INT messages read (of any system)."""
    alerts_sent: int = 0
    texts_sent: int = 0
    heartbeats_sent: int = 0

    @property
    def ignored_system(self) -> int:
        """IMU messages of other systems in all (the status topic's ``service.mavlink.rejected.other_system``)."""
        return sum(dict(self.ignored_systems).values())

    def reject(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + n

    def count_sent(
        self, name: Literal["alerts_sent", "texts_sent", "heartbeats_sent"], n: int = 1
    ) -> None:
        """``name`` += ``n`` under a lock: the delivery lanes and the heartbeat send from worker
        threads at once, and an unlocked ``+=`` loses counts."""
        with _SENT_LOCK:
            setattr(self, name, getattr(self, name) + n)


# Fields of each IMU message in the order ImuBatcher reads them: time, accel xyz, gyro xyz, temperature,
# then the HIGHRES_IMU validity bits and the instance id of the messages that carry one.
_COMMON_FIELDS = ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "temperature")
FIELD_NAMES: Mapping[ImuMessage, tuple[str, ...]] = {
    ImuMessage.RAW_IMU: ("time_usec", *_COMMON_FIELDS, "id"),
    ImuMessage.SCALED_IMU: ("time_boot_ms", *_COMMON_FIELDS),
    ImuMessage.SCALED_IMU2: ("time_boot_ms", *_COMMON_FIELDS),
    ImuMessage.SCALED_IMU3: ("time_boot_ms", *_COMMON_FIELDS),
    ImuMessage.HIGHRES_IMU: ("time_usec", *_COMMON_FIELDS, "fields_updated", "id"),
}
"""The fields of each IMU message :func:`imu_fields_si` takes, in its columns' order."""
_FIELDS: Mapping[ImuMessage, Callable[[MavlinkMessage], tuple[float, ...]]] = {
    kind: attrgetter(*names) for kind, names in FIELD_NAMES.items()
}


_GPS_FIELDS = attrgetter(*GPS_RAW_INT_FIELDS)

_WITH_ID = (ImuMessage.RAW_IMU, ImuMessage.HIGHRES_IMU)
_IMU_MSG_IDS = {
    ImuMessage.RAW_IMU: mavlink2.MAVLINK_MSG_ID_RAW_IMU,
    ImuMessage.SCALED_IMU: mavlink2.MAVLINK_MSG_ID_SCALED_IMU,
    ImuMessage.SCALED_IMU2: mavlink2.MAVLINK_MSG_ID_SCALED_IMU2,
    ImuMessage.SCALED_IMU3: mavlink2.MAVLINK_MSG_ID_SCALED_IMU3,
    ImuMessage.HIGHRES_IMU: mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU,
}


class ImuBatcher:
    """Parsed MAVLink messages in, their IMU fields out as one array per message type (no I/O).

    :meth:`add` keeps the raw fields of the selected IMU messages (one C-level
    ``attrgetter`` per message) and counts what pymavlink refused
    (``BAD_DATA``, :class:`LinkRejection`); :meth:`take_fields` hands over
    everything kept since the last call, one array per message type, and
    :meth:`take` turns that into batches with :attr:`converter`. A reader
    process sends the arrays and the service converts them
    (:mod:`protocols.mavlink_process`): the reader's core is then left to
    pymavlink's parse, which sets the rate it keeps up with.

    IMU messages are read from one system only, ``counters.imu_system``: the
    configured ``autopilot_system``, else ``imu_system`` (the system a previous
    reader of this link took, handed over), else the system of the first IMU
    message added. Two systems' samples merged into one IMU stream would hide
    each other's faults: the others' IMU messages are counted
    (:attr:`LinkCounters.ignored_system`, per system in
    :attr:`LinkCounters.ignored_systems`) and left out.
    """

    def __init__(
        self, settings: MavlinkSettings, counters: LinkCounters, *, imu_system: int | None = None
    ):
        self.settings = settings
        self.counters = counters
        if settings.autopilot_system is not None:
            counters.imu_system = settings.autopilot_system
        elif imu_system is not None:
            counters.imu_system = imu_system
        self.converter = ImuConverter(settings, counters)
        self._types = {m.value: m for m in settings.messages}
        self._rows: dict[ImuMessage, list[tuple[float, ...]]] = {}
        self._gnss: list[tuple[float, ...]] = []
        self.pending = 0
        """Messages kept since the last :meth:`take_fields`."""

    def add(self, messages: Iterable[MavlinkMessage]) -> None:
        """Keep the IMU messages of ``messages`` from :attr:`LinkCounters.imu_system` (the first one's
        system when it is None); other types are ignored, other systems' and refused bytes counted."""
        counters = self.counters
        system, ignored = counters.imu_system, counters.ignored_systems
        types, all_rows = self._types, self._rows
        seen = kept = 0
        for msg in messages:
            kind = types.get(msg.get_type())
            if kind is None:
                if isinstance(msg, mavlink2.MAVLink_bad_data):
                    self._refused(msg)
                elif isinstance(msg, mavlink2.MAVLink_gps_raw_int_message):
                    self._gnss_message(msg)
                continue
            seen += 1
            source = msg.get_srcSystem()
            if source != system:
                if system is None:
                    system = counters.imu_system = source
                else:
                    ignored[source] = ignored.get(source, 0) + 1
                    continue
            rows = all_rows.get(kind)
            if rows is None:
                rows = all_rows[kind] = []
            rows.append(_FIELDS[kind](msg))
            kept += 1
        counters.messages += seen
        self.pending += kept

    def _gnss_message(self, msg: MavlinkMessage) -> None:
        """Keep a GPS_RAW_INT of the IMUs' system (its clock is theirs); one of another system, or
        before any IMU message chose the system, is counted (:attr:`LinkRejection.GNSS_OTHER_SYSTEM`)."""
        self.counters.gnss_messages += 1
        if msg.get_srcSystem() != self.counters.imu_system:
            self.counters.reject(LinkRejection.GNSS_OTHER_SYSTEM)
            return
        self._gnss.append(_GPS_FIELDS(msg))

    def take_gnss(self) -> np.ndarray | None:
        """The GPS_RAW_INT messages kept since the last call (float64, a row per message, columns
        :data:`GPS_RAW_INT_FIELDS`); None when there were none."""
        rows, self._gnss = self._gnss, []
        return np.array(rows, dtype=np.float64) if rows else None

    def _refused(self, bad: MavlinkMessage) -> None:
        reason = str(bad.reason)
        data = bytes(bad.data)
        if reason == "Bad prefix":
            self.counters.reject(LinkRejection.GARBAGE_BYTES, len(data))
        elif reason.startswith("invalid MAVLink CRC"):
            self.counters.reject(LinkRejection.BAD_CRC)
        elif reason == "Invalid signature":
            signed = (
                data[:1] == bytes([mavlink2.PROTOCOL_MARKER_V2])
                and len(data) > 2
                and bool(data[2] & mavlink2.MAVLINK_IFLAG_SIGNED)
            )
            self.counters.reject(LinkRejection.BAD_SIGNATURE if signed else LinkRejection.UNSIGNED)
        else:
            self.counters.reject(LinkRejection.MALFORMED)

    def take_fields(self) -> list[tuple[ImuMessage, np.ndarray]]:
        """The kept messages' fields, one float64 array per message type (a row per message, in the
        order of :data:`_FIELDS`), in order of each type's first message."""
        rows_by_kind, self._rows, self.pending = self._rows, {}, 0
        samples = self.counters.imu_samples
        out = []
        for kind, rows in rows_by_kind.items():
            samples[kind.value] = samples.get(kind.value, 0) + len(rows)
            out.append((kind, np.array(rows, dtype=np.float64)))
        return out

    def take(self) -> list[SampleBatch]:
        """The kept samples as one batch per IMU and message type, in order of their first message."""
        return [b for kind, a in self.take_fields() for b in self.converter.batches(kind, a)]


@dataclass(frozen=True)
class ImuFieldsSI:
    """One message type's messages in SI (:func:`imu_fields_si`), the HIGHRES_IMU ones without all
    six triad fields updated left out (``kept`` says which rows stay, ``not_updated`` counts the
    others); ``ids`` the ``id`` field of the types that have one (the IMU is the message's base
    index plus it), else None."""

    kept: np.ndarray
    not_updated: int
    t_s: np.ndarray
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray
    temp_c: np.ndarray
    has_temp: np.ndarray
    ids: np.ndarray | None


def imu_fields_si(kind: ImuMessage, a: np.ndarray, raw_scale: ImuScale) -> ImuFieldsSI:
    """The fields of ``kind`` messages (float64, a row per message, columns :data:`FIELD_NAMES`) in SI,
    with the units of :func:`decode_imu_message` and its floating-point operations (the same values
    to the bit)."""
    kept = np.ones(a.shape[0], dtype=bool)
    if kind is ImuMessage.HIGHRES_IMU:
        kept = np.asarray(_triads_updated(a[:, 8].astype(np.int64)), dtype=bool)
        if not kept.all():
            a = a[kept]
        t_s, acc, gyr = a[:, 0] * 1e-6, a[:, 1:4], a[:, 4:7]
        has_temp = (a[:, 8].astype(np.int64) & _HIGHRES_TEMPERATURE_BIT) != 0
        temp = a[:, 7]
    else:
        scale = raw_scale if kind is ImuMessage.RAW_IMU else MILLI_UNITS
        t_s = a[:, 0] * (1e-6 if kind is ImuMessage.RAW_IMU else 1e-3)
        acc = a[:, 1:4] * scale.accel_mps2_per_lsb
        gyr = a[:, 4:7] * scale.gyro_rps_per_lsb
        # 0 is "no temperature" (decode_imu_message).
        has_temp = a[:, 7] != 0
        temp = a[:, 7] * scale.temp_c_per_lsb
    ids = a[:, -1].astype(np.int64) if kind in _WITH_ID else None
    return ImuFieldsSI(kept, int((~kept).sum()), t_s, acc, gyr, temp, has_temp, ids)


class ImuConverter:
    """The fields of one message type's messages (:meth:`ImuBatcher.take_fields`) as one
    :class:`~protocols.frames.SampleBatch` per IMU (no I/O).

    One array operation per message type, with the units and IMU mapping of
    :func:`decode_imu_message` (the same floating-point operations, so the
    same values to the bit). ``seq`` counts batches per IMU. A batch carries
    temperatures only if every sample in it has one; one that is no valid
    frame is counted in ``counters`` by its :class:`~protocols.frames.FrameError` reason.
    """

    def __init__(self, settings: MavlinkSettings, counters: LinkCounters):
        self.settings = settings
        self.counters = counters
        self._seq: dict[int, int] = {}

    def batches(self, kind: ImuMessage, a: np.ndarray) -> list[SampleBatch]:
        base = self.settings.imu_index[kind]
        si = imu_fields_si(kind, a, self.settings.raw_scale)
        if si.not_updated:
            self.counters.reject(LinkRejection.FIELDS_NOT_UPDATED, si.not_updated)
            if not si.t_s.size:
                return []
        t_s, acc, gyr, temp, has_temp, ids = (
            si.t_s, si.accel_mps2, si.gyro_rps, si.temp_c, si.has_temp, si.ids
        )  # fmt: skip
        parts: list[tuple[int, slice | np.ndarray]] = [(base, slice(None))]
        if ids is not None and ids.any():
            first = np.unique(ids, return_index=True)[1]
            parts = [(base + int(ids[k]), ids == ids[k]) for k in sorted(first)]
        out = []
        for imu, sel in parts:
            with_temp = bool(has_temp[sel].all())
            seq = self._seq.get(imu, 0)
            try:
                batch = SampleBatch(
                    self.settings.vehicle,
                    imu,
                    seq,
                    t_s[sel],
                    acc[sel],
                    gyr[sel],
                    temp[sel] if with_temp else None,
                )
            except FrameError as exc:
                self.counters.reject(exc.reason.value, len(t_s[sel]))
                continue
            self._seq[imu] = seq + 1
            out.append(batch)
        return out


READ_BYTES = 65_536
"""Bytes asked of the connection per read (a whole UDP datagram; TCP and serial give what is there)."""
READ_SAMPLES_MAX = 4_096
"""IMU messages read before :meth:`MavlinkLink.read` returns even if more are waiting (bounds one call's work)."""
REREADS_MAX = 8
"""Start bytes inside refused frames tried as the start of a packet per read of the connection
(:func:`parse_all`, and the bytes left incomplete at a datagram's end). Junk before good packets
costs one or two; the bound keeps a datagram of start bytes (each try decodes a frame of up to
280 bytes) from costing the reader 0.4 s instead of 2 ms."""
DROPS_PERIOD_S = 1.0
"""A UDP link reads its socket's kernel drops at most this often (:class:`KernelDrops`)."""


class MavlinkLink:
    """A MAVLink 2 connection of an onboard health monitor.

    Reads IMU messages as :class:`~protocols.frames.SampleBatch` (one batch per
    IMU of the messages read together, ``seq`` counted per IMU), sends
    HEARTBEAT and STATUSTEXT. Blocking calls: in a service run :meth:`read` in
    a thread or use :class:`MavlinkSource`. A context manager (closes the port).

    Reading takes whatever the connection holds (a UDP datagram, up to
    :data:`READ_BYTES` of a stream) and hands it to pymavlink's parser at once
    (:func:`parse_all`); the messages go through an :class:`ImuBatcher`.
    A UDP datagram holds whole packets: bytes of a packet left incomplete at
    its end are counted as garbage and dropped, so one bad datagram never
    swallows the packets of the next. A frame that failed its check is read
    again where a whole packet starts inside it (:func:`parse_all`), and bytes
    left incomplete at a datagram's end from their second byte, so a stray
    start byte or a packet cut short does not swallow the good packets after it.

    With a signing key, unsigned and wrongly signed IMU and GPS_RAW_INT messages are refused
    (pymavlink's check, :class:`LinkRejection`) unless ``accept_unsigned``;
    other message types are not read, so they may come unsigned (a radio's
    RADIO_STATUS, as the MAVLink signing rules allow).

    IMU messages are read from one MAVLink system (:class:`ImuBatcher`):
    ``autopilot_system``, else ``imu_system`` (the system a previous link of
    these settings read, :mod:`protocols.mavlink_process` hands it to a new
    reader), else the first one heard.
    """

    def __init__(self, settings: MavlinkSettings, *, imu_system: int | None = None):
        self.settings = settings
        self._conn = mavutil.mavlink_connection(
            settings.device,
            baud=settings.baud,
            source_system=settings.source_system,
            source_component=settings.source_component,
        )
        use_mavlink2(self._conn)
        if settings.signing_key is not None:
            # GNSS velocity is an input of a check that raises events: it must be signed too.
            imu_ids = frozenset(_IMU_MSG_IDS[m] for m in settings.messages) | {
                mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT
            }
            self._conn.setup_signing(
                settings.signing_key,
                sign_outgoing=True,
                link_id=settings.signing_link_id,
                # pymavlink asks this for every message that is unsigned or fails the check.
                allow_unsigned_callback=(lambda mav, msg_id: True)
                if settings.accept_unsigned
                else (lambda mav, msg_id: msg_id not in imu_ids),
            )
            keep_replay_window(self._conn.mav, self._signing_stale)
        self._datagrams = isinstance(self._conn, mavutil.mavudp)
        self.udp_rcvbuf_granted_bytes: int | None = None
        """The receive buffer the kernel granted a UDP link (at most ``net.core.rmem_max``); None on others."""
        self._kernel_drops: KernelDrops | None = None
        if self._datagrams:
            # The kernel holds datagrams while the pipeline has the interpreter: at 50 k/s the
            # default (~200 kB) lasts a few ms. The kernel caps this at net.core.rmem_max.
            port = self._conn.port
            port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, settings.udp_rcvbuf_bytes)
            self.udp_rcvbuf_granted_bytes = granted_rcvbuf_bytes(port)
            self._kernel_drops = KernelDrops(port)
        self._send_lock = threading.Lock()
        self._chunk_id = 0
        self.counters = LinkCounters()
        self._batcher = ImuBatcher(settings, self.counters, imu_system=imu_system)

    @property
    def connection(self) -> mavutil.mavfile:
        """The pymavlink connection (its ``mav`` is a MAVLink 2 ``ardupilotmega`` instance)."""
        return self._conn

    def read(self, timeout_s: float, *, gather_s: float = 0.0) -> list[SampleBatch]:
        """The IMU samples that arrive, one batch per IMU; ``[]`` if nothing came within ``timeout_s``.

        After the first bytes, reading goes on for ``gather_s`` (the batches are
        larger, the first sample waits that long) or until
        :data:`READ_SAMPLES_MAX` messages are kept. The time is looked at after
        each read of the connection, not only once nothing more waits: a reader
        that fell behind hands its backlog over in several calls, and a message
        waits for the parse of what came before it, not of all that came after.
        Under 50 k messages/s that cut the reader's share of a fault's latency
        from p90 13.5 / max 20 ms to 5.2 / 9 ms (``bench_mavlink_e2e.py``).
        """
        self._gather(timeout_s, gather_s)
        return self._batcher.take()

    def read_fields(
        self, timeout_s: float, *, gather_s: float = 0.0
    ) -> list[tuple[ImuMessage, np.ndarray]]:
        """:meth:`read`, with the messages' fields left unconverted (:meth:`ImuBatcher.take_fields`):
        what a reader process sends, for an :class:`ImuConverter` on the service's side."""
        self._gather(timeout_s, gather_s)
        return self._batcher.take_fields()

    def take_gnss(self) -> np.ndarray | None:
        """The GPS_RAW_INT fields read with the last :meth:`read` (:meth:`ImuBatcher.take_gnss`)."""
        return self._batcher.take_gnss()

    def _gather(self, timeout_s: float, gather_s: float) -> None:
        conn, batcher = self._conn, self._batcher
        deadline: float | None = None
        wait_s = timeout_s
        while conn.select(wait_s):
            if deadline is None:
                deadline = time.monotonic() + gather_s
            while batcher.pending < READ_SAMPLES_MAX:
                data = conn.recv(READ_BYTES)
                if not data:
                    break
                messages, rereads = parse_all(conn.mav, data, rereads=REREADS_MAX)
                batcher.add(messages)
                if self._datagrams:
                    self._end_of_datagram(rereads)
                if time.monotonic() >= deadline:
                    break
            wait_s = deadline - time.monotonic()
            if wait_s <= 0 or batcher.pending >= READ_SAMPLES_MAX:
                break
        if self._kernel_drops is not None and (total := self._kernel_drops.total()) is not None:
            self.counters.dropped_kernel = total

    def _end_of_datagram(self, rereads: int) -> None:
        """A datagram holds whole packets: a frame still incomplete at its end began at a stray start
        byte or was cut short. That byte is garbage; the bytes after it are read again (good packets
        may follow it) while ``rereads`` last, the rest are garbage."""
        mav = self._conn.mav
        while mav.buf_len() > 0 and rereads > 0:
            rereads -= 1
            self.counters.reject(LinkRejection.GARBAGE_BYTES, 1)
            mav.buf_index += 1
            mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
            if mav.buf_len() > 0:
                messages, rereads = parse_all(mav, b"", rereads=rereads)
                self._batcher.add(messages)
        if left := mav.buf_len():
            self.counters.reject(LinkRejection.GARBAGE_BYTES, left)
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink2.HEADER_LEN_V1 + 2

    def _signing_stale(self) -> None:
        self.counters.signing_stale += 1

    def send(self, msg: MavlinkMessage) -> None:
        """Send a message built by one of the typed builders (signed if signing is configured)."""
        with self._send_lock:
            self._conn.mav.send(msg)

    def send_heartbeat(self) -> None:
        """One HEARTBEAT (the service sends it at 1 Hz)."""
        self.send(heartbeat_message())
        self.counters.count_sent("heartbeats_sent")

    def send_text(self, text: str, severity: Severity) -> int:
        """Send free text as STATUSTEXT (chunked beyond 50 characters); returns messages sent."""
        with self._send_lock:
            self._chunk_id = self._chunk_id % 65535 + 1
            chunk_id = self._chunk_id
        messages = statustext_messages(text, severity=severity, chunk_id=chunk_id)
        for msg in messages:
            self.send(msg)
        self.counters.count_sent("texts_sent", len(messages))
        return len(messages)

    def send_alert(self, event: Event) -> str:
        """Send the event's :func:`alert_text` as one STATUSTEXT with its severity; returns the text."""
        text = alert_text(event)
        self.send(statustext_messages(text, severity=event.severity)[0])
        self.counters.count_sent("alerts_sent")
        return text

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> MavlinkLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def granted_rcvbuf_bytes(sock: socket.socket) -> int:
    """The receive buffer the kernel granted ``sock``, in the bytes asked for with ``SO_RCVBUF``.

    Linux reports twice the bytes granted (the other half is for its own
    bookkeeping, ``man 7 socket``) and grants at most ``net.core.rmem_max``
    (212,992 on a stock kernel).
    """
    reported = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    return reported // 2 if sys.platform.startswith("linux") else reported


_PROC_UDP = {socket.AF_INET: "/proc/net/udp", socket.AF_INET6: "/proc/net/udp6"}


class KernelDrops:
    """Datagrams the kernel dropped at one UDP socket since it was opened (Linux).

    The ``drops`` column of ``/proc/net/udp`` (``udp6``) on the socket's row,
    found by its inode: datagrams that came while the receive buffer was full
    (the kernel's ``RcvbufErrors``, of this socket alone) or that failed their
    checksum. The file is read at most every :data:`DROPS_PERIOD_S`: it lists
    every UDP socket of the host, and a read took 0.07 ms with a few and 2.7 ms
    with a thousand here, in the reader that sets the link's speed.
    """

    def __init__(self, sock: socket.socket):
        self._inode = str(os.fstat(sock.fileno()).st_ino)
        self._path = _PROC_UDP.get(sock.family)
        self._total: int | None = None
        self._read_s = -DROPS_PERIOD_S

    def total(self) -> int | None:
        """The socket's drops so far (as last read); None where the kernel does not list them
        (not Linux, no row)."""
        now = time.monotonic()
        if self._path is not None and now - self._read_s >= DROPS_PERIOD_S:
            self._read_s = now
            self._total = self._read()
        return self._total

    def _read(self) -> int | None:
        assert self._path is not None
        try:
            with open(self._path, encoding="ascii") as f:
                next(f, None)  # the header
                for line in f:
                    cols = line.split()
                    if len(cols) > 12 and cols[9] == self._inode:
                        return int(cols[12])
        except (OSError, ValueError):
            return None
        return None


def parse_all(
    mav: mavlink2.MAVLink, data: bytes, *, rereads: int = 0
) -> tuple[list[MavlinkMessage], int]:
    """The messages pymavlink parses out of ``data`` (with what its buffer held before): ``parse_buffer``
    without its last call, made on an empty buffer, that can only say "no more" (one message per UDP
    datagram: one call instead of two, about 1 µs of the 10 µs a message costs).

    A frame that fails its check, or of a message the dialect does not know, is read again from
    a start byte inside it where a whole packet starts (:func:`_read_again`), up to ``rereads``
    start bytes tried in all; returns the messages and the re-reads left.
    """
    msg = mav.parse_char(data)
    if msg is None:
        return [], rereads
    out = [msg]
    while True:
        kind = msg.__class__
        if rereads > 0 and (kind is _UNKNOWN or (kind is _BAD_DATA and _false_start(msg))):
            frame = bytes(msg.get_msgbuf() if kind is _UNKNOWN else msg.data)
            # A refused frame with a real header, or a MAVLink 2 message of another dialect (a stray
            # start byte rarely makes valid flags): a packet whole inside it is its payload.
            swallowed_only = (
                _genuine_header(frame)
                if kind is _BAD_DATA
                else frame[0] == mavlink2.PROTOCOL_MARKER_V2
            )
            tried, resumed = _read_again(mav, frame, rereads, swallowed_only=swallowed_only)
            rereads -= tried
            if kind is _UNKNOWN and resumed is not None:
                # Not a message but junk before a packet: counted as garbage, as junk is.
                out[-1] = _BAD_DATA(frame[:resumed], "Bad prefix")
        if mav.buf_len() <= 0 or (msg := mav.parse_char(b"")) is None:
            return out, rereads
        out.append(msg)


_BAD_DATA = mavlink2.MAVLink_bad_data
_UNKNOWN = mavlink2.MAVLink_unknown


def _false_start(bad: MavlinkMessage) -> bool:
    """Whether a refused frame may have begun at a stray start byte: its framing or CRC failed (a
    wrong signature or junk before any start byte is what it says it is)."""
    reason = str(bad.reason)
    return reason != "Bad prefix" and reason != "Invalid signature"


_START_BYTES = (mavlink2.PROTOCOL_MARKER_V1, mavlink2.PROTOCOL_MARKER_V2)


def _genuine_header(frame: bytes) -> bool:
    """Whether a refused frame's header is a real packet's: a message id of the dialect and a payload
    no longer than that message's (a packet hit by bit errors or short of bytes, not a stray start
    byte, whose "header" is whatever bytes followed it)."""
    if frame[0] == mavlink2.PROTOCOL_MARKER_V2 and len(frame) >= mavlink2.HEADER_LEN_V2:
        msg_id = int.from_bytes(frame[7:10], "little")
    elif frame[0] == mavlink2.PROTOCOL_MARKER_V1 and len(frame) >= mavlink2.HEADER_LEN_V1:
        msg_id = frame[5]
    else:
        return False
    kind = mavlink2.mavlink_map.get(msg_id)
    return kind is not None and 0 < frame[1] <= kind.unpacker.size


_HEADER_V1: int = mavlink2.HEADER_LEN_V1
_HEADER_V2: int = mavlink2.HEADER_LEN_V2
_SIGNATURE_BYTES: int = mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN
_FRAME_MAX_BYTES = _HEADER_V2 + 255 + 2 + _SIGNATURE_BYTES


def _frame_bytes(buf: bytes) -> int:
    """The length of the frame a start byte at ``buf[0]`` announces (its header's length byte and,
    for MAVLink 2, signature flag); a frame whose header is not all there counts as long."""
    if len(buf) < 3:
        return _FRAME_MAX_BYTES
    if buf[0] == mavlink2.PROTOCOL_MARKER_V1:
        return _HEADER_V1 + 2 + buf[1]
    signed = _SIGNATURE_BYTES if buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED else 0
    return _HEADER_V2 + 2 + buf[1] + signed


def _read_again(
    mav: mavlink2.MAVLink, frame: bytes, budget: int, *, swallowed_only: bool
) -> tuple[int, int | None]:
    """Resume parsing inside ``frame``, the last frame pymavlink consumed, where a whole packet starts;
    returns the start bytes tried (at most ``budget``) and where in ``frame`` parsing resumes (None:
    nowhere, the frame stays consumed).

    pymavlink takes the byte after a start byte as the frame's length and consumes that many
    bytes: when the frame fails its check, or carries a message id the dialect does not know
    (then nothing is checked), the good packets in them are lost: after a stray 0xFD, or a
    packet cut short. The parser is put back to the first start byte inside the frame from
    which a message of the dialect decodes with its CRC (tried on a parser of its own, without
    signing: the link's parser checks the signature when it reads it). A start byte inside the
    payload of a packet hit by a bit error starts no such message: that frame is dropped
    whole, as before, and the packets after it are read. With ``swallowed_only`` (a refused
    frame whose header is a real one, :func:`_genuine_header`) only a packet reaching past the
    frame's end is taken, one the frame swallowed: a packet whole inside it is payload (a .tlog
    downloaded by FILE_TRANSFER_PROTOCOL). So too for a MAVLink 2 frame of a message id the
    dialect lacks (another dialect's message: junk after a stray start byte rarely has valid
    flags); a MAVLink 1 one is more likely junk (its one-byte id is often one the dialect
    lacks): any packet inside it is taken.
    """
    emptied = mav.buf_len() <= 0
    rest = b"" if emptied else bytes(mav.buf[mav.buf_index : mav.buf_index + _FRAME_MAX_BYTES])
    tried = 0
    for j in range(1, len(frame)):
        if frame[j] not in _START_BYTES:
            continue
        if swallowed_only and j + _frame_bytes(frame[j:] + rest[:3]) <= len(frame):
            continue
        if tried == budget:
            break
        tried += 1
        probe = mavlink2.MAVLink(None)
        probe.robust_parsing = True
        msg = probe.parse_char(frame[j:] + rest)
        if msg is None or isinstance(msg, (mavlink2.MAVLink_bad_data, mavlink2.MAVLink_unknown)):
            continue
        if emptied:
            mav.buf = bytearray(frame[j:])
            mav.buf_index = 0
        else:
            mav.buf_index -= len(frame) - j
        return tried, j
    return tried, None


NEW_STREAM_WINDOW = 6_000_000
"""pymavlink's rule: a new signed stream is refused when stamped more than this (one minute, in the
signing stamp's 10 µs units) before the newest stamp seen."""


def keep_replay_window(mav: mavlink2.MAVLink, on_stale: Callable[[], None] = lambda: None) -> None:
    """Only a packet whose signature verifies moves its stream's replay window; a packet signed with
    the key but refused as old is told apart from a forged one.

    pymavlink (2.4.50) records a signed packet's time stamp for its (link id, system,
    component) before it compares the signature: one forged packet with a time stamp far
    ahead made every later genuine packet of that stream fail as old. The check stays
    pymavlink's; a failed one only has the stream's previous time stamp put back.

    A packet refused for its time stamp (not newer than its stream's window, or a new stream
    more than a minute older than the newest stamp seen) is checked once more by pymavlink as
    if its stream's window were just below it, and the window put back whatever the answer:
    when the signature verifies, ``on_stale`` is called. Such packets are replays, or come from
    an autopilot whose clock went back after a packet stamped ahead: that stream stays refused
    until its stamps pass the window (or the daemon restarts), and the count says why. Bringing
    the window back was tried and dropped: whatever rule does it lets some recorded packets be
    replayed (those sent during a reception gap, or accepted before a clock went back).
    """
    check = mav.check_signature
    stamps = mav.signing.stream_timestamps

    def restore(key: tuple[int, int, int], before: int | None) -> None:
        if before is None:
            stamps.pop(key, None)
        else:
            stamps[key] = before

    def checked(msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        key = (msgbuf[-13], src_system, src_component)
        before = stamps.get(key)
        if check(msgbuf, src_system, src_component):
            return True
        restore(key, before)
        stamp = int.from_bytes(msgbuf[-12:-6], "little")
        if before is not None:
            old = stamp <= before
        else:
            old = stamp + NEW_STREAM_WINDOW < mav.signing.timestamp
        if old:
            stamps[key] = stamp - 1
            signed_with_key = check(msgbuf, src_system, src_component)
            restore(key, before)
            if signed_with_key:
                on_stale()
        return False

    mav.check_signature = checked


def use_mavlink2(conn: mavutil.mavfile) -> mavutil.mavfile:
    """Give a pymavlink connection its own MAVLink 2 ``ardupilotmega`` parser/encoder (module docstring)."""
    conn.mav = mavlink2.MAVLink(
        conn, srcSystem=conn.source_system, srcComponent=conn.source_component
    )
    conn.mav.robust_parsing = True
    conn.WIRE_PROTOCOL_VERSION = mavlink2.WIRE_PROTOCOL_VERSION
    conn.first_byte = (
        False  # pymavlink's auto-switch would rewrite os.environ and the global dialect
    )
    return conn


READER_RETRY_S = 1.0
"""The pause of :class:`MavlinkSource`'s reader after a failed read."""
GNSS_CAPACITY = 1024
"""GPS_RAW_INT epochs a :class:`MavlinkSource` holds for the GNSS task (100 s of a 10 Hz receiver:
it rides out the IMU groups that hold the fleet's lock, as :class:`protocols.zenoh_adapter.GnssSource`)."""


class ImuLink(Protocol):
    """What the service uses of a link: :class:`MavlinkLink`, or
    :class:`protocols.mavlink_process.MavlinkProcessLink` (the same link read in a child process)."""

    settings: MavlinkSettings
    counters: LinkCounters

    def read(self, timeout_s: float, *, gather_s: float = 0.0) -> list[SampleBatch]: ...

    def take_gnss(self) -> np.ndarray | None: ...

    def send_heartbeat(self) -> None: ...

    def send_text(self, text: str, severity: Severity) -> int: ...

    def send_alert(self, event: Event) -> str: ...

    def close(self) -> None: ...


class MavlinkSource(BatchSource):
    """IMU batches from a link (:class:`ImuLink`) for asyncio: a reader thread and a bounded ring.

    The thread reads the link (:meth:`MavlinkLink.read`, waiting ``poll_s`` at
    a time so :meth:`close` returns promptly) and gathers the samples of
    ``gather_s`` after the first into one batch per IMU: the pipeline's cost is
    per batch, and ``gather_s`` is the latency that buys. It logs the link's
    rejected input and the datagrams the kernel dropped: a reason not logged
    before at once, more of the same at most once per :data:`~protocols.log_rate.LOG_PERIOD_S`. The ring holds up to
    ``capacity`` samples; when the consumer lags, the oldest batches are
    dropped and their samples counted in :attr:`dropped_overload`.
    ``async for batch in source`` or ``await source.get()``; create it inside
    the running loop (or pass ``loop``).

    Without a configured ``autopilot_system``, each system whose IMU messages
    the link left out (:attr:`LinkCounters.ignored_systems`) is logged once,
    with the system it reads and how to choose another.
    """

    def __init__(
        self,
        link: ImuLink,
        *,
        capacity: int = 65_536,
        gather_s: float = 0.0,
        poll_s: float = 0.1,
        loop: asyncio.AbstractEventLoop | None = None,
    ):
        self.link = link
        self._ring: ThreadToAsyncRing[SampleBatch] = ThreadToAsyncRing(
            capacity, loop or asyncio.get_running_loop(), weight=lambda b: b.n_samples
        )
        self._stop = threading.Event()
        self._gather_s = float(gather_s)
        self._poll_s = float(poll_s)
        self.failures = 0
        self.last_failure: Exception | None = None
        self._rejections_log = LogRate()
        self._drops_log = LogRate()
        self._stale_log = LogRate()
        self._systems_logged: set[int] = set()
        self.gnss_rows: ThreadToAsyncRing[np.ndarray] = ThreadToAsyncRing(
            GNSS_CAPACITY, loop or asyncio.get_running_loop(), weight=len
        )
        """The link's GPS_RAW_INT fields (:meth:`ImuLink.take_gnss`), for
        :class:`protocols.mavlink_gnss.MavlinkGnssSource`; epochs dropped when full counted in its
        ``dropped``."""
        self._thread = threading.Thread(
            target=self._run, name=f"mavlink-{link.settings.device}", daemon=True
        )
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                batches = self.link.read(self._poll_s, gather_s=self._gather_s)
            except Exception as exc:
                # A reader that died would end MAVLink input for good, silently: the failure is
                # kept (:attr:`failures`, :attr:`last_failure`) for the daemon to log and count,
                # and reading resumes after a pause.
                self.failures += 1
                self.last_failure = exc
                self._stop.wait(READER_RETRY_S)
                continue
            for batch in batches:
                self._ring.put(batch)
            if (gnss := self.link.take_gnss()) is not None:
                self.gnss_rows.put(gnss)
            self._log_rejections()
            self._log_kernel_drops()
            self._log_signing_stale()
            self._log_other_systems()

    def _log_rejections(self) -> None:
        new = self._rejections_log.due(dict(self.link.counters.rejected))
        if new:
            _log.warning(
                "mavlink %s: rejected %s (counted on the status topic as service.mavlink.rejected.*)",
                self.link.settings.device,
                ", ".join(f"{n} {k}" for k, n in sorted(new.items())),
            )

    def _log_other_systems(self) -> None:
        """Once per system id (at most 256 lines): IMU messages of a system other than the one the
        link locked onto (none is configured) were left out."""
        counters = self.link.counters
        if self.link.settings.autopilot_system is not None or len(counters.ignored_systems) == len(
            self._systems_logged
        ):
            return
        for system in sorted(dict(counters.ignored_systems).keys() - self._systems_logged):
            self._systems_logged.add(system)
            _log.warning(
                "mavlink %s: IMU messages of system %d ignored: this link's IMUs come from system %s, "
                "the first heard; set [mavlink] autopilot_system to choose (counted on the status "
                "topic as service.mavlink.rejected.other_system)",
                self.link.settings.device,
                system,
                counters.imu_system,
            )

    def _log_signing_stale(self) -> None:
        self._log_total(
            self._stale_log,
            "signing_stale",
            "mavlink %s: %d packet(s) signed with the key were refused as older than their stream's "
            "window (service.mavlink.signing_stale; %d in all): replays, or an autopilot clock that "
            "went back after a packet stamped ahead; such a stream stays refused until its stamps "
            "pass the window or this daemon restarts",
        )

    def _log_kernel_drops(self) -> None:
        self._log_total(
            self._drops_log,
            "dropped_kernel",
            "mavlink %s: the kernel dropped %d datagrams (%d in all): the socket's receive buffer "
            "was full, the reader is behind its input (service.mavlink.dropped_kernel)",
        )

    def _log_total(self, rate: LogRate, counter: str, text: str) -> None:
        """Log ``text`` (device, count since the last line, total) when the link's ``counter`` grew
        and ``rate`` says a line is due."""
        total = getattr(self.link.counters, counter)
        new = rate.due({counter: total} if total else {})
        if new:
            _log.warning(text, self.link.settings.device, new[counter], total)

    @property
    def dropped_overload(self) -> int:
        """Samples dropped because the consumer lagged."""
        return self._ring.dropped

    @property
    def queued(self) -> int:
        """Batches read and not yet taken by the consumer."""
        return len(self._ring)

    async def get(self) -> SampleBatch:
        """The next batch; ``EOFError`` after :meth:`close` once drained."""
        return await self._ring.get()

    def get_nowait(self) -> SampleBatch | None:
        """The next batch if one is waiting, else ``None``."""
        return self._ring.get_nowait()

    def close(self, *, timeout_s: float = 5.0) -> None:
        """Stop the reader thread (within ``poll_s``) and end iteration; the link stays open."""
        self._stop.set()
        self._thread.join(timeout_s)
        self._ring.close()
        self.gnss_rows.close()
