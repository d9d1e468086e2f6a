"""Throughput of F0 + the stationarity detector, batch and per-sample, on one core.

Targets (issue 2): batch ≥ 5 million samples/s, per-sample ≥ 100,000 samples/s.
Input: a simulated MEMS multi-position session (both triads, 100 Hz), repeated
to the batch size. Each figure is the best of five runs. Run:
``taskset -c 0 python benchmarks/bench_f0_detector.py`` (one core).
"""

from __future__ import annotations

import numpy as np
from stopwatch import best_s

from estimators.conventions import Triad
from estimators.scalar import F0Config, F0Monitor, derive_lambda0, f0_batch, triad_reference
from estimators.session import ImuSession
from estimators.sim import Grade, multi_position_spec, simulate
from estimators.static_detector import StreamingStaticDetector, detect_static


def main() -> None:
    sim = simulate(
        multi_position_spec(grade=Grade.MEMS, static_s=5.0, transition_s=3.0), seed=1
    ).session
    g = triad_reference(Triad.ACCEL, latitude_deg=45.0)
    lam = derive_lambda0(noise_std_norm=sim.accel_mps2[:400].std(axis=0) / g, false_alarm_prob=1e-6)
    config = F0Config(lambda0=lam.lambda0, reference=g)
    compensated = F0Config(
        lambda0=lam.lambda0,
        reference=g,
        bias_norm=(1e-3, -2e-3, 5e-4),
        matrix=np.eye(3) + 1e-3 * np.arange(9).reshape(3, 3),
    )

    reps = int(np.ceil(2_000_000 / sim.n_samples))
    n = reps * sim.n_samples
    period = sim.t_s[-1] + 1.0 / sim.rate_hz
    big = ImuSession(
        (sim.t_s[None, :] + period * np.arange(reps)[:, None]).ravel(),
        np.tile(sim.accel_mps2, (reps, 1)),
        np.tile(sim.gyro_rps, (reps, 1)),
    )

    def batch() -> None:
        det = detect_static(big, rate_hz=100.0)
        f0_batch(big.accel_mps2, det.static, config)

    t_det = best_s(lambda: detect_static(big, rate_hz=100.0), 5)
    static = detect_static(big, rate_hz=100.0).static
    t_f0 = best_s(lambda: f0_batch(big.accel_mps2, static, config), 5)
    t_f0c = best_s(lambda: f0_batch(big.accel_mps2, static, compensated), 5)
    t_both = best_s(batch, 5)
    print(f"batch, {n:,} samples:")
    print(f"  detector        {n / t_det / 1e6:8.2f} M samples/s")
    print(f"  F0              {n / t_f0 / 1e6:8.2f} M samples/s")
    print(f"  F0 compensated  {n / t_f0c / 1e6:8.2f} M samples/s")
    print(f"  F0 + detector   {n / t_both / 1e6:8.2f} M samples/s   (target >= 5)")

    m = sim.n_samples
    t_l = sim.t_s.tolist()
    a_l = sim.accel_mps2.tolist()
    g_l = sim.gyro_rps.tolist()

    def per_sample() -> None:
        det = StreamingStaticDetector(rate_hz=100.0)
        mon = F0Monitor(config)
        update, check = det.update, mon.check
        for i in range(m):
            ax, ay, az = a_l[i]
            gx, gy, gz = g_l[i]
            check(ax, ay, az, det.static_now)
            update(t_l[i], ax, ay, az, gx, gy, gz)

    def detector_only() -> None:
        det = StreamingStaticDetector(rate_hz=100.0)
        update = det.update
        for i in range(m):
            ax, ay, az = a_l[i]
            gx, gy, gz = g_l[i]
            update(t_l[i], ax, ay, az, gx, gy, gz)

    def f0_only() -> None:
        mon = F0Monitor(config)
        check = mon.check
        for i in range(m):
            ax, ay, az = a_l[i]
            check(ax, ay, az, True)

    print(f"per sample, {m:,} samples (pure Python):")
    print(f"  detector        {m / best_s(detector_only, 5) / 1e3:8.1f} k samples/s")
    print(f"  F0              {m / best_s(f0_only, 5) / 1e3:8.1f} k samples/s")
    print(f"  F0 + detector   {m / best_s(per_sample, 5) / 1e3:8.1f} k samples/s   (target >= 100)")


if __name__ == "__main__":
    main()
