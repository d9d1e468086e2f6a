"""Hostile input against the real daemon and router processes: it keeps monitoring the healthy vehicles
and says what happened (issue 15)."""

from __future__ import annotations

import dataclasses
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from service_support import (
    EventStream,
    batches_of,
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
    unit,
    write_config,
)

from protocols.events import Event, Predicate, Severity, StreamCause, encode_event, make_event
from protocols.frames import encode_frame
from protocols.zenoh_adapter import ZENOH_MAX_MESSAGE_BYTES, EventReceiver, frame_key
from service.checkpoint import CheckpointStore
from service.outbox import Outbox, OutboxUnavailable

pytestmark = pytest.mark.network


def to_the_fault(vehicle: str, *, batch_samples: int):
    """The demo unit's frames up to 3 s after its fault: its F0 event and nothing more."""
    sc = unit()[2]
    frames = batches_of(sc.session, vehicle=vehicle, imu=0, batch_samples=batch_samples)
    return [b for b in frames if b.t_s[-1] < sc.fault_s + 3.0]


def test_poisoned_keys_rates_and_checkpoints_cost_only_their_unit(tmp_path):
    """Before the start, two checkpoints that cannot be resumed (a rate of 1e300 Hz, undecodable bytes);
    while running, a frame on a key whose IMU index is a superscript digit and a new IMU whose samples
    are 1 ns apart. The daemon starts, moves both checkpoints aside and says so, counts both frames'
    rejections on the status topic, delivers the healthy vehicle's F0 event, stops cleanly on SIGTERM,
    and starts again."""
    good, poisoned, stamps = "uav-h", "uav-q", "uav-s"
    sc = unit()[2]
    frames = list(batches_of(sc.session, vehicle=good, imu=0, batch_samples=100))
    frames = [b for b in frames if b.t_s[-1] < sc.fault_s + 3.0]
    expected = run_fleet(offline_fleet(), frames, finish=False)
    assert [e.predicate for e in expected] == [Predicate.F0]
    source = offline_fleet()
    run_fleet(source, list(batches_of(sc.session, vehicle=poisoned, imu=0, batch_samples=100))[:30])
    (tmp_path / "data").mkdir()
    with CheckpointStore(tmp_path / "data" / "checkpoints.sqlite") as store:
        store.save(
            f"{poisoned}/0", {**source.pipelines[(poisoned, 0)].state_dict(), "rate_hz": 1e300}
        )
        store.save(f"{poisoned}/1", {"n": 1})
    db = sqlite3.connect(tmp_path / "data" / "checkpoints.sqlite")
    db.execute("UPDATE checkpoints SET payload = x'c1c1c1' WHERE key = ?", (f"{poisoned}/1",))
    db.commit()
    db.close()
    hostile_rate = [
        dataclasses.replace(b, vehicle=stamps, t_s=1e-9 * np.arange(b.n_samples) + 1e-7 * k)
        for k, b in enumerate(frames[:20])
    ]
    with zenoh_router() as port:
        # uav-q has its passport: the rate, not the passport, is what its checkpoint fails on.
        config = write_config(
            tmp_path, port, put_store(tmp_path, [(good, 0), (stamps, 0), (poisoned, 0)])
        )
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status = Statuses(ground)
            got = []
            with EventReceiver(
                ground, lambda e: got.append(e.event_id) if e.vehicle == good else None
            ):
                first = ServiceProcess(config)
                try:
                    wait_subscribed(vehicle, frame_key(good, 0))
                    superscript = dataclasses.replace(frames[0], vehicle="uav-x", imu=2)
                    vehicle.put("ins/uav-x/imu/²", encode_frame(superscript))
                    publish_blocking(vehicle, hostile_rate)
                    publish_blocking(vehicle, frames)
                    wait_until(lambda: got == [e.event_id for e in expected], timeout_s=60,
                               what=lambda: f"the healthy vehicle's F0 event (got {got})")  # fmt: skip
                    n_hostile = sum(b.n_samples for b in hostile_rate)
                    wait_until(
                        lambda: (
                            status.counter(stamps, "imu0.samples.rejected.implausible_rate")
                            == n_hostile
                            and status.counter(good, "service.frames.rejected.key_mismatch") == 1
                        ),
                        timeout_s=30,
                        what=lambda: f"the rejections on the status topic ({status.get(stamps)})",
                    )
                    assert status.counter(poisoned, "checkpoints.discarded") == 1
                finally:
                    code = first.terminate()
            assert code == 0, first.lines
            moved = [line for line in first.lines if "moved aside" in line]
            assert len(moved) == 2 and any("1e+300" in line for line in moved), first.lines
            with CheckpointStore(tmp_path / "data" / "checkpoints.sqlite") as store:
                assert sorted(k for k, _ in store.quarantined()) == [
                    f"{poisoned}/0",
                    f"{poisoned}/1",
                ]
            second = ServiceProcess(config)
            assert second.terminate() == 0
            assert not any("moved aside" in line for line in second.lines), second.lines


