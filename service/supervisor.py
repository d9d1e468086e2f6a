"""Supervision of the daemon's long-lived asyncio tasks: no task dies silently.

Each task runs under :meth:`Supervisor.start`. An exception other than cancellation is logged
with its traceback, counted (``service.task.<name>.failures`` on the status topic) and the task
is started again after a back-off that doubles from :attr:`Supervisor.backoff_initial_s` up to
:attr:`Supervisor.backoff_max_s`. A task that fails :attr:`Supervisor.max_failures` times in a row
without reporting progress in between is not restarted: :attr:`Supervisor.fatal` is set and the
daemon exits with :data:`EXIT_TASK_FAILED`, so that systemd (``Restart=on-failure``) starts it
afresh.

A task reports progress with :meth:`Supervisor.beat` (called from inside the task: the name is
that of the running task); the status topic shows the wall time of each task's last progress
(``service.task.<name>.last_progress_unix_ms``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from service.log_setup import logger

EXIT_TASK_FAILED = 70
"""Exit status when a task keeps failing (EX_SOFTWARE of sysexits.h)."""

log = logger("supervisor")


@dataclass
class TaskHealth:
    """What the supervisor knows of one task."""

    started_unix_s: float
    last_progress_unix_s: float | None = None
    beats: int = 0
    failures: int = 0
    failures_in_a_row: int = 0


class Supervisor:
    """Starts, restarts and watches the daemon's tasks (module docstring).

    Parameters
    ----------
    backoff_initial_s, backoff_max_s : delay before the first restart of a failed task, and its
        upper bound as it doubles with each failure in a row.
    max_failures : failures in a row, without progress in between, after which the daemon exits.
    wall : the wall clock of the liveness times (s since the Unix epoch).
    """

    def __init__(
        self,
        *,
        backoff_initial_s: float = 0.5,
        backoff_max_s: float = 30.0,
        max_failures: int = 5,
        wall: Callable[[], float] = time.time,
    ):
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.max_failures = max_failures
        self._wall = wall
        self.health: dict[str, TaskHealth] = {}
        self.tasks: dict[str, asyncio.Task[None]] = {}
        self.fatal = asyncio.Event()
        self.exit_code = EXIT_TASK_FAILED
        """The daemon's exit status once :attr:`fatal` is set."""
        self._stopping = asyncio.Event()

    def start(self, name: str, work: Callable[[], Awaitable[None]]) -> asyncio.Task[None]:
        """Run ``work()`` as the task ``name``, again after each failure (module docstring)."""
        if name in self.health:
            raise ValueError(f"a task named {name!r} is already supervised")
        self.health[name] = TaskHealth(started_unix_s=self._wall())
        task = self.tasks[name] = asyncio.create_task(self._supervise(name, work), name=name)
        return task

    def stop_restarts(self) -> None:
        """The daemon stops: a task that fails from now on is not started again."""
        self._stopping.set()

    def cancel_all(self) -> None:
        """Cancel every task still running (before the resources they use are closed)."""
        for task in self.tasks.values():
            task.cancel()

    def fail(self, reason: str, *, code: int = EXIT_TASK_FAILED) -> None:
        """A condition no restart of a task can mend: logged, and the daemon exits (:attr:`fatal`) with ``code``."""
        log.critical("%s; the daemon exits with status %d", reason, code)
        self.exit_code = code
        self.fatal.set()

    def beats(self, *names: str) -> int:
        """How many times these tasks reported progress so far."""
        return sum(self.health[n].beats for n in names if n in self.health)

    def beat(self) -> None:
        """The running task made progress (a no-op outside a supervised task)."""
        task = asyncio.current_task()
        health = None if task is None else self.health.get(task.get_name())
        if health is not None:
            health.beats += 1
            health.last_progress_unix_s = self._wall()
            health.failures_in_a_row = 0

    async def _supervise(self, name: str, work: Callable[[], Awaitable[None]]) -> None:
        health = self.health[name]
        while True:
            try:
                await work()
                return
            except Exception:
                health.failures += 1
                health.failures_in_a_row += 1
                if health.failures_in_a_row >= self.max_failures:
                    log.critical(
                        "task %s failed %d times in a row without progress; the daemon exits "
                        "with status %d so that it is started afresh",
                        name, health.failures_in_a_row, EXIT_TASK_FAILED, exc_info=True,
                    )  # fmt: skip
                    self.fatal.set()
                    return
                delay_s = min(
                    self.backoff_max_s,
                    self.backoff_initial_s * 2.0 ** (health.failures_in_a_row - 1),
                )
                if self._stopping.is_set():
                    log.error("task %s failed while the daemon stops", name, exc_info=True)
                    return
                log.error(
                    "task %s failed (failure %d, counted as service.task.%s.failures); restarting it in %.1f s",
                    name, health.failures, name, delay_s, exc_info=True,
                )  # fmt: skip
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stopping.wait(), delay_s)
            if self._stopping.is_set():
                return

    def counters(self) -> dict[str, int]:
        """Each task's failures and the time of its last progress (of its start before any), for the status topic."""
        out = {}
        for name, h in self.health.items():
            out[f"service.task.{name}.failures"] = h.failures
            last = h.started_unix_s if h.last_progress_unix_s is None else h.last_progress_unix_s
            out[f"service.task.{name}.last_progress_unix_ms"] = int(last * 1000)
        return out
