"""Shared helpers of the service tests: ephemeral ports, Zenoh router and client sessions, waits."""

from __future__ import annotations

import asyncio
import functools
import importlib.util
import json
import socket
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import zenoh
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from protocols.events import decode_event
from protocols.frames import SampleBatch
from protocols.mavlink_adapter import imu_message
from service.config import config_from_dict
from service.daemon import Service
from service.demo import demo_passport, demo_scenario
from service.pipeline import FleetProcessor, PipelineOptions

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


RMEM_MAX = Path("/proc/sys/net/core/rmem_max")
"""``net.core.rmem_max``: the most receive buffer the kernel grants a socket."""
# The service reads these Linux files (protocols.mavlink_adapter.KernelDrops, granted_rcvbuf_bytes);
# where they are absent it counts no drops, and the tests of those counts have nothing to check.
needs_udp_drops = pytest.mark.skipif(
    not Path("/proc/net/udp").exists(), reason="the kernel lists no UDP socket's drops (not Linux)"
)
needs_rmem_max = pytest.mark.skipif(
    not RMEM_MAX.exists(), reason="no net.core.rmem_max to cap the buffer (not Linux)"
)


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` as a module (the folder is not a package: scripts run from it)."""
    path = BENCHMARKS / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    # Registered first: its dataclasses look their module up while the file runs.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@functools.cache
def _demo_unit():
    return demo_passport()


def demo_fleet(**limits: Any) -> FleetProcessor:
    """A fleet whose every IMU has the demo unit's passport, at the demo site's gravity (``limits``:
    FleetProcessor's admission limits, its own where not given)."""
    passport, g = _demo_unit()
    return FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
        **limits,
    )


def free_tcp_port() -> int:
    """A TCP port the OS just handed out on 127.0.0.1 (ephemeral; released for the caller to bind)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zenoh_client_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def zenoh_router_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


@contextmanager
def zenoh_router(port: int | None = None) -> Iterator[int]:
    """An in-process Zenoh router on 127.0.0.1; yields its port and closes it on exit."""
    port = free_tcp_port() if port is None else port
    session = zenoh.open(zenoh_router_config(port))
    try:
        yield port
    finally:
        session.close()


def wait_until(
    predicate: Callable[[], bool], *, timeout_s: float, what: str | Callable[[], str]
) -> None:
    """Poll ``predicate`` until it holds; fail with ``what`` (a text, or a function giving one) after ``timeout_s``.

    The wait is on a condition, not a fixed delay: it returns as soon as the
    condition holds; the small poll interval only bounds the CPU spent waiting.
    """
    deadline = time.monotonic() + timeout_s
    tick = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {what() if callable(what) else what}"
            )
        tick.wait(0.01)


def batches_of(session, *, vehicle: str, imu: int, batch_samples: int, first_seq: int = 0):
    """The samples of an :class:`~estimators.session.ImuSession` as consecutive frames."""
    n = session.n_samples
    for k, start in enumerate(range(0, n, batch_samples)):
        sl = slice(start, min(n, start + batch_samples))
        yield SampleBatch(
            vehicle,
            imu,
            first_seq + k,
            session.t_s[sl],
            session.accel_mps2[sl],
            session.gyro_rps[sl],
            None if session.temp_c is None else session.temp_c[sl],
        )


def disagreeing_pair(vehicle: str, *, batch_samples: int = 100) -> list[SampleBatch]:
    """Two IMUs of ``vehicle`` as they arrive, frame by frame in turn: IMU0 the demo's session without
    its fault, IMU1 with its z accelerometer off by 0.1 g from one second after landing (beyond the
    cross-IMU limit of 0.75 m/s²)."""
    clean = demo_scenario(fault_magnitude=0.0)
    bad = demo_scenario(fault_index=2, fault_magnitude=0.1)
    pairs = zip(
        batches_of(clean.session, vehicle=vehicle, imu=0, batch_samples=batch_samples),
        batches_of(bad.session, vehicle=vehicle, imu=1, batch_samples=batch_samples),
        strict=True,
    )
    return [b for pair in pairs for b in pair]


def run_fleet(fleet, batches, *, finish: bool = True) -> list:
    """Feed frames to a FleetProcessor with arrival time = data time; returns every event (and the end-of-data ones)."""
    events = []
    for b in batches:
        events += fleet.process(b, arrival_s=float(b.t_s[-1]))
    if finish:
        events += fleet.finish()
    return events


STOP_TIMEOUT_S = 60.0
"""How long a stopped service may take to drain and write its checkpoints (the unit's TimeoutStopSec is 20 s)."""


class ServiceThread:
    """An in-process :class:`service.daemon.Service` on its own event loop in a thread (a context manager).

    ``__enter__`` returns once the service takes frames (timeout 30 s); ``__exit__`` stops it the
    way SIGTERM does (drain, checkpoints) and joins the thread.
    """

    def __init__(self, config, **service_options):
        self.service = Service(config, **service_options)
        self._loop = asyncio.new_event_loop()
        self._stop = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="ins-health-service", daemon=True)

    def _main(self) -> None:
        async def go():
            self._stop = asyncio.Event()
            ready = asyncio.Event()
            task = asyncio.create_task(self.service.run(self._stop, ready=ready))
            await asyncio.wait(
                [task, asyncio.create_task(ready.wait())], return_when=asyncio.FIRST_COMPLETED
            )
            self._ready.set()
            await task

        try:
            self._loop.run_until_complete(go())
        except BaseException as exc:  # reported to the test by __enter__/__exit__
            self._error = exc
            self._ready.set()
        finally:
            self._loop.close()

    def __enter__(self) -> ServiceThread:
        self._thread.start()
        if not self._ready.wait(30.0):
            raise AssertionError("the service did not start within 30 s")
        if self._error is not None:
            raise self._error
        return self

    def call(self, fn, *args):
        """Run ``fn(*args)`` on the service's loop and return its result (thread-safe access to its state)."""
        done = threading.Event()
        box = {}

        def run():
            try:
                box["value"] = fn(*args)
            except BaseException as exc:
                box["error"] = exc
            done.set()

        self._loop.call_soon_threadsafe(run)
        if not done.wait(30.0):
            raise AssertionError("the service loop did not answer within 30 s")
        if "error" in box:
            raise box["error"]
        return box["value"]

    def __exit__(self, *exc) -> None:
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(STOP_TIMEOUT_S)
        if self._thread.is_alive() and exc[0] is None:
            raise AssertionError(
                f"the service did not stop within {STOP_TIMEOUT_S} s of the stop request"
            )
        if self._error is not None and exc[0] is None:
            raise self._error


def wait_subscribed(session, key: str, *, timeout_s: float = 10.0) -> None:
    """Wait until some subscriber matches ``key`` (the service declared its frame subscription)."""
    pub = session.declare_publisher(key)
    try:
        wait_until(
            lambda: pub.matching_status.matching, timeout_s=timeout_s, what=f"a subscriber on {key}"
        )
    finally:
        pub.undeclare()


def service_config(
    tmp_path, *, port: int | None, passport_dir, name: str = "ins-health", **sections
):
    """A ServiceConfig for tests: data under ``tmp_path``, Zenoh client of the router on ``port`` (None: no Zenoh)."""
    raw = {
        "service": {
            "name": name,
            "data_dir": str(tmp_path / name),
            "passport_dir": str(passport_dir),
            "status_period_s": 0.2,
        },
        "zenoh": {"enabled": False} if port is None else {"connect": [f"tcp/127.0.0.1:{port}"]},
    }
    for section, values in sections.items():
        raw.setdefault(section, {}).update(values)
    return config_from_dict(raw)


class EventStream:
    """A plain subscriber on ``ins/*/health/events``: every event id as it was put on the wire (no dedup)."""

    def __init__(self, session, vehicles: str = "*"):
        self.ids: list[str] = []
        self._lock = threading.Lock()

        def on_sample(sample):
            event = decode_event(sample.payload.to_bytes())
            with self._lock:
                self.ids.append(event.event_id)

        self._sub = session.declare_subscriber(f"ins/{vehicles}/health/events", on_sample)

    def snapshot(self) -> list[str]:
        with self._lock:
            return list(self.ids)

    def close(self) -> None:
        self._sub.undeclare()


def free_udp_port() -> int:
    """A UDP port the OS just handed out on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mavlink_packets(
    session, kind, *, imu_id: int = 0, start_s: float = -1e9, mav=None
) -> list[bytes]:
    """Each sample of ``session`` from ``start_s`` on as one packed MAVLink 2 message of ``kind`` (an autopilot's
    stream); ``mav`` packs them (e.g. a connection's, to sign them), by default an unsigning one of system 1."""
    if mav is None:
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=mavlink2.MAV_COMP_ID_AUTOPILOT1)
    out = []
    for k in range(int(np.searchsorted(session.t_s, start_s)), session.n_samples):
        msg = imu_message(
            kind,
            t_s=float(session.t_s[k]),
            accel_mps2=session.accel_mps2[k],
            gyro_rps=session.gyro_rps[k],
            imu_id=imu_id,
        )
        out.append(msg.pack(mav))
    return out


def receive_until(
    conn, types: list[str], done: Callable[[list], bool], *, timeout_s: float, what: str
) -> list:
    """MAVLink messages of ``types`` from a pymavlink connection until ``done(messages)`` holds.

    ``timeout_s`` is a deadline for the whole wait, not an idle timeout: a peer
    that keeps sending other matching messages (heartbeats) cannot extend it.
    """
    deadline = time.monotonic() + timeout_s
    got: list = []
    while not done(got):
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {what}; got {dict(Counter(m.get_type() for m in got))}"
            )
        msg = conn.recv_match(type=types, blocking=True, timeout=min(left, 0.5))
        if msg is not None:
            got.append(msg)
    return got


def of_type(messages: list, kind: str) -> list:
    """The MAVLink messages of one type, in arrival order."""
    return [m for m in messages if m.get_type() == kind]


@contextmanager
def served_vehicle(
    tmp_path, passport_dir, **sections
) -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A router on 127.0.0.1, an in-process service of it (``service_config``'s sections) and two
    client sessions: a vehicle's and a ground station's."""
    with zenoh_router() as port:
        cfg = service_config(tmp_path, port=port, passport_dir=passport_dir, **sections)
        with (
            ServiceThread(cfg),
            zenoh.open(zenoh_client_config(port)) as vehicle,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            yield vehicle, ground
