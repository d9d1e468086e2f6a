"""The supervisor of the daemon's tasks, the watchdog's rule and the notification socket, in-process."""

from __future__ import annotations

import asyncio
import logging
import os
import socket

import pytest

from service.notify import FramePathWatch, Notifier
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


def test_the_frame_path_is_healthy_while_frames_move_or_none_wait():
    watch = FramePathWatch()
    assert watch.healthy(taken=0, waiting=5)  # the first look
    assert not watch.healthy(taken=0, waiting=5)  # frames wait, none taken: hung
    assert watch.healthy(taken=3, waiting=5)  # frames taken
    assert watch.healthy(taken=3, waiting=0)  # idle, nothing waits
    assert not watch.healthy(taken=3, waiting=1)
    assert (watch.checks, watch.stalls) == (5, 2)


def test_notifications_reach_the_socket_systemd_names(tmp_path):
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as manager:
        manager.bind(path)
        manager.settimeout(10)
        env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2500000", "WATCHDOG_PID": str(os.getpid())}
        notifier = Notifier(env)
        assert notifier.watchdog_s == 2.5
        notifier.send("READY=1", "STATUS=onboard running")
        notifier.send("WATCHDOG=1")
        notifier.close()
        assert manager.recv(4096) == b"READY=1\nSTATUS=onboard running"
        assert manager.recv(4096) == b"WATCHDOG=1"
    assert notifier.pings == 1


@pytest.mark.parametrize(
    "env",
    [
        {},
        {"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"},
        {"WATCHDOG_USEC": "x"},
    ],
)
def test_no_watchdog_without_one_for_this_process(env):
    assert Notifier(env).watchdog_s is None


def test_a_missing_socket_is_reported_once_and_sending_goes_on(tmp_path, caplog):
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "none")})
    with caplog.at_level(logging.ERROR, logger="ins_health"):
        notifier.send("READY=1")
        notifier.send("WATCHDOG=1")
    notifier.close()
    (record,) = caplog.records
    assert record.getMessage().startswith(f"cannot notify the service manager at {tmp_path}/none: ")
