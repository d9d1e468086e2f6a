"""When a STATUSTEXT alert may go out: repeats suppressed, distinct alerts paced, none dropped."""

from __future__ import annotations

import math

from estimators.conventions import Triad
from protocols.events import (
    Event,
    EventCause,
    Predicate,
)


class AlertPolicy:
    """When a STATUSTEXT alert may go out (no flood on the operator's screen; the Zenoh stream stays complete).

    * A *repeat* — the same (vehicle, IMU, predicate, sensor, axis, cause) within
      ``min_interval_s`` of the last one sent — is suppressed: it counts as delivered.
    * Distinct alerts are *paced*, at most ``max_per_s``: an alert that comes too soon is
      deferred (the sink refuses it and the outbox retries it), never dropped, so a new fault
      is not lost behind the alert of another.
    """

    def __init__(self, *, min_interval_s: float, max_per_s: float):
        if not (min_interval_s > 0 and max_per_s > 0):
            raise ValueError(
                f"need min_interval_s > 0 and max_per_s > 0, got {min_interval_s!r}, {max_per_s!r}"
            )
        self.min_interval_s = float(min_interval_s)
        self.period_s = 1.0 / float(max_per_s)
        self._next_s = -math.inf
        self._last: dict[
            tuple[str, int, Predicate, Triad | None, str | None, EventCause], float
        ] = {}
        self.suppressed = 0
        self.deferred = 0

    def decide(self, event: Event, now_s: float) -> bool | None:
        """True: send now; False: suppressed repeat (drop); None: defer (try again later)."""
        if now_s < self._next_s:
            self.deferred += 1
            return None
        key = (event.vehicle, event.imu, event.predicate, event.triad, event.axis, event.cause)
        last = self._last.get(key)
        if last is not None and now_s - last < self.min_interval_s:
            self.suppressed += 1
            return False
        self._last[key] = now_s
        self._next_s = now_s + self.period_s
        return True
