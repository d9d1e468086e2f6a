"""systemd's notification protocol (sd_notify(3)), a datagram to ``$NOTIFY_SOCKET``, and the watchdog's rule.

The unit (``deploy/ins-health.service``) is ``Type=notify`` with ``WatchdogSec=``: the daemon
sends ``READY=1`` once it takes frames, ``WATCHDOG=1`` while its frame path is healthy
(:class:`FramePathWatch`), and ``STOPPING=1`` when SIGTERM starts the drain. Without
``$NOTIFY_SOCKET`` (not started by systemd) every send is a no-op. The protocol is a few
lines of socket code, so no library is added for it.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

from service.log_setup import logger

log = logger("notify")


class Notifier:
    """Sends notifications to the service manager named by ``environ`` (``NOTIFY_SOCKET``, ``WATCHDOG_USEC``).

    A failed send is logged once and otherwise ignored: the manager's own timeouts
    (start, watchdog) then say what is wrong.
    """

    def __init__(self, environ: Mapping[str, str] = os.environ):
        path = environ.get("NOTIFY_SOCKET", "")
        # "@name" is a socket in the abstract namespace (a leading NUL byte).
        self._address = "\0" + path[1:] if path.startswith("@") else path
        self._socket: socket.socket | None = None
        self._failed = False
        self.pings = 0
        self.watchdog_s = _watchdog_period_s(environ)

    @property
    def enabled(self) -> bool:
        return bool(self._address)

    def send(self, *assignments: str) -> None:
        """Send ``READY=1``, ``WATCHDOG=1``, ``STATUS=…``, … in one datagram."""
        if not self._address:
            return
        try:
            if self._socket is None:
                self._socket = socket.socket(
                    socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC
                )
            self._socket.sendto("\n".join(assignments).encode(), self._address)
            self.pings += "WATCHDOG=1" in assignments
        except OSError as exc:
            if not self._failed:
                self._failed = True
                log.error("cannot notify the service manager at %s: %s", self._address, exc)

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def _watchdog_period_s(environ: Mapping[str, str]) -> float | None:
    """The watchdog timeout systemd set for this process (``WATCHDOG_USEC``, ``WATCHDOG_PID``), or ``None``."""
    pid = environ.get("WATCHDOG_PID")
    try:
        if pid is not None and int(pid) != os.getpid():
            return None
        usec = int(environ.get("WATCHDOG_USEC", "0"))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


class FramePathWatch:
    """Whether the frame path is healthy, checked once per watchdog period.

    Healthy means frames were taken off the input queues since the last check, or none were
    waiting: an idle daemon with no input (no vehicle, no router) is not hung, and restarting it
    would not help. A frame path that has frames waiting and takes none for a whole period is
    hung, whatever the cause (a blocked pipeline, a dead intake task); so is a loop that never
    gets to run the check.
    """

    def __init__(self) -> None:
        self._taken = -1
        self.checks = 0
        self.stalls = 0

    def healthy(self, *, taken: int, waiting: int) -> bool:
        """``taken``: frames taken off the queues so far (monotonic); ``waiting``: frames queued now."""
        moved = taken != self._taken
        self._taken = taken
        self.checks += 1
        self.stalls += not (moved or waiting == 0)
        return moved or waiting == 0
