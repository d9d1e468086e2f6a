"""The health data an autopilot logs itself: ArduPilot ``VIBE`` and batch sampler, MAVLink ``VIBRATION``, PX4 ``vehicle_imu_status``.

Read in a pass of their own over the log (:func:`read_firmware_health`), with the libraries that
define them, in SI; summarised by :mod:`estimators.firmware_health` (definitions and thresholds):

* DataFlash ``.bin``/``.log`` (:class:`protocols.logs.DataFlashStream`, pymavlink's decoding):
  ``VIBE`` with an ``IMU`` field (ArduPilot 4.0 on): the levels ``VibeX/Y/Z`` (m/s²) and the clip
  counter ``Clip`` of that accelerometer instance; without one (earlier): the levels of the primary
  accelerometer and one counter per accelerometer, ``Clip0..2``.
  ``ISBH``/``ISBD`` (ArduPilot ``AP_Logger/LogStructure.h``): a header per batch (``N`` its number,
  ``type`` 0 accelerometer / 1 gyro, ``instance``, ``mul``, ``smp_cnt``, ``SampleUS`` the first
  sample's time, ``smp_rate`` Hz), then ``ISBD`` messages of batch ``N`` (``seqno``) with 32 int16
  samples per axis each, ``value × mul`` (m/s² or rad/s): one high-rate stream per sensor.
* ``.tlog`` (pymavlink): ``VIBRATION``: ``vibration_x/y/z`` (m/s², the primary accelerometer's,
  as ``VIBE``) and ``clipping_0..2``, one counter per accelerometer.
* ULog (pyulog, this topic only): each ``vehicle_imu_status`` instance: the accelerometer and gyro
  vibration metrics, coning, ``accel_clipping``/``gyro_clipping`` per axis, and the rates
  (``accel_rate_hz``, ``gyro_rate_hz``, ``accel_raw_rate_hz``, ``gyro_raw_rate_hz``).

A log the libraries cannot read for these messages gives no figures and says why (``unread``);
the IMU samples are read on their own (:mod:`protocols.logs`).
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
from collections.abc import Collection, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimators.firmware_health import (
    ARDUPILOT_CLIP_SOURCE,
    ARDUPILOT_VIBE_LIMITS_MPS2,
    ARDUPILOT_VIBE_SOURCE,
    BATCH_SATURATED,
    PX4_ACCEL_VIBE_LIMITS,
    PX4_VIBE_SOURCE,
    BatchStream,
    BatchStreamAccumulator,
    LevelSummary,
    counter_growth,
    counter_start,
    level_summary,
)
from protocols.logs import DataFlashStream, LogFormat

BATCH_SENSORS = {0: "accel", 1: "gyro"}
"""``ISBH.type``: ArduPilot's ``AP_InertialSensor::IMU_SENSOR_TYPE_ACCEL`` (0) and ``_GYRO`` (1)."""
_BATCH_UNITS = {"accel": "m/s^2", "gyro": "rad/s"}


@dataclass(frozen=True)
class FirmwareVibration:
    """One accelerometer's (or IMU's) vibration as the firmware logged it.

    ``instance``: the firmware's sensor instance, None for "the primary accelerometer" (``VIBRATION``
    and ``VIBE`` before ArduPilot 4.0); ``accel``: its level (``unit``) judged against ``limits``
    (warning, error) of ``source``; PX4 only: ``gyro`` (``gyro_unit``) and ``coning`` (rad²),
    ``clipping_axes`` (accelerometer growth per axis x, y, z) and ``rates_hz`` (medians).
    """

    message: str
    instance: int | None
    accel: LevelSummary
    unit: str
    limits: tuple[float, float]
    source: str
    gyro: LevelSummary | None = None
    gyro_unit: str | None = None
    coning: LevelSummary | None = None
    clipping_axes: list[int] | None = None
    rates_hz: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class BatchSensor:
    """One sensor's batch-sampler stream (``ISBH``/``ISBD``): ``sensor`` accel or gyro, its instance."""

    sensor: str
    instance: int
    unit: str
    stream: BatchStream


