"""A fleet through Zenoh routers: N vehicles × M IMUs over K service instances, every piece its own process.

Per configuration, all on 127.0.0.1:

* **routers** — ``python -m protocols.zenoh_router``; with ``--routers 2`` the
  second one connects to the first (a mesh, ``deploy/SCALING.md``). Instance
  ``k`` and publisher ``j`` connect to router ``k mod R`` and ``j mod R``, and
  the ground station to router 0, so with two routers frames and events cross
  the mesh.
* **K instances** — ``ins-health run --config`` each, with its own data
  directory and its share of the fleet by key expression: vehicle ``s<k>-<n>``
  belongs to instance ``k``, whose ``frames_key`` is ``ins/s<k>-$*/imu/*``.
* **publishers** — one process per instance's share (at most one per core),
  each playing its vehicles at the data rate in frames of ``--frame`` samples
  (``CongestionControl.BLOCK``, pre-encoded frames). Every vehicle's IMU 0
  gets a +0.05 g z-accelerometer bias step at :data:`FAULT_S` (below the
  cross-IMU limit, so the expected events are exactly those of the
  single-IMU pipelines); the vehicles start a fraction of a frame apart so
  their frames do not arrive in lock step.
* **ground station** — this process: an acknowledging
  :class:`~protocols.zenoh_adapter.EventReceiver` on the whole fleet and a
  status subscriber.

The expected events are computed offline from the same frames
(:class:`~service.pipeline.FleetProcessor`, arrival = data time); the frame
whose processing raises a vehicle's F0 event is the one that *completes* the
fault, and its publication time is recorded by the publisher (one system-wide
monotonic clock, ``CLOCK_MONOTONIC``).

One row per configuration:

* ``offered`` — samples published / publishing time (all publishers);
* ``accepted`` — samples the instances' status shows accepted / time from the
  first publication until the last of them was accepted; in total and per
  instance (mean, and the slowest);
* ``drops`` — frames dropped by the instances' queues plus frames published
  but never received;
* ``lag`` — how long after the last publication the last sample was accepted
  (a service that keeps up lags by about one status period, 0.2 s);
* ``CPU`` — % of one core over the run, per process: instances (mean/max),
  routers, publishers (mean);
* ``p50``/``p99`` — completing frame published → event received at the ground station;
* ``once`` — every expected event id arrived at the ground station's
  application exactly once, no other event arrived, and each vehicle's status
  came from one instance only (``yes``/``no``).

``--state [IMUS ...]``: the CPU cost of one status period (every vehicle's
status built and encoded) and of a checkpoint (all IMUs changed, one, none)
with hundreds of IMUs in one instance, in this process.

``--sweep``: for each frame size, one instance with doubling IMU counts until
it stops keeping up (drops, or a lag above :data:`KEEP_UP_LAG_S`), then 2, 4, …
instances up to half the cores (at least 2) at half that load each, with one
router and with two. Sized from ``os.sched_getaffinity``, so it runs unchanged
on a many-core machine. ``--quick``: 2 vehicles × 2 IMUs, 2 instances, 2
routers, frames of 100, 3 s (the test suite's smoke test).

Run: ``python benchmarks/bench_fleet.py --sweep`` (or ``--quick``, or one
configuration with ``--vehicles --imus --instances --routers --frame``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.conventions import Triad  # noqa: E402
from estimators.passport import Passport  # noqa: E402
from estimators.sim import Fault, FaultKind, simulate, static_spec  # noqa: E402
from protocols.events import Event, Predicate, Status, event_id  # noqa: E402
from protocols.frames import SampleBatch, encode_frame  # noqa: E402
from protocols.zenoh_adapter import (  # noqa: E402
    EventReceiver,
    Mode,
    ZenohSettings,
    frame_key,
    open_session,
    subscribe_status,
)
from protocols.zenoh_router import RouterProcess, free_local_port  # noqa: E402

FAULT_S = 1.5
"""Data time of every vehicle's fault (IMU 0, +0.05 g on the z accelerometer's bias)."""
FAULT_G = 0.05
STATUS_PERIOD_S = 0.2
KEEP_UP_LAG_S = 1.0
"""An instance keeps up when its last sample is accepted within this long of the last publication."""
SETTLE_S = 5.0
"""How long to wait for a status or event that has stopped coming before calling it missing."""
SWEEP_FRAMES = {1000: 48, 100: 24, 20: 12}
"""Frame size → IMUs of the first (single-instance) sweep row; doubled until it stops keeping up."""
SWEEP_DOUBLINGS = 4
IMUS_PER_VEHICLE = 3
STATE_IMUS = (30, 300, 900)
"""IMU counts of the status and checkpoint cost measurement (``--state``, and after ``--sweep``)."""


@dataclasses.dataclass(frozen=True)
class Setup:
    vehicles: int
    imus: int
    instances: int
    routers: int
    frame: int
    rate_hz: float = 1000.0
    duration_s: float = 6.0


QUICK = Setup(vehicles=2, imus=2, instances=2, routers=2, frame=100, duration_s=3.0)
"""``--quick``: the test suite's smoke test."""


