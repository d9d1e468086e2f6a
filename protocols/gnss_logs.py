"""GNSS velocity from logged flights, for the thrust-axis check (:mod:`estimators.thrust_gnss`).

The receiver's own velocity, never a filter's (the EKF's velocity is built from the accelerometer
under test and would agree with its fault). Converted here to SI, East-North-Up, on the log's IMU
clock:

* PX4 ULog (pyulog): topics :data:`ULOG_GNSS_TOPICS`, ``timestamp`` µs (``timestamp_sample``,
  where the message has it, is 0 in the shared SITL log), ``vel_n_m_s``, ``vel_e_m_s``,
  ``vel_d_m_s``; an epoch counts with ``fix_type`` ≥ 3 and ``vel_ned_valid``. Of the topics and
  instances the log holds, the one with the most such epochs is taken, a tie going to
  ``vehicle_gps_position``, then to the lowest instance: the check learns its noise and judges on
  epochs, and the others are said (:attr:`GnssTrack.unused`; one whose message version lacks a
  field :attr:`GnssTrack.unreadable`, ``vel_ned_valid`` excepted: no flag). Each receiver's
  ``sensor_gps`` instance is kept apart, never mixed: receivers differ in lag and noise; an
  instance subscribed twice is one receiver.
* ArduPilot DataFlash ``.bin``/``.log`` (pymavlink): message ``GPS`` (instance ``I`` 0 where the
  format has it), ``TimeUS`` µs (ArduCopter 3.1: ``T`` ms), ground speed ``Spd`` m/s along the course ``GCrs`` (degrees from
  north), ``VZ`` m/s down; ``Status`` ≥ 3 (3D fix).
* MAVLink ``.tlog`` (pymavlink) and a live link: ``GPS_RAW_INT``, ``time_usec`` (the autopilot's
  boot clock, as its IMU messages), ``vel`` cm/s along ``cog`` cdeg; ``fix_type`` ≥ 3. It has no
  vertical velocity: the vertical is the centred difference of ``alt`` (mm), the mean vertical
  velocity over the two neighbouring epochs (:func:`estimators.thrust_gnss.up_velocity_from_altitude`).
  Unknown speed or course (``UINT16_MAX``) leaves the epoch out.

Left out and counted by reason (:attr:`GnssTrack.rejected`): no 3D fix, a velocity the receiver
flags not valid (ULog), a value not finite or unknown, a velocity component above
:data:`~estimators.thrust_gnss.MAX_SPEED_MPS` (in every format, as the live intake does: a
GPS_RAW_INT speed can reach 655 m/s, and its vertical, from an altitude jump, more), a time not
after the previous epoch's.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from estimators._typing import FloatArray
from estimators.thrust_gnss import MAX_SPEED_MPS, up_velocity_from_altitude
from protocols.logs import LogFormat, detect_format
from protocols.mavlink_settings import GPS_RAW_INT_FIELDS, MILLI_UNITS

GPS_FIX_3D = 3
SEARCH_BLOCK_BYTES = 1 << 20
UNKNOWN_U16 = 65535
ULOG_GNSS_TOPICS = ("vehicle_gps_position", "sensor_gps")
"""PX4 topics of the receivers' own solution with NED velocity and its validity flag:
``vehicle_gps_position``, what PX4's sensors module publishes from the receivers (the selected
one, or the blend of several weighted by their reported accuracy; no IMU in it), and
``sensor_gps``, each receiver's own (an instance per receiver; on newer PX4 the only one a log
may hold). PX4's default logging profile writes the first every 100 ms, the second every 1 s."""


class GnssLogError(ValueError):
    """A log whose GNSS records cannot be read (the reason, with the file)."""


@dataclass(frozen=True)
class GnssTrack:
    """GNSS velocity epochs of one receiver: ``t_s`` (M,) s on the IMU clock, ``vel_enu_mps``
    (M, 3); ``source`` the message or topic; ``rejected`` epochs left out by reason; ``unused``
    the other GNSS topics or instances the log holds, not taken, with their usable epochs;
    ``unreadable`` those not taken for a field their message version lacks, with the reason."""

    t_s: FloatArray
    vel_enu_mps: FloatArray
    source: str
    rejected: dict[str, int] = field(default_factory=dict)
    unused: dict[str, int] = field(default_factory=dict)
    unreadable: dict[str, str] = field(default_factory=dict)

    @property
    def rate_hz(self) -> float:
        return 1.0 / float(np.median(np.diff(self.t_s))) if self.t_s.size > 1 else 0.0