def test_store_entries_that_are_not_small_regular_files_cost_only_their_unit(tmp_path):
    """Beside a good passport: a FIFO, a directory, a symlink to a FIFO, a 100 MB sparse file and JSON
    nested beyond the parser's limit, each filed as another unit's entry. The daemon starts (reading a
    FIFO would wait forever for a writer), monitors the good unit (its F0 event arrives), takes frames
    of a refused unit with the stream checks only (its entry read again, at run time), reports every
    refusal with its reason on the status topic and in its log, and ends on SIGTERM."""
    good = "uav-p"
    frames = to_the_fault(good, batch_samples=100)
    expected = run_fleet(offline_fleet(), frames, finish=False)
    assert [e.predicate for e in expected] == [Predicate.F0]
    root = put_store(tmp_path, [(good, 0)])
    os.mkfifo(root / good / "imu1.passport.json")
    (root / good / "imu2.passport.json").mkdir()
    (root / "uav-link").mkdir()
    (root / "uav-link" / "imu0.passport.json").symlink_to(root / good / "imu1.passport.json")
    (root / "uav-big").mkdir()
    with open(root / "uav-big" / "imu0.passport.json", "wb") as f:
        f.truncate(100 * 2**20)
    (root / "uav-deep").mkdir()
    (root / "uav-deep" / "imu0.passport.json").write_text("[" * 100_000 + "]" * 100_000)
    refused = {"not_a_regular_file": 3, "too_large": 1, "nested_too_deeply": 1}
    with ground_and_vehicle(tmp_path, root) as (config, ground, vehicle, status):
        got = []
        with EventReceiver(ground, lambda e: got.append(e.event_id)):
            daemon = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key(good, 1))
                fifo_unit = [dataclasses.replace(b, imu=1) for b in frames[:5]]
                publish_blocking(vehicle, fifo_unit)
                publish_blocking(vehicle, frames)
                wait_until(lambda: got == [e.event_id for e in expected], timeout_s=60,
                           what=lambda: f"the good unit's F0 event (got {got})")  # fmt: skip
                n_fifo = sum(b.n_samples for b in fifo_unit)
                wait_until(
                    lambda: (
                        status.counter(good, "imu1.samples.accepted") == n_fifo
                        and all(
                            status.counter(good, f"service.passports.rejected.{k}") == n
                            for k, n in refused.items()
                        )
                    ),
                    timeout_s=30,
                    what=lambda: f"the refusals on the status topic ({status.get(good)})",
                )
            finally:
                code = daemon.terminate()
    assert code == 0, daemon.lines
    for unit_name, why in [
        (f"{good} IMU1", "not a regular file (a FIFO)"),
        (f"{good} IMU2", "not a regular file (a directory)"),
        ("uav-link IMU0", "not a regular file (a FIFO)"),
        ("uav-big IMU0", "104857600 bytes exceeds the limit"),
        ("uav-deep IMU0", "nested too deeply"),
    ]:
        assert any(unit_name in line and why in line for line in daemon.lines), (
            unit_name,
            daemon.lines,
        )


