"""The daemon never stops silently (issue 15): a failing task is restarted and counted, a router that is
not there at start is waited for in the background, SIGTERM ends every state, and the systemd
watchdog is fed only while the frame path moves. Real router and daemon processes on 127.0.0.1."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import sqlite3
import threading

import pytest
import zenoh
from pymavlink import mavutil
from service_support import (
    ServiceThread,
    batches_of,
    free_tcp_port,
    free_udp_port,
    mavlink_packets,
    receive_until,
    run_fleet,
    service_config,
    wait_subscribed,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)
from test_service_faults import (
    ServiceProcess,
    Statuses,
    offline_fleet,
    publish_blocking,
    put_store,
    unit,
    write_config,
)

from protocols.events import Predicate
from protocols.mavlink_adapter import ImuMessage, use_mavlink2
from protocols.zenoh_adapter import EventReceiver, frame_key
from service.commands.run import STOP_BOUND_S
from service.daemon import Service
from service.notify import Notifier
from service.supervisor import EXIT_TASK_FAILED

pytestmark = pytest.mark.network


def healthy_frames(vehicle: str):
    """The healthy vehicle's frames up to 3 s after its fault, and the one F0 event they raise."""
    sc = unit()[2]
    frames = [
        b
        for b in batches_of(sc.session, vehicle=vehicle, imu=0, batch_samples=100)
        if b.t_s[-1] < sc.fault_s + 3.0
    ]
    expected = run_fleet(offline_fleet(), frames, finish=False)
    assert [e.predicate for e in expected] == [Predicate.F0]
    return frames, [e.event_id for e in expected]


def test_an_unreachable_router_is_said_the_mavlink_side_is_served_and_sigterm_ends_it(tmp_path):
    """No router on the configured endpoint: the daemon says so, runs, answers on MAVLink, ignores
    SIGHUP (and says so), and SIGTERM (while it still tries to connect) ends it with status 0 within
    the stop bound."""
    udp = free_udp_port()
    config = write_config(
        tmp_path, port=free_tcp_port(), passports=put_store(tmp_path, []), mavlink_port=udp
    )
    daemon = ServiceProcess(config)
    try:
        assert any("zenoh: cannot reach ['tcp/127.0.0.1:" in line for line in daemon.lines)
        peer = use_mavlink2(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{udp}", source_system=1, source_component=1
            )
        )
        try:
            # The daemon answers the peer it heard from (udpin learns the address).
            peer.mav.heartbeat_send(2, 3, 0, 0, 0)
            receive_until(
                peer,
                ["HEARTBEAT"],
                lambda msgs: bool(msgs),
                timeout_s=30,
                what="the daemon's HEARTBEAT",
            )
        finally:
            peer.close()
        # SIGHUP (a closed terminal) killed the daemon with no drain: it is said and ignored.
        daemon.proc.send_signal(signal.SIGHUP)
        wait_until(
            lambda: any("SIGHUP ignored" in line for line in daemon.lines),
            timeout_s=30.0,
            what="the SIGHUP line",
        )
        assert daemon.proc.poll() is None, daemon.lines
    finally:
        daemon.proc.send_signal(signal.SIGTERM)
        # A deadline on the wait, not a timing assertion: a daemon that ignores SIGTERM never ends.
        code = daemon.proc.wait(STOP_BOUND_S + 30)
    assert code == 0, daemon.lines
    assert not any("Traceback" in line for line in daemon.lines), daemon.lines


