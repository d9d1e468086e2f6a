"""Hostile input against the real daemon and router processes: it keeps monitoring the healthy vehicles
and says what happened (issue 15)."""

from __future__ import annotations

import dataclasses
import os
import sqlite3

import numpy as np
import pytest
import zenoh
from service_support import (
    batches_of,
    run_fleet,
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
from protocols.frames import encode_frame
from protocols.zenoh_adapter import ZENOH_MAX_MESSAGE_BYTES, EventReceiver, frame_key
from service.checkpoint import CheckpointStore

pytestmark = pytest.mark.network


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
        config = write_config(tmp_path, port, put_store(tmp_path, [(good, 0), (stamps, 0)]))
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
    sc = unit()[2]
    frames = [
        b
        for b in batches_of(sc.session, vehicle=good, imu=0, batch_samples=100)
        if b.t_s[-1] < sc.fault_s + 3.0
    ]
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
    with zenoh_router() as port:
        config = write_config(tmp_path, port, root)
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status = Statuses(ground)
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
