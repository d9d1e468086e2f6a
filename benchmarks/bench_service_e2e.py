"""End to end through a Zenoh router on 127.0.0.1: samples/s of one IMU, and fault-to-event latency.

Three processes, as in a deployment: a Zenoh router (``python -m
protocols.zenoh_router``), the service (``ins-health run --config``, a client of
the router, durable outbox with fsync), and this script as the vehicle (frame
publisher) and the ground station (event receiver that acknowledges).

* **Throughput** — one IMU at 1 kHz, 15 min of a resting unit in frames of
  20, 100 and 1000 samples published as fast as the service takes them: at most
  :data:`IN_FLIGHT_SAMPLES` ahead of what the status topic (every 0.2 s) shows
  accepted, so the service's frame queue never overflows (a drop would be
  counted there and fails the run); samples/s = samples / (time from the first
  publication until the status shows them all accepted). Target ≥ 200,000
  samples/s.
  Beside it, the pipeline alone (the same frames through
  :class:`~service.pipeline.FleetProcessor` in this process, no transport, no
  decoding, no outbox), frame by frame and as the service takes a backlog off
  its queue (``process_queued`` in groups of ``QUEUED_SAMPLES_MAX`` samples).
* **Latency** — ``TRIALS`` vehicles, one after the other: 1.5 s of a resting
  unit then a +0.1 g z-bias fault, in frames of 20 samples published at the
  data rate. The frame that *completes* the fault is the one whose processing
  raises the F0 event (found by running the same frames offline: F0 waits for
  the static detector's final, trimmed decision, W − 1 + trim = 749 samples
  after the first faulty one); latency = reception of the event at the ground
  station − publication of that frame. Target p99 < 20 ms.
* **Transport floor** — the same path without the service: a message published
  here, echoed by a bare Zenoh client process, received here (four hops through
  the router), for scale.

Run: ``python benchmarks/bench_service_e2e.py``.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from host_steal import STEAL_WINDOW_S, HostSteal, percentiles, print_by_steal  # noqa: E402

from estimators.conventions import Triad  # noqa: E402
from estimators.session import ImuSession  # noqa: E402
from estimators.sim import Fault, FaultKind, simulate, static_spec  # noqa: E402
from protocols.events import Event, Status  # noqa: E402
from protocols.frames import SampleBatch  # noqa: E402
from protocols.zenoh_adapter import (  # noqa: E402
    EventReceiver,
    FramePublisher,
    Mode,
    ZenohSettings,
    frame_key,
    subscribe_status,
    zenoh_config,
)
from protocols.zenoh_router import RouterProcess, free_local_port  # noqa: E402
from service.demo import demo_passport  # noqa: E402
from service.intake import QUEUED_SAMPLES_MAX  # noqa: E402
from service.passport_store import PassportStore  # noqa: E402
from service.pipeline import FleetProcessor, PipelineOptions  # noqa: E402

RATE_HZ = 1000.0
THROUGHPUT_SAMPLES = 900_000
THROUGHPUT_FRAMES = (20, 100, 1000)
IN_FLIGHT_SAMPLES = 300_000
QUEUE_FRAMES = 4096
"""Samples published ahead of those accepted: 1.5 s of the target rate (and at most half the service's queue of :data:`QUEUE_FRAMES`)."""
TRIALS = 60
TRIAL_FRAME = 20
ECHO_ROUNDS = 200
ECHO = """
import sys, threading, zenoh
from protocols.zenoh_adapter import Mode, ZenohSettings, open_session
s = open_session(ZenohSettings(mode=Mode.CLIENT, connect=(sys.argv[1],)))
pub = s.declare_publisher("bench/pong")
s.declare_subscriber("bench/ping", lambda smp: pub.put(smp.payload.to_bytes()))
print("ready", flush=True)
threading.Event().wait()
"""


def client(port: int) -> zenoh.Config:
    return zenoh_config(ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",)))


def frames_of(session: ImuSession, vehicle: str, size: int) -> list[SampleBatch]:
    assert session.accel_mps2 is not None and session.gyro_rps is not None
    return [
        SampleBatch(
            vehicle,
            0,
            k,
            session.t_s[i : i + size],
            session.accel_mps2[i : i + size],
            session.gyro_rps[i : i + size],
        )
        for k, i in enumerate(range(0, session.n_samples, size))
    ]


def wait(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        tick.wait(0.001)


def matching(pub: zenoh.Publisher) -> bool:
    """Whether the publisher has a subscriber (zenoh's stub says bool, 1.x returns a MatchingStatus)."""
    status: object = pub.matching_status
    return bool(getattr(status, "matching", status))


def wait_running(stderr: IO[str]) -> list[str]:
    """Read the service's log until its ``running`` line; the lines after it are collected by a thread
    into the list returned (a pipe nobody reads would block the service's logging)."""
    lines: list[str] = []
    for line in stderr:
        lines.append(line)
        if "running" in line:
            threading.Thread(target=lambda: lines.extend(stderr), daemon=True).start()
            return lines
    raise RuntimeError(f"the service did not start: {lines}")


def wait_route(session: zenoh.Session, key: str) -> None:
    pub = session.declare_publisher(key)
    try:
        wait(lambda: matching(pub), 20.0, f"a subscriber on {key}")
    finally:
        pub.undeclare()


def main() -> None:
    passport, g = demo_passport()
    options = PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4)
    rest = simulate(
        static_spec(duration_s=THROUGHPUT_SAMPLES / RATE_HZ, rate_hz=RATE_HZ, latitude_deg=45.0),
        seed=2,
    ).session
    trial_spec = static_spec(duration_s=4.0, rate_hz=RATE_HZ, latitude_deg=45.0)
    trial = simulate(
        dataclasses.replace(trial_spec, faults=(Fault(FaultKind.STEP, Triad.ACCEL, 2, 1.5, 0.1),)),
        seed=3,
    ).session

    # The frame whose processing raises the F0 event, from the same frames offline.
    offline = FleetProcessor(passports=lambda v, i: passport, options=options)
    completing = next(
        k
        for k, b in enumerate(frames_of(trial, "probe", TRIAL_FRAME))
        if offline.process(b, arrival_s=0.0)
    )
    alone, queued = {}, {}
    for size in THROUGHPUT_FRAMES:
        fleet = FleetProcessor(passports=lambda v, i: passport, options=options)
        frames = frames_of(rest, "alone", size)
        t0 = time.perf_counter()
        for b in frames:
            fleet.process(b, arrival_s=0.0)
        alone[size] = rest.n_samples / (time.perf_counter() - t0)
        # As the service takes a backlog off its queue: groups of QUEUED_SAMPLES_MAX samples.
        fleet = FleetProcessor(passports=lambda v, i: passport, options=options)
        per_group = max(1, QUEUED_SAMPLES_MAX // size)
        t0 = time.perf_counter()
        for k in range(0, len(frames), per_group):
            fleet.process_queued(frames[k : k + per_group], arrival_s=0.0)
        queued[size] = rest.n_samples / (time.perf_counter() - t0)

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        store = PassportStore(tmp / "passports")
        trial_vehicles = [f"lat-{k}" for k in range(TRIALS)]
        vehicles = [f"rate-{n}" for n in THROUGHPUT_FRAMES] + trial_vehicles
        for v in vehicles:
            store.put(v, 0, passport)
        port = free_local_port()
        config = tmp / "bench.toml"
        config.write_text(
            f'[service]\ndata_dir = "{tmp / "data"}"\npassport_dir = "{store.root}"\nstatus_period_s = 0.2\n'
            f'[site]\ngravity_mps2 = {g!r}\n[zenoh]\nconnect = ["tcp/127.0.0.1:{port}"]\n'
            f"[validity]\ntimeout_s = 600.0\n[pipeline]\nqueue_capacity = {QUEUE_FRAMES}\nmax_vehicles = 1000\n"
        )
        with RouterProcess(f"tcp/127.0.0.1:{port}"):
            service = subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(config)], cwd=ROOT,
                                       stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
            try:
                assert service.stderr is not None
                wait_running(service.stderr)
                with zenoh.open(client(port)) as vehicle, zenoh.open(client(port)) as ground:
                    accepted, dropped = {}, {}

                    def on_status(st: Status) -> None:
                        accepted[st.vehicle] = st.counters.get("imu0.samples.accepted", 0)
                        dropped[st.vehicle] = st.counters.get("service.frames.dropped_overload", 0)

                    subscribe_status(ground, on_status)
                    received: dict[str, float] = {}

                    def on_event(e: Event) -> None:
                        received.setdefault(e.vehicle, time.perf_counter())

                    EventReceiver(ground, on_event)

                    # Throughput.
                    rates = {}
                    for size in THROUGHPUT_FRAMES:
                        name = f"rate-{size}"
                        frames = frames_of(rest, name, size)
                        wait_route(vehicle, frame_key(name, 0))
                        with FramePublisher(
                            vehicle, name, 0, congestion_control=zenoh.CongestionControl.BLOCK
                        ) as pub:
                            # Never more frames ahead than half the service's queue holds.
                            in_flight = min(IN_FLIGHT_SAMPLES, size * QUEUE_FRAMES // 2)
                            t0 = time.perf_counter()
                            for k, b in enumerate(frames):
                                ahead = k * size - in_flight
                                if accepted.get(name, 0) < ahead:
                                    wait(
                                        lambda: accepted.get(name, 0) >= ahead,
                                        600.0,
                                        "the service to catch up",
                                    )
                                pub.publish(b)
                            t_pub = time.perf_counter() - t0
                            wait(
                                lambda: (
                                    accepted.get(name, 0) >= rest.n_samples
                                    or dropped.get(name, 0) > 0
                                ),
                                600.0,
                                "the throughput stream",
                            )
                            t_all = time.perf_counter() - t0
                        if dropped.get(name, 0):
                            raise RuntimeError(
                                f"the service dropped {dropped[name]} frames: the measurement is void"
                            )
                        rates[size] = (rest.n_samples / t_all, t_pub, t_all)

                    # Transport floor: publish, echo by a bare client process, receive.
                    echo = subprocess.Popen(
                        [sys.executable, "-c", ECHO, f"tcp/127.0.0.1:{port}"],
                        cwd=ROOT,
                        stdout=subprocess.PIPE,
                        text=True,
                    )
                    try:
                        assert echo.stdout is not None
                        echo.stdout.readline()
                        pong, stamp = threading.Event(), [0.0]

                        def on_pong(_: zenoh.Sample) -> None:
                            stamp[0] = time.perf_counter()
                            pong.set()

                        ground.declare_subscriber("bench/pong", on_pong)
                        ping = vehicle.declare_publisher("bench/ping")
                        wait(lambda: matching(ping), 20.0, "the echo process")
                        floor_ms = []
                        for _ in range(ECHO_ROUNDS):
                            pong.clear()
                            t0 = time.perf_counter()
                            ping.put(b"x" * 2000)
                            if not pong.wait(5.0):
                                raise RuntimeError("no echo")
                            floor_ms.append((stamp[0] - t0) * 1e3)
                            time.sleep(0.005)  # rounds apart, as the trials are
                    finally:
                        echo.kill()
                        echo.wait(10)

                    # Latency.
                    lat_ms, stolen = [], []
                    steal = HostSteal()
                    for v in trial_vehicles:
                        trial_frames = frames_of(trial, v, TRIAL_FRAME)
                        wait_route(vehicle, frame_key(v, 0))
                        with FramePublisher(
                            vehicle, v, 0, congestion_control=zenoh.CongestionControl.BLOCK
                        ) as pub:
                            t_start = time.perf_counter()
                            for k, b in enumerate(trial_frames[: completing + 1]):
                                # At the data rate: frame k is due when its last sample has been measured.
                                due = t_start + (k + 1) * TRIAL_FRAME / RATE_HZ
                                while time.perf_counter() < due:
                                    time.sleep(max(0.0, due - time.perf_counter() - 0.0005))
                                pub.publish(b)
                            t_done = time.perf_counter()
                            wait(lambda: v in received, 30.0, f"the F0 event of {v}")
                        lat_ms.append((received[v] - t_done) * 1e3)
                        stolen.append(steal.fraction(t_done - STEAL_WINDOW_S, received[v]))
                    steal.close()
            finally:
                service.terminate()
                service.wait(60)
    lat = np.array(lat_ms)
    print(
        "end to end through a Zenoh router on 127.0.0.1 (router, service and this script: 3 processes)"
    )
    print(f"  throughput, one IMU at 1 kHz, {rest.n_samples} samples (target >= 200 k samples/s):")
    for size, (rate, t_pub, t_all) in rates.items():
        print(
            f"    frames of {size:5d}: {rate / 1e3:7.1f} k samples/s end to end (published in {t_pub:.2f} s, "
            f"all accepted after {t_all:.2f} s); pipeline alone {alone[size] / 1e3:7.1f} k samples/s frame by frame, "
            f"{queued[size] / 1e3:7.1f} k queued"
        )
    print(
        f"  latency, frame completing a fault -> event received ({TRIALS} trials, frames of {TRIAL_FRAME} at 1 kHz):"
    )
    print(f"    all trials:{percentiles(lat)}   (target p99 < 20 ms)")
    print_by_steal(lat, stolen)
    print(
        "    includes the pipeline on that frame, the outbox commit (SQLite WAL, fsync) and the acknowledged delivery"
    )
    floor = np.array(floor_ms)
    print(
        f"  transport floor, 2 kB published -> echoed by a bare Zenoh client -> received (same 4 hops, {ECHO_ROUNDS} rounds):"
    )
    print(f"   {percentiles(floor)}")


if __name__ == "__main__":
    main()
