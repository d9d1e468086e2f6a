"""Soak: good vehicles and hostile inputs through a router and the daemon, for a fixed stretch of frames.

Three processes, as deployed: a Zenoh router, the daemon (``ins-health run``, Zenoh and a MAVLink
UDP link), and this script as the vehicles, the attackers and the ground station.

* **Good vehicles** (``--vehicles``, default 3) stream the demo's unit (handling, flight, a +30 %
  z accelerometer scale fault after landing, handling again: 117 s at 200 Hz in frames of 20) again
  and again, time running on, each pass ("wave") played in ``--wave-s`` seconds of wall time; the
  run lasts ``--minutes`` (default 2, the CI size; 60 is the benchmark), a fixed number of frames
  for a given size. The same frames run offline through the same pipelines give the events
  expected; the ground station (an acknowledging :class:`~protocols.zenoh_adapter.EventReceiver`)
  must receive exactly those, each once.
* **Hostile inputs**, one every ``--hostile-every-s`` in turn: frame keys whose IMU index is a
  non-ASCII or non-canonical number, a payload on another IMU's key, random bytes, a map with wrong
  types, a frame with a NaN, samples 1 ns apart, absurd and backward time stamps, a flood of IMU
  indices, a payload over the size limit, MAVLink garbage and MAVLink packets with a bad CRC.

It prints the daemon's resident memory (``VmRSS``) over time, the inputs sent per class, what the
status topic counted (every ``rejected``, ``unknown``, ``dropped`` counter; task failures, i.e.
restarts), the events delivered against those expected, and how long SIGTERM took to end the
daemon. Exit status 1 when the events differ, a task failed, or the daemon did not end cleanly.

Run: ``python benchmarks/bench_soak.py [--minutes 60]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from protocols._schema import MAX_MESSAGE_BYTES  # noqa: E402
from protocols.frames import SampleBatch, encode_frame  # noqa: E402
from protocols.mavlink_adapter import ImuMessage, imu_message  # noqa: E402
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
from service.config import config_from_dict  # noqa: E402
from service.demo import DEMO_FRAME_SAMPLES, demo_passport, demo_scenario  # noqa: E402
from service.passport_store import PassportStore  # noqa: E402
from service.pipeline import FleetProcessor  # noqa: E402
from service.pipeline.options import pipeline_options  # noqa: E402

GAP_S = 0.5
"""Data time between the end of one wave and the start of the next (the unit rests)."""


def client(port: int) -> zenoh.Config:
    return zenoh_config(ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",)))


class Waves:
    """The good vehicles' frames, one wave at a time (an hour's frames would not fit in memory at once)."""

    def __init__(self, vehicles: list[str]):
        self.session = demo_scenario().session
        self.vehicles = vehicles
        self.period_s = float(self.session.t_s[-1] - self.session.t_s[0]) + GAP_S
        self.starts = list(range(0, self.session.n_samples, DEMO_FRAME_SAMPLES))
        self.frames_per_wave = len(self.starts) * len(vehicles)

    def wave(self, w: int) -> list[SampleBatch]:
        """Wave ``w``: every good vehicle's frames interleaved by time; seq and time run on across waves."""
        s, out = self.session, []
        for k, i in enumerate(self.starts):
            sl = slice(i, min(s.n_samples, i + DEMO_FRAME_SAMPLES))
            for v in self.vehicles:
                out.append(
                    SampleBatch(v, 0, w * len(self.starts) + k, s.t_s[sl] + w * self.period_s,
                                s.accel_mps2[sl], s.gyro_rps[sl], None)
                )  # fmt: skip
        return out


