"""Memory of the daemon and of the project's router against the IMUs served and the frames carried.

For each fleet size (``--imus``, default 1 4 16 64: one vehicle per IMU), a router
(``python -m protocols.zenoh_router``) and the daemon (``ins-health run``) start afresh as separate
processes, and this script publishes the demo's unit (handling, flight, a scale fault after landing,
handling again: 117 s at 200 Hz in frames of 20, :class:`bench_soak.Waves`) for every IMU, in real
time by default (``--speed``), for ``--seconds`` of wall time. Every ``--every-s`` it reads both
processes' ``VmRSS`` and ``VmHWM`` from ``/proc/<pid>/status``.

It prints one row per fleet size: frames published, each process's resident memory after start-up
(the first sample), at the end and its peak, and its growth: the least-squares slope of ``VmRSS``
over the second half of the run (after the pipelines' start-up: positions, fits), in MB per hour
and per 10,000 frames. The one-hour figure is the end value plus that slope over the rest of the
hour: an extrapolation from a short run, which holds only if the growth stays linear (what grows
with the data, a unit's positions, is bounded by ``[pipeline]`` limits; a leak would not be).

``--flood N`` measures the router alone under bursts instead: three rounds of six publisher sessions
(each a client with Zenoh's defaults, shared memory on, as a vehicle's may be) putting ``N`` frames
of 100 samples (5.6 KB) as fast as the router takes them (``CongestionControl.BLOCK``, as ``ins-health
publish`` does) to one subscriber, the router's ``VmRSS`` after each round
(:data:`protocols.zenoh_adapter.SHARED_MEMORY` says what it found).

Run: ``python benchmarks/bench_memory.py [--imus 1 4 16 64] [--seconds 120] [--flood 4000]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh
from bench_soak import Waves, _toml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocols.frames import encode_frame  # noqa: E402
from protocols.zenoh_adapter import Mode, ZenohSettings, frame_key, zenoh_config  # noqa: E402
from protocols.zenoh_router import RouterProcess, free_local_port  # noqa: E402
from service.demo import demo_passport  # noqa: E402
from service.passport_store import PassportStore  # noqa: E402

HOUR_S = 3600.0


def vm_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process, MB."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024
    return fields["VmRSS"], fields["VmHWM"]


@dataclass
class Trace:
    """One process's memory samples: (wall s, frames published, VmRSS MB), and its peak."""

    samples: list[tuple[float, int, float]]
    peak_mb: float = 0.0

    def add(self, t_s: float, frames: int, pid: int) -> None:
        rss, hwm = vm_mb(pid)
        self.samples.append((t_s, frames, rss))
        self.peak_mb = max(self.peak_mb, hwm)

    def slope(self, column: int) -> float:
        """MB per unit of ``column`` (0: s, 1: frames) over the second half of the samples."""
        half = self.samples[len(self.samples) // 2 :]
        x = np.array([s[column] for s in half], dtype=float)
        y = np.array([s[2] for s in half])
        return float(np.polyfit(x, y, 1)[0]) if len(half) >= 2 and np.ptp(x) > 0 else 0.0

    def row(self) -> str:
        first, last = self.samples[0][2], self.samples[-1][2]
        per_h = self.slope(0) * HOUR_S
        per_10k = self.slope(1) * 1e4
        hour = last + self.slope(0) * max(0.0, HOUR_S - self.samples[-1][0])
        return f"{first:6.0f} {last:6.0f} {self.peak_mb:6.0f} {per_h:+8.1f} {per_10k:+8.2f} {hour:7.0f}"


def publisher(port: int, waves: Waves, speed: float, seconds: float, sent: list[int]) -> None:
    """Publish the waves in data time / ``speed`` of wall time until ``seconds`` have passed."""
    settings = ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",))
    with zenoh.open(zenoh_config(settings)) as session:
        pubs = {
            v: session.declare_publisher(
                frame_key(v, 0), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for v in waves.vehicles
        }
        t0, w = time.perf_counter(), 0
        while True:
            for batch in waves.wave(w):
                due = (batch.t_s[-1] - waves.session.t_s[0]) / speed
                if (wait := t0 + due - time.perf_counter()) > 0:
                    time.sleep(wait)
                if time.perf_counter() - t0 >= seconds:
                    return
                pubs[batch.vehicle].put(encode_frame(batch))
                sent[0] += 1
            w += 1


def measure(n_imus: int, args: argparse.Namespace) -> tuple[int, Trace, Trace]:
    passport, g = demo_passport()
    vehicles = [f"mem-{k:02d}" for k in range(n_imus)]
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        store = PassportStore(tmp / "passports")
        for v in vehicles:
            store.put(v, 0, passport)
        port = free_local_port()
        raw = {
            "service": {"name": "mem", "data_dir": str(tmp / "data"), "passport_dir": str(store.root)},
            "site": {"gravity_mps2": g},
            "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]},
            "validity": {"timeout_s": 600.0},
        }  # fmt: skip
        (tmp / "mem.toml").write_text(_toml(raw))
        with RouterProcess(f"tcp/127.0.0.1:{port}") as router:
            daemon = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "run", "--config", str(tmp / "mem.toml"),
                 "--log-level", "warning"],
                cwd=ROOT, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            try:
                time.sleep(3.0)  # the daemon's start and its session
                traces = Trace([]), Trace([])
                sent = [0]
                pub = threading.Thread(
                    target=publisher, args=(port, Waves(vehicles), args.speed, args.seconds, sent)
                )
                t0 = time.perf_counter()
                pub.start()
                while pub.is_alive():
                    t = time.perf_counter() - t0
                    for trace, pid in zip(traces, (daemon.pid, router.pid), strict=True):
                        assert pid is not None
                        trace.add(t, sent[0], pid)
                    pub.join(args.every_s)
                for trace, pid in zip(traces, (daemon.pid, router.pid), strict=True):
                    assert pid is not None
                    trace.add(time.perf_counter() - t0, sent[0], pid)
            finally:
                daemon.terminate()
                daemon.wait(60)
    return sent[0], *traces


FLOOD_PUBLISHERS = 6
FLOOD_FRAME_BYTES = 5600


def flood(frames: int) -> None:
    """The router's VmRSS after each of three rounds of bursts (module docstring)."""
    port = free_local_port()
    default_client = zenoh.Config()
    default_client.insert_json5("mode", '"client"')
    default_client.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    default_client.insert_json5("scouting/multicast/enabled", "false")

    def burst(k: int) -> None:
        with zenoh.open(default_client) as session:
            pub = session.declare_publisher(
                frame_key(f"flood-{k}", 0), congestion_control=zenoh.CongestionControl.BLOCK
            )
            payload = bytes(FLOOD_FRAME_BYTES)
            for _ in range(frames):
                pub.put(payload)

    settings = ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",))
    received = [0]
    with (
        RouterProcess(f"tcp/127.0.0.1:{port}") as router,
        zenoh.open(zenoh_config(settings)) as sub,
    ):
        assert router.pid is not None
        sub.declare_subscriber("ins/*/imu/*", lambda _: received.__setitem__(0, received[0] + 1))
        print(f"router at start: {vm_mb(router.pid)[0]:.0f} MB")
        for r in range(3):
            threads = [threading.Thread(target=burst, args=(k,)) for k in range(FLOOD_PUBLISHERS)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            time.sleep(1.0)
            rss, hwm = vm_mb(router.pid)
            print(
                f"after round {r + 1} ({FLOOD_PUBLISHERS} x {frames} frames, {received[0]} received "
                f"in all): router VmRSS {rss:.0f} MB, VmHWM {hwm:.0f} MB"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--imus", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--seconds", type=float, default=120.0, help="wall time per fleet size")
    ap.add_argument("--speed", type=float, default=1.0, help="data time per wall time")
    ap.add_argument("--every-s", type=float, default=5.0, help="memory sampled this often")
    ap.add_argument("--flood", type=int, help="frames per publisher: the router under bursts")
    args = ap.parse_args()
    if args.flood is not None:
        flood(args.flood)
        return
    print(
        f"bench_memory: {args.seconds:g} s per fleet size, data at {args.speed:g}x real time "
        f"(200 Hz, frames of 20 samples: {10 * args.speed:g} frames/s per IMU)"
    )
    head = "start    end   peak   MB/h  MB/10kf  1h est"
    print(f"{'IMUs':>4} {'frames':>7} | daemon {head} | router {head}")
    for n in args.imus:
        frames, daemon, router = measure(n, args)
        print(f"{n:4d} {frames:7d} |        {daemon.row()} |        {router.row()}", flush=True)


if __name__ == "__main__":
    main()