def _track(
    t_s: FloatArray,
    vel: FloatArray,
    fix_ok: np.ndarray,
    source: str,
    vel_ok: np.ndarray | None = None,
    max_speed_mps: float = np.inf,
) -> GnssTrack:
    """The epochs with a 3D fix, a velocity not flagged invalid (``vel_ok``, where the record has
    the flag), finite values and no velocity component above ``max_speed_mps`` (so a speed above
    it), in increasing time; the rest counted."""
    rejected: dict[str, int] = {}
    keep = np.asarray(fix_ok, bool)
    rejected["no_3d_fix"] = int((~keep).sum())
    if vel_ok is not None:
        rejected["velocity_not_valid"] = int((keep & ~vel_ok).sum())
        keep &= vel_ok
    finite = np.all(np.isfinite(vel), axis=1) & np.isfinite(t_s)
    rejected["not_finite"] = int((keep & ~finite).sum())
    keep &= finite
    if np.isfinite(max_speed_mps):
        fast = np.any(np.abs(np.where(keep[:, None], vel, 0.0)) > max_speed_mps, axis=1)
        rejected[f"speed_over_{max_speed_mps:g}_mps"] = int(fast.sum())
        keep &= ~fast
    t, v = t_s[keep], vel[keep]
    later = np.r_[True, t[1:] > np.maximum.accumulate(t)[:-1]] if t.size else np.empty(0, bool)
    rejected["time_not_increasing"] = int((~later).sum())
    return GnssTrack(t[later], v[later], source, {k: n for k, n in rejected.items() if n})


def read_gnss_track(path: str | os.PathLike[str]) -> GnssTrack | None:
    """The GNSS velocity of a log, or None when it holds no GNSS velocity record at all.

    Raises :class:`GnssLogError` when the records are there and cannot be read.
    """
    fmt = detect_format(path)
    try:
        if fmt is LogFormat.ULOG:
            return _ulog(path)
        if fmt is LogFormat.TLOG:
            return _tlog(path)
        return _dataflash(path, fmt)
    except GnssLogError:
        raise
    except Exception as exc:  # pyulog and pymavlink raise their own, struct and index errors
        raise GnssLogError(f"{os.fspath(path)}: GNSS records unreadable: {exc}") from exc


def _mentions(path: str | os.PathLike[str], *names: bytes) -> bool:
    """Whether the file's bytes hold any of ``names`` anywhere: a topic or message of that name
    cannot be in a log whose bytes do not hold it. pyulog and pymavlink's text reader decode every
    record in Python to find the few GNSS ones, as long as reading the IMU again: a log without
    GNSS skips that. Read in blocks of :data:`SEARCH_BLOCK_BYTES` (a mapped file's pages would count
    in the process's resident memory), each searched with the last bytes before it."""
    tail = b""
    keep = max(map(len, names)) - 1
    with open(path, "rb") as fh:
        while block := fh.read(SEARCH_BLOCK_BYTES):
            window = tail + block
            if any(name in window for name in names):
                return True
            tail = window[max(0, len(window) - keep) :]
    return False


def _ulog(path: str | os.PathLike[str]) -> GnssTrack | None:
    from pyulog import ULog

    if not _mentions(path, *(topic.encode() for topic in ULOG_GNSS_TOPICS)):
        return None
    # pyulog prints its findings on a damaged file to stdout, where --json writes (protocols.ulog).
    with contextlib.redirect_stdout(io.StringIO()):
        log = ULog(os.fspath(path), list(ULOG_GNSS_TOPICS), disable_str_exceptions=True)
    # An instance subscribed twice (ULog allows it: two message ids) is one receiver.
    instances: dict[tuple[int, int], list[dict[str, np.ndarray]]] = {}
    for d in log.data_list:
        instances.setdefault((ULOG_GNSS_TOPICS.index(d.name), d.multi_id), []).append(d.data)
    several = {topic for topic, multi_id in instances if multi_id > 0}
    tracks, unreadable = [], {}
    for (topic, multi_id), parts in sorted(instances.items()):
        name = ULOG_GNSS_TOPICS[topic]
        source = f"{name}.{multi_id}" if topic in several else name
        try:
            tracks.append(_ulog_track(_merged(parts), source))
        except KeyError as exc:
            unreadable[source] = f"no field {exc.args[0]}"
    if not tracks:
        if unreadable:  # read_gnss_track says it with the file
            raise ValueError("; ".join(f"{s}: {why}" for s, why in unreadable.items()))
        if log.file_corruption:
            # Its bytes name a GNSS topic, and a damaged definition drops its records unsaid.
            raise ValueError(
                f"the file is damaged and no record of {' or '.join(ULOG_GNSS_TOPICS)} was read"
            )
        return None
    taken = max(tracks, key=lambda track: track.t_s.size)  # the first of a tie (module docstring)
    unused = {track.source: int(track.t_s.size) for track in tracks if track is not taken}
    return replace(taken, unused=unused, unreadable=unreadable)