def test_oversized_zenoh_puts_are_dropped_by_zenoh_or_refused_and_counted(tmp_path):
    """Three puts of 4 MiB on a frame key, through a router that does not bound message sizes.
    The daemon's session drops the first while reassembling it (transport/link/rx/max_message_size;
    Zenoh 1.10.2 then lets the next ones through in full, see protocols.zenoh_adapter), and the
    others are refused before unpacking and counted (too_large). The link stays up and the healthy
    vehicle's F0 event arrives with every one of its frames received."""
    good = "uav-g"
    frames = [b for b in batches_of(unit()[2].session, vehicle=good, imu=0, batch_samples=100)]
    frames = [b for b in frames if b.t_s[-1] < unit()[2].fault_s + 3.0]
    assert ZENOH_MAX_MESSAGE_BYTES < 4 << 20
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [(good, 0)]))
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status, got = Statuses(ground), []
            with EventReceiver(ground, lambda e: got.append(e.predicate)):
                daemon = ServiceProcess(config)
                try:
                    wait_subscribed(vehicle, frame_key("uav-big", 0))
                    big = vehicle.declare_publisher(
                        frame_key("uav-big", 0), congestion_control=zenoh.CongestionControl.BLOCK
                    )
                    for _ in range(3):
                        big.put(b"\x00" * (4 << 20))
                    publish_blocking(vehicle, frames)
                    wait_until(lambda: Predicate.F0 in got, timeout_s=60, what="the F0 event")
                    wait_until(
                        lambda: status.counter(good, "imu0.frames.accepted") == len(frames),
                        timeout_s=30,
                        what=lambda: f"the frames counted: {status.get(good)}",
                    )
                    counters = status.get(good).counters
                finally:
                    assert daemon.terminate() == 0
    too_large = counters.get("service.frames.rejected.too_large", 0)
    # Without the bound all three would reach the decoder.
    assert too_large < 3
    assert counters["service.frames.received"] == len(frames) + too_large


def test_an_outbox_locked_by_another_process_delays_no_event_and_stores_each_once_when_released(
    tmp_path,
):
    """Another process holds the outbox's write lock (``BEGIN EXCLUSIVE``) while a faulty vehicle and a
    second one publish: the events cannot be stored. The daemon says ``outbox unavailable`` on the status
    topic and in its log, goes on taking frames (both vehicles' are all processed) and delivers both
    events from memory while the lock is held (before, it held them and took no frame until the lock
    went). The lock is released: the events are stored as delivered, none is put on the wire again."""
    faulty, other = "uav-f", "uav-o"
    frames = {v: to_the_fault(v, batch_samples=200) for v in (faulty, other)}
    want = sorted(
        e.event_id for v in frames for e in run_fleet(offline_fleet(), frames[v], finish=False)
    )
    assert len(want) == 2
    passports = put_store(tmp_path, [(faulty, 0), (other, 0)])
    with ground_and_vehicle(tmp_path, passports) as (config, ground, vehicle, status):
        got = []
        wire = EventStream(ground)
        with EventReceiver(ground, lambda e: got.append(e.event_id)):
            daemon = ServiceProcess(config)
            try:
                lock = sqlite3.connect(tmp_path / "data" / "outbox.sqlite", isolation_level=None)
                lock.execute("BEGIN EXCLUSIVE")
                try:
                    wait_subscribed(vehicle, frame_key(faulty, 0))
                    publish_blocking(vehicle, frames[faulty])
                    publish_blocking(vehicle, frames[other])
                    wait_until(lambda: sorted(got) == want, timeout_s=60,
                               what=lambda: f"both vehicles' events from memory (got {got})")  # fmt: skip
                    n = {v: sum(b.n_samples for b in frames[v]) for v in frames}
                    wait_until(lambda: all(status.counter(v, "imu0.samples.accepted") == n[v] for v in frames)
                               and status.counter(other, "service.outbox.held_events") == 2,
                               timeout_s=60, what=lambda: f"every frame taken ({status.get(other)})")  # fmt: skip
                    held = status.get(other).counters
                    assert held["service.outbox.unavailable"] == 1 == held["service.storage.fault"]
                    assert held["service.outbox.write_failures"] >= 1
                finally:
                    lock.execute("ROLLBACK")
                    lock.close()
                wait_until(
                    lambda: status.counter(other, "service.outbox.unavailable") == 0,
                    timeout_s=30,
                    what=lambda: f"the outbox available again ({status.get(other)})",
                )
                after = status.get(other).counters
                with Outbox(tmp_path / "data" / "outbox.sqlite", sinks=("zenoh",)) as ob:
                    assert sorted(p.id for p in ob.stored()) == want and ob.pending("zenoh") == []
            finally:
                code = daemon.terminate()
    assert code == 0, daemon.lines
    assert len(got) == len(set(got)) == 2 and sorted(wire.snapshot()) == want
    assert after["service.outbox.unavailable_episodes"] == 1
    assert after.get("service.frames.dropped_overload", 0) == 0
    assert any("outbox unavailable (database is locked)" in line for line in daemon.lines), (
        daemon.lines
    )
    assert any("outbox available again" in line for line in daemon.lines), daemon.lines


FULL_PAGES = 40
"""Size of the full outbox of the disk-full test, in SQLite pages of 4096 bytes."""