class Hostile:
    """The hostile inputs, one class at a time in turn; counts what was sent per class."""

    def __init__(self, session: zenoh.Session, mavlink_port: int, template: SampleBatch, seed: int):
        self.session = session
        self.sent: Counter[str] = Counter()
        self._rng = np.random.default_rng(seed)
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._mav_addr = ("127.0.0.1", mavlink_port)
        self._mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self._t = template
        self._k = 0
        self._classes = [
            self.key_superscript, self.key_arabic_digit, self.key_leading_zero, self.key_mismatch,
            self.random_bytes, self.wrong_types, self.nan_sample, self.one_ns_apart,
            self.absurd_time, self.time_backwards, self.imu_flood, self.oversized,
            self.mavlink_garbage, self.mavlink_bad_crc,
        ]  # fmt: skip

    def send_next(self) -> None:
        fn = self._classes[self._k % len(self._classes)]
        self._k += 1
        fn()
        self.sent[fn.__name__] += 1

    def _frame(self, vehicle: str, imu: int = 0, **changes) -> bytes:
        seq = self._k
        return encode_frame(
            dataclasses.replace(self._t, vehicle=vehicle, imu=imu, seq=seq, **changes)
        )

    def key_superscript(self) -> None:
        self.session.put("ins/evil-k/imu/²", self._frame("evil-k", 2))

    def key_arabic_digit(self) -> None:
        self.session.put("ins/evil-k/imu/٣", self._frame("evil-k", 3))

    def key_leading_zero(self) -> None:
        self.session.put("ins/evil-k/imu/03", self._frame("evil-k", 3))

    def key_mismatch(self) -> None:
        self.session.put(frame_key("evil-m", 0), self._frame("evil-m", 1))

    def random_bytes(self) -> None:
        self.session.put(frame_key("evil-g", 0), self._rng.bytes(int(self._rng.integers(1, 4000))))

    def wrong_types(self) -> None:
        raw = msgpack.unpackb(self._frame("evil-w"), raw=False)
        self.session.put(frame_key("evil-w", 0), msgpack.packb({**raw, "imu": "zero", "seq": -1.5}))

    def nan_sample(self) -> None:
        accel = self._t.accel_mps2.copy()
        accel[3, 1] = np.nan
        self.session.put(frame_key("evil-n", 0), self._frame("evil-n", accel_mps2=accel))

    def one_ns_apart(self) -> None:
        t = 1e-9 * np.arange(self._t.n_samples) + 1e-7 * self._k
        self.session.put(frame_key("evil-t", 0), self._frame("evil-t", t_s=t))

    def absurd_time(self) -> None:
        t = 1e15 + 0.005 * np.arange(self._t.n_samples) + self._k
        self.session.put(frame_key("evil-a", 0), self._frame("evil-a", t_s=t))

    def time_backwards(self) -> None:
        t = 1e4 - 0.005 * self._k * self._t.n_samples + 0.005 * np.arange(self._t.n_samples)
        self.session.put(frame_key("evil-b", 0), self._frame("evil-b", t_s=t))

    def imu_flood(self) -> None:
        for imu in range(16):
            self.session.put(frame_key("evil-i", imu), self._frame("evil-i", imu))

    def oversized(self) -> None:
        self.session.put(frame_key("evil-o", 0), self._rng.bytes(MAX_MESSAGE_BYTES + 1))

    def mavlink_garbage(self) -> None:
        self._udp.sendto(self._rng.bytes(int(self._rng.integers(1, 280))), self._mav_addr)

    def mavlink_bad_crc(self) -> None:
        msg = imu_message(
            ImuMessage.SCALED_IMU, t_s=float(self._k), accel_mps2=self._t.accel_mps2[0],
            gyro_rps=self._t.gyro_rps[0], imu_id=0,
        )  # fmt: skip
        packet = bytearray(msg.pack(self._mav))
        packet[-1] ^= 0xFF
        self._udp.sendto(bytes(packet), self._mav_addr)

    def close(self) -> None:
        self._udp.close()


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=2.0, help="length of the run (default 2)")
    ap.add_argument("--vehicles", type=int, default=3, help="good vehicles (default 3)")
    ap.add_argument(
        "--wave-s", type=float, default=30.0, help="wall time of one pass of the unit's 117 s"
    )
    ap.add_argument(
        "--hostile-every-s", type=float, default=0.25, help="one hostile input per this many s"
    )
    ap.add_argument(
        "--rss-every-s", type=float, default=10.0, help="memory sampled every this many s"
    )
    args = ap.parse_args()
    n_waves = max(1, round(args.minutes * 60.0 / args.wave_s))
    passport, g = demo_passport()
    good = [f"uav-{k}" for k in range(args.vehicles)]

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        store = PassportStore(tmp / "passports")
        for v in good:
            store.put(v, 0, passport)
        port, udp = free_local_port(), free_local_port()
        raw = {
            "service": {"name": "soak", "data_dir": str(tmp / "data"), "passport_dir": str(store.root),
                        "status_period_s": 0.5, "checkpoint_period_s": 10.0},
            "site": {"gravity_mps2": g},
            "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]},
            "mavlink": {"enabled": True, "device": f"udpin:127.0.0.1:{udp}", "vehicle": "mav1"},
            "validity": {"timeout_s": 600.0},
        }  # fmt: skip
        (tmp / "soak.toml").write_text(_toml(raw))
        waves = Waves(good)
        # The same frames through the same pipelines in this process, frame by frame as they are
        # published: the events expected.
        offline = FleetProcessor(
            passports=lambda v, i: passport, options=pipeline_options(config_from_dict(raw))
        )
        n_good = n_waves * waves.frames_per_wave
        print(
            f"soak: {n_waves} waves x {args.vehicles} vehicles = {n_good} good frames "
            f"({n_good * DEMO_FRAME_SAMPLES} samples) in {n_waves * args.wave_s:.0f} s; one "
            f"hostile input every {args.hostile_every_s:g} s",
            flush=True,
        )
        with RouterProcess(f"tcp/127.0.0.1:{port}"):
            daemon = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "run", "--config", str(tmp / "soak.toml"),
                 "--log-level", "warning"],
                cwd=ROOT, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            log: list[str] = []
            threading.Thread(target=lambda: log.extend(daemon.stderr), daemon=True).start()
            ok = _soak(args, port, udp, daemon, waves, n_waves, offline)
            t_stop = time.perf_counter()
            daemon.terminate()
            code = daemon.wait(60)
            print(f"SIGTERM to exit: {time.perf_counter() - t_stop:.2f} s, exit status {code}")
        warnings = [line.rstrip() for line in log]
        print(f"daemon log at warning and above: {len(warnings)} lines")
        for line in warnings[:20]:
            print(f"  {line[:200]}")
        return 0 if ok and code == 0 else 1


