"""No fault event lost or withheld (issue 29): delivery per (sink, vehicle), and storage faults that
degrade without silencing, against real router, daemon and MAVLink peer processes on 127.0.0.1."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
import time

import pytest
import zenoh
from pymavlink import mavutil
from service_support import (
    EventStream,
    free_udp_port,
    mavlink_packets,
    of_type,
    receive_until,
    run_fleet,
    wait_subscribed,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)
from test_service_faults import (
    ROOT,
    ServiceProcess,
    Statuses,
    ground_and_vehicle,
    offline_fleet,
    publish_blocking,
    put_store,
)
from test_service_hostile import FULL_PAGES, fill_outbox, to_the_fault
from test_service_mavlink import daemon_config, stream
from test_service_mavlink import unit as mavlink_unit

from protocols.events import Predicate
from protocols.mavlink_adapter import ImuMessage, use_mavlink2
from protocols.zenoh_adapter import EventReceiver, frame_key
from service.daemon import EXIT_STORAGE
from service.outbox import Outbox

pytestmark = pytest.mark.network

DELIVERY_BOUND_S = 30.0
"""Within this an event whose ground station acknowledges must arrive (the daemon retries every 0.2 s)."""


def fault_ids(vehicle: str) -> list[str]:
    return [
        e.event_id
        for e in run_fleet(offline_fleet(), to_the_fault(vehicle, batch_samples=200), finish=False)
    ]


def test_a_vehicle_nobody_acknowledges_holds_up_only_its_own_events(tmp_path):
    """Vehicle B's ground station is offline (no acknowledging receiver for B); B's fault comes first,
    then A's. A's ground station gets A's event within the bound while B's waits (before: delivery took
    the outbox in order and stopped at B's event, so A got nothing until B's was acknowledged). The
    status says what waits for whom; once B's ground station is up, B's event arrives, once."""
    a, b = "uav-a", "uav-b"
    want = {v: fault_ids(v) for v in (a, b)}
    assert all(len(ids) == 1 for ids in want.values())
    with ground_and_vehicle(tmp_path, put_store(tmp_path, [(a, 0), (b, 0)])) as peers:
        config, ground, vehicle, status = peers
        got = {a: [], b: []}
        daemon = ServiceProcess(config)
        try:
            with EventReceiver(ground, lambda e: got[a].append(e.event_id), vehicles=a):
                wait_subscribed(vehicle, frame_key(b, 0))
                publish_blocking(vehicle, to_the_fault(b, batch_samples=200))
                wait_until(lambda: status.counter(b, "service.delivery.zenoh.retries") >= 2, timeout_s=60,
                           what=lambda: f"B's event refused for want of an acknowledgement ({status.get(b)})")  # fmt: skip
                publish_blocking(vehicle, to_the_fault(a, batch_samples=200))
                wait_until(lambda: got[a] == want[a], timeout_s=DELIVERY_BOUND_S,
                           what=lambda: f"A's event while B's waits (got {got[a]})")  # fmt: skip
                wait_until(lambda: status.counter(b, "outbox.pending.zenoh") == 1
                           and status.counter(a, "outbox.pending.zenoh") == 0, timeout_s=30,
                           what=lambda: f"the backlog per vehicle ({status.get(a)}, {status.get(b)})")  # fmt: skip
            with EventReceiver(ground, lambda e: got[b].append(e.event_id), vehicles=b):
                wait_until(lambda: got[b] == want[b], timeout_s=DELIVERY_BOUND_S,
                           what=lambda: f"B's event once its ground station is up (got {got[b]})")  # fmt: skip
        finally:
            assert daemon.terminate() == 0, daemon.lines


def test_a_zenoh_backlog_that_fills_the_outbox_does_not_withhold_the_mavlink_alert(tmp_path):
    """The ground station is offline and its events fill the outbox (``outbox_max_mb`` reached, SQLite's
    'database or disk is full', as on a full disk). The autopilot's gyro fault comes over MAVLink: its
    event cannot be stored, and is held in memory and sent as STATUSTEXT from there (before: held until
    the Zenoh backlog drained, and the autopilot heard nothing)."""
    _passport, _g, sc, start = mavlink_unit()
    fillers, _last = fill_outbox(tmp_path / "data", ("zenoh", "mavlink"))
    mav_port = free_udp_port()
    with zenoh_router() as zport, zenoh.open(zenoh_client_config(zport)) as ground:
        status = Statuses(ground)
        config = daemon_config(tmp_path, zport, mav_port)
        config.write_text(config.read_text().replace(
            "[service]\n", f"[service]\noutbox_max_mb = {FULL_PAGES * 4096 / 1e6!r}\n"))  # fmt: skip
        daemon = ServiceProcess(config)
        try:
            peer = use_mavlink2(mavutil.mavlink_connection(f"udpout:127.0.0.1:{mav_port}"))
            try:
                stream(
                    peer, mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start), status
                )
                got = receive_until(peer, ["STATUSTEXT"], lambda msgs: len(of_type(msgs, "STATUSTEXT")) >= 1,
                                    timeout_s=DELIVERY_BOUND_S, what="the F0 alert")  # fmt: skip
            finally:
                peer.close()
            wait_until(lambda: status.counter("mav1", "service.outbox.unavailable") == 1, timeout_s=30,
                       what=lambda: f"the outbox said unavailable ({status.get('mav1')})")  # fmt: skip
        finally:
            daemon.terminate()
    assert len(fillers) > 50 and "IMU0" in got[0].text
    assert any("outbox unavailable (database or disk is full)" in line for line in daemon.lines)


def test_a_data_directory_removed_under_the_daemon_is_said_refused_to_a_second_and_ends_it_non_zero(
    tmp_path,
):
    """The data directory is deleted while the daemon runs (class 8). The daemon says so and counts it;
    a second daemon on the same configuration is refused (before, it made the folder anew and ran
    beside the first); a fault raised after the deletion is delivered (from memory: the deleted outbox
    would lose it at the next start); SIGTERM then exits with status 74, saying the event could not be
    stored (before: 0, and the event was gone at the next start, unlogged)."""
    v = "uav-d"
    want = fault_ids(v)
    with ground_and_vehicle(tmp_path, put_store(tmp_path, [(v, 0)])) as peers:
        config, ground, vehicle, status = peers
        got = []
        with EventReceiver(ground, lambda e: got.append(e.event_id)):
            daemon = ServiceProcess(config)
            try:
                shutil.rmtree(tmp_path / "data")
                wait_until(lambda: any("was removed" in line for line in daemon.lines), timeout_s=30,
                           what=lambda: f"the removal said ({daemon.lines[-3:]})")  # fmt: skip
                second = subprocess.run(
                    [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
                    capture_output=True, text=True, timeout=120, cwd=ROOT,
                )  # fmt: skip
                assert second.returncode == 1, second.stderr
                assert (
                    f"in use by another ins-health daemon (pid {daemon.proc.pid})" in second.stderr
                )
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, to_the_fault(v, batch_samples=200))
                wait_until(lambda: got == want, timeout_s=DELIVERY_BOUND_S,
                           what=lambda: f"the fault after the removal (got {got})")  # fmt: skip
                wait_until(lambda: status.counter(v, "service.storage.data_dir_lost") == 1
                           and status.counter(v, "service.storage.fault") == 1, timeout_s=30,
                           what=lambda: f"the storage fault on the status topic ({status.get(v)})")  # fmt: skip
            finally:
                code = daemon.terminate()
    assert code == EXIT_STORAGE, daemon.lines
    assert any("1 held event(s) could not be stored (1 of them delivered to every sink" in line
               for line in daemon.lines), daemon.lines  # fmt: skip


@contextlib.contextmanager
def _receiving_daemon(tmp_path, v: str, service: str):
    """A router, the ground's receiver of every event (their ids in ``got``), and the daemon (``service``:
    more ``[service]`` lines) taking ``v``'s frames; stopped at the end if it still runs."""
    with ground_and_vehicle(tmp_path, put_store(tmp_path, [(v, 0)]), service=service) as (
        config, ground, vehicle, status,
    ):  # fmt: skip
        got: list[str] = []
        with EventReceiver(ground, lambda e: got.append(e.event_id)):
            daemon = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key(v, 0))
                yield daemon, vehicle, status, got
            finally:
                if daemon.proc.poll() is None:
                    daemon.terminate()


