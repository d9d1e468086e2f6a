"""Delivery latency per vehicle with 1 of 16 ground stations offline, against all online; memory held
per event while storage is down (issue 29).

* **Latency** — a Zenoh router process on 127.0.0.1; in this process the daemon's delivery as it runs
  it (the SQLite outbox with fsync, :class:`~service.outbox_writer.OutboxWriter`,
  :class:`~service.delivery.SinkDelivery` and :class:`~service.sinks.ZenohEventSink` with the
  defaults ``ack_timeout_s`` 1 s and ``delivery_retry_s`` 0.5 s) and, on a second session, an
  acknowledging :class:`~protocols.zenoh_adapter.EventReceiver` per ground station that is up.
  Every :data:`PERIOD_S` each of the 16 vehicles raises one event, written as the intake writes
  them; latency = received by its ground station − written. Two runs: every ground station up;
  vehicle 0's down (its events wait, retried), alternated :data:`PAIRS` times. p50/p99 over the vehicles that are up, and the
  ratio of the two runs (≈ 1: the offline vehicle holds up only its own events). Before issue 29
  delivery stopped at the first unacknowledged event: every vehicle waited.
* **Memory** — the outbox locked by another connection (``BEGIN EXCLUSIVE``, as another process
  holding it, a read-only or full disk): :data:`HELD` F0-like events written are held in memory
  (and delivered from there); tracemalloc's growth per event.

* **Backlog** (``--backlog N``) — the outbox alone with N events pending for one vehicle nobody
  acknowledges (the default ``outbox_max_pending`` is 100,000): the cost of ``put``, ``ack``,
  ``pending_vehicles`` and of another vehicle's turn through the outbox (its event put, the
  vehicles read, its lane's events read and acked: what the delivery does per event besides the
  transport). Outbox schema 1 read the whole backlog on each (pruning, the vehicles of the pending
  rows); schema 2 keys the lanes in ``pending`` and prunes only the events just delivered. Then
  the latency run with vehicle 0's ground station down, without and with N of its events pending
  at the start.

Run: ``python benchmarks/bench_delivery.py`` (``--quick``: fewer rounds; ``--backlog N``: the backlog
figures only).
"""

from __future__ import annotations

import argparse
import asyncio
import sqlite3
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from host_steal import percentiles  # noqa: E402

from protocols.events import (  # noqa: E402
    Event,
    Predicate,
    Severity,
    StreamCause,
    encode_event,
    make_event,
)
from protocols.zenoh_adapter import (  # noqa: E402
    AckMode,
    EventReceiver,
    Mode,
    ZenohSettings,
    zenoh_config,
)
from protocols.zenoh_router import RouterProcess, free_local_port  # noqa: E402
from service.delivery import SinkDelivery  # noqa: E402
from service.outbox import Outbox  # noqa: E402
from service.outbox_writer import OutboxWriter  # noqa: E402
from service.sinks import ZenohEventSink  # noqa: E402

VEHICLES = 16
PERIOD_S = 0.1
ROUNDS = 100
QUICK_ROUNDS = 20
ACK_TIMEOUT_S = 1.0
RETRY_S = 0.5
HELD = 10_000
PAIRS = 3
"""Runs of each kind, alternated (one with ``--quick``)."""


def event(vehicle: str, k: int) -> Event:
    """An F0-like event with the text and numbers of a real one."""
    return make_event(vehicle=vehicle, imu=0, t_s=64.5 + k, predicate=Predicate.F0,
                      cause=StreamCause.OUT_OF_SHELL, severity=Severity.WARNING, triad="accel",
                      estimate=0.0319, nominal=0.0, tolerance=0.00452, unit="1")  # fmt: skip


