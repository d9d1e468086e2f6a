"""A MAVLink link read in a process of its own: pymavlink's parse off the service's interpreter.

pymavlink parses in Python: framing, CRC, signature and unpacking cost about
10 µs a message, and a link of one message per UDP datagram adds a system
call each. In the service's process that work takes the interpreter from the
pipeline (one GIL), and one instance read about 30 k messages/s of one sample
each. :class:`MavlinkProcessLink` runs :class:`~protocols.mavlink_adapter.MavlinkLink`
in a child process (``python -m protocols.mavlink_process``, a fresh
interpreter: nothing of the service's threads or sockets is inherited, and the
service's main module is not imported again) that opens the device, reads and parses, gathers ``gather_s`` of
samples, and sends their fields over a pipe, one array per message type
(:meth:`~protocols.mavlink_adapter.MavlinkLink.read_fields`). The service
turns them into batches (:class:`~protocols.mavlink_adapter.ImuConverter`):
the child's core is left to pymavlink's parse, which sets the rate a link
keeps up with (under 50 k messages/s of the latency benchmark the child
was, at times, that core's whole time).

The child is the link's only owner, so everything sent (HEARTBEAT, STATUSTEXT,
signed when signing is on) goes through it too: a command over a second pipe,
answered when the child has written it (or with the error it met). The
service's side makes and numbers the batches (``seq`` per IMU, continued across child
restarts), counts what was sent when the child answers, and adds up the
counters of what the child read (deltas with every batch and at least every
:data:`COUNTERS_PERIOD_S`, taken in by :meth:`MavlinkProcessLink.read`), so
:attr:`counters` is the link's whole history whatever the child's. A child that dies (killed, out of
memory) makes the next :meth:`MavlinkProcessLink.read` raise
:class:`ReaderProcessEnded`; the read after that starts a new child.
The GPS_RAW_INT messages of the IMUs' system go over the same pipe, their fields as they are
(``("gnss", rows)`` before the fields and counters they were read with), for
:meth:`MavlinkProcessLink.take_gnss`. The pipe's messages are those of :data:`PROTOCOL_VERSION`, which
the child says when it is ready: a child of another version (the package replaced under a running
service, then a child restarted) is refused with that said, rather than misread.
The system whose IMU messages are read (``autopilot_system``, else the first
heard: :class:`~protocols.mavlink_adapter.ImuBatcher`) is chosen in the child,
which leaves the others' messages out before they cost the pipe anything, and
reported with its counters (:attr:`LinkCounters.imu_system`); the service hands
it to each new child, so that a restart does not let another system's IMU in.
The child ignores SIGINT, SIGTERM and SIGHUP (systemd signals the unit's whole group, and a closed
terminal the whole process group; the service logs and ignores SIGHUP):
it ends when the service closes the command pipe, or when the service is gone.
"""

from __future__ import annotations

import gc
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from protocols.events import Event, Severity
from protocols.frames import SampleBatch
from protocols.mavlink_adapter import (
    READER_RETRY_S,
    ImuConverter,
    LinkCounters,
    MavlinkLink,
)
from protocols.mavlink_settings import MavlinkSettings

# The folder the top package of this module's name is found in: the checkout for
# ``protocols.mavlink_process``, site-packages for ``ins_health.protocols.mavlink_process``.
_ROOT = Path(__file__).resolve().parents[__spec__.name.count(".")]
PROTOCOL_VERSION = 2
"""The pipe's messages: 1 ``ready``, ``fields``, ``failure``, ``error``; 2 adds ``gnss`` (and the
version in ``ready``, which version 1 left out)."""
START_TIMEOUT_S = 60.0
"""Longest wait for a child to import, open the device and say it is ready."""
REPLY_TIMEOUT_S = 5.0
"""Longest wait for the child to say it has written a message (a serial port may block)."""
COUNTERS_PERIOD_S = 0.2
"""The child reports its counters at least this often, batches or not (rejected input shows)."""
STOP_TIMEOUT_S = 2.0
"""The child has this long to close its device after the command pipe closes; then it is killed."""


