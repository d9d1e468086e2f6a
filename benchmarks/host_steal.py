"""CPU time a virtual machine's host took from it ("steal"), sampled for the latency benchmarks.

On a virtual machine the hypervisor can hold a virtual CPU off its physical
core; Linux counts that time as *steal* in ``/proc/stat`` (``man 5 proc``: the
eighth value of the ``cpu`` line, in ticks of ``SC_CLK_TCK``). Every process of
a benchmark is then late at once, at every stage, by up to tens of
milliseconds, whatever the service does. :class:`HostSteal` samples the
counters in a thread so that a benchmark can say, for each trial, how much of
the machine's CPU time the host took around it.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

PROC_STAT = Path("/proc/stat")
STEAL_WINDOW_S = 0.5
"""A trial's steal is measured from this long before the message or frame that completes its fault to its event."""
PERIOD_S = 0.05
"""Sampling period (the counters move in ticks of 10 ms on most kernels)."""


def _read(path: Path) -> tuple[int, int] | None:
    """(steal ticks, all ticks) of every CPU together; None where there is no such file."""
    try:
        fields = path.read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    ticks = [int(v) for v in fields[1:]]
    # guest and guest_nice (9th, 10th) are already inside user and nice.
    return ticks[7], sum(ticks[:8])


class HostSteal:
    """Steal and total CPU ticks sampled every :data:`PERIOD_S`, stamped with ``time.perf_counter`` (the
    benchmarks' clock: CLOCK_MONOTONIC on Linux, the same in every process), until :meth:`close`."""

    def __init__(self, path: Path = PROC_STAT, period_s: float | None = PERIOD_S):
        self._path = path
        self._period_s = period_s
        self._samples: list[tuple[float, int, int]] = []
        """(time, steal ticks, all ticks), appended whole (a reader never sees half a sample)."""
        self._stop = threading.Event()
        self.available = _read(path) is not None
        """False where the machine has no ``/proc/stat`` (then every fraction is None)."""
        self._thread = threading.Thread(target=self._run, name="host-steal", daemon=True)
        if self.available and period_s is not None:
            self._thread.start()

    def sample(self) -> None:
        """Take one sample now (the thread does, every ``period_s``; with ``period_s=None`` only calls do)."""
        now = _read(self._path)
        if now is not None:
            self._samples.append((time.perf_counter(), *now))

    def _run(self) -> None:
        assert self._period_s is not None
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self._period_s)

    def fraction(self, t0_s: float, t1_s: float) -> float | None:
        """Share of all CPUs' time the host took between the samples around ``t0_s`` and ``t1_s``
        (``time.perf_counter``, s); None when no sample precedes ``t0_s`` or follows ``t1_s``.

        Asked right after ``t1_s``, it waits for the thread's next sample (up to three periods).
        """
        if self._period_s is not None and self._thread.is_alive():
            deadline = time.perf_counter() + 3 * self._period_s
            while self._samples and self._samples[-1][0] < t1_s and time.perf_counter() < deadline:
                time.sleep(self._period_s / 5)
        t, steal, total = np.array(self._samples, dtype=float).reshape(-1, 3).T
        i = int(np.searchsorted(t, t0_s, side="right")) - 1
        j = int(np.searchsorted(t, t1_s, side="left"))
        if i < 0 or j >= len(t) or total[j] == total[i]:
            return None
        return float((steal[j] - steal[i]) / (total[j] - total[i]))

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def percentiles(lat_ms: np.ndarray) -> str:
    """p50, p99 and max of latencies in ms, as one line."""
    return (
        f" p50 {np.percentile(lat_ms, 50):6.2f} ms   p99 {np.percentile(lat_ms, 99):6.2f} ms   "
        f"max {lat_ms.max():6.2f} ms"
    )


def print_by_steal(lat_ms: np.ndarray, stolen: list[float | None]) -> None:
    """The latencies split by the CPU time the host took around each trial (:mod:`host_steal`)."""
    unmeasured = sum(s is None for s in stolen)
    if not stolen or unmeasured:
        why = "no /proc/stat" if unmeasured == len(stolen) else "no sample around them"
        print(f"    host steal time: not measured for {unmeasured} of {len(stolen)} trials ({why})")
        return
    share = np.array(stolen, dtype=float)
    print(
        f"    CPU time the host took (steal) from {STEAL_WINDOW_S:g} s before each trial's completing input to "
        f"its event: "
        f"median {np.median(share):.1%}, max {share.max():.1%}"
    )
    # "None": not one tick (10 ms on most kernels) counted around the trial, whose own event takes about
    # that long; a single stolen tick is the size of the whole latency.
    for name, sel in (("no steal", share == 0.0), ("some steal", share > 0.0)):
        if sel.any():
            print(f"    {name:12s} {int(sel.sum()):3d} trials:{percentiles(lat_ms[sel])}")