@dataclasses.dataclass
class Row:
    setup: Setup
    offered: float
    accepted: float
    per_instance: list[float]
    drops: int
    lag_s: float
    cpu_instances: list[float]
    cpu_routers: list[float]
    cpu_publishers: list[float]
    latency_ms: np.ndarray
    exactly_once: bool
    problems: list[str]

    @property
    def kept_up(self) -> bool:
        return self.drops == 0 and self.lag_s <= KEEP_UP_LAG_S


def vehicle_names(setup: Setup) -> list[list[str]]:
    """Per instance, the vehicles it owns (round robin, named ``s<instance>-<n>``)."""
    owned: list[list[str]] = [[] for _ in range(setup.instances)]
    for n in range(setup.vehicles):
        owned[n % setup.instances].append(f"s{n % setup.instances}-{n:04d}")
    return owned


def imu_data(setup: Setup) -> list[dict[str, np.ndarray]]:
    """The samples of IMU 0…M−1 (every vehicle plays the same ones; IMU 0 carries the fault)."""
    spec = static_spec(duration_s=setup.duration_s, rate_hz=setup.rate_hz, latitude_deg=45.0)
    out = []
    for m in range(setup.imus):
        faults = (Fault(FaultKind.STEP, Triad.ACCEL, 2, FAULT_S, FAULT_G),) if m == 0 else ()
        s = simulate(dataclasses.replace(spec, faults=faults), seed=20 + m).session
        out.append({k: np.asarray(getattr(s, k)) for k in ("t_s", "accel_mps2", "gyro_rps")})
    return out


def frames_of(data: dict[str, np.ndarray], vehicle: str, imu: int, size: int) -> list[SampleBatch]:
    n = len(data["t_s"])
    return [
        SampleBatch(
            vehicle,
            imu,
            k,
            data["t_s"][i : i + size],
            data["accel_mps2"][i : i + size],
            data["gyro_rps"][i : i + size],
        )
        for k, i in enumerate(range(0, n, size))
    ]


def expected(
    setup: Setup, data: list[dict[str, np.ndarray]], passport: Passport, g: float
) -> tuple[list[tuple[Any, ...]], int]:
    """The events of one vehicle offline (as ``(imu, predicate, triad, axis, cause, t_s)``) and the F0-completing frame of IMU 0."""
    from service.pipeline import FleetProcessor, PipelineOptions

    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
        max_imus_per_vehicle=setup.imus,
    )
    per_imu = [frames_of(d, "probe", m, setup.frame) for m, d in enumerate(data)]
    events, completing = [], None
    for k in range(len(per_imu[0])):
        for m in range(setup.imus):
            raised = fleet.process(per_imu[m][k], arrival_s=float(per_imu[m][k].t_s[-1]))
            if completing is None and m == 0 and any(e.predicate is Predicate.F0 for e in raised):
                completing = k
            events += raised
    if completing is None:
        raise RuntimeError("the injected fault raises no F0 event offline")
    return [(e.imu, e.predicate, e.triad, e.axis, e.cause, e.t_s) for e in events], completing