def test_a_late_router_is_joined_a_failing_task_is_restarted_and_the_events_still_arrive(tmp_path):
    """The router comes up after the daemon; the daemon connects and says so. Then another process locks
    the checkpoint database: the checkpoint task fails, its traceback is logged, the failure is counted on
    the status topic and the task restarted; once the lock is gone checkpoints resume, and the healthy
    vehicle's F0 event arrives. Every task's liveness is on the status topic."""
    v = "uav-s"
    frames, want = healthy_frames(v)
    port = free_tcp_port()
    config = write_config(tmp_path, port=port, passports=put_store(tmp_path, [(v, 0)]))
    daemon = ServiceProcess(config)
    try:
        with zenoh_router(port):
            wait_until(
                lambda: any("zenoh: connected" in line for line in daemon.lines),
                timeout_s=60,
                what=lambda: f"the daemon connecting to the late router ({daemon.lines})",
            )
            with (
                zenoh.open(zenoh_client_config(port)) as ground,
                zenoh.open(zenoh_client_config(port)) as vehicle,
            ):
                status = Statuses(ground)
                got: list[str] = []
                with EventReceiver(ground, lambda e: got.append(e.event_id)):
                    wait_subscribed(vehicle, frame_key(v, 0), timeout_s=30)
                    publish_blocking(vehicle, frames[:30])
                    wait_until(lambda: status.counter(v, "imu0.samples.accepted") == 3000,
                               timeout_s=60, what="the first frames processed")  # fmt: skip
                    lock = sqlite3.connect(
                        tmp_path / "data" / "checkpoints.sqlite", isolation_level=None
                    )
                    try:
                        lock.execute("BEGIN EXCLUSIVE")
                        publish_blocking(vehicle, frames[30:31])
                        wait_until(lambda: status.counter(v, "service.task.checkpoints.failures") >= 1,
                                   timeout_s=60, what=lambda: f"the checkpoint failure counted ({status.get(v)})")  # fmt: skip
                        failed_ms = status.counter(
                            v, "service.task.checkpoints.last_progress_unix_ms"
                        )
                    finally:
                        lock.execute("ROLLBACK")
                        lock.close()
                    publish_blocking(vehicle, frames[31:])
                    wait_until(lambda: got == want, timeout_s=60,
                               what=lambda: f"the healthy vehicle's F0 event (got {got})")  # fmt: skip
                    wait_until(lambda: status.counter(v, "service.task.checkpoints.last_progress_unix_ms") > failed_ms,
                               timeout_s=60, what="a checkpoint after the lock is gone")  # fmt: skip
                    counters = status.get(v).counters
    finally:
        daemon.proc.send_signal(signal.SIGTERM)
        code = daemon.proc.wait(STOP_BOUND_S + 30)
    assert code == 0, daemon.lines
    for task in ("frames", "deliver-zenoh", "status", "checkpoints", "zenoh-connect"):
        assert counters[f"service.task.{task}.last_progress_unix_ms"] > 0, (task, counters)
    assert counters["service.task.frames.failures"] == 0
    failed = [line for line in daemon.lines if "task checkpoints failed" in line]
    assert failed and "Traceback (most recent call last):" in failed[0], daemon.lines
    assert "database is locked" in failed[0]


class Manager:
    """The service manager's side of $NOTIFY_SOCKET: a unix datagram socket the test binds."""

    def __init__(self, path):
        self.path = str(path)
        self.datagrams: list[str] = []
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(self.path)
        self._lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        while True:
            try:
                data = self._sock.recv(4096)
            except OSError:
                return
            with self._lock:
                self.datagrams.append(data.decode())

    def seen(self) -> list[str]:
        with self._lock:
            return list(self.datagrams)

    def close(self) -> None:
        self._sock.close()


def test_ready_then_watchdog_pings_that_stop_when_the_frame_path_hangs(tmp_path, caplog):
    """READY=1 comes once the daemon runs; WATCHDOG=1 comes while frames flow; once the frame path's task
    is gone and frames wait, the stall is logged and no ping is sent over several checks."""
    v = "uav-w"
    frames, _ = healthy_frames(v)
    manager = Manager(tmp_path / "notify")
    notifier = Notifier({"NOTIFY_SOCKET": manager.path, "WATCHDOG_USEC": "400000"})
    try:
        with zenoh_router() as port:
            cfg = service_config(tmp_path, port=port, passport_dir=put_store(tmp_path, [(v, 0)]), name="onboard",
                                 site={"gravity_mps2": unit()[1]}, validity={"timeout_s": 600.0})  # fmt: skip
            with (
                caplog.at_level(logging.INFO, logger="ins_health"),
                ServiceThread(cfg, notifier=notifier) as svc,
                zenoh.open(zenoh_client_config(port)) as vehicle,
            ):
                wait_until(lambda: manager.seen(), timeout_s=30, what="READY=1")
                assert manager.seen()[0] == "READY=1\nSTATUS=onboard running"
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, frames[:40])

                def taken() -> int:
                    pipe = svc.call(lambda: svc.service.fleet.pipelines.get((v, 0)))
                    return 0 if pipe is None else svc.call(lambda: pipe.n_samples)

                wait_until(lambda: taken() == 4000, timeout_s=60, what="the frames processed")
                wait_until(lambda: manager.seen().count("WATCHDOG=1") >= 3, timeout_s=30,
                           what="watchdog pings while frames flow")  # fmt: skip
                # The frame path's task gone (as a bug outside supervision would leave it): frames wait.
                svc.call(lambda: svc.service.supervisor.tasks["frames"].cancel())
                publish_blocking(vehicle, frames[40:60])

                def watch():
                    return svc.call(
                        lambda: (svc.service.notifier.pings, svc.service.frame_watch.stalls)
                    )

                wait_until(lambda: watch()[1] >= 1, timeout_s=30, what="the stall seen")
                pings, stalls = watch()
                wait_until(lambda: watch()[1] >= stalls + 3, timeout_s=30, what="three more checks")
                assert watch()[0] == pings
                assert taken() == 4000
                wait_until(lambda: manager.seen().count("WATCHDOG=1") == pings, timeout_s=30,
                           what="every ping sent received")  # fmt: skip
            wait_until(lambda: "STOPPING=1" in manager.seen(), timeout_s=30, what="STOPPING=1")
    finally:
        manager.close()
    assert any(
        "the frame path is stalled" in r.getMessage() and r.levelno == logging.ERROR
        for r in caplog.records
    )