def fill_outbox(data: Path, sinks: tuple[str, ...]) -> tuple[list[str], Event]:
    """An outbox of :data:`FULL_PAGES` in ``data`` filled with another vehicle's events pending for
    ``sinks``: their ids, and the last event, which did not fit."""
    fillers: list[str] = []
    data.mkdir()
    with Outbox(data / "outbox.sqlite", sinks=sinks, max_bytes=FULL_PAGES * 4096) as ob:
        # Large events until one does not fit, then events smaller than F0's until none does.
        for text in ("x" * 900, "x"):
            while True:
                filler = make_event(vehicle="uav-fill", imu=0, t_s=float(len(fillers)), predicate=Predicate.TIMEOUT,
                                    cause=StreamCause.NO_DATA, severity=Severity.WARNING, text=text)  # fmt: skip
                try:
                    ob.put(filler.event_id, filler.vehicle, encode_event(filler))
                except OutboxUnavailable as exc:
                    assert "database or disk is full" in str(exc)
                    break
                fillers.append(filler.event_id)
    return fillers, filler


def test_a_full_outbox_holds_the_events_until_deliveries_make_room(tmp_path):
    """The outbox is full (its ``outbox_max_mb`` reached: SQLite's own 'database or disk is full', as on
    a full disk) of events of another vehicle that no receiver has acknowledged yet. The faulty
    vehicle's F0 event cannot be stored: the daemon says ``outbox unavailable`` and holds it. A receiver
    comes up: the waiting events are delivered, their history gives way, the F0 event is stored and
    arrives, exactly once, and the daemon says the outbox is back."""
    v = "uav-d"
    frames = to_the_fault(v, batch_samples=200)
    expected = run_fleet(offline_fleet(), frames, finish=False)
    want = [e.event_id for e in expected]
    fillers, last = fill_outbox(tmp_path / "data", ("zenoh",))
    # The last that did not fit is smaller than the F0 event: F0 cannot fit either.
    assert len(encode_event(last)) < len(encode_event(expected[0]))
    passports = put_store(tmp_path, [(v, 0)])
    limit = f"outbox_max_mb = {FULL_PAGES * 4096 / 1e6!r}\n"
    with ground_and_vehicle(tmp_path, passports, service=limit) as (
        config,
        ground,
        vehicle,
        status,
    ):
        daemon = ServiceProcess(config)
        try:
            wait_subscribed(vehicle, frame_key(v, 0))
            publish_blocking(vehicle, frames)
            wait_until(lambda: status.counter(v, "service.outbox.unavailable") == 1,
                       timeout_s=60, what=lambda: f"outbox unavailable on the status topic ({status.get(v)})")  # fmt: skip
            got = []
            with EventReceiver(ground, lambda e: got.append(e.event_id)):
                wait_until(lambda: sorted(got) == sorted(fillers + want), timeout_s=60,
                           what=lambda: f"the waiting events, then F0 ({len(got)} of {len(fillers) + 1})")  # fmt: skip
                wait_until(
                    lambda: (
                        status.counter(v, "service.outbox.unavailable") == 0
                        and status.counter(v, "imu0.samples.accepted")
                        == sum(b.n_samples for b in frames)
                    ),
                    timeout_s=30,
                    what=lambda: f"the outbox available again ({status.get(v)})",
                )
        finally:
            code = daemon.terminate()
    assert code == 0, daemon.lines
    assert len(fillers) > 50 and len(got) == len(set(got))
    assert any("outbox unavailable (database or disk is full)" in line for line in daemon.lines), (
        daemon.lines
    )
    assert any("outbox available again" in line for line in daemon.lines), daemon.lines


