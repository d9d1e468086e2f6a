"""The supervisor of the daemon's tasks, in-process."""

from __future__ import annotations

import asyncio
import logging

from service.supervisor import Supervisor


def _run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


def _supervisor(**kw) -> Supervisor:
    clock = iter(range(1000, 10_000))
    return Supervisor(backoff_initial_s=0.001, backoff_max_s=0.004, wall=lambda: next(clock), **kw)


def test_a_failing_task_is_logged_with_its_traceback_counted_and_restarted(caplog):
    runs = []

    async def work():
        runs.append(len(runs))
        if len(runs) <= 2:
            raise RuntimeError(f"boom {len(runs)}")

    async def main():
        sup = _supervisor()
        await sup.start("intake", work)
        return sup

    with caplog.at_level(logging.ERROR, logger="ins_health"):
        sup = _run(main())
    assert runs == [0, 1, 2] and not sup.fatal.is_set()
    assert sup.counters()["service.task.intake.failures"] == 2
    failures = [r for r in caplog.records if "task intake failed" in r.getMessage()]
    assert len(failures) == 2
    assert all(r.exc_info is not None and r.exc_info[0] is RuntimeError for r in failures)
    assert "boom 1" in str(failures[0].exc_info[1])


def test_a_task_failing_again_and_again_without_progress_makes_the_daemon_exit(caplog):
    runs = []

    async def work():
        runs.append(1)
        raise OSError("disk gone")

    async def main():
        sup = _supervisor(max_failures=4)
        await sup.start("checkpoints", work)
        return sup

    with caplog.at_level(logging.ERROR, logger="ins_health"):
        sup = _run(main())
    assert len(runs) == 4 and sup.fatal.is_set()
    assert any(
        r.levelno == logging.CRITICAL and "4 times in a row" in r.getMessage()
        for r in caplog.records
    )


def test_progress_between_failures_keeps_the_task_restarting():
    runs = []

    async def work():
        runs.append(1)
        sup.beat()
        if len(runs) < 10:
            raise OSError("transient")

    async def main():
        await sup.start("deliver", work)

    sup = _supervisor(max_failures=2)
    _run(main())
    assert len(runs) == 10 and not sup.fatal.is_set()
    counters = sup.counters()
    assert counters["service.task.deliver.failures"] == 9
    # The wall clock of the last beat (the fake clock ticks once per reading).
    assert counters["service.task.deliver.last_progress_unix_ms"] > 1000 * 1000


def test_a_task_failing_while_the_daemon_stops_is_not_restarted():
    runs = []

    async def work():
        runs.append(1)
        raise OSError("gone")

    async def main():
        sup = _supervisor()
        sup.stop_restarts()
        await sup.start("status", work)

    _run(main())
    assert runs == [1]


def test_liveness_before_any_progress_is_the_start_time():
    sup = Supervisor(wall=lambda: 12.5)

    async def start():
        await sup.start("idle", lambda: asyncio.sleep(0))

    _run(start())
    assert sup.counters() == {
        "service.task.idle.failures": 0,
        "service.task.idle.last_progress_unix_ms": 12500,
    }