class ReaderProcessEnded(ConnectionError):
    """The reader process is gone (its exit code in the message); the next read starts another."""


class ReaderProcessFailed(OSError):
    """The reader process could not open the device, or its read failed (its traceback in the message)."""


# What the child reads; what it sends is counted here when it answers (so at once, not with the next batch).
_SCALARS = ("messages", "gnss_messages", "dropped_kernel", "signing_stale")
_TABLES = ("imu_samples", "rejected", "ignored_systems")


def _delta(now: LinkCounters, before: LinkCounters) -> dict[str, Any]:
    """What ``now`` gained over ``before`` (plain values: the child runs as ``__main__``), and ``before`` set to ``now``;
    the system whose IMU messages are read as it is."""
    d: dict[str, Any] = {"imu_system": now.imu_system}
    for name in _SCALARS:
        value = getattr(now, name)
        d[name] = value - getattr(before, name)
        setattr(before, name, value)
    for name in _TABLES:
        table, seen = dict(getattr(now, name)), getattr(before, name)
        d[name] = {k: n - seen.get(k, 0) for k, n in table.items() if n != seen.get(k, 0)}
        seen.update(table)
    return d


def _add(counters: LinkCounters, d: dict[str, Any]) -> None:
    if d["imu_system"] is not None:
        counters.imu_system = d["imu_system"]
    for name in _SCALARS:
        setattr(counters, name, getattr(counters, name) + d[name])
    for name in _TABLES:
        table = getattr(counters, name)
        for k, n in d[name].items():
            table[k] = table.get(k, 0) + n


