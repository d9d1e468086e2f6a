"""The MAVLink link's settings and the names of what it reads, without pymavlink.

:class:`MavlinkSettings` (the ``[mavlink]`` table of the service configuration), the IMU
message types and their scales, and the reasons bytes are turned away: what the service's
configuration and the log readers share with :mod:`protocols.mavlink_adapter`, without
importing pymavlink and its dialects (about 40 ms of CPU with the bytecode cached, 0.3 s
compiled), which a replay of a ULog never uses.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from estimators.conventions import STANDARD_GRAVITY_MPS2

MAV_COMP_ID_ONBOARD_COMPUTER = 191
"""The component id of an onboard computer (pymavlink's ``MAV_COMP_ID_ONBOARD_COMPUTER``)."""


class ImuMessage(StrEnum):
    """The MAVLink messages read as IMU samples."""

    RAW_IMU = "RAW_IMU"
    SCALED_IMU = "SCALED_IMU"
    SCALED_IMU2 = "SCALED_IMU2"
    SCALED_IMU3 = "SCALED_IMU3"
    HIGHRES_IMU = "HIGHRES_IMU"


@dataclass(frozen=True)
class ImuScale:
    """SI value of one count of an integer IMU message."""

    accel_mps2_per_lsb: float
    gyro_rps_per_lsb: float
    temp_c_per_lsb: float


MILLI_UNITS = ImuScale(STANDARD_GRAVITY_MPS2 * 1e-3, 1e-3, 1e-2)
"""mG, mrad/s, cdegC: fixed by the standard for SCALED_IMU*."""
RAW_IMU_ARDUPILOT = MILLI_UNITS
"""ArduPilot's RAW_IMU scaling (the default for RAW_IMU)."""

DEFAULT_IMU_INDEX: Mapping[ImuMessage, int] = {
    ImuMessage.RAW_IMU: 0,
    ImuMessage.SCALED_IMU: 0,
    ImuMessage.SCALED_IMU2: 1,
    ImuMessage.SCALED_IMU3: 2,
    ImuMessage.HIGHRES_IMU: 0,
}


GPS_RAW_INT_FIELDS = ("time_usec", "fix_type", "vel", "cog", "alt")
"""The GPS_RAW_INT fields a link keeps (:meth:`ImuBatcher.take_gnss`), in the column order of
:func:`protocols.gnss_logs.gps_raw_int_si`."""


# --------------------------------------------------------------------------- the link

UDP_RCVBUF_BYTES = 4 << 20
"""Receive buffer asked for a UDP link by default (the kernel grants at most ``net.core.rmem_max``)."""
UDP_RCVBUF_MIN_BYTES = 4096
"""The least receive buffer a UDP link may ask for (the kernel's own floor is about this)."""


_NETWORK_DEVICES = ("udpin:", "udpout:", "udpbcast:", "udp:", "tcp:", "tcpin:")
_OTHER_DEVICES = ("uds:", "unix:", "mcast:", "wsserver:", "ws:", "wss:")
"""Unix sockets, multicast UDP (``mcast:`` or ``mcast:IP:PORT``, SITL's and MAVProxy's), websockets."""
_LOG_SUFFIXES = (".bin", ".log", ".tlog", ".px4log", ".raw", ".mavlink")


def _check_device(device: str) -> None:
    """A live link's pymavlink connection string, else ``ValueError`` at configuration time.

    pymavlink takes any other string with a colon for a UDP address (``bogus:://`` failed only at
    start, "UDP ports must be specified as host:port"), reads a log file for a path to one, and runs
    a regular file under ``/bin/`` or named ``.elf`` as a child process."""
    for prefix in _NETWORK_DEVICES:
        if device.startswith(prefix):
            host, sep, port = device[len(prefix) :].rpartition(":")
            # pymavlink splits at the first colon: an IPv6 host never opens.
            if not (sep and host and port.isdigit() and int(port) <= 65535) or ":" in host:
                raise ValueError(
                    f"mavlink device {device!r}: {prefix} takes HOST:PORT (a port 0..65535; "
                    "pymavlink has no IPv6 address)"
                )
            return
    if device.startswith(_OTHER_DEVICES):
        return
    if ":" in device or device.lower().endswith(_LOG_SUFFIXES) or os.path.isfile(device):
        raise ValueError(
            f"mavlink device {device!r} is no live link: give udpin:, udpout:, udpbcast:, udp:, tcp: or "
            "tcpin: with HOST:PORT, uds: or unix: with a socket path, mcast:, ws:, wss: or wsserver:, "
            "or a serial device path without a colon (/dev/ttyACM0, /dev/serial/by-id/...)"
        )


@dataclass(frozen=True)
class MavlinkSettings:
    """One MAVLink link; :meth:`from_dict` reads the ``[mavlink]`` table of the service configuration.

    Attributes
    ----------
    device : pymavlink connection string: ``udpin:0.0.0.0:14550``, ``udpout:host:port``,
        ``tcp:host:port``, ``tcpin:host:port``, or a serial device ``/dev/ttyACM0``.
    vehicle : vehicle id given to the batches read from this link.
    baud : serial baud rate.
    source_system : our MAVLink system id (an onboard computer uses its vehicle's, usually 1).
    source_component : our component id (default MAV_COMP_ID_ONBOARD_COMPUTER = 191).
    autopilot_system : accept IMU messages only from this system id. None (the default): from the
        system of the first IMU message the link reads; the IMU messages of any other system (a
        second vehicle on a shared radio or UDP bus, a simulator, a ground station replaying a
        log) are then refused, counted and logged once per system id (:class:`ImuBatcher`).
    messages : IMU message types read.
    imu_index : message type → IMU index (module docstring).
    raw_scale : scaling of RAW_IMU counts.
    signing_key : 32-byte MAVLink 2 signing secret; when set, everything sent is signed and
        only IMU messages signed with it are read (unsigned, wrongly signed and replayed ones
        are refused and counted, :class:`LinkRejection`).
    signing_link_id : link id in the signature.
    accept_unsigned : with signing on, still read IMU messages that are unsigned or fail the
        check (default false; a transition aid while autopilots are being given the key).
    udp_rcvbuf_bytes : receive buffer asked for a UDP link, bytes (the kernel grants at most
        ``net.core.rmem_max``). What it holds is the longest backlog a reader behind its input
        builds before the kernel drops datagrams (counted, :attr:`LinkCounters.dropped_kernel`).
        The kernel charges each datagram about 800 bytes besides its own: the default,
        :data:`UDP_RCVBUF_BYTES`, held 10,082 datagrams of one HIGHRES_IMU message (0.2 s of 50 k
        messages/s) or 3,640 of 20 (1.5 s) on Linux 6. A smaller one bounds how stale a sample
        read late can be.
    """

    device: str
    vehicle: str
    baud: int = 115200
    source_system: int = 1
    source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER
    autopilot_system: int | None = None
    messages: tuple[ImuMessage, ...] = tuple(ImuMessage)
    imu_index: Mapping[ImuMessage, int] = field(default_factory=lambda: dict(DEFAULT_IMU_INDEX))
    raw_scale: ImuScale = RAW_IMU_ARDUPILOT
    signing_key: bytes | None = None
    signing_link_id: int = 1
    accept_unsigned: bool = False
    udp_rcvbuf_bytes: int = UDP_RCVBUF_BYTES

    def __post_init__(self) -> None:
        _check_device(self.device)
        if (
            not isinstance(self.udp_rcvbuf_bytes, int)
            or self.udp_rcvbuf_bytes < UDP_RCVBUF_MIN_BYTES
        ):
            raise ValueError(
                f"udp_rcvbuf_bytes must be an integer of at least {UDP_RCVBUF_MIN_BYTES}, got {self.udp_rcvbuf_bytes!r}"
            )
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError(f"a MAVLink 2 signing key has 32 bytes, got {len(self.signing_key)}")
        for name in ("source_system", "source_component", "signing_link_id"):
            value = getattr(self, name)
            if not 0 <= value <= 255:
                raise ValueError(f"{name} must be in 0..255, got {value}")
        object.__setattr__(self, "messages", tuple(ImuMessage(m) for m in self.messages))

    _PLAIN_KEYS = (
        "device",
        "vehicle",
        "baud",
        "source_system",
        "source_component",
        "autopilot_system",
        "signing_link_id",
        "accept_unsigned",
        "udp_rcvbuf_bytes",
    )
    """The keys taken as they are; the others are converted (:meth:`from_dict`)."""
    _KEYS = (
        *_PLAIN_KEYS,
        "messages",
        "imu_index",
        "raw_scale",
        "signing_key_hex",
        "signing_key_file",
    )

    @classmethod
    def from_dict(cls, table: Mapping[str, Any]) -> MavlinkSettings:
        """From a plain dict: as the attributes, with the key as ``signing_key_hex`` (64 hex digits) or
        ``signing_key_file`` (a regular file holding them, e.g. ``openssl rand -hex 32``), ``raw_scale`` as ``{accel_mps2_per_lsb, gyro_rps_per_lsb, temp_c_per_lsb}`` and
        ``imu_index`` as ``{"SCALED_IMU2": 1, ...}``. Errors are ``ValueError`` naming the key."""
        unknown = sorted(set(table) - set(cls._KEYS))
        if unknown:
            raise ValueError(f"unknown mavlink setting(s) {unknown}; allowed: {list(cls._KEYS)}")
        for name in ("device", "vehicle"):
            if not isinstance(table.get(name), str) or not table[name]:
                raise ValueError(f"mavlink {name} must be a non-empty string")
        kw: dict[str, Any] = {k: table[k] for k in cls._PLAIN_KEYS if k in table}
        try:
            if "messages" in table:
                kw["messages"] = tuple(ImuMessage(m) for m in table["messages"])
            if "imu_index" in table:
                kw["imu_index"] = {
                    **DEFAULT_IMU_INDEX,
                    **{ImuMessage(k): int(v) for k, v in table["imu_index"].items()},
                }
        except ValueError as exc:
            raise ValueError(
                f"mavlink messages/imu_index: {exc}; known: {[m.value for m in ImuMessage]}"
            ) from None
        if "raw_scale" in table:
            kw["raw_scale"] = ImuScale(**{k: float(v) for k, v in table["raw_scale"].items()})
        if "signing_key_hex" in table and "signing_key_file" in table:
            raise ValueError("mavlink signing_key_hex and signing_key_file: give one of them")
        if "signing_key_hex" in table:
            kw["signing_key"] = _signing_key(table["signing_key_hex"], "signing_key_hex")
        if "signing_key_file" in table:
            kw["signing_key"] = _signing_key(
                read_key_file(table["signing_key_file"]), "signing_key_file"
            )
        return cls(**kw)


KEY_FILE_MAX_BYTES = 1024


def read_key_file(path: str | os.PathLike[str]) -> str:
    """The text of a signing-key file: a regular file, opened without blocking, at most
    :data:`KEY_FILE_MAX_BYTES` read (a FIFO or a device is refused, never waited on).
    ``ValueError`` naming the file otherwise."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise ValueError(f"mavlink signing_key_file {str(path)!r}: {exc.strerror}") from None
    with os.fdopen(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError(f"mavlink signing_key_file {str(path)!r} is not a regular file")
        data = fh.read(KEY_FILE_MAX_BYTES + 1)
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        raise ValueError(f"mavlink signing_key_file {str(path)!r} is not text") from None


def _signing_key(text: object, name: str) -> bytes:
    try:
        key = bytes.fromhex(str(text).strip()) if isinstance(text, str) else None
    except ValueError:
        key = None
    if key is None or len(key) != 32:
        raise ValueError(f"mavlink {name} must hold 64 hexadecimal digits (32 bytes)")
    return key


class LinkRejection(StrEnum):
    """Why bytes received on the link were turned away before any IMU sample was read from them.

    Counted in :attr:`LinkCounters.rejected` (the status topic's
    ``service.mavlink.rejected.<reason>``) next to the sample-level reasons of
    :class:`~protocols._schema.Reason`. Framing, CRC and signature checks are
    pymavlink's; this only sorts what pymavlink refused.
    """

    GARBAGE_BYTES = "garbage_bytes"
    """Bytes outside any packet: no start marker, or a packet cut short at the end of a datagram (counts bytes)."""
    BAD_CRC = "bad_crc"
    """Packets whose checksum (CRC-16/MCRF4XX with the message's CRC_EXTRA) does not match."""
    MALFORMED = "malformed"
    """Packets with a length or flags no MAVLink packet has."""
    UNSIGNED = "unsigned"
    """IMU and GPS_RAW_INT messages without a signature while a signing key is configured."""
    BAD_SIGNATURE = "bad_signature"
    """IMU and GPS_RAW_INT messages signed with another key, or replayed (a time stamp not newer
    than the stream's last)."""
    GNSS_OTHER_SYSTEM = "gnss_other_system"
    """GPS_RAW_INT messages of a system other than the one whose IMU messages are read, or sent
    before any IMU message chose it: another clock than the IMUs'."""
    FIELDS_NOT_UPDATED = "fields_not_updated"
    """HIGHRES_IMU messages whose ``fields_updated`` does not flag all six accelerometer and gyro
    fields: what they hold there is no new measurement (a held or zeroed value)."""
