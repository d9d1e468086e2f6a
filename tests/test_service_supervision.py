"""The daemon never stops silently (issue 15): a failing task is restarted and counted, a router that is
not there at start is waited for in the background, SIGTERM ends every state, and the systemd
watchdog is fed only while the frame path moves; a checkpoint store that refuses writes (disk full,
file locked) stops none of it. Real router and daemon processes on 127.0.0.1."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import socket
import sqlite3
import threading
import time

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

from protocols.events import Predicate, Severity, StreamCause, encode_event, make_event
from protocols.mavlink_adapter import ImuMessage, use_mavlink2
from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key
from service.checkpoint import CheckpointStore, CheckpointUnavailable
from service.commands.run import STOP_BOUND_S
from service.daemon import CONNECT_PAUSE_S, Service
from service.notify import Notifier
from service.outbox_writer import HeldEvent
from service.supervisor import EXIT_TASK_FAILED, Supervisor

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


def hear_heartbeat(peer) -> None:
    """Until the peer hears the daemon's HEARTBEAT (1 Hz)."""
    receive_until(
        peer, ["HEARTBEAT"], lambda msgs: bool(msgs), timeout_s=60, what="the daemon's HEARTBEAT"
    )


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
            hear_heartbeat(peer)
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


def test_a_late_router_is_joined_a_locked_checkpoint_file_is_waited_out_and_the_events_arrive(
    tmp_path,
):
    """The router comes up after the daemon; the daemon connects and says so. Then another process locks
    the checkpoint database: the checkpoint writes fail, are logged (once) and counted on the status topic,
    and the checkpoint task goes on (it does not fail); once the lock is gone checkpoints resume, and the
    healthy vehicle's F0 event arrives. Every task's liveness is on the status topic."""
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
                        wait_until(lambda: status.counter(v, "service.checkpoints.write_failures") >= 1,
                                   timeout_s=60, what=lambda: f"the checkpoint failure counted ({status.get(v)})")  # fmt: skip
                        assert status.counter(v, "service.checkpoints.unavailable") == 1
                    finally:
                        lock.execute("ROLLBACK")
                        lock.close()
                    publish_blocking(vehicle, frames[31:])
                    wait_until(lambda: got == want, timeout_s=60,
                               what=lambda: f"the healthy vehicle's F0 event (got {got})")  # fmt: skip
                    wait_until(lambda: status.counter(v, "service.checkpoints.unavailable") == 0,
                               timeout_s=60, what="a checkpoint after the lock is gone")  # fmt: skip
                    counters = status.get(v).counters
    finally:
        daemon.proc.send_signal(signal.SIGTERM)
        code = daemon.proc.wait(STOP_BOUND_S + 30)
    assert code == 0, daemon.lines
    for task in ("frames", "deliver-zenoh", "status", "checkpoints", "zenoh-connect"):
        assert counters[f"service.task.{task}.last_progress_unix_ms"] > 0, (task, counters)
    assert counters["service.task.frames.failures"] == 0
    assert counters["service.task.checkpoints.failures"] == 0
    assert counters["service.checkpoints.unavailable_episodes"] == 1
    failed = [line for line in daemon.lines if "checkpoints cannot be saved" in line]
    assert len(failed) == 1 and "(database is locked)" in failed[0], daemon.lines
    assert len([line for line in daemon.lines if "checkpoints saved again after" in line]) == 1
    assert not any("Traceback" in line for line in daemon.lines), daemon.lines


class CountedStatuses(Statuses):
    """:class:`Statuses` that also counts the status messages received."""

    def __init__(self, session):
        self.received = 0
        super().__init__(session)

    def _on(self, status) -> None:
        super()._on(status)
        with self._lock:
            self.received += 1


def running(svc: ServiceThread) -> bool:
    """Fails the wait at once when the daemon gives up (a task failed again and again)."""
    assert not svc.service.supervisor.fatal.is_set(), "the daemon is exiting: a task kept failing"
    return True


def checkpointed_samples(svc: ServiceThread, vehicle: str) -> int | None:
    """How many samples the unit's saved checkpoint has taken (None: no checkpoint saved)."""
    cp = svc.call(lambda: svc.service.checkpoints.load(f"{vehicle}/0"))
    return None if cp is None else int(cp.state["n_samples"])


