"""Episodes of a store that refuses writes (the outbox, the checkpoints): when one began, the writes
that failed in it and in all, how many there were. The stores' writers say what the episodes mean
(held events, state kept in memory) and log their start and end."""

from __future__ import annotations

from collections.abc import Callable


class Outage:
    """The unavailability episodes of one store. ``clock``: a monotonic clock, s."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._since: float | None = None
        self.failures_now = 0
        """Writes that failed in the episode going on (0 when none is)."""
        self.write_failures = 0
        self.episodes = 0

    @property
    def ongoing(self) -> bool:
        return self._since is not None

    def lasted(self) -> float | None:
        """How long the episode going on has lasted, s (None: none is)."""
        return None if self._since is None else self._clock() - self._since

    def failed(self) -> bool:
        """A write failed; True when it begins an episode (the writer logs it then)."""
        self.write_failures += 1
        self.failures_now += 1
        if self._since is not None:
            return False
        self._since = self._clock()
        self.episodes += 1
        return True

    def ended(self) -> float | None:
        """A write succeeded: how long the episode it ends lasted, s; None when none was going on."""
        if self._since is None:
            return None
        lasted = self._clock() - self._since
        self._since, self.failures_now = None, 0
        return lasted

    def counters(self, name: str) -> dict[str, int]:
        """``<name>.write_failures`` and ``<name>.unavailable_episodes``, for the status topic."""
        return {
            f"{name}.write_failures": self.write_failures,
            f"{name}.unavailable_episodes": self.episodes,
        }