@dataclass(frozen=True)
class FirmwareHealth:
    """What the log's own health data say (module docstring): ``clipped`` accelerometer instance →
    clipped samples over the log (the growth of the firmware's counters); ``clipped_before_log``: what
    the counters held at the log's first message (clips since boot before it); ``unread``: why none
    was read."""

    vibration: list[FirmwareVibration] = field(default_factory=list)
    clipped: dict[int, int] = field(default_factory=dict)
    clipped_before_log: dict[int, int] = field(default_factory=dict)
    clip_message: str = ""
    clip_source: str = ""
    batches: list[BatchSensor] = field(default_factory=list)
    unread: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The report's plain form (spectra left out: they are plotted)."""
        return {
            "vibration": [asdict(v) for v in self.vibration],
            "clipped": {str(k): n for k, n in sorted(self.clipped.items())},
            "clipped_before_log": {str(k): n for k, n in sorted(self.clipped_before_log.items())},
            "clip_message": self.clip_message,
            "clip_source": self.clip_source,
            "batches": [
                {
                    "sensor": b.sensor,
                    "instance": b.instance,
                    "unit": b.unit,
                    "samples": b.stream.samples,
                    "blocks": b.stream.blocks,
                    "unusable_blocks": b.stream.unusable_blocks,
                    "rate_hz": b.stream.rate_hz,
                    "noise": b.stream.noise,
                    "saturated": b.stream.saturated,
                }
                for b in self.batches
            ],
            "unread": self.unread,
        }


FIRMWARE_MESSAGES = frozenset({"VIBE", "ISBH", "ISBD", "VIBRATION", "vehicle_imu_status"})
"""The message types (ULog topics) read here."""


def read_firmware_health(
    path: str | os.PathLike[str], log_format: LogFormat, held: Collection[str] | None = None
) -> FirmwareHealth:
    """The firmware's own health data of a log (module docstring). ``held``: the message types (ULog
    ``topic.instance``) the log holds, as its reader counted them (:attr:`protocols.logs.LogStats.held`):
    a log that holds none of :data:`FIRMWARE_MESSAGES` is not read again."""
    path = Path(path)
    if held is not None and not FIRMWARE_MESSAGES & {k.split(".")[0] for k in held}:
        return FirmwareHealth()
    try:
        if log_format is LogFormat.ULOG:
            return _ulog(path)
        if log_format is LogFormat.TLOG:
            return _tlog(path)
        return _dataflash(path, binary=log_format is LogFormat.DATAFLASH_BIN)
    except (
        OSError,
        ValueError,
        TypeError,
        AttributeError,
        KeyError,
        IndexError,
        struct.error,
    ) as exc:
        # A message the libraries cannot decode costs these figures, said, not the IMU report.
        return FirmwareHealth(unread=f"{type(exc).__name__}: {exc}")


def _ardupilot_vibe(
    message: str, instance: int | None, levels: list[tuple[float, float, float]]
) -> FirmwareVibration:
    return FirmwareVibration(
        message=message,
        instance=instance,
        accel=level_summary(np.array(levels, dtype=float), ARDUPILOT_VIBE_LIMITS_MPS2),
        unit="m/s^2",
        limits=ARDUPILOT_VIBE_LIMITS_MPS2,
        source=ARDUPILOT_VIBE_SOURCE,
    )


def _dataflash(path: Path, *, binary: bool) -> FirmwareHealth:
    stream = DataFlashStream(
        path, binary=binary, wanted=frozenset({"VIBE", "ISBH", "ISBD"}), held={}
    )
    levels: dict[int | None, list[tuple[float, float, float]]] = {}
    counters: dict[int, list[float]] = {}
    batches = _Batches()
    for msg in stream:
        name = msg.get_type()
        if name == "VIBE":
            fields = msg.get_fieldnames()
            inst = int(msg.IMU) if "IMU" in fields else None
            levels.setdefault(inst, []).append(
                (float(msg.VibeX), float(msg.VibeY), float(msg.VibeZ))
            )
            if "Clip" in fields and inst is not None:
                counters.setdefault(inst, []).append(float(msg.Clip))
            for k in range(3):
                if f"Clip{k}" in fields:
                    counters.setdefault(k, []).append(float(getattr(msg, f"Clip{k}")))
        elif name == "ISBH":
            batches.header(msg)
        else:
            batches.data(msg)
    return FirmwareHealth(
        vibration=[_ardupilot_vibe("VIBE", i, v) for i, v in sorted(levels.items(), key=_key)],
        clipped={k: counter_growth(np.array(v)) for k, v in sorted(counters.items())},
        clipped_before_log={k: counter_start(np.array(v)) for k, v in sorted(counters.items())},
        clip_message="VIBE" if counters else "",
        clip_source=ARDUPILOT_CLIP_SOURCE if counters else "",
        batches=batches.result(),
    )


def _key(item: tuple[int | None, Any]) -> int:
    return -1 if item[0] is None else item[0]


