"""The gross test's smallest caught fault and its false alarms, on a consumer-MEMS nominal passport.

A unit rests for ``--rest-s`` (10 s) with the consumer class's white noise at 50 and 200 Hz
(:mod:`estimators.nominal_passport`, gravity along z). For each fault size — ``|a|`` off g (above and
below) or a gyro zero signal off the passport on x — ``--trials`` seeded rests are run through
:func:`estimators.gross.gross_batch`; the smallest size found in at least 95 % of them is printed
beside the predicted one (``tolerance + (z + z_power)·σ_mean``, module docstring), then the failures
declared on fault-free rests (``--false-trials`` of them) and the monitor's cost per sample and frame
(one hour at 1 kHz in frames of 5, 100 and gross_batch's block).

Run: ``python benchmarks/bench_gross.py [--rest-s 10] [--trials 100] [--false-trials 2000]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.conventions import STANDARD_GRAVITY_MPS2, Triad  # noqa: E402
from estimators.gross import BLOCK_WINDOWS, GrossMonitor, gross_batch  # noqa: E402
from estimators.nominal_passport import (  # noqa: E402
    CLASS_TOLERANCES,
    NOISE_REFERENCE_RATE_HZ,
    SensorClass,
)
from estimators.session import ImuSession  # noqa: E402

G = STANDARD_GRAVITY_MPS2
CLS = CLASS_TOLERANCES[SensorClass.CONSUMER_MEMS]
BLOCK = BLOCK_WINDOWS * 500
"""gross_batch's block at 1 kHz (windows of 500 samples)."""


def rest(
    rate_hz: float, duration_s: float, seed: int, accel_dev: float, gyro_dev: float
) -> ImuSession:
    rng = np.random.default_rng(seed)
    n = round(rate_hz * duration_s)
    k = math.sqrt(rate_hz / NOISE_REFERENCE_RATE_HZ)
    accel = np.array([0.0, 0.0, G + accel_dev]) + rng.normal(
        0, CLS.accel.noise_density_si * k, (n, 3)
    )
    gyro = np.array([gyro_dev, 0.0, 0.0]) + rng.normal(0, CLS.gyro.noise_density_si * k, (n, 3))
    return ImuSession(np.arange(n) / rate_hz, accel, gyro)


def found(rate_hz: float, rest_s: float, trials: int, accel_dev: float, gyro_dev: float) -> float:
    hits = 0
    for seed in range(trials):
        res = gross_batch(rest(rate_hz, rest_s, seed, accel_dev, gyro_dev), None, gravity_mps2=G)
        hits += any(c.raised for c in res.changes)
    return hits / trials


def smallest(rate_hz, rest_s, trials, predicted, make) -> tuple[float, float]:
    """Smallest size (a grid of 0.2 σ_mean steps around the prediction) found in ≥ 95 % of trials."""
    lo, step = predicted[0], predicted[1]
    size = lo - 10 * step
    while found(rate_hz, rest_s, trials, *make(size)) < 0.95:
        size += step
    return size, found(rate_hz, rest_s, trials, *make(size))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rest-s", type=float, default=10.0)
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--false-trials", type=int, default=2000)
    args = ap.parse_args()
    print(
        f"gross test, consumer_mems nominal passport, {args.rest_s:g} s at rest, {args.trials} trials per size"
    )
    print("  rate   test            predicted MDF   smallest found >=95%   (found)   sigma_mean")
    for rate in (50.0, 200.0):
        probe = gross_batch(rest(rate, args.rest_s, 0, 0.0, 0.0), None, gravity_mps2=G)
        ca, cg = probe.coverage[Triad.ACCEL], probe.coverage[Triad.GYRO]
        m = ca.z + ca.z_power
        sa, sg = ca.sigma_mean_si[2], cg.sigma_mean_si[0]
        cfg = probe.config
        cases = (
            ("|a| above g", cfg.accel_tol_high_mps2 + m * sa, sa, lambda d: (d, 0.0), "m/s^2"),
            ("|a| below g", cfg.accel_tol_low_mps2 + m * sa, sa, lambda d: (-d, 0.0), "m/s^2"),
            ("gyro x offset", cg.tolerance_si[0] + m * sg, sg, lambda d: (0.0, d), "rad/s"),
        )
        for name, pred, sig, make, unit in cases:
            size, rate_found = smallest(rate, args.rest_s, args.trials, (pred, 0.2 * sig), make)
            print(
                f"  {rate:4.0f}   {name:14s}  {pred:.4f} {unit:6s}  {size:.4f} {unit:6s}"
                f"          ({rate_found:.0%})    {sig:.2e}"
            )
    for rate in (50.0, 200.0):
        declared = windows = 0
        for seed in range(args.false_trials):
            res = gross_batch(
                rest(rate, args.rest_s, 10_000 + seed, 0.0, 0.0), None, gravity_mps2=G
            )
            declared += sum(c.raised for c in res.changes)
            windows += res.coverage[Triad.ACCEL].windows + res.coverage[Triad.GYRO].windows
        print(
            f"  {rate:.0f} Hz fault-free: {declared} failures declared over {args.false_trials} rests "
            f"({windows} windows tested)"
        )
    hour = rest(1000.0, 3600.0, 1, 0.0, 0.0)
    cfg = gross_batch(rest(1000.0, 1.0, 0, 0.0, 0.0), None, gravity_mps2=G).config
    for frame in (5, 100, BLOCK):
        mon = GrossMonitor(cfg)
        t0 = time.perf_counter()
        for i in range(0, hour.n_samples, frame):
            sl = slice(i, i + frame)
            mon.update(hour.t_s[sl], hour.accel_mps2[sl], hour.gyro_rps[sl])
        dt = time.perf_counter() - t0
        print(
            f"  GrossMonitor.update, 1 h at 1 kHz in frames of {frame}: "
            f"{1e9 * dt / hour.n_samples:.0f} ns/sample, {1e6 * dt * frame / hour.n_samples:.1f} us/frame"
        )


if __name__ == "__main__":
    main()