def _soak(args, port, udp, daemon, waves, n_waves, offline) -> bool:
    good = waves.vehicles
    expected: list[str] = []
    got: list[str] = []
    latest: dict[str, Any] = {}
    lock = threading.Lock()

    def on_event(e) -> None:
        if e.vehicle in good:
            with lock:
                got.append(e.event_id)

    def on_status(st) -> None:
        with lock:
            latest[st.vehicle] = st

    with zenoh.open(client(port)) as vehicle, zenoh.open(client(port)) as ground:
        receiver = EventReceiver(ground, on_event)
        status_sub = subscribe_status(ground, on_status)
        pubs = {
            v: FramePublisher(vehicle, v, 0, congestion_control=zenoh.CongestionControl.BLOCK)
            for v in good
        }
        deadline = time.monotonic() + 60
        while not all(p.matched for p in pubs.values()):
            if time.monotonic() > deadline or daemon.poll() is not None:
                raise RuntimeError("the daemon did not subscribe to the frames")
            time.sleep(0.05)
        wave = waves.wave(0)
        hostile = Hostile(vehicle, udp, wave[0], seed=1)
        start = time.monotonic()
        next_hostile, next_rss = start, start
        rss = []
        print(f"{'t (s)':>7s} {'RSS (MB)':>9s} {'good frames':>12s} {'hostile':>8s} {'events':>7s}")
        sent = 0
        for w in range(n_waves):
            wave = wave if w == 0 else waves.wave(w)
            per_frame_s = args.wave_s / len(wave)
            wave_start = start + w * args.wave_s
            for k, b in enumerate(wave):
                now = time.monotonic()
                due = wave_start + k * per_frame_s
                if due > now:
                    time.sleep(due - now)
                pubs[b.vehicle].publish(b)
                sent += 1
                expected += [e.event_id for e in offline.process(b, arrival_s=float(b.t_s[-1]))]
                now = time.monotonic()
                if now >= next_hostile:
                    hostile.send_next()
                    next_hostile += args.hostile_every_s
                if now >= next_rss:
                    rss.append((now - start, rss_mb(daemon.pid)))
                    with lock:
                        n_events = len(got)
                    print(
                        f"{rss[-1][0]:7.0f} {rss[-1][1]:9.1f} {sent:12d} {sum(hostile.sent.values()):8d} {n_events:7d}",
                        flush=True,
                    )
                    next_rss += args.rss_every_s
        # Delivery catches up: every expected event, or a minute.
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with lock:
                if len(got) >= len(expected):
                    break
            time.sleep(0.2)
        time.sleep(2 * 0.5)  # two more status periods: the last counters
        rss.append((time.monotonic() - start, rss_mb(daemon.pid)))
        for p in pubs.values():
            p.close()
        status_sub.undeclare()
        receiver.close()
        hostile.close()
        with lock:
            delivered, statuses = list(got), dict(latest)

    print(f"RSS: first {rss[0][1]:.1f} MB, max {max(r for _, r in rss):.1f} MB, last {rss[-1][1]:.1f} MB "
          f"after {rss[-1][0]:.0f} s")  # fmt: skip
    print("hostile inputs sent: " + ", ".join(f"{k} {n}" for k, n in sorted(hostile.sent.items())))
    counted: Counter[str] = Counter()
    service_level: dict[str, int] = {}
    for st in statuses.values():
        for name, n in st.counters.items():
            if name.startswith("service."):
                service_level[name] = max(service_level.get(name, 0), n)
            elif any(w in name for w in ("rejected", "unknown", "over_", "dropped")):
                counted[f"{st.vehicle}.{name}"] += n
    for name, n in sorted(service_level.items()):
        if n and any(
            w in name
            for w in (
                "rejected",
                "unknown",
                "over_",
                "dropped",
                "undecodable",
                "errors",
                "mavlink.",
            )
        ):
            counted[name] = n
    print("counted on the status topic (non-zero):")
    for name, n in sorted(counted.items()):
        if n:
            print(f"  {name} {n}")
    restarts = {
        k: n
        for k, n in service_level.items()
        if k.endswith(".failures") and k.startswith("service.task.")
    }
    print(
        f"task failures (each one a restart): {sum(restarts.values())} {restarts if any(restarts.values()) else ''}"
    )
    dup = len(delivered) - len(set(delivered))
    missing = [e for e in expected if e not in set(delivered)]
    unexpected = [e for e in set(delivered) if e not in set(expected)]
    print(f"events: expected {len(expected)}, delivered {len(set(delivered))} (missing {len(missing)}, "
          f"unexpected {len(unexpected)}, duplicates {dup})")  # fmt: skip
    return not missing and not unexpected and not dup and not any(restarts.values())


def _toml(raw: dict) -> str:
    lines = []
    for section, values in raw.items():
        lines.append(f"[{section}]")
        for k, v in values.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


if __name__ == "__main__":
    sys.exit(main())
