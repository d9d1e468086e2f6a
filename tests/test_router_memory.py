"""The project's router keeps no client's shared-memory pool: its memory does not grow with the
publishers it has routed from.

With Zenoh's shared memory on (its default, and a vehicle's publisher may keep it), each client
puts payloads over 3 KB in a 16 MB pool of its own in /dev/shm, and a router that shares memory maps
every pool it routes from and keeps it mapped: 51 → 364 MB after three rounds of six publishers
(``benchmarks/bench_memory.py --flood 4000``). Whether a pool is mapped is a fact of the router's
address space, read from ``/proc/<pid>/maps``: no timing and no memory threshold.
"""

from __future__ import annotations

import queue
import sys
from pathlib import Path

import pytest
import zenoh
from service_support import free_tcp_port

from protocols.zenoh_adapter import Mode, ZenohSettings, frame_key, zenoh_config
from protocols.zenoh_router import RouterProcess

FRAME_BYTES = 5600
"""A frame of 100 samples: over Zenoh's 3 KB threshold of the shared-memory transport."""


def zenoh_pools(pid: int) -> list[str]:
    """The Zenoh shared-memory segments mapped into a process."""
    maps = Path(f"/proc/{pid}/maps").read_text().splitlines()
    return [line for line in maps if "/dev/shm/" in line and line.endswith(".zenoh")]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/<pid>/maps")
def test_the_router_maps_no_publishers_shared_memory():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    vehicle = zenoh.Config()  # Zenoh's defaults: shared memory on
    vehicle.insert_json5("mode", '"client"')
    vehicle.insert_json5("connect/endpoints", f'["{endpoint}"]')
    vehicle.insert_json5("scouting/multicast/enabled", "false")
    service = zenoh_config(ZenohSettings(mode=Mode.CLIENT, connect=(endpoint,)))
    got: queue.Queue[int] = queue.Queue()
    with RouterProcess(endpoint) as router, zenoh.open(service) as sub:
        assert router.pid is not None
        sub.declare_subscriber("ins/*/imu/*", lambda s: got.put(len(s.payload.to_bytes())))
        for k in range(3):
            with zenoh.open(vehicle) as session:
                pub = session.declare_publisher(
                    frame_key(f"uav-{k}", 0), congestion_control=zenoh.CongestionControl.BLOCK
                )
                for _ in range(50):
                    pub.put(bytes(FRAME_BYTES))
                assert [got.get(timeout=10.0) for _ in range(50)] == [FRAME_BYTES] * 50
        assert zenoh_pools(router.pid) == []
