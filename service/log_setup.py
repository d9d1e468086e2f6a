"""The daemon's log: the standard :mod:`logging` module, one line per record, journald-friendly.

Every module of the daemon logs to a child of the ``ins_health`` logger. :func:`logging_to`
sends them to one stream as one line per record (a traceback is folded into its record's line,
its lines separated by `` | ``), each starting with ``ins-health:``:

* under journald (``JOURNAL_STREAM`` names the stream, as systemd sets it for a unit whose
  output goes to the journal) the line carries no time stamp, the journal adds its own, and
  starts with the record's syslog priority ``<N>`` (``<6>`` info, ``<4>`` warning, ``<3>``
  error), which journald files as the entry's priority (``journalctl -p warning``) and strips;
* elsewhere it starts with the UTC time and the level name:
  ``2026-11-25T03:40:00.123Z INFO ins-health: onboard running``.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import TextIO

LOGGER_NAME = "ins_health"
LEVELS = ("debug", "info", "warning", "error")
"""The levels ``ins-health run --log-level`` accepts."""

_SYSLOG_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}


def logger(name: str) -> logging.Logger:
    """The logger of one part of the daemon (``ins_health.<name>``)."""
    return logging.getLogger(f"{LOGGER_NAME}.{name}")


def under_journald(stream: TextIO, environ: Mapping[str, str]) -> bool:
    """Whether ``stream`` is connected to the journal.

    systemd sets ``JOURNAL_STREAM=<device>:<inode>`` of the stream it connected to the journal
    (systemd.exec(5)); a child whose output was redirected elsewhere inherits the variable,
    so the stream itself is compared with it.
    """
    value = environ.get("JOURNAL_STREAM", "")
    try:
        device, inode = (int(part) for part in value.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (device, inode)


class OneLineFormatter(logging.Formatter):
    """A record (with its traceback, if any) as one line; see the module docstring for the two forms."""

    def __init__(self, *, journald: bool) -> None:
        super().__init__()
        self.journald = journald

    def format(self, record: logging.LogRecord) -> str:
        text = " | ".join(line.rstrip() for line in super().format(record).splitlines() if line)
        if self.journald:
            return f"<{_SYSLOG_PRIORITY.get(record.levelno, 6)}>ins-health: {text}"
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        return f"{stamp}.{int(record.msecs):03d}Z {record.levelname} ins-health: {text}"


@contextmanager
def logging_to(
    stream: TextIO, *, level: str = "info", environ: Mapping[str, str] = os.environ
) -> Iterator[logging.Handler]:
    """Send the daemon's records of ``level`` and above to ``stream`` while the context lasts."""
    if level not in LEVELS:
        raise ValueError(f"log level must be one of {list(LEVELS)}, got {level!r}")
    root = logging.getLogger(LOGGER_NAME)
    handler = logging.StreamHandler(stream)
    handler.setFormatter(OneLineFormatter(journald=under_journald(stream, environ)))
    saved = root.level, root.propagate
    root.addHandler(handler)
    root.setLevel(level.upper())
    root.propagate = False
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(saved[0])
        root.propagate = saved[1]