def test_checkpoints_a_crash_or_a_hand_left_unreadable_cost_only_themselves(tmp_path):
    """A checkpoint file cut or overwritten stopped the daemon at every start (under systemd, for
    good); a row whose key names no unit stopped it too, and one naming an invalid vehicle id broke
    the status topic of the whole fleet. Now the file is moved aside, the rows are quarantined, and
    the healthy vehicle is monitored as before."""
    good = "uav-h"
    frames = to_the_fault(good, batch_samples=100)
    expected = [e.event_id for e in run_fleet(offline_fleet(), frames, finish=False)]
    data = tmp_path / "data"
    data.mkdir()
    (data / "checkpoints.sqlite").write_bytes(os.urandom(8192))
    got: list[str] = []
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [(good, 0)]))
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
            EventReceiver(ground, lambda e: got.append(e.event_id)),
        ):
            status = Statuses(ground)
            first = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key(good, 0))
                publish_blocking(vehicle, frames)
                wait_until(lambda: got == expected, timeout_s=60,
                           what=lambda: f"the healthy vehicle's F0 event (got {got})")  # fmt: skip
                wait_until(
                    lambda: status.counter(good, "service.checkpoints.store_replaced") == 1,
                    timeout_s=30,
                    what=lambda: f"the replaced store on the status topic ({status.get(good)})",
                )
            finally:
                assert first.terminate() == 0, first.lines
            assert any("could not be opened" in line for line in first.lines), first.lines
            assert len(list(data.glob("checkpoints.sqlite.unreadable-*"))) == 1
            with CheckpointStore(data / "checkpoints.sqlite") as store:
                assert store.keys() == [f"{good}/0"]
                store.save("noslash", {"n": 1})
                store.save("bad vehicle!/0", {"n": 1})
            status.forget()
            second = ServiceProcess(config)
            try:
                # Its checkpointed unit is back before its first frame, and says so.
                wait_until(lambda: status.counter(good, "checkpoints.restored") == 1, timeout_s=30,
                           what=lambda: f"the healthy vehicle's status ({status.get(good)})")  # fmt: skip
            finally:
                assert second.terminate() == 0, second.lines
    with CheckpointStore(data / "checkpoints.sqlite") as store:
        assert sorted(k for k, _ in store.quarantined()) == ["bad vehicle!/0", "noslash"]


def test_an_unreadable_outbox_stops_the_start_with_one_line_saying_what_to_do(tmp_path):
    """It may hold events not yet delivered, so it is not moved aside as the checkpoints are; but the
    reason was the last frame of a folded traceback."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "outbox.sqlite").write_bytes(os.urandom(8192))
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [("uav-h", 0)]))
        proc = subprocess.run(
            [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    (line,) = [ln for ln in proc.stderr.splitlines() if "CRITICAL" in ln]
    assert "the daemon cannot start: outbox" in line and "move it aside" in line
    assert "Traceback" not in proc.stderr


def test_a_second_daemon_on_the_same_data_directory_is_refused_naming_the_first(tmp_path):
    """Both started and took every frame before: the same units checkpointed twice, one status name
    published by two processes."""
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [("uav-h", 0)]))
        first = ServiceProcess(config)
        try:
            second = subprocess.run(
                [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
                capture_output=True, text=True, timeout=120, cwd=ROOT,
            )  # fmt: skip
        finally:
            assert first.terminate() == 0, first.lines
        assert second.returncode == 1, second.stderr
        assert f"is in use by another ins-health daemon (pid {first.proc.pid})" in second.stderr
        # Once the first has ended, the directory is free again.
        assert ServiceProcess(config).terminate() == 0


def test_checkpoints_of_vehicles_gone_for_long_do_not_fill_the_vehicle_limit_at_start(tmp_path):
    """300 retired vehicles' checkpoints were all admitted at every start: the first 256 filled
    max_vehicles and a real vehicle without a passport had every frame refused."""
    data = tmp_path / "data"
    data.mkdir()
    with CheckpointStore(data / "checkpoints.sqlite") as store:
        store.save_many(
            {f"old-{k:03d}/0": {"n": 1} for k in range(300)}, now_unix_s=time.time() - 8 * 86_400
        )
    frames = to_the_fault("uav-np", batch_samples=100)[:20]
    passports = put_store(tmp_path, [("uav-h", 0)])
    with ground_and_vehicle(tmp_path, passports) as (config, _, vehicle, status):
        service = ServiceProcess(config)
        try:
            wait_subscribed(vehicle, frame_key("uav-np", 0))
            publish_blocking(vehicle, frames)
            wait_until(
                lambda: status.counter("uav-np", "imu0.frames.accepted") == len(frames),
                timeout_s=30,
                what=lambda: f"the new vehicle's frames accepted ({status.get('uav-np')})",
            )
            assert status.get("old-000") is None
        finally:
            assert service.terminate() == 0, service.lines


def test_events_left_pending_for_a_sink_taken_out_of_the_configuration_are_said_at_start(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    with Outbox(data / "outbox.sqlite", sinks=("zenoh", "mavlink")) as ob:
        ob.put_many([(f"{k:032d}", "uav-h", b"E") for k in range(3)])
        ob.ack("zenoh", [e.seq for e in ob.pending("zenoh")])
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [("uav-h", 0)]))
        service = ServiceProcess(config)
        assert service.terminate() == 0, service.lines
    said = [ln for ln in service.lines if "events pending for sinks not configured now" in ln]
    assert len(said) == 1 and said[0].endswith(": 3 for mavlink"), service.lines
