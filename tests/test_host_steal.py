"""The benchmarks' measure of the CPU time a virtual machine's host took (benchmarks/host_steal.py)."""

from __future__ import annotations

import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from service_support import load_benchmark


@pytest.fixture(scope="module")
def host_steal() -> ModuleType:
    return load_benchmark("host_steal")


def stat_line(user: int, system: int, idle: int, steal: int, guest: int) -> str:
    # /proc/stat's cpu line: user nice system idle iowait irq softirq steal guest guest_nice
    return f"cpu  {user} 0 {system} {idle} 0 0 0 {steal} {guest} {guest}\ncpu0 1 2 3\n"


def test_the_share_stolen_is_steal_over_all_ticks_between_the_samples_around_the_window(
    host_steal: ModuleType, tmp_path: Path
) -> None:
    stat = tmp_path / "stat"
    stat.write_text(stat_line(100, 50, 800, 50, 40))
    steal = host_steal.HostSteal(stat, period_s=None)
    steal.sample()
    after_first = time.perf_counter()
    # 1000 more ticks, 150 of them stolen; guest time is inside user already and is not counted twice.
    stat.write_text(stat_line(300, 100, 1400, 200, 140))
    steal.sample()
    after_second = time.perf_counter()
    stat.write_text(stat_line(400, 100, 1800, 200, 140))
    steal.sample()
    assert steal.fraction(after_first, after_first) == pytest.approx(0.15)
    # Across both intervals: 150 of 1500 ticks.
    assert steal.fraction(after_first, after_second) == pytest.approx(0.10)
    # A window beyond the samples is not measured.
    assert steal.fraction(after_first, time.perf_counter() + 1.0) is None


def test_a_machine_without_proc_stat_says_steal_was_not_measured(
    host_steal: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    steal = host_steal.HostSteal(tmp_path / "absent", period_s=0.01)
    assert not steal.available
    assert steal.fraction(0.0, time.perf_counter()) is None
    steal.close()
    host_steal.print_by_steal(np.array([5.0, 6.0]), [None, None])
    assert "not measured for 2 of 2 trials (no /proc/stat)" in capsys.readouterr().out


def test_trials_are_split_into_those_with_no_steal_and_the_rest(
    host_steal: ModuleType, capsys: pytest.CaptureFixture[str]
) -> None:
    lat_ms = np.array([9.0, 10.0, 30.0])
    host_steal.print_by_steal(lat_ms, [0.0, 0.005, 0.2])
    out = capsys.readouterr().out
    quiet = next(line for line in out.splitlines() if "no steal" in line)
    stolen = next(line for line in out.splitlines() if "some steal" in line)
    assert "1 trials" in quiet and "max   9.00 ms" in quiet
    assert "2 trials" in stolen and "max  30.00 ms" in stolen


def test_asked_right_after_its_window_it_waits_for_the_next_sample(
    host_steal: ModuleType, tmp_path: Path
) -> None:
    stat = tmp_path / "stat"
    stat.write_text(stat_line(100, 50, 800, 50, 0))
    steal = host_steal.HostSteal(stat, period_s=0.05)
    time.sleep(0.12)
    # Every sample up to now read the first line; the next one, taken after the call, reads this.
    stat.write_text(stat_line(300, 100, 1400, 200, 0))
    now = time.perf_counter()
    share = steal.fraction(now - 0.1, now)
    steal.close()
    assert share == pytest.approx(0.15)
