"""Smoke test of benchmarks/bench_fleet.py --quick: routers, instances and publishers as processes; delivery only, never a speed."""

from __future__ import annotations

import pytest
from service_support import load_benchmark

pytestmark = [pytest.mark.network, pytest.mark.slow]


def test_quick_fleet_delivers_every_expected_event_exactly_once() -> None:
    bench = load_benchmark("bench_fleet")
    # Two meshed routers, two instances partitioned by key expression, two vehicles of two IMUs.
    row = bench.run(bench.QUICK)
    assert row.exactly_once, row.problems
    assert row.latency_ms.size == row.setup.vehicles