def test_a_data_directory_moved_away_and_back_is_storage_again_and_its_held_event_stored_once(
    tmp_path,
):
    """The data directory is moved away while the daemon runs (a mount over it and its removal, as a
    card's remount shows it) and comes back, the same folder, before ``storage_timeout_s`` (4 s here).
    The fault raised while it was away is delivered from memory; once it is back the daemon says so,
    stores the held event (delivered: nothing pending), goes on past the timeout and exits 0 at SIGTERM
    (before: the fault was never cleared, the daemon ended itself with 74 four seconds later and the
    event, never stored, was said lost)."""
    v = "uav-m"
    want = fault_ids(v)
    data, away = tmp_path / "data", tmp_path / "away"
    with _receiving_daemon(tmp_path, v, "storage_timeout_s = 4.0\n") as (
        daemon,
        vehicle,
        status,
        got,
    ):
        data.rename(away)
        wait_until(lambda: any("was removed" in line for line in daemon.lines), timeout_s=30,
                   what=lambda: f"the removal said ({daemon.lines[-3:]})")  # fmt: skip
        publish_blocking(vehicle, to_the_fault(v, batch_samples=200))
        wait_until(lambda: got == want, timeout_s=DELIVERY_BOUND_S,
                   what=lambda: f"the fault while the folder is away (got {got})")  # fmt: skip
        away.rename(data)
        wait_until(lambda: any("is back after" in line for line in daemon.lines)
                   or daemon.proc.poll() is not None, timeout_s=30,
                   what=lambda: f"storage back said ({daemon.lines[-3:]})")  # fmt: skip
        assert daemon.proc.poll() is None, "\n".join(daemon.lines)
        wait_until(lambda: status.counter(v, "service.outbox.stored") == 1, timeout_s=30,
                   what=lambda: f"the held event stored ({status.get(v)})")  # fmt: skip
        time.sleep(4.0)  # past storage_timeout_s: the daemon goes on
        code = daemon.terminate()
    assert code == 0, "\n".join(daemon.lines)
    with Outbox(data / "outbox.sqlite", sinks=("zenoh",)) as outbox:
        assert [p.id for p in outbox.stored()] == want and outbox.pending("zenoh") == []


