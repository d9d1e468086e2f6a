"""The service under faults: kill -9, a router restart, and bad input of every kind (real Zenoh on 127.0.0.1)."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from service_support import (
    EventStream,
    ServiceThread,
    batches_of,
    free_tcp_port,
    run_fleet,
    service_config,
    wait_subscribed,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)

from protocols.events import Predicate
from protocols.frames import SampleBatch, encode_frame
from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key, subscribe_status
from protocols.zenoh_router import RouterProcess
from service.checkpoint import CheckpointStore
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore
from service.pipeline import FleetProcessor, PipelineOptions

pytestmark = pytest.mark.network
ROOT = Path(__file__).parents[1]


@functools.cache
def unit():
    passport, g = demo_passport()
    return passport, g, demo_scenario()


def offline_fleet():
    passport, g, _ = unit()
    return FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
    )


def put_store(tmp_path, keys) -> Path:
    store = PassportStore(tmp_path / "passports")
    for v, i in keys:
        store.put(v, i, unit()[0])
    return store.root


class Statuses:
    """The latest status per vehicle, from the status topic."""

    def __init__(self, session):
        self._lock = threading.Lock()
        self.latest = {}
        self._sub = subscribe_status(session, self._on)

    def _on(self, status) -> None:
        with self._lock:
            self.latest[status.vehicle] = status

    def counter(self, vehicle: str, name: str) -> int:
        with self._lock:
            st = self.latest.get(vehicle)
            return 0 if st is None else st.counters.get(name, 0)

    def get(self, vehicle: str):
        with self._lock:
            return self.latest.get(vehicle)

    def forget(self) -> None:
        """Drop what was received so far (a restarted daemon's status is waited for afresh)."""
        with self._lock:
            self.latest.clear()


@contextlib.contextmanager
def ground_and_vehicle(tmp_path, passports: Path, *, service: str = ""):
    """A router, the daemon's configuration for it (``service``: more ``[service]`` lines), a ground and a
    vehicle session, and the status topic seen from the ground."""
    with zenoh_router() as port:
        config = write_config(tmp_path, port, passports)
        config.write_text(config.read_text().replace("[service]\n", f"[service]\n{service}"))
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            yield config, ground, vehicle, Statuses(ground)


def publish_blocking(session, batches) -> None:
    with FramePublisher(
        session,
        batches[0].vehicle,
        batches[0].imu,
        congestion_control=zenoh.CongestionControl.BLOCK,
    ) as pub:
        for b in batches:
            pub.publish(b)


class ServiceProcess:
    """``ins-health run --config FILE`` as a child process; started when it says ``running`` (an input
    connected) or ``waiting for`` (started, its inputs not yet there: a late router)."""

    def __init__(self, config_path: Path):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "run", "--config", str(config_path)],
            cwd=ROOT, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        self.lines: list[str] = []
        ready = threading.Event()

        def read():
            for line in self.proc.stderr:
                self.lines.append(line.rstrip())
                if line.rstrip().endswith(" running") or " waiting for " in line:
                    ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(60) or self.proc.poll() is not None:
            raise AssertionError(f"the service did not start: {self.lines}")

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)

    def terminate(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(60)


def write_config(tmp_path, port: int, passports: Path, *, mavlink_port: int | None = None) -> Path:
    """The daemon's config file: Zenoh client of the router on ``port``; a MAVLink link too with ``mavlink_port``."""
    path = tmp_path / "service.toml"
    text = f"""
[service]
name = "onboard"
data_dir = "{tmp_path / "data"}"
passport_dir = "{passports}"
status_period_s = 0.2
checkpoint_period_s = 0.2
delivery_retry_s = 0.2
[site]
gravity_mps2 = {unit()[1]!r}
[zenoh]
connect = ["tcp/127.0.0.1:{port}"]
ack_timeout_s = 0.3
[validity]
timeout_s = 600.0
"""
    if mavlink_port is not None:
        text += f'[mavlink]\nenabled = true\ndevice = "udpin:127.0.0.1:{mavlink_port}"\nvehicle = "mav1"\n'
    path.write_text(text)
    return path


def test_kill_9_between_outbox_and_delivery_then_restart_delivers_every_event_exactly_once(
    tmp_path,
):
    """No receiver acknowledges while the service runs, so its events wait in the outbox; it is SIGKILLed,
    a receiver comes up, the service restarts: each event arrives once, and the positions survived."""
    v = "uav-k"
    frames = list(batches_of(unit()[2].session, vehicle=v, imu=0, batch_samples=100))
    want = [e.event_id for e in run_fleet(offline_fleet(), frames, finish=False)]
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [(v, 0)]))
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
        ):
            status = Statuses(ground)
            first = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, frames)
                total = sum(b.n_samples for b in frames)
                wait_until(
                    lambda: status.counter(v, "imu0.samples.accepted") == total,
                    timeout_s=60,
                    what="every sample processed",
                )
                wait_until(lambda: status.counter(v, "service.outbox.pending.zenoh") == len(want), timeout_s=30,
                           what=lambda: f"the events held (status {status.get(v)})")  # fmt: skip
                checkpoints = CheckpointStore(tmp_path / "data" / "checkpoints.sqlite")
                wait_until(lambda: (cp := checkpoints.load(f"{v}/0")) is not None and cp.state["n_samples"] == total,
                           timeout_s=30, what="a checkpoint after the last frame")  # fmt: skip
                positions = checkpoints.load(f"{v}/0").state["n_positions"]
                checkpoints.close()
            finally:
                first.kill()
            assert first.proc.returncode == -signal.SIGKILL
            got = []
            wire = EventStream(ground)
            with EventReceiver(ground, lambda e: got.append(e.event_id)):
                second = ServiceProcess(config)
                try:
                    wait_until(
                        lambda: len(got) == len(want),
                        timeout_s=60,
                        what="the held events after the restart",
                    )
                    wait_until(lambda: status.counter(v, "service.outbox.pending.zenoh") == 0 and status.get(v).imus,
                               timeout_s=30, what="an empty outbox")  # fmt: skip
                    restored = status.get(v).imus[0]
                finally:
                    assert second.terminate() == 0
            assert got == want and wire.snapshot() == want
            assert restored.positions == positions > 20 and restored.samples == total
            assert any("running" in line for line in second.lines)


