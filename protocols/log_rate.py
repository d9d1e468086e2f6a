"""Logging rejected input at a bounded rate: the counters are on the status topic, the log says when
they grow (the MAVLink reader's rejections, the Zenoh frames the intake refuses)."""

from __future__ import annotations

import time

LOG_PERIOD_S = 10.0
"""At most one log line per this period about rejected input (the counters are on the status topic)."""


class LogRate:
    """Which growth of some counts to log now: a kind not logged before at once (a broken CRC seconds
    after the first garbage used to wait a whole period), more of a kind already logged at most once
    per :data:`LOG_PERIOD_S`. The kinds are few, so the log stays bounded."""

    def __init__(self) -> None:
        self._logged: dict[str, int] = {}
        self._at_s = -LOG_PERIOD_S

    def due(self, current: dict[str, int]) -> dict[str, int]:
        """What ``current`` gained since the last line logged, if a line is due now; else ``{}``."""
        if current == self._logged:
            return {}
        now = time.monotonic()
        if now - self._at_s < LOG_PERIOD_S and current.keys() <= self._logged.keys():
            return {}
        new = {
            k: n - self._logged.get(k, 0) for k, n in current.items() if n != self._logged.get(k, 0)
        }
        self._logged, self._at_s = current, now
        return new