def client(port: int) -> zenoh.Config:
    return zenoh_config(ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",)))


def latency_run(port: int, *, offline: set[int], rounds: int, backlog: int = 0) -> np.ndarray:
    """Latencies (ms) of the events of the vehicles whose ground station is up; ``backlog`` events of
    the first offline vehicle already pending when the run starts."""
    vehicles = [f"veh-{k:02d}" for k in range(VEHICLES)]
    written: dict[str, float] = {}
    received: dict[str, float] = {}
    lock = threading.Lock()

    def got(e: Event) -> None:
        with lock:
            received[e.event_id] = time.monotonic()

    with (
        tempfile.TemporaryDirectory() as tmp,
        zenoh.open(client(port)) as onboard,
        zenoh.open(client(port)) as ground,
    ):
        receivers = [
            EventReceiver(ground, got, vehicles=v)
            for k, v in enumerate(vehicles)
            if k not in offline
        ]
        time.sleep(1.0)  # the receivers' queryables reach the daemon's session

        async def run() -> None:
            wake, stop = asyncio.Event(), asyncio.Event()
            path = Path(tmp) / "outbox.sqlite"
            if backlog:
                # Filled before the run and closed (its log checkpointed into the file), as a
                # backlog that grew over hours would be.
                with Outbox(path, sinks=("zenoh",)) as outbox:
                    fill(outbox, vehicles[min(offline)], backlog)
            with Outbox(path, sinks=("zenoh",)) as outbox:
                writer = OutboxWriter(outbox, on_stored=lambda n, v: wake.set(),
                                      on_held=wake.set, clock=time.monotonic)  # fmt: skip
                sink = ZenohEventSink(onboard, ack=AckMode.RECEIVER, ack_timeout_s=ACK_TIMEOUT_S,
                                      min_acks=1, max_lanes=VEHICLES)  # fmt: skip
                delivery = SinkDelivery(sink, outbox, writer, retry_s=RETRY_S, idle=lambda: None,
                                        sent=lambda: None, count=lambda name: None,
                                        transport_error=print, beat=lambda: None)  # fmt: skip
                task = asyncio.create_task(delivery.run(wake, stop))
                for r in range(rounds):
                    for v in vehicles:
                        e = event(v, r)
                        written[e.event_id] = time.monotonic()
                        writer.write([e])
                    await asyncio.sleep(PERIOD_S)
                online = {
                    event(v, r).event_id
                    for r in range(rounds)
                    for k, v in enumerate(vehicles)
                    if k not in offline
                }
                deadline = time.monotonic() + 10.0
                while not online <= received.keys() and time.monotonic() < deadline:
                    await asyncio.sleep(0.05)
                stop.set()
                wake.set()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
                sink.close()

        asyncio.run(run())
        for r in receivers:
            r.close()
    with lock:
        lat = [received[i] - written[i] for i in received if i in written]
    return 1e3 * np.asarray(lat)


def memory_per_held_event(n: int) -> float:
    """Bytes of Python heap per event held while the outbox refuses writes."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "outbox.sqlite"
        with Outbox(path, sinks=("zenoh", "mavlink")) as outbox:
            writer = OutboxWriter(outbox, on_stored=lambda n, v: None, on_held=lambda: None,
                                  clock=time.monotonic, max_held=n)  # fmt: skip
            other = sqlite3.connect(path, isolation_level=None)
            other.execute("BEGIN EXCLUSIVE")
            events = [event(f"veh-{k % VEHICLES:02d}", k) for k in range(n)]
            tracemalloc.start()
            before = tracemalloc.take_snapshot()
            writer.write(events[:1])
            for e in events[1:]:
                writer.write([e])
            after = tracemalloc.take_snapshot()
            tracemalloc.stop()
            grown = sum(s.size_diff for s in after.compare_to(before, "filename"))
            assert writer.counters()["outbox.held_events"] == n
            other.execute("ROLLBACK")
            other.close()
    # The events themselves are made by the pipeline either way; what holding adds is counted
    # together with them here (their encoding, the bookkeeping): an upper bound.
    return grown / n


def fill(outbox: Outbox, vehicle: str, n: int) -> None:
    """``n`` events of ``vehicle`` pending in ``outbox`` (raised before any of a run's)."""
    for start in range(0, n, 10_000):
        batch = [event(vehicle, -1 - k) for k in range(start, min(n, start + 10_000))]
        outbox.put_many((e.event_id, vehicle, encode_event(e)) for e in batch)


def backlog_costs(n: int, *, turns: int = 200) -> dict[str, float]:
    """Median ms per call with ``n`` events pending for one vehicle (module docstring); at ``n`` beyond
    ``turns``, as at the bound ``outbox_max_pending``, each put gives up one of the backlog."""
    stuck, other = "veh-stuck", "veh-other"
    payload = bytes(200)
    with tempfile.TemporaryDirectory() as tmp:
        with Outbox(
            Path(tmp) / "outbox.sqlite", sinks=("zenoh",), max_pending=max(n, turns)
        ) as outbox:
            fill(outbox, stuck, n)
            times: dict[str, list[float]] = {
                k: [] for k in ("put", "ack", "pending_vehicles", "turn")
            }
            for k in range(turns):
                t0 = time.perf_counter()
                outbox.put(f"{n + k:032x}", other, payload)
                t1 = time.perf_counter()
                outbox.pending_vehicles("zenoh")
                t2 = time.perf_counter()
                lane = outbox.pending("zenoh", vehicle=other, limit=16)
                t3 = time.perf_counter()
                outbox.ack_ids("zenoh", [p.id for p in lane])
                t4 = time.perf_counter()
                times["put"].append(t1 - t0)
                times["pending_vehicles"].append(t2 - t1)
                times["ack"].append(t4 - t3)
                times["turn"].append(t4 - t0)
    return {k: 1e3 * float(np.median(v)) for k, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help=f"{QUICK_ROUNDS} rounds instead of {ROUNDS}"
    )
    parser.add_argument(
        "--backlog",
        type=int,
        metavar="N",
        help="only the outbox costs with N events pending for one vehicle",
    )
    args = parser.parse_args()
    rounds = QUICK_ROUNDS if args.quick else ROUNDS
    if args.backlog is not None:
        for n in (1, args.backlog):
            costs = backlog_costs(n)
            print(f"outbox, {n} events pending for one vehicle: median ms per call: "
                  + ", ".join(f"{k} {v:.2f}" for k, v in costs.items()))  # fmt: skip
        port = free_local_port()
        with RouterProcess(f"tcp/127.0.0.1:{port}"):
            for n in (0, args.backlog):
                lat = latency_run(port, offline={0}, rounds=rounds, backlog=n)
                print(f"  vehicle 0's down with {n} events pending, the other 15 ({lat.size} events):"
                      f"{percentiles(lat)}")  # fmt: skip
        return
    port = free_local_port()
    print(f"delivery latency: {VEHICLES} vehicles, one event each every {PERIOD_S * 1e3:.0f} ms, "
          f"{rounds} rounds; ack_timeout_s {ACK_TIMEOUT_S:g}, delivery_retry_s {RETRY_S:g}")  # fmt: skip
    all_up, one_down = [], []
    with RouterProcess(f"tcp/127.0.0.1:{port}"):
        # Alternated: the load of a shared machine drifts over minutes.
        for _ in range(1 if args.quick else PAIRS):
            all_up.append(latency_run(port, offline=set(), rounds=rounds))
            one_down.append(latency_run(port, offline={0}, rounds=rounds))
    all_up, one_down = np.concatenate(all_up), np.concatenate(one_down)
    print(f"  all {VEHICLES} ground stations up ({all_up.size} events):{percentiles(all_up)}")
    print(f"  vehicle 0's down, the other 15 ({one_down.size} events):{percentiles(one_down)}")
    for q in (50, 99):
        ratio = np.percentile(one_down, q) / np.percentile(all_up, q)
        print(f"  p{q} ratio one down / all up: {ratio:.2f}")
    per_event = memory_per_held_event(HELD if not args.quick else HELD // 10)
    print(
        f"memory while storage is down: {per_event:.0f} bytes per held event (tracemalloc, event included)"
    )


if __name__ == "__main__":
    main()