KILLS = 5
"""SIGKILLs of the random-moment test: three anywhere, two while the disagreement stands."""
KILL_CHUNK = 30
"""Frames the vehicle side publishes before it waits for the daemon to take them."""


def test_kill_9_at_random_moments_every_event_once_and_a_disagreement_never_raised_again(tmp_path):
    """Two vehicles: uav-c with two IMUs that disagree from the landing on (IMU1's z accelerometer off by
    0.1 g; both are flagged, a pair), uav-k with the demo's scale-factor fault. The daemon is SIGKILLed
    after seeded random frames and restarted each time; the vehicle side resumes every unit after the
    last frame of its checkpoint (a source that replays what the monitor did not keep). Every event id of
    the same frames run offline arrives exactly once at the acknowledging receiver and no other does:
    a restart neither loses an event nor raises the disagreement again under a new id."""
    rng = np.random.default_rng(15)
    clean, bad = (
        demo_scenario(fault_magnitude=0.0),
        demo_scenario(fault_index=2, fault_magnitude=0.1),
    )
    streams = {
        ("uav-c", 0): clean.session,
        ("uav-c", 1): bad.session,
        ("uav-k", 0): unit()[2].session,
    }
    frames = {
        key: list(batches_of(s, vehicle=key[0], imu=key[1], batch_samples=100))
        for key, s in streams.items()
    }
    n_frames = min(map(len, frames.values()))
    samples = {key: np.cumsum([b.n_samples for b in f[:n_frames]]) for key, f in frames.items()}
    order = [(key, k) for k in range(n_frames) for key in streams]
    offline, expected, raised_at = offline_fleet(), [], None
    for n, (key, k) in enumerate(order):
        expected += offline.process(frames[key][k], arrival_s=float(frames[key][k].t_s[-1]))
        if raised_at is None and any(e.predicate is Predicate.CROSS_IMU for e in expected):
            raised_at = n
    want = [e.event_id for e in expected]
    assert [(e.vehicle, e.imu) for e in expected if e.predicate is Predicate.CROSS_IMU] == [
        ("uav-c", 0),
        ("uav-c", 1),
    ]
    # The norms of the two units moved apart too, once (its state is in the vehicle's checkpoint).
    assert [(e.vehicle, e.imu) for e in expected if e.predicate is Predicate.CROSS_IMU_NORM] == [
        ("uav-c", 1)
    ]
    assert {e.vehicle for e in expected} == {"uav-c", "uav-k"}
    kill_at = sorted(
        [*rng.choice(np.arange(10, raised_at), 3, replace=False),
         *rng.choice(np.arange(raised_at + 1, len(order) - 10), KILLS - 3, replace=False)]
    )  # fmt: skip
    data = tmp_path / "data"
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, list(streams)))
        with (
            zenoh.open(zenoh_client_config(port)) as ground,
            zenoh.open(zenoh_client_config(port)) as vehicle,
            contextlib.ExitStack() as publishers,
        ):
            pubs = {
                key: publishers.enter_context(
                    FramePublisher(vehicle, *key, congestion_control=zenoh.CongestionControl.BLOCK)
                )
                for key in streams
            }
            status = Statuses(ground)
            got = []
            with EventReceiver(ground, lambda e: got.append(e.event_id)):
                for stop in [*kill_at, len(order)]:
                    resume = {key: 0 for key in streams}
                    if (data / "checkpoints.sqlite").exists():
                        with CheckpointStore(data / "checkpoints.sqlite") as checkpoints:
                            for key in streams:
                                cp = checkpoints.load(f"{key[0]}/{key[1]}")
                                resume[key] = 0 if cp is None else cp.state["last_seq"] + 1
                    status.forget()
                    daemon = ServiceProcess(config)
                    for key in streams:
                        wait_subscribed(vehicle, frame_key(*key))
                    todo = [(key, k) for key, k in order[:stop] if k >= resume[key]]
                    for start in range(0, len(todo), KILL_CHUNK):
                        sent = {}
                        for key, k in todo[start : start + KILL_CHUNK]:
                            pubs[key].publish(frames[key][k])
                            sent[key] = k
                        if start + KILL_CHUNK < len(todo):
                            # Paced by the daemon (its queue never overflows): the kill finds the
                            # last chunk in flight and checkpoints behind it.
                            wait_until(lambda: all(status.counter(v, f"imu{i}.samples.accepted") == samples[(v, i)][k]
                                                   for (v, i), k in sent.items()),
                                       timeout_s=60, what=lambda: f"the daemon to take {sent}")  # fmt: skip
                    if stop < len(order):
                        daemon.kill()
                        assert daemon.proc.returncode == -signal.SIGKILL
                try:
                    wait_until(lambda: sorted(got) == sorted(want), timeout_s=60,
                               what=lambda: f"every event (got {got}, want {want})")  # fmt: skip
                    wait_until(lambda: all(status.counter(v, f"imu{i}.samples.accepted") == samples[(v, i)][-1]
                                           for v, i in streams), timeout_s=30, what="every sample")  # fmt: skip
                finally:
                    assert daemon.terminate() == 0
    assert len(got) == len(set(got)) == len(want)