def test_events_pending_in_a_removed_data_directory_are_said_lost_at_sigterm_and_exit_74(tmp_path):
    """The ground station is offline, so the fault's event waits in the outbox; then the data directory
    is deleted and the daemon stopped. The pending event is in a file no later start sees: the daemon
    says it is lost and exits 74 (before: 0, saying it would be sent at the next start)."""
    v = "uav-p"
    with ground_and_vehicle(tmp_path, put_store(tmp_path, [(v, 0)])) as peers:
        config, _ground, vehicle, status = peers
        daemon = ServiceProcess(config)
        try:
            wait_subscribed(vehicle, frame_key(v, 0))
            publish_blocking(vehicle, to_the_fault(v, batch_samples=200))
            wait_until(lambda: status.counter(v, "outbox.pending.zenoh") == 1, timeout_s=60,
                       what=lambda: f"the fault pending ({status.get(v)})")  # fmt: skip
            shutil.rmtree(tmp_path / "data")
            wait_until(lambda: any("was removed" in line for line in daemon.lines), timeout_s=30,
                       what=lambda: f"the removal said ({daemon.lines[-3:]})")  # fmt: skip
        finally:
            code = daemon.terminate()
    assert code == EXIT_STORAGE, "\n".join(daemon.lines)
    assert any(
        "1 event deliveries still pending" in line and "lost" in line for line in daemon.lines
    )