class MavlinkProcessLink:
    """A :class:`~protocols.mavlink_adapter.MavlinkLink` served by a child process (module docstring).

    The same calls as the in-process link: :meth:`read` (batches, ``seq``
    counted here), :meth:`send_heartbeat`, :meth:`send_text`,
    :meth:`send_alert`, :meth:`close`, :attr:`counters`, :attr:`settings`.
    ``gather_s`` is the child's: it gathers that long after the first bytes
    before it sends what it has. Opening raises :class:`ReaderProcessFailed`
    with the child's reason when the device cannot be opened.
    """

    def __init__(self, settings: MavlinkSettings, *, gather_s: float = 0.0, poll_s: float = 0.1):
        self.settings = settings
        self.counters = LinkCounters(imu_system=settings.autopilot_system)
        self.restarts = 0
        """Children started after the first (each after one ended)."""
        self.udp_rcvbuf_granted_bytes: int | None = None
        """The receive buffer the kernel granted the child's UDP socket (None on other links)."""
        self._gather_s = float(gather_s)
        self._poll_s = float(poll_s)
        self._converter = ImuConverter(settings, self.counters)
        self._gnss: list[np.ndarray] = []
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._data: Connection | None = None
        self._cmd: Connection | None = None
        self._calls = 0
        """Commands sent to a child so far: each reply names its command's number."""
        self._closed = False
        self._start()

    @property
    def pid(self) -> int | None:
        """The running child's process id (None while none runs)."""
        return None if self._proc is None else self._proc.pid

    def _start(self) -> None:
        data, data_child = socket.socketpair()
        cmd, cmd_child = socket.socketpair()
        env = dict(os.environ)
        # The child imports this package from where the service does, installed or not.
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(_ROOT), env.get("PYTHONPATH")]))
        with data_child, cmd_child:
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    __spec__.name,
                    str(data_child.fileno()),
                    str(cmd_child.fileno()),
                ],
                pass_fds=(data_child.fileno(), cmd_child.fileno()),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                env=env,
            )
        data_conn, cmd_conn = Connection(data.detach()), Connection(cmd.detach())
        try:
            # The system a previous child read (None: the child takes the first it hears).
            cmd_conn.send((self.settings, self._gather_s, self._poll_s, self.counters.imu_system))
            if not data_conn.poll(START_TIMEOUT_S):
                raise ReaderProcessFailed(
                    f"mavlink {self.settings.device}: the reader process did not start within {START_TIMEOUT_S:.0f} s"
                )
            first = data_conn.recv()
            if first[0] != "ready":
                raise ReaderProcessFailed(f"mavlink {self.settings.device}: {first[1]}")
            version = first[2] if len(first) > 2 else 1
            if version != PROTOCOL_VERSION:
                raise ReaderProcessFailed(
                    f"mavlink {self.settings.device}: the reader process speaks version {version}, "
                    f"this service {PROTOCOL_VERSION} (the package was replaced: restart the service)"
                )
            self.udp_rcvbuf_granted_bytes = first[1]
        except (EOFError, OSError) as exc:
            data_conn.close()
            cmd_conn.close()
            _end(proc)
            if isinstance(exc, ReaderProcessFailed):
                raise
            raise ReaderProcessFailed(
                f"mavlink {self.settings.device}: the reader process ended at start (exit code {proc.returncode})"
            ) from None
        with self._lock:
            self._proc, self._data, self._cmd = proc, data_conn, cmd_conn

    def read(self, timeout_s: float, *, gather_s: float = 0.0) -> list[SampleBatch]:
        """The batches the child sent, ``[]`` if none came within ``timeout_s``.

        ``gather_s`` is accepted for the in-process link's signature; the child
        gathers for the ``gather_s`` it was started with. Raises
        :class:`ReaderProcessEnded` once when the child is gone (the next call
        starts another) and :class:`ReaderProcessFailed` when its read failed.
        """
        if self._data is None:
            if self._closed:
                return []
            self._start()
            self.restarts += 1
        data = self._data
        assert data is not None
        try:
            if not data.poll(timeout_s):
                return []
            message = data.recv()
        except (EOFError, OSError):
            raise self._ended() from None
        if message[0] == "failure":
            raise ReaderProcessFailed(f"mavlink {self.settings.device}: {message[1]}")
        if message[0] == "gnss":
            self._gnss.append(message[1])
            return []
        fields, delta = message[1], message[2]
        _add(self.counters, delta)
        return [b for kind, a in fields for b in self._converter.batches(kind, a)]

    def take_gnss(self) -> np.ndarray | None:
        """The GPS_RAW_INT fields the child sent since the last call
        (:meth:`~protocols.mavlink_adapter.MavlinkLink.take_gnss`); None when it sent none."""
        rows, self._gnss = self._gnss, []
        return np.concatenate(rows) if rows else None

    def _ended(self) -> ReaderProcessEnded:
        return ReaderProcessEnded(
            f"mavlink {self.settings.device}: the reader process ended (exit code {self._let_go()}); "
            "the next read starts another"
        )

    def _let_go(self) -> int | None:
        """Forget the child: close its command pipe (it ends on that), wait for it, close its data pipe.

        Its exit code; None when none ran.
        """
        with self._lock:
            proc, data, cmd = self._proc, self._data, self._cmd
            self._proc = self._data = self._cmd = None
        if cmd is not None:
            cmd.close()
        code = None if proc is None else _end(proc)
        if data is not None:
            data.close()
        return code

    def _call(self, name: str, *args: object) -> Any:
        with self._lock:
            cmd = self._cmd
            if cmd is None:
                raise ReaderProcessEnded(
                    f"mavlink {self.settings.device}: no reader process to send through"
                )
            self._calls += 1
            tag = self._calls
            deadline_s = time.monotonic() + REPLY_TIMEOUT_S
            try:
                cmd.send((tag, name, *args))
                while True:
                    if not cmd.poll(max(0.0, deadline_s - time.monotonic())):
                        raise TimeoutError(
                            f"mavlink {self.settings.device}: the reader process did not write within {REPLY_TIMEOUT_S:.0f} s"
                        )
                    # A reply to a call that timed out before is not this call's: an alert whose
                    # write failed would be taken for one sent (and acked).
                    replied, ok, result = cmd.recv()
                    if replied == tag:
                        break
            except EOFError:
                raise ReaderProcessEnded(
                    f"mavlink {self.settings.device}: the reader process is gone"
                ) from None
        if not ok:
            raise ReaderProcessFailed(f"mavlink {self.settings.device}: {result}")
        return result

    def send_heartbeat(self) -> None:
        """One HEARTBEAT (the service sends it at 1 Hz)."""
        self._call("send_heartbeat")
        self.counters.count_sent("heartbeats_sent")

    def send_text(self, text: str, severity: Severity) -> int:
        """Free text as STATUSTEXT (chunked beyond 50 characters); returns messages sent."""
        n = int(self._call("send_text", text, severity))
        self.counters.count_sent("texts_sent", n)
        return n

    def send_alert(self, event: Event) -> str:
        """The event's :func:`~protocols.mavlink_adapter.alert_text` as one STATUSTEXT; returns the text."""
        text = str(self._call("send_alert", event))
        self.counters.count_sent("alerts_sent")
        return text

    def close(self) -> None:
        """End the child (it closes the device) and wait for it; :meth:`read` then returns ``[]``."""
        self._closed = True
        self._let_go()

    def __enter__(self) -> MavlinkProcessLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _end(proc: subprocess.Popen[bytes]) -> int:
    """Wait :data:`STOP_TIMEOUT_S` for the child to end by itself, then kill it; its exit code."""
    try:
        return proc.wait(STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


# --------------------------------------------------------------------------- the child


def serve(data: Connection, cmd: Connection) -> None:
    """The child's work: open the link, then read and report until the command pipe closes."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    try:
        settings, gather_s, poll_s, imu_system = cmd.recv()
    except (EOFError, OSError):
        return
    try:
        link = MavlinkLink(settings, imu_system=imu_system)
    except Exception as exc:
        data.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    # pymavlink's dialect tables live as long as the child: out of the collector's full passes, which
    # would hold the batches back (the service's command does the same, service.commands.run).
    gc.collect()
    gc.freeze()
    stop = threading.Event()
    threading.Thread(target=_commands, args=(link, cmd, stop), daemon=True).start()
    reported = LinkCounters()
    try:
        data.send(("ready", link.udp_rcvbuf_granted_bytes, PROTOCOL_VERSION))
        last_s = time.monotonic()
        while not stop.is_set():
            try:
                fields = link.read_fields(poll_s, gather_s=gather_s)
            except Exception:
                data.send(("failure", traceback.format_exc()))
                stop.wait(READER_RETRY_S)
                continue
            if (gnss := link.take_gnss()) is not None:
                data.send(("gnss", gnss))
            now = time.monotonic()
            if fields or now - last_s >= COUNTERS_PERIOD_S:
                data.send(("fields", fields, _delta(link.counters, reported)))
                last_s = now
    except (BrokenPipeError, EOFError, ConnectionError):
        pass  # the service is gone: nobody to read for
    finally:
        link.close()


_COMMANDS = ("send_heartbeat", "send_text", "send_alert")


def _commands(link: MavlinkLink, cmd: Connection, stop: threading.Event) -> None:
    """Write what the service asks and answer (its number, True, result) or (its number, False, the
    error); the pipe's end stops the child."""
    try:
        while True:
            tag, name, *args = cmd.recv()
            try:
                if name not in _COMMANDS:
                    raise ValueError(f"unknown command {name!r}")
                reply = (tag, True, getattr(link, name)(*args))
            except Exception as exc:
                reply = (tag, False, f"{type(exc).__name__}: {exc}")
            cmd.send(reply)
    except (EOFError, OSError):
        pass
    finally:
        stop.set()


if __name__ == "__main__":
    serve(Connection(int(sys.argv[1])), Connection(int(sys.argv[2])))