def test_router_stopped_and_restarted_during_a_run(tmp_path):
    """Events raised while nobody can receive them are held; the router goes down and comes back; the
    service reconnects, delivers them, and takes frames again."""
    v = "uav-r"
    sc = unit()[2]
    frames = list(batches_of(sc.session, vehicle=v, imu=0, batch_samples=100))
    before = [b for b in frames if b.t_s[-1] < sc.fault_s + 3.0]
    after = frames[len(before) :][:20]
    expected = run_fleet(offline_fleet(), before, finish=False)
    assert [e.predicate for e in expected] == [Predicate.F0]
    want = [e.event_id for e in expected]
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    port = int(endpoint.rsplit(":", 1)[1])
    router = RouterProcess(endpoint).start()
    try:
        cfg = service_config(tmp_path, port=port, passport_dir=put_store(tmp_path, [(v, 0)]), site={"gravity_mps2": unit()[1]},
                             validity={"timeout_s": 600.0}, service={"delivery_retry_s": 0.2}, zenoh={"ack_timeout_s": 0.3})  # fmt: skip
        with ServiceThread(cfg) as svc:
            with zenoh.open(zenoh_client_config(port)) as vehicle:
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, before)
                wait_until(lambda: svc.call(lambda: svc.service.outbox.counts().pending_by_sink["zenoh"]) == len(want),
                           timeout_s=60, what="the F0 event held in the outbox")  # fmt: skip
            router.stop()
            router.start()
            with (
                zenoh.open(zenoh_client_config(port)) as ground,
                zenoh.open(zenoh_client_config(port)) as vehicle,
            ):
                got = []
                with EventReceiver(ground, lambda e: got.append(e.event_id)):
                    wait_until(
                        lambda: got == want,
                        timeout_s=60,
                        what="the held event after the router restart",
                    )
                wait_subscribed(vehicle, frame_key(v, 0), timeout_s=30)
                publish_blocking(vehicle, after)
                total = sum(b.n_samples for b in before + after)
                wait_until(lambda: svc.call(lambda: svc.service.fleet.pipelines[(v, 0)].n_samples) == total,
                           timeout_s=30, what="frames after the restart")  # fmt: skip
    finally:
        router.stop()