# ---------------------------------------------------------------------- publisher process


def publisher_main(spec_path: str) -> None:
    """One publisher process: its vehicles' frames at the data rate once told ``go <monotonic t0>``."""
    import zenoh

    spec = json.loads(Path(spec_path).read_text())
    setup = Setup(**spec["setup"])
    arrays = np.load(spec["data"])
    data = [
        {k: arrays[f"{k}{m}"] for k in ("t_s", "accel_mps2", "gyro_rps")} for m in range(setup.imus)
    ]
    frame_s = setup.frame / setup.rate_hz
    session: Any = open_session(ZenohSettings(mode=Mode.CLIENT, connect=(spec["router"],)))
    schedule = []
    pubs: list[Any] = []
    for vehicle, phase in spec["vehicles"]:
        for m in range(setup.imus):
            pub = session.declare_publisher(
                frame_key(vehicle, m), congestion_control=zenoh.CongestionControl.BLOCK
            )
            pubs.append(pub)
            for b in frames_of(data[m], vehicle, m, setup.frame):
                due = phase * frame_s + (b.seq + 1) * frame_s
                mark = vehicle if (m == 0 and b.seq == spec["completing"]) else None
                schedule.append((due, m, pub, encode_frame(b), len(b.t_s), mark))
    schedule.sort(key=lambda s: (s[0], s[1]))
    deadline = time.monotonic() + 30.0
    while not all(p.matching_status.matching for p in pubs):
        if time.monotonic() > deadline:
            raise SystemExit("publisher: no instance subscribed to some of its vehicles")
        time.sleep(0.01)
    print("ready", flush=True)
    t0 = float(sys.stdin.readline().split()[1])
    cpu0 = time.process_time()
    marks: dict[str, float] = {}
    samples = 0
    first = None
    for due, _m, pub, payload, n, mark in schedule:
        wait_s = t0 + due - time.monotonic()
        if wait_s > 0.0005:
            time.sleep(wait_s)
        pub.put(payload)
        now = time.monotonic()
        first = now if first is None else first
        samples += n
        if mark is not None:
            marks[mark] = now
    last = time.monotonic()
    cpu = time.process_time() - cpu0
    result = {
        "samples": samples,
        "frames": len(schedule),
        "first": first,
        "last": last,
        "cpu": cpu / max(last - t0, 1e-9),
        "marks": marks,
    }
    print(json.dumps(result), flush=True)
    # Closing the session at once could discard frames still in its send queue.
    sys.stdin.readline()
    for p in pubs:
        p.undeclare()
    session.close()


# ---------------------------------------------------------------------- the run


def tell(proc: subprocess.Popen[str], line: str) -> None:
    if proc.stdin is None:
        raise RuntimeError("no pipe to the publisher")
    proc.stdin.write(line + "\n")
    proc.stdin.flush()


