"""Smoke test of benchmarks/bench_fleet.py --quick: routers, instances and publishers as processes; delivery only, never a speed."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

pytestmark = [pytest.mark.network, pytest.mark.slow]

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_fleet.py"


def load_bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_fleet", BENCH)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {BENCH}")
    module = importlib.util.module_from_spec(spec)
    # Registered first: its dataclasses look their module up while the file runs.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_quick_fleet_delivers_every_expected_event_exactly_once() -> None:
    bench = load_bench()
    # Two meshed routers, two instances partitioned by key expression, two vehicles of two IMUs.
    row = bench.run(bench.QUICK)
    assert row.exactly_once, row.problems
    assert row.latency_ms.size == row.setup.vehicles