def test_a_router_out_of_reach_beyond_connect_timeout_ends_the_daemon_non_zero(tmp_path, caplog):
    """With ``connect_timeout_s`` set, the daemon gives up on an absent router: it says so and its
    run ends with status 70 (systemd restarts it), having drained what it opened."""
    cfg = service_config(tmp_path, port=free_tcp_port(), passport_dir=put_store(tmp_path, []),
                         zenoh={"connect_timeout_s": 0.5})  # fmt: skip

    async def run() -> int:
        return await asyncio.wait_for(Service(cfg).run(asyncio.Event()), 60)

    with caplog.at_level(logging.INFO, logger="ins_health"):
        assert asyncio.run(run()) == EXIT_TASK_FAILED
    assert any(
        r.levelno == logging.CRITICAL
        and "zenoh: no router at ['tcp/127.0.0.1:" in r.getMessage()
        and "within connect_timeout_s = 0.5 s" in r.getMessage()
        for r in caplog.records
    )


def fail_one_read(source):
    """The reader's read raises once (a serial port that went away); nothing to wait for after."""
    read = source.link.read
    failed = threading.Event()

    def fail_once(timeout_s, **kw):
        if not failed.is_set():
            failed.set()
            raise OSError("device reports readiness to read but returned no data")
        return read(timeout_s, **kw)

    source.link.read = fail_once
    return lambda: True


def kill_reader_process(source):
    """The child process that reads the link (``[mavlink] reader = "process"``, the default) is
    killed; another must be started."""
    link = source.link
    first = link.pid
    assert first is not None
    os.kill(first, signal.SIGKILL)
    return lambda: link.restarts == 1 and link.pid not in (None, first)


@pytest.mark.parametrize(
    ("fail", "said"), [(fail_one_read, "returned no data"), (kill_reader_process, "exit code -9")]
)
def test_a_failed_mavlink_reader_is_logged_counted_and_reading_resumes(
    tmp_path, caplog, fail, said
):
    """The failure is logged with its traceback and counted, and the IMU messages sent afterwards are read."""
    udp = free_udp_port()
    cfg = service_config(tmp_path, port=None, passport_dir=put_store(tmp_path, []),
                         mavlink={"enabled": True, "device": f"udpin:127.0.0.1:{udp}", "vehicle": "mav1"})  # fmt: skip
    packets = mavlink_packets(unit()[2].session, ImuMessage.SCALED_IMU)[:50]
    with caplog.at_level(logging.ERROR, logger="ins_health"), ServiceThread(cfg) as svc:
        source = svc.service.mavlink_source
        recovered = fail(source)
        wait_until(lambda: source.failures == 1, timeout_s=30, what="the failure counted")
        wait_until(recovered, timeout_s=30, what="the reader back")
        peer = use_mavlink2(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{udp}", source_system=1, source_component=1
            )
        )
        try:
            peer.write(b"".join(packets))
            wait_until(lambda: source.link.counters.messages == len(packets), timeout_s=30,
                       what="the messages sent after the failure read")  # fmt: skip
        finally:
            peer.close()
        wait_until(
            lambda: any("the MAVLink reader failed" in r.getMessage() for r in caplog.records),
            timeout_s=30,
            what="the failure logged",
        )
    (record,) = [r for r in caplog.records if "the MAVLink reader failed" in r.getMessage()]
    assert record.exc_info is not None and said in str(record.exc_info[1])