def hear(proc: subprocess.Popen[str]) -> str:
    return "" if proc.stdout is None else proc.stdout.readline().strip()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (``/proc/<pid>/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_for(cond: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while not cond():
        if time.monotonic() > deadline:
            return False
        tick.wait(0.005)
    return True


class Ground:
    """The ground station: events (acknowledged, deduplicated by id) and the latest status of each vehicle."""

    def __init__(self, session: Any):
        self.lock = threading.Lock()
        self.events: dict[str, list[tuple[str, float]]] = {}
        self.status: dict[str, dict[str, Any]] = {}
        self.owners: dict[str, set[str]] = {}
        self.progress_s = time.monotonic()
        self.receiver = EventReceiver(session, self._on_event)
        self.sub: Any = subscribe_status(session, self._on_status)

    def _on_event(self, event: Event) -> None:
        with self.lock:
            self.events.setdefault(event.vehicle, []).append((event.event_id, time.monotonic()))

    def _on_status(self, st: Status) -> None:
        with self.lock:
            old = self.status.get(st.vehicle, {}).get("accepted", -1)
            accepted = sum(n for k, n in st.counters.items() if k.endswith(".samples.accepted"))
            if accepted != old:
                self.progress_s = time.monotonic()
            self.status[st.vehicle] = {
                "service": st.service,
                "accepted": accepted,
                "dropped": st.counters.get("service.frames.dropped_overload", 0),
                "received": st.counters.get("service.frames.received", 0),
            }
            self.owners.setdefault(st.vehicle, set()).add(st.service)

    def accepted(self, vehicles: list[str]) -> int:
        with self.lock:
            return sum(self.status.get(v, {}).get("accepted", 0) for v in vehicles)

    def close(self) -> None:
        self.sub.undeclare()
        self.receiver.close()


def instance_config(
    tmp: Path, k: int, router: str, g: float, setup: Setup, passports: Path
) -> Path:
    path = tmp / f"instance{k}.toml"
    path.write_text(
        f'[service]\nname = "ins-health-{k}"\ndata_dir = "{tmp / f"data{k}"}"\n'
        f'passport_dir = "{passports}"\nstatus_period_s = {STATUS_PERIOD_S}\n'
        f"[site]\ngravity_mps2 = {g!r}\n"
        f'[zenoh]\nconnect = ["{router}"]\nframes_key = "ins/s{k}-$*/imu/*"\n'
        f"[validity]\ntimeout_s = 600.0\n"
        f"[pipeline]\nqueue_capacity = 4096\nmax_vehicles = {max(1, setup.vehicles)}\n"
        f"max_imus_per_vehicle = {setup.imus}\n"
    )
    return path


def start_instance(config: Path, log: Path) -> subprocess.Popen[bytes]:
    with log.open("w") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def run(setup: Setup, unit: tuple[Passport, float] | None = None) -> Row:
    """Run one configuration (module docstring) and return its row."""
    from service.demo import demo_passport
    from service.passport_store import PassportStore

    passport, g = unit if unit is not None else demo_passport()
    data = imu_data(setup)
    offline, completing = expected(setup, data, passport, g)
    owned = vehicle_names(setup)
    everyone = [v for vs in owned for v in vs]
    expect = {
        v: {
            event_id(vehicle=v, imu=i, predicate=p, triad=tr, axis=ax, cause=c, t_s=t)
            for i, p, tr, ax, c, t in offline
        }
        for v in everyone
    }
    problems: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp_name:
        tmp = Path(tmp_name)
        store = PassportStore(tmp / "passports")
        for v in everyone:
            for m in range(setup.imus):
                store.put(v, m, passport)
        arrays: dict[str, Any] = {f"{k}{m}": d[k] for m, d in enumerate(data) for k in d}
        np.savez(tmp / "data.npz", **arrays)
        endpoints = [f"tcp/127.0.0.1:{free_local_port()}" for _ in range(setup.routers)]
        routers = [RouterProcess(endpoints[0])]
        routers += [RouterProcess(e, connect=(endpoints[0],)) for e in endpoints[1:]]
        procs: list[subprocess.Popen[Any]] = []
        try:
            for r in routers:
                r.start()
            ground_session: Any = open_session(
                ZenohSettings(mode=Mode.CLIENT, connect=(endpoints[0],))
            )
            ground = Ground(ground_session)
            instances = [
                start_instance(
                    instance_config(tmp, k, endpoints[k % setup.routers], g, setup, store.root),
                    tmp / f"instance{k}.log",
                )
                for k in range(setup.instances)
            ]
            procs += instances
            n_pub = max(1, min(len(everyone), setup.instances, len(os.sched_getaffinity(0))))
            shares: list[list[str]] = [[] for _ in range(n_pub)]
            for n, v in enumerate(everyone):
                shares[n % n_pub].append(v)
            publishers: list[subprocess.Popen[str]] = []
            for j, share in enumerate(shares):
                spec = tmp / f"publisher{j}.json"
                spec.write_text(
                    json.dumps(
                        {
                            "setup": dataclasses.asdict(setup),
                            "data": str(tmp / "data.npz"),
                            "router": endpoints[(j + 1) % setup.routers],
                            "completing": completing,
                            "vehicles": [
                                (v, (everyone.index(v) / max(1, len(everyone)))) for v in share
                            ],
                        }
                    )
                )
                publishers.append(
                    subprocess.Popen(
                        [sys.executable, __file__, "--publisher", str(spec)],
                        cwd=ROOT,
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        text=True,
                    )
                )
            procs += publishers
            for p in publishers:
                if hear(p) != "ready":
                    raise RuntimeError("a publisher did not start (see its stderr above)")
            cpu0 = {p.pid: cpu_seconds(p.pid) for p in instances}
            router_pids = [pid for r in routers if (pid := r.pid) is not None]
            cpu0.update({pid: cpu_seconds(pid) for pid in router_pids})
            t0 = time.monotonic() + 0.2
            for p in publishers:
                tell(p, f"go {t0!r}")
            results = [json.loads(hear(p)) for p in publishers]
            published = sum(r["samples"] for r in results)
            t_first = min(r["first"] for r in results)
            t_last = max(r["last"] for r in results)
            wait_for(
                lambda: (
                    ground.accepted(everyone) >= published
                    or time.monotonic() - ground.progress_s > SETTLE_S
                ),
                600.0,
            )
            t_accepted = ground.progress_s
            # Up to the last progress: a stalled run's idle wait is not part of its CPU load.
            wall = max(t_accepted, t_last) - t0
            cpu = {pid: (cpu_seconds(pid) - c) / wall for pid, c in cpu0.items()}
            marks = {v: t for r in results for v, t in r["marks"].items()}
            wait_for(
                lambda: all(len(ground.events.get(v, ())) >= len(expect[v]) for v in everyone),
                SETTLE_S,
            )
            # Anything late or extra has had its chance to arrive.
            time.sleep(2 * STATUS_PERIOD_S)
            for p in publishers:
                tell(p, "bye")
            for p in publishers:
                # A lagging instance may still hold frames in the session's queue: the
                # finally below ends a publisher that does not close in time.
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(60)
            with ground.lock:
                got = {v: list(ev) for v, ev in ground.events.items()}
                status = {v: dict(s) for v, s in ground.status.items()}
                owners = {v: set(s) for v, s in ground.owners.items()}
            ground.close()
            ground_session.close()
        finally:
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in procs:
                try:
                    p.wait(60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
            for r in routers:
                r.stop()

    latency = []
    for v in everyone:
        ids = [e for e, _ in got.get(v, [])]
        if sorted(ids) != sorted(expect[v]):
            problems.append(
                f"{v}: {len(ids)} event(s) received, {len(set(ids) & expect[v])} of {len(expect[v])} expected"
            )
        if len(owners.get(v, ())) != 1:
            problems.append(f"{v}: status from {sorted(owners.get(v, ()))}")
        f0 = [t for e, t in got.get(v, []) if e in expect[v]]
        if f0 and v in marks:
            latency.append((min(f0) - marks[v]) * 1e3)
    services = sorted({s["service"] for s in status.values()})
    per_service = {
        s: sum(st["accepted"] for st in status.values() if st["service"] == s) for s in services
    }
    # Service-wide counters ride on every vehicle's status: one reading per instance.
    dropped = {
        s: max(st["dropped"] for st in status.values() if st["service"] == s) for s in services
    }
    received = {
        s: max(st["received"] for st in status.values() if st["service"] == s) for s in services
    }
    frames_published = sum(r["frames"] for r in results)
    drops = sum(dropped.values()) + max(0, frames_published - sum(received.values()))
    span = max(t_accepted - t_first, t_last - t_first, 1e-9)
    total = sum(per_service.values())
    return Row(
        setup=setup,
        offered=published / max(t_last - t_first, 1e-9),
        accepted=total / span,
        per_instance=[per_service.get(f"ins-health-{k}", 0) / span for k in range(setup.instances)],
        drops=drops,
        lag_s=max(0.0, t_accepted - t_last) if total >= published else float("inf"),
        cpu_instances=[cpu[p.pid] * 100 for p in instances],
        cpu_routers=[cpu[pid] * 100 for pid in router_pids],
        cpu_publishers=[r["cpu"] * 100 for r in results],
        latency_ms=np.array(latency),
        exactly_once=not problems,
        problems=problems,
    )


# ---------------------------------------------------------------------- status and checkpoints


def state_cost(n_imus: int, unit: tuple[Passport, float]) -> str:
    """One status period and one checkpoint of ``n_imus`` IMUs in one instance, as the daemon does them (CPU ms).

    In this process (no transport): every IMU has taken 2 s of frames of 1000;
    then the status of every vehicle (built and encoded), a checkpoint of all
    of them, and a checkpoint after one IMU took one more frame.
    """
    from protocols.events import encode_status
    from service.checkpoint import CheckpointStore, encode_state
    from service.pipeline import FleetProcessor, PipelineOptions

    passport, g = unit
    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
        max_vehicles=n_imus,
        max_imus_per_vehicle=IMUS_PER_VEHICLE,
    )
    setup = Setup(1, IMUS_PER_VEHICLE, 1, 1, 1000, duration_s=3.0)
    data = imu_data(setup)
    n_vehicles = -(-n_imus // IMUS_PER_VEHICLE)
    keys = [(f"v{n:04d}", m) for n in range(n_vehicles) for m in range(IMUS_PER_VEHICLE)][:n_imus]
    frames = {key: frames_of(data[key[1]], key[0], key[1], 1000) for key in keys}
    for k in range(2):
        for key in keys:
            fleet.process(frames[key][k], arrival_s=float(k))

    def checkpoint(store: CheckpointStore) -> float:
        t0 = time.process_time()
        store.save_encoded(
            {
                f"{v}/{i}": encode_state(fleet.pipelines[(v, i)].state_dict())
                for v, i in fleet.changed_keys()
            }
        )
        return (time.process_time() - t0) * 1e3

    t0 = time.process_time()
    for v in fleet.vehicles():
        encode_status(fleet.status(v, service="bench", now_unix_s=0.0))
    status_ms = (time.process_time() - t0) * 1e3
    with tempfile.TemporaryDirectory(prefix="bench-fleet-state-") as tmp:
        with CheckpointStore(Path(tmp) / "checkpoints.sqlite") as store:
            all_ms = checkpoint(store)
            idle_ms = checkpoint(store)
            fleet.process(frames[keys[0]][2], arrival_s=2.0)
            one_ms = checkpoint(store)
    return (
        f"{n_imus:5d} IMUs ({n_vehicles} vehicles): status of every vehicle {status_ms:7.1f} ms; "
        f"checkpoint of all {all_ms:7.1f} ms, of one changed IMU {one_ms:6.1f} ms, of none {idle_ms:6.1f} ms"
    )


# ---------------------------------------------------------------------- table

HEADER = (
    f"{'veh':>4} {'IMUs':>5} {'inst':>4} {'rtr':>3} {'frame':>5} | {'offered':>8} {'accepted':>8} "
    f"{'/inst':>7} {'slowest':>7} | {'drops':>5} {'lag s':>5} | {'CPU% inst':>9} {'rtr':>7} {'pub':>4} | "
    f"{'p50 ms':>6} {'p99 ms':>6} | once"
)


def format_row(row: Row) -> str:
    s = row.setup
    lat = row.latency_ms
    p50, p99 = (np.percentile(lat, 50), np.percentile(lat, 99)) if lat.size else (float("nan"),) * 2
    inst = row.cpu_instances
    return (
        f"{s.vehicles:4d} {s.vehicles * s.imus:5d} {s.instances:4d} {s.routers:3d} {s.frame:5d} | "
        f"{row.offered / 1e3:7.1f}k {row.accepted / 1e3:7.1f}k {np.mean(row.per_instance) / 1e3:6.1f}k "
        f"{min(row.per_instance) / 1e3:6.1f}k | {row.drops:5d} {row.lag_s:5.1f} | "
        f"{np.mean(inst):4.0f}/{max(inst):<4.0f} {'/'.join(f'{c:.0f}' for c in row.cpu_routers):>7} "
        f"{np.mean(row.cpu_publishers):4.0f} | {p50:6.1f} {p99:6.1f} | "
        f"{'yes' if row.exactly_once else 'no'}"
    )


def show(row: Row) -> None:
    print(format_row(row), flush=True)
    for p in row.problems[:5]:
        print(f"      {p}", flush=True)


def sweep(unit: tuple[Passport, float], rate_hz: float, duration_s: float) -> None:
    cores = len(os.sched_getaffinity(0))
    ladder = [k for k in (2, 4, 8, 16, 32, 64, 128) if k <= max(2, cores // 2)]
    for frame, imus in SWEEP_FRAMES.items():
        best = None
        for _ in range(SWEEP_DOUBLINGS):
            vehicles = max(1, imus // IMUS_PER_VEHICLE)
            row = run(Setup(vehicles, IMUS_PER_VEHICLE, 1, 1, frame, rate_hz, duration_s), unit)
            show(row)
            if not row.kept_up:
                break
            best = vehicles
            imus *= 2
        if best is None:
            continue
        for k in ladder:
            vehicles = max(k, best * k // 2)
            for routers in (1, 2):
                setup = Setup(vehicles, IMUS_PER_VEHICLE, k, routers, frame, rate_hz, duration_s)
                show(run(setup, unit))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--publisher", help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="the smoke test's configuration")
    parser.add_argument("--sweep", action="store_true", help="the ladder sized to the cores")
    parser.add_argument("--vehicles", type=int, default=4)
    parser.add_argument("--imus", type=int, default=IMUS_PER_VEHICLE)
    parser.add_argument("--instances", type=int, default=1)
    parser.add_argument("--routers", type=int, default=1, choices=(1, 2))
    parser.add_argument("--frame", type=int, default=100, help="samples per frame")
    parser.add_argument("--rate", type=float, default=1000.0, help="samples/s of each IMU")
    parser.add_argument("--duration", type=float, default=6.0, help="data seconds per IMU")
    parser.add_argument(
        "--state",
        type=int,
        nargs="*",
        metavar="IMUS",
        help="only the status and checkpoint cost of this many IMUs in one instance",
    )
    args = parser.parse_args()
    if args.publisher:
        publisher_main(args.publisher)
        return
    from service.demo import demo_passport

    unit = demo_passport()
    if args.state is not None:
        for n in args.state or STATE_IMUS:
            print(state_cost(n, unit), flush=True)
        return
    print(
        f"fleet through Zenoh routers on 127.0.0.1, {len(os.sched_getaffinity(0))} cores, "
        f"load average {os.getloadavg()[0]:.1f}; samples/s; CPU in % of one core"
    )
    print(HEADER, flush=True)
    if args.sweep:
        sweep(unit, args.rate, args.duration)
        print("status and checkpoint cost in one instance (CPU of the service's loop):")
        for n in STATE_IMUS:
            print(state_cost(n, unit), flush=True)
        return
    setup = (
        QUICK
        if args.quick
        else Setup(
            args.vehicles,
            args.imus,
            args.instances,
            args.routers,
            args.frame,
            args.rate,
            args.duration,
        )
    )
    row = run(setup, unit)
    show(row)
    if not row.exactly_once:
        sys.exit(1)


if __name__ == "__main__":
    main()
