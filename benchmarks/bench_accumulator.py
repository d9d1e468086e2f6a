"""Throughput of the position accumulator (static detector + positions), per sample vs in batches.

Input: a simulated MEMS multi-position session (both triads, temperature, 100 Hz
and 400 Hz). ``update`` is fed sample by sample the way the service did
(rows as plain floats); ``update_batch`` gets the same samples in batches of
the given size. Target: ≥ 200,000 samples/s in batches. Each figure is the best
of three runs. Run: ``taskset -c 0 python benchmarks/bench_accumulator.py`` (one core).
"""

from __future__ import annotations

import numpy as np
from stopwatch import best_s

from estimators.positions import PositionAccumulator
from estimators.sim import Grade, RampTemperature, multi_position_spec, simulate


def _per_sample(session, rate_hz: float) -> None:
    acc = PositionAccumulator(rate_hz=rate_hz)
    rows = np.column_stack(
        [session.t_s, session.accel_mps2, session.gyro_rps, session.temp_c]
    ).tolist()
    update = acc.update
    for t, ax, ay, az, gx, gy, gz, tc in rows:
        update(t, ax, ay, az, gx, gy, gz, tc)
    acc.flush()


def _batched(session, rate_hz: float, batch: int) -> None:
    acc = PositionAccumulator(rate_hz=rate_hz)
    t, a, g, tc = session.t_s, session.accel_mps2, session.gyro_rps, session.temp_c
    for i in range(0, t.size, batch):
        acc.update_batch(t[i : i + batch], a[i : i + batch], g[i : i + batch], tc[i : i + batch])
    acc.flush()


def main() -> None:
    for rate_hz in (100.0, 400.0):
        spec = multi_position_spec(
            grade=Grade.MEMS,
            n_positions=18,
            static_s=10.0,
            transition_s=3.0,
            rate_hz=rate_hz,
            temperature=RampTemperature(20.0, 0.02),
        )
        session = simulate(spec, seed=1).session
        n = session.n_samples
        per = n / best_s(lambda: _per_sample(session, rate_hz), 3)
        print(f"{rate_hz:5.0f} Hz, {n} samples: update        {per:12,.0f} samples/s")
        for batch in (10, 100, 1000, 10000):
            rate = n / best_s(lambda: _batched(session, rate_hz, batch), 3)
            print(
                f"{rate_hz:5.0f} Hz, batches of {batch:5d}: update_batch {rate:12,.0f} samples/s  ({rate / per:5.1f}×)"
            )


if __name__ == "__main__":
    main()