def taken_samples(svc: ServiceThread, vehicle: str) -> int:
    pipe = svc.call(lambda: svc.service.fleet.pipelines.get((vehicle, 0)))
    return 0 if pipe is None else svc.call(lambda: pipe.n_samples)


def test_a_full_disk_under_the_checkpoints_is_counted_logged_retried_and_the_daemon_goes_on(
    tmp_path, caplog, monkeypatch
):
    """Every checkpoint write fails ("database or disk is full", as SQLite says it), many more times
    than the supervisor's failures in a row: frames are still processed, status published and the
    fault's event delivered; the failures are counted on the status topic and logged once, and the
    checkpoint task never fails. Once the store takes writes again the state of the last frame is saved,
    and the log says after how long."""
    v = "uav-f"
    frames, want = healthy_frames(v)
    full = threading.Event()
    save = CheckpointStore.save_encoded

    def save_encoded(self, *args, **kwargs):
        if full.is_set():
            raise CheckpointUnavailable("database or disk is full")
        return save(self, *args, **kwargs)

    monkeypatch.setattr(CheckpointStore, "save_encoded", save_encoded)
    supervisor = Supervisor(backoff_initial_s=0.05, max_failures=2)
    with zenoh_router() as port:
        cfg = service_config(tmp_path, port=port, passport_dir=put_store(tmp_path, [(v, 0)]), name="onboard",
                             site={"gravity_mps2": unit()[1]}, validity={"timeout_s": 600.0},
                             service={"checkpoint_period_s": 0.2})  # fmt: skip
        with (
            caplog.at_level(logging.INFO, logger="ins_health"),
            ServiceThread(cfg, supervisor=supervisor) as svc,
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status = CountedStatuses(ground)
            got: list[str] = []
            with EventReceiver(ground, lambda e: got.append(e.event_id)):
                wait_subscribed(vehicle, frame_key(v, 0), timeout_s=30)
                full.set()
                publish_blocking(vehicle, frames[:30])
                wait_until(lambda: running(svc) and status.counter(v, "service.checkpoints.write_failures") >= 4,
                           timeout_s=60, what=lambda: f"failed checkpoints counted ({status.get(v)})")  # fmt: skip
                seen = status.received
                publish_blocking(vehicle, frames[30:])
                wait_until(lambda: running(svc) and got == want, timeout_s=60,
                           what=lambda: f"the healthy vehicle's F0 event (got {got})")  # fmt: skip
                total = sum(len(b.t_s) for b in frames)
                wait_until(
                    lambda: taken_samples(svc, v) == total,
                    timeout_s=60,
                    what="every frame processed",
                )
                wait_until(
                    lambda: status.received >= seen + 5, timeout_s=60, what="status while it fails"
                )
                failing = status.get(v).counters
                assert checkpointed_samples(svc, v) is None  # nothing could be saved
                full.clear()
                wait_until(lambda: running(svc) and checkpointed_samples(svc, v) == total, timeout_s=60,
                           what="the state of the last frame saved once the store takes writes")  # fmt: skip
                wait_until(lambda: status.counter(v, "service.checkpoints.unavailable") == 0,
                           timeout_s=60, what="the store said available again")  # fmt: skip
                after = status.get(v).counters
    assert failing["service.checkpoints.unavailable"] == 1
    assert failing["service.checkpoints.write_failures"] >= 4
    assert failing["service.task.checkpoints.failures"] == 0
    assert after["service.checkpoints.unavailable_episodes"] == 1
    assert after["service.task.checkpoints.failures"] == 0
    assert supervisor.health["checkpoints"].failures == 0
    said = [r for r in caplog.records if "checkpoints cannot be saved" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.ERROR
    assert "(database or disk is full)" in said[0].getMessage()
    back = [r for r in caplog.records if "checkpoints saved again after" in r.getMessage()]
    assert len(back) == 1, [r.getMessage() for r in caplog.records]


def test_a_locked_checkpoint_file_holds_up_neither_the_frames_nor_the_status(tmp_path, caplog):
    """Another process (a backup, an operator's sqlite3 shell) holds the checkpoint file's write lock
    while a vehicle streams at five times real time into a frame queue of 32: each checkpoint attempt
    gives up within the store's short busy timeout, so no frame is dropped from the queue, the status
    keeps coming and the failed attempts are retried and counted; once the lock is gone the state of the
    last frame is saved. (SQLite's default 5 s wait held the whole loop at each attempt.)"""
    v = "uav-l"
    frames = list(batches_of(unit()[2].session, vehicle=v, imu=0, batch_samples=20))  # 0.1 s each
    with zenoh_router() as port:
        cfg = service_config(tmp_path, port=port, passport_dir=put_store(tmp_path, [(v, 0)]), name="onboard",
                             site={"gravity_mps2": unit()[1]}, validity={"timeout_s": 600.0},
                             service={"checkpoint_period_s": 0.2}, pipeline={"queue_capacity": 32})  # fmt: skip
        with (
            caplog.at_level(logging.INFO, logger="ins_health"),
            ServiceThread(cfg) as svc,
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status = CountedStatuses(ground)
            wait_subscribed(vehicle, frame_key(v, 0), timeout_s=30)
            publish_blocking(vehicle, frames[:20])
            wait_until(
                lambda: checkpointed_samples(svc, v) == 400, timeout_s=60, what="a first checkpoint"
            )
            lock = sqlite3.connect(svc.service.config.checkpoint_path, isolation_level=None)
            lock.execute("BEGIN EXCLUSIVE")
            try:
                before = status.received
                sent = 20
                with FramePublisher(
                    vehicle, v, 0, congestion_control=zenoh.CongestionControl.BLOCK
                ) as pub:
                    # At least 100 frames (2 s), and until the lock has made a few attempts fail.
                    while sent < 420 and not (
                        sent >= 120 and status.counter(v, "service.checkpoints.write_failures") >= 4
                    ):
                        pub.publish(frames[sent])
                        sent += 1
                        time.sleep(0.02)
                during = status.received - before
                locked = status.get(v).counters

                def counted() -> int:
                    return status.counter(v, "imu0.frames.accepted") + status.counter(
                        v, "service.frames.dropped_overload"
                    )

                wait_until(lambda: counted() == sent, timeout_s=60,
                           what=lambda: f"every frame sent processed or dropped ({status.get(v)})")  # fmt: skip
                dropped = status.counter(v, "service.frames.dropped_overload")
            finally:
                lock.execute("ROLLBACK")
                lock.close()
            taken = taken_samples(svc, v)
            wait_until(lambda: checkpointed_samples(svc, v) == taken, timeout_s=60,
                       what="the state of the last frame saved once the lock is gone")  # fmt: skip
    assert dropped == 0, (
        f"{dropped} frames dropped from the queue while the checkpoint file was locked"
    )
    assert taken == 20 * sent
    # One status every 0.2 s, a frame every 0.02 s: 10 a status period, 25 allowed.
    assert during >= (sent - 20) / 25, (during, sent)
    assert locked["service.checkpoints.write_failures"] >= 4, locked
    assert locked["service.checkpoints.unavailable"] == 1
    assert locked["service.task.checkpoints.failures"] == 0
    said = [
        r.getMessage() for r in caplog.records if "checkpoints cannot be saved" in r.getMessage()
    ]
    assert len(said) == 1 and "(database is locked)" in said[0], said


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


def test_a_checkpoint_is_not_taken_ahead_of_events_held_while_it_yields(tmp_path):
    """A checkpoint yields to the loop between vehicles; a group run meanwhile may have its events
    held (the outbox unavailable). The state of the vehicles after that point would be saved ahead
    of those events (after kill -9, resumed past events never stored): it checked only once, at the
    start. Now nothing is written, the units stay unsaved, and it is counted as deferred."""
    vehicles = ("uav-a", "uav-b")
    mavlink = {"enabled": True, "device": f"udpin:127.0.0.1:{free_udp_port()}", "vehicle": "mav1"}
    cfg = service_config(
        tmp_path,
        port=None,
        passport_dir=put_store(tmp_path, [(v, 0) for v in vehicles]),
        mavlink=mavlink,
    )
    session = unit()[2].session
    with ServiceThread(cfg) as svc:
        s = svc.service
        frames = [
            b
            for v in vehicles
            for b in list(batches_of(session, vehicle=v, imu=0, batch_samples=50))[:3]
        ]
        svc.call(s.intake.process, frames)
        writer = s._running().writer
        taken = s.fleet.checkpoint_states
        held = make_event(vehicle="uav-b", imu=0, t_s=1.0, predicate=Predicate.TIMEOUT,
                          cause=StreamCause.NO_DATA, severity=Severity.WARNING)  # fmt: skip

        def held_after_the_first(vehicle, imus):
            out = taken(vehicle, imus)
            # What the yield let happen: an event the outbox did not take, not yet delivered.
            writer._held.append(HeldEvent(held, encode_event(held)))
            return out

        s.fleet.checkpoint_states = held_after_the_first
        asyncio.run_coroutine_threadsafe(s.checkpoint(), svc._loop).result(30)
        writer._held.clear()
        s.fleet.checkpoint_states = taken
        assert s._running().checkpoints.keys() == []
        assert s.fleet.service_counters["checkpoints.deferred"] == 1
        assert sorted(svc.call(s.fleet.changed_keys)) == [(v, 0) for v in vehicles]


def test_a_mavlink_device_not_there_at_start_is_opened_when_it_comes(tmp_path, caplog):
    """The autopilot's TCP port not up yet (or a USB serial adapter not plugged in): the daemon stopped
    at start with a traceback, Zenoh input included. Now it runs, says so once, counts the attempts,
    and opens the link when the port comes: the peer then hears its HEARTBEAT."""
    port = free_tcp_port()
    mavlink = {
        "enabled": True,
        "device": f"tcp:127.0.0.1:{port}",
        "vehicle": "mav1",
        "reader": "thread",
    }
    cfg = service_config(tmp_path, port=None, passport_dir=put_store(tmp_path, []), mavlink=mavlink)
    with caplog.at_level(logging.INFO, logger="ins_health"), ServiceThread(cfg) as svc:
        s = svc.service
        wait_until(
            lambda: svc.call(lambda: s.fleet.service_counters.get("mavlink.open_failures", 0)) >= 1,
            timeout_s=60,
            what="a failed attempt counted",
        )
        assert s.mavlink_source is None
        peer = use_mavlink2(mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}"))
        try:
            hear_heartbeat(peer)
        finally:
            peer.close()
    said = [r.getMessage() for r in caplog.records]
    assert sum("cannot open it" in m for m in said) == 1, said
    assert any(m == f"mavlink tcp:127.0.0.1:{port}: open" for m in said), said


def test_sigterm_while_a_mavlink_open_hangs_ends_the_daemon_within_the_stop_bound(tmp_path):
    """The autopilot's TCP port answers no connection (its backlog full: the connect hangs) while the
    daemon tries again to open it. The attempt ran in the loop's executor, which asyncio.run waits
    for at exit without a bound: SIGTERM took a minute (the reader process's start timeout), past the
    stop bound and systemd's stop timeout. The attempt is now a thread of its own, left behind."""
    port = free_tcp_port()
    config = tmp_path / "service.toml"
    config.write_text(
        f"""
[service]
data_dir = "{tmp_path / "data"}"
passport_dir = "{put_store(tmp_path, [])}"
[zenoh]
enabled = false
[mavlink]
enabled = true
device = "tcp:127.0.0.1:{port}"
"""
    )
    daemon = ServiceProcess(config)
    try:
        wait_until(
            lambda: any("cannot open it" in line for line in daemon.lines),
            timeout_s=60,
            what="the first attempt refused",
        )
        with socket.socket() as listener:
            listener.bind(("127.0.0.1", port))
            listener.listen(0)
            fillers = [socket.socket() for _ in range(3)]
            for c in fillers:
                c.setblocking(False)
                with contextlib.suppress(BlockingIOError):
                    c.connect(("127.0.0.1", port))
            # The next attempt starts CONNECT_PAUSE_S after the first; SIGTERM comes while it hangs.
            threading.Event().wait(CONNECT_PAUSE_S + 1.5)
            daemon.proc.send_signal(signal.SIGTERM)
            # A deadline on the wait, not a timing assertion: the old daemon took 60 s.
            code = daemon.proc.wait(STOP_BOUND_S + 5)
            for c in fillers:
                c.close()
    finally:
        if daemon.proc.poll() is None:
            daemon.kill()
    assert code == 0, daemon.lines