def _frame_map(batch: SampleBatch) -> dict:
    return msgpack.unpackb(encode_frame(batch), raw=False)


def test_bad_input_is_counted_and_reported_and_the_diagnosis_is_intact(tmp_path):
    """Malformed bytes, wrong types and lengths, NaN, a payload on another IMU's key, duplicated and
    out-of-order frames, a time jump, an unknown vehicle and a flood beyond capacity: every one is
    counted on the status topic, nothing crashes, and the IMU's events are those of the same sequence
    run offline (the fault is still detected and named)."""
    v = "uav-b"
    sc = unit()[2]
    good = list(batches_of(sc.session, vehicle=v, imu=0, batch_samples=100))
    # A time jump: everything after frame 10 comes 10 s later.
    good = good[:10] + [dataclasses.replace(b, t_s=b.t_s + 10.0) for b in good[10:]]
    nan = dataclasses.replace(
        good[3],
        accel_mps2=np.where(np.arange(300).reshape(100, 3) == 7, np.nan, good[3].accel_mps2),
    )
    bad = {
        "malformed": b"\xc1\x00not msgpack",
        "missing_field": msgpack.packb(
            {k: val for k, val in _frame_map(good[0]).items() if k != "gyro_rps"}
        ),
        "wrong_type": msgpack.packb({**_frame_map(good[0]), "imu": "zero"}),
        "wrong_length": msgpack.packb(
            {**_frame_map(good[0]), "accel_mps2": _frame_map(good[0])["accel_mps2"][:-8]}
        ),
        "non_finite": encode_frame(nan),
        "key_mismatch": encode_frame(dataclasses.replace(good[0], imu=3)),
    }
    # The IMU0 stream as sent: bad payloads early on, a duplicate, a frame resent late.
    script = [("frame", b) for b in good[:5]]
    script += [("bytes", reason, payload) for reason, payload in bad.items()]
    script += [("frame", good[5]), ("frame", good[5]), ("frame", good[6]), ("frame", good[4])]
    script += [("frame", b) for b in good[7:]]
    offline = offline_fleet()
    want = []
    for item in script:
        want += (
            offline.process(item[1], arrival_s=0.0)
            if item[0] == "frame"
            else offline.reject(v, 0, item[1])
        )
    with zenoh_router() as port:
        cfg = service_config(tmp_path, port=port, passport_dir=put_store(tmp_path, [(v, 0), (v, 1)]), site={"gravity_mps2": unit()[1]},
                             service={"vehicles": [v]}, validity={"timeout_s": 600.0}, pipeline={"queue_capacity": 8})  # fmt: skip
        with (
            ServiceThread(cfg) as svc,
            zenoh.open(zenoh_client_config(port)) as vehicle,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            status = Statuses(ground)
            got = []
            with EventReceiver(ground, lambda e: got.append(e.event_id) if e.imu == 0 else None):
                # A flood on IMU1 first: small frames, far faster than the service takes them.
                wait_subscribed(vehicle, frame_key(v, 1))
                flood = [
                    dataclasses.replace(b, imu=1, seq=k)
                    for k, b in enumerate(batches_of(sc.session, vehicle=v, imu=1, batch_samples=5))
                ][:2400]
                publish_blocking(vehicle, flood)
                stranger = next(batches_of(sc.session, vehicle="stranger", imu=0, batch_samples=10))
                vehicle.put(frame_key("stranger", 0), encode_frame(stranger))
                wait_until(
                    lambda: status.counter(v, "service.frames.rejected.unknown_vehicle") == 1,
                    timeout_s=30,
                    what="the stranger counted",
                )
                # The IMU0 stream at a pace the service keeps up with (the queue holds 8 frames):
                # a few frames, then wait until the queue is empty.
                with FramePublisher(
                    vehicle, v, 0, congestion_control=zenoh.CongestionControl.BLOCK
                ) as pub:
                    for k, item in enumerate(script):
                        if item[0] == "frame":
                            pub.publish(item[1])
                        else:
                            vehicle.put(
                                frame_key(v, 0),
                                item[2],
                                congestion_control=zenoh.CongestionControl.BLOCK,
                            )
                        if k % 4 == 3:
                            sent = len(flood) + 2 + k
                            wait_until(lambda: svc.call(lambda: svc.service.source.counters.received) >= sent
                                       and svc.call(lambda: svc.service.source.queued) == 0, timeout_s=30, what="the queue to drain")  # fmt: skip
                wait_until(lambda: len(got) >= len(want), timeout_s=60, what="the events of IMU0")
                accepted = sum(b.n_samples for b in good)
                wait_until(
                    lambda: status.counter(v, "imu0.samples.accepted") == accepted,
                    timeout_s=30,
                    what="a status after the stream",
                )
                st = status.get(v)
            assert svc.call(lambda: svc.service.fleet.pipelines[(v, 0)].n_samples) == accepted
    assert got == [e.event_id for e in want]
    assert {Predicate.F0, Predicate.F6} <= {e.predicate for e in want}
    c = st.counters
    for reason in (
        "malformed",
        "missing_field",
        "wrong_type",
        "wrong_length",
        "non_finite",
        "key_mismatch",
    ):
        assert c[f"service.frames.rejected.{reason}"] == 1, reason
    assert c["imu0.frames.rejected.non_finite"] == 1 and c["imu0.frames.rejected.key_mismatch"] == 1
    assert (
        c["imu0.frames.duplicate"] == 1
        and c["imu0.frames.out_of_order"] == 1
        and c["imu0.time_jumps"] == 1
    )
    assert c["service.frames.rejected.unknown_vehicle"] == 1
    assert c["service.frames.dropped_overload"] > 0
    assert c["imu1.frames.accepted"] + c["service.frames.dropped_overload"] == len(flood)
    assert c["service.frames.received"] == len(flood) + 1 + len(script)