def _mount_read_only_tmpfs(path) -> str | None:
    """A read-only tmpfs mounted over ``path``; None, or why the machine forbids it."""
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(path)],
                          capture_output=True, text=True)  # fmt: skip
    return None if proc.returncode == 0 else f"mount refused: {proc.stderr.strip()}"


def test_a_data_directory_turned_read_only_past_storage_timeout_ends_the_daemon_with_74(tmp_path):
    """A read-only file system takes the data directory's place while the daemon runs (a read-only
    tmpfs mounted over it, as a failing SD card remounted read-only shows it; a remount of the daemon's
    own mount is refused while it holds files open for writing). The daemon says the storage fault,
    goes on delivering (the fault raised after it arrives) and, storage still away past
    ``storage_timeout_s`` (5 s here), exits with status 74 for systemd to restart it (before: it wrote
    on into files no later start would see, fed the watchdog, and never said a thing)."""
    v = "uav-r"
    want = fault_ids(v)
    data = tmp_path / "data"
    with _receiving_daemon(tmp_path, v, "storage_timeout_s = 5.0\n") as (
        daemon,
        vehicle,
        _status,
        got,
    ):
        if (why := _mount_read_only_tmpfs(data)) is not None:
            pytest.skip(why)
        try:
            publish_blocking(vehicle, to_the_fault(v, batch_samples=200))
            wait_until(lambda: got == want, timeout_s=DELIVERY_BOUND_S,
                       what=lambda: f"the fault after the storage went (got {got})")  # fmt: skip
            code = daemon.proc.wait(60)
        finally:
            subprocess.run(["umount", "-l", str(data)], check=False)
    assert code == EXIT_STORAGE, daemon.lines
    assert any(
        "storage unavailable for" in line and "storage_timeout_s = 5" in line
        for line in daemon.lines
    )


def test_the_same_fault_at_the_same_uptime_after_a_reboot_is_a_new_event_delivered_once(tmp_path):
    """The vehicle reboots (its seq and time since boot start again) and the same fault returns at the
    same uptime (class 4). Its event is a new one of the new epoch and reaches the ground station
    (before: it had the first one's id, and the outbox dropped it as already delivered); every event
    arrives once, as the same frames give offline."""
    v = "uav-e"
    frames = to_the_fault(v, batch_samples=200)
    offline = offline_fleet()
    first = [e.event_id for e in run_fleet(offline, frames, finish=False)]
    after = run_fleet(offline, frames, finish=False)
    assert [e.epoch for e in after] == [1] * len(after) and after[-1].predicate is Predicate.F0
    want = first + [e.event_id for e in after]
    with ground_and_vehicle(tmp_path, put_store(tmp_path, [(v, 0)])) as peers:
        config, ground, vehicle, status = peers
        got = []
        wire = EventStream(ground)
        with EventReceiver(ground, lambda e: got.append(e.event_id)):
            daemon = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, frames)
                wait_until(
                    lambda: got == first,
                    timeout_s=DELIVERY_BOUND_S,
                    what=lambda: f"the first fault ({got})",
                )
                publish_blocking(vehicle, frames)
                wait_until(lambda: got == want, timeout_s=DELIVERY_BOUND_S,
                           what=lambda: f"the fault after the reboot (got {got}, want {want})")  # fmt: skip
                wait_until(lambda: status.counter(v, "imu0.new_runs") == 1, timeout_s=30,
                           what=lambda: f"the new run counted ({status.get(v)})")  # fmt: skip
            finally:
                assert daemon.terminate() == 0, daemon.lines
    assert wire.snapshot() == want