def _merged(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One instance's fields from its subscriptions, in time order (each subscription's own)."""
    if len(parts) == 1:
        return parts[0]
    f = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(f["timestamp"], kind="stable")
    return {k: v[order] for k, v in f.items()}


def _ulog_track(f: dict[str, np.ndarray], source: str) -> GnssTrack:
    """The epochs of one instance of a :data:`ULOG_GNSS_TOPICS` topic: NED m/s to ENU, µs to s;
    a ``vel_ned_valid`` the message version lacks is no flag. KeyError: a field it lacks."""
    vel = np.column_stack([f["vel_e_m_s"], f["vel_n_m_s"], -np.asarray(f["vel_d_m_s"], float)])
    fix_ok = np.asarray(f["fix_type"]) >= GPS_FIX_3D
    vel_ok = np.asarray(f["vel_ned_valid"]) != 0 if "vel_ned_valid" in f else None
    t_s = np.asarray(f["timestamp"], float) * 1e-6
    return _track(t_s, vel.astype(float), fix_ok, source, vel_ok, MAX_SPEED_MPS)


def _messages(path: str | os.PathLike[str], kind: str) -> list[Any]:
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(os.fspath(path))
    try:
        out = []
        while (msg := conn.recv_match(type=kind)) is not None:
            out.append(msg)
        return out
    finally:
        conn.close()


def _dataflash(path: str | os.PathLike[str], fmt: LogFormat) -> GnssTrack | None:
    if fmt is LogFormat.DATAFLASH_BIN:
        msgs = _bin_gps_messages(path)
    elif _mentions(path, b"GPS"):
        msgs = _messages(path, "GPS")
    else:
        return None
    msgs = [m for m in msgs if int(getattr(m, "I", 0)) == 0]
    if not msgs:
        return None
    rows = np.array([[_boot_time_us(m), m.Status, m.Spd, m.GCrs, m.VZ] for m in msgs], float)
    course = np.radians(rows[:, 3])
    vel = np.column_stack([rows[:, 2] * np.sin(course), rows[:, 2] * np.cos(course), -rows[:, 4]])
    return _track(rows[:, 0] * 1e-6, vel, rows[:, 1] >= GPS_FIX_3D, "GPS", None, MAX_SPEED_MPS)


def _bin_gps_messages(path: str | os.PathLike[str]) -> list[Any]:
    """The ``GPS`` messages of a binary log as pymavlink ``DFMessage`` values, found by the numpy
    scan of :mod:`protocols.dataflash_numpy`: pymavlink's reader builds a message of every record
    (the IMU's at 1 kHz) to hand out the few GPS ones, half of a replay's time on a 1 kHz log.
    pymavlink stays the oracle (tests/test_thrust_gnss_replay.py)."""
    from protocols.dataflash_numpy import DataFlashScan

    scan = DataFlashScan(Path(path), wanted=frozenset(["GPS"]), held={}, flush=1)
    return list(scan)


def _boot_time_us(msg: Any) -> float:
    """The boot clock of a DataFlash GPS record: ``TimeUS``; before it (ArduCopter 3.1) ``TimeMS``
    was the GPS week's time and ``T`` the boot clock in ms."""
    if hasattr(msg, "TimeUS"):
        return float(msg.TimeUS)
    return float(msg.T) * 1e3


def gps_raw_int_rows(msgs: list[Any]) -> FloatArray:
    """(M, 5) ``[t_s, fix_type, speed m/s, course rad, alt m]`` of GPS_RAW_INT messages; unknown
    speed or course are NaN."""
    return gps_raw_int_si(
        np.array([[getattr(m, f) for f in GPS_RAW_INT_FIELDS] for m in msgs], float)
    )


def gps_raw_int_si(raw: FloatArray) -> FloatArray:
    """:func:`gps_raw_int_rows` of the messages' fields (M, 5), columns :data:`GPS_RAW_INT_FIELDS`
    (what a live link's reader keeps, :mod:`protocols.mavlink_gnss`)."""
    rows = np.asarray(raw, float)
    out = np.column_stack(
        [
            rows[:, 0] * 1e-6,
            rows[:, 1],
            np.where(rows[:, 2] == UNKNOWN_U16, np.nan, rows[:, 2] * 1e-2),
            np.where(rows[:, 3] == UNKNOWN_U16, np.nan, np.radians(rows[:, 3] * 1e-2)),
            rows[:, 4] * 1e-3,
        ]
    )
    return out


def gps_raw_int_altitudes(rows: FloatArray) -> np.ndarray:
    """Indices of the rows of :func:`gps_raw_int_rows` whose altitudes give the vertical: those with
    a fix and a clock later than every row with a fix before (a clock that went back and forward
    again gave the centred difference times out of order)."""
    idx = np.flatnonzero(rows[:, 1] >= GPS_FIX_3D)
    t = rows[idx, 0]
    later = np.r_[True, t[1:] > np.maximum.accumulate(t)[:-1]] if t.size else np.empty(0, bool)
    return idx[later]


def gps_raw_int_track(rows: FloatArray) -> GnssTrack:
    """A track from :func:`gps_raw_int_rows` (the vertical from the altitude; module docstring)."""
    fix_ok = rows[:, 1] >= GPS_FIX_3D
    t = rows[:, 0]
    up = np.full(t.size, np.nan)
    good = gps_raw_int_altitudes(rows)
    if good.size >= 3:
        up[good] = up_velocity_from_altitude(t[good], rows[good, 4])
    speed, course = rows[:, 2], rows[:, 3]
    vel = np.column_stack([speed * np.sin(course), speed * np.cos(course), up])
    return _track(t, vel, fix_ok, "GPS_RAW_INT", None, MAX_SPEED_MPS)


def _tlog(path: str | os.PathLike[str]) -> GnssTrack | None:
    rows = _scanned_gps_raw_int_rows(path)
    if rows is None:
        msgs = _messages(path, "GPS_RAW_INT")
        rows = gps_raw_int_rows(msgs) if msgs else np.zeros((0, 5))
    return gps_raw_int_track(rows) if rows.shape[0] else None


def _scanned_gps_raw_int_rows(path: str | os.PathLike[str]) -> FloatArray | None:
    """:func:`gps_raw_int_rows` of a tlog's GPS_RAW_INT records found by the numpy scan of
    :mod:`protocols.tlog_numpy` (pymavlink's reader builds a message of every record, the IMU's at
    1 kHz, to hand out the few GPS ones); None where the scan stops short of the end (damage,
    signed packets): pymavlink reads that file. pymavlink stays the oracle
    (tests/test_thrust_gnss_replay.py)."""
    from protocols.tlog_numpy import TlogScan

    scan = TlogScan(
        Path(path),
        held={},
        dropped={},
        flush=1,
        raw_scale=MILLI_UNITS,
        imu_index={},
        records=frozenset(["GPS_RAW_INT"]),
    )
    for _ in scan:
        pass
    if scan.stopped_at is not None:
        return None
    rec = scan.records["GPS_RAW_INT"]
    if not rec:
        return np.zeros((0, 5))
    r = np.concatenate(rec)
    return gps_raw_int_si(np.column_stack([r[f].astype(float) for f in GPS_RAW_INT_FIELDS]))


def gps_raw_int_messages(
    t_s: FloatArray, vel_enu_mps: FloatArray, alt_m: FloatArray, *, source_system: int = 1
) -> list[bytes]:
    """Packed MAVLink 2 GPS_RAW_INT messages (3D fix) of a receiver, as an autopilot sends them (for
    tests and the demo). Speed, course and altitude quantize to cm/s, cdeg and mm."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    mav = mavlink2.MAVLink(
        None, srcSystem=source_system, srcComponent=mavlink2.MAV_COMP_ID_AUTOPILOT1
    )
    v = np.asarray(vel_enu_mps, float)
    speed = np.hypot(v[:, 0], v[:, 1])
    course_cdeg = np.round(np.degrees(np.arctan2(v[:, 0], v[:, 1])) * 100.0) % 36000
    return [
        mavlink2.MAVLink_gps_raw_int_message(
            time_usec=round(t * 1e6), fix_type=GPS_FIX_3D, lat=0, lon=0,
            alt=round(alt_m[k] * 1e3), eph=100, epv=150, vel=round(speed[k] * 100.0),
            cog=int(course_cdeg[k]), satellites_visible=12,
        ).pack(mav)
        for k, t in enumerate(np.asarray(t_s, float))
    ]  # fmt: skip


def append_gps_raw_int(
    path: str | os.PathLike[str],
    t_s: FloatArray,
    vel_enu_mps: FloatArray,
    alt_m: FloatArray,
    *,
    wall_start_s: float = 1.7e9,
    source_system: int = 1,
) -> int:
    """Append :func:`gps_raw_int_messages` to a telemetry log (beside
    :func:`protocols.logs.write_tlog`'s IMU records; record stamps ``wall_start_s + t_s``);
    returns the number written."""
    packets = gps_raw_int_messages(t_s, vel_enu_mps, alt_m, source_system=source_system)
    with open(path, "ab") as fh:
        for t, packet in zip(np.asarray(t_s, float), packets, strict=True):
            fh.write(struct.pack(">Q", round((wall_start_s + t) * 1e6)) + packet)
    return len(packets)