class _Batches:
    """``ISBH``/``ISBD`` gathered batch by batch into a :class:`BatchStreamAccumulator` per sensor."""

    def __init__(self) -> None:
        self._head: Any = None
        self._parts: list[np.ndarray] = []
        self._acc: dict[tuple[str, int], BatchStreamAccumulator] = {}

    def header(self, msg: Any) -> None:
        self._flush()
        self._head = msg

    def data(self, msg: Any) -> None:
        if self._head is not None and int(msg.N) == int(self._head.N):
            self._parts.append(np.array([msg.x, msg.y, msg.z], dtype=np.int64).T)

    def _flush(self) -> None:
        head, parts = self._head, self._parts
        self._head, self._parts = None, []
        if head is None or not parts or int(head.type) not in BATCH_SENSORS:
            return
        raw = np.vstack(parts)
        key = (BATCH_SENSORS[int(head.type)], int(head.instance))
        acc = self._acc.setdefault(key, BatchStreamAccumulator())
        saturated = int((np.abs(raw) >= BATCH_SATURATED).sum())
        with np.errstate(divide="ignore", invalid="ignore"):  # a multiplier of 0: counted unusable
            acc.add(raw / float(head.mul), float(head.smp_rate), saturated)

    def result(self) -> list[BatchSensor]:
        self._flush()
        return [
            BatchSensor(sensor, inst, _BATCH_UNITS[sensor], acc.result())
            for (sensor, inst), acc in sorted(self._acc.items())
        ]


def _tlog_messages(path: Path, kind: str) -> Iterator[Any]:
    from pymavlink import mavutil

    from protocols.mavlink_adapter import use_mavlink2

    conn = use_mavlink2(mavutil.mavlogfile(str(path), notimestamps=False))
    try:
        while (msg := conn.recv_msg()) is not None:
            if msg.get_type() == kind:
                yield msg
    finally:
        conn.close()


def _tlog(path: Path) -> FirmwareHealth:
    levels: list[tuple[float, float, float]] = []
    counters: dict[int, list[float]] = {}
    for msg in _tlog_messages(path, "VIBRATION"):
        levels.append((float(msg.vibration_x), float(msg.vibration_y), float(msg.vibration_z)))
        for k in range(3):
            counters.setdefault(k, []).append(float(getattr(msg, f"clipping_{k}")))
    if not levels:
        return FirmwareHealth()
    return FirmwareHealth(
        vibration=[_ardupilot_vibe("VIBRATION", None, levels)],
        clipped={k: counter_growth(np.array(v)) for k, v in sorted(counters.items())},
        clipped_before_log={k: counter_start(np.array(v)) for k, v in sorted(counters.items())},
        clip_message="VIBRATION",
        clip_source=ARDUPILOT_CLIP_SOURCE,
    )


def _ulog(path: Path) -> FirmwareHealth:
    from pyulog import ULog

    # pyulog prints its findings on a damaged file to stdout, where --json writes.
    with contextlib.redirect_stdout(io.StringIO()):
        log = ULog(str(path), ["vehicle_imu_status"])
    vibration = []
    clipped, before = {}, {}
    for d in sorted(log.data_list, key=lambda d: d.multi_id):
        data = d.data
        new = "delta_angle_coning_metric" in data
        unit, gyro_unit = ("m/s^2", "rad/s") if new else ("m/s", "rad")
        coning = data.get("delta_angle_coning_metric", data.get("gyro_coning_vibration"))
        accel_clip = [
            counter_growth(data[f"accel_clipping[{k}]"])
            for k in range(3)
            if f"accel_clipping[{k}]" in data
        ]
        rates = {
            k: float(np.median(r))
            for k in ("accel_rate_hz", "gyro_rate_hz", "accel_raw_rate_hz", "gyro_raw_rate_hz")
            if k in data and (r := data[k][np.isfinite(data[k])]).size
        }
        vibration.append(
            FirmwareVibration(
                message="vehicle_imu_status",
                instance=int(d.multi_id),
                accel=level_summary(data["accel_vibration_metric"], PX4_ACCEL_VIBE_LIMITS[unit]),
                unit=unit,
                limits=PX4_ACCEL_VIBE_LIMITS[unit],
                source=PX4_VIBE_SOURCE,
                gyro=level_summary(data["gyro_vibration_metric"]),
                gyro_unit=gyro_unit,
                coning=None if coning is None else level_summary(coning),
                clipping_axes=accel_clip or None,
                rates_hz=rates,
            )
        )
        if accel_clip:
            clipped[int(d.multi_id)] = sum(accel_clip)
            before[int(d.multi_id)] = sum(
                counter_start(data[f"accel_clipping[{k}]"])
                for k in range(3)
                if f"accel_clipping[{k}]" in data
            )
    return FirmwareHealth(
        vibration=vibration,
        clipped=clipped,
        clipped_before_log=before,
        clip_message="vehicle_imu_status" if clipped else "",
        clip_source="PX4 vehicle_imu_status accel_clipping: samples at the end of the range, per axis"
        if clipped
        else "",
    )
