"""The thrust-axis check against GNSS: detection time against fault size and GNSS rate, false
alarms per flight hour, and its cost per sample (estimators.thrust_gnss, issue 32).

Flights: the project's flight profile (``flight_spec``: 10 s rest, ``Fly``, 10 s rest), consumer
MEMS at 100 Hz, a receiver at 5 or 10 Hz with white velocity noise ``σ_v`` (1.5 σ_v vertically) and
0.15 s of latency (:mod:`estimators.sim.gnss`). A fault is injected into the samples from
mid-flight on: a z zero-signal step (m/s²) or a z scale step; each of ``--flights`` seeded
flights (240 s of flight) is judged once per fault, and the fraction found within 10 s, the
median and the 95th percentile of the delay are printed with the check's own MDF(10 s); a z step
of the size each fault-free flight states as its MDF tells whether that statement holds (95 %).
False alarms: ``--hours`` of fault-free flight in ``--flight-s`` flights at each rate (σ_v
0.05 m/s), counted against the design rate of 0.001 per flight hour. Cost: one hour of flight fed
in frames of 100 IMU samples and 10 epochs (the daemon's path) and at once (replay).

Run: ``python benchmarks/bench_thrust_gnss.py [--flights 100] [--hours 100] [--short]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.sim import Fly, flight_spec, simulate  # noqa: E402
from estimators.sim.gnss import gnss_velocity  # noqa: E402
from estimators.thrust_gnss import (  # noqa: E402
    THRUST_AXIS,
    ThrustAxisConfig,
    ThrustAxisMonitor,
    thrust_axis_batch,
)

FALSE_ALARMS_PER_HOUR = ThrustAxisConfig().false_alarms_per_hour

REST_S = 10.0
LATENCY_S = 0.15
FAULTS = (("zero signal", 0.05), ("zero signal", 0.1), ("zero signal", 0.3))
FAULTS += (("scale", 0.005), ("scale", 0.01), ("scale", 0.03))
RECEIVERS = ((10.0, 0.05), (5.0, 0.05), (10.0, 0.1), (5.0, 0.1))


def receiver(truth, rate_hz: float, sd: float, seed: int):
    rng = np.random.default_rng(1_000_000 + seed)
    return gnss_velocity(truth, rate_hz=rate_hz, vel_sd_mps=sd, latency_s=LATENCY_S, rng=rng)


def inject(t_s, accel, onset_s: float, kind: str, size: float):
    out = accel.copy()
    after = t_s >= onset_s
    if kind == "zero signal":
        out[after, THRUST_AXIS] += size
    else:
        out[after, THRUST_AXIS] *= 1.0 + size
    return out


def detection(flights: int, fly_s: float) -> None:
    """Each fault of FAULTS, and a z zero-signal step of the size the fault-free flight's own
    coverage states as its MDF in 10 s (it should be found in 95 % of the flights)."""
    onset = REST_S + fly_s / 2
    cases = [*FAULTS, ("at the MDF", 0.0)]
    delays: dict[tuple[tuple[float, float], tuple[str, float]], list[float]] = {
        (r, f): [] for r in RECEIVERS for f in cases
    }
    mdf: dict[tuple[float, float], list[float]] = {r: [] for r in RECEIVERS}
    early = 0
    for seed in range(flights):
        res = simulate(flight_spec(fly=Fly(fly_s), rest_s=REST_S), seed)
        s = res.session
        for rec in RECEIVERS:
            gt, gv = receiver(res.truth, *rec, seed)
            _, clean = thrust_axis_batch(s.t_s, s.accel_mps2, s.gyro_rps, gt, gv)
            stated = clean.mdf_mps2(10.0) or np.nan
            mdf[rec].append(stated)
            for kind, size in cases:
                if kind == "at the MDF":
                    accel = inject(s.t_s, s.accel_mps2, onset, "zero signal", stated)
                else:
                    accel = inject(s.t_s, s.accel_mps2, onset, kind, size)
                ev, _ = thrust_axis_batch(s.t_s, accel, s.gyro_rps, gt, gv)
                alarms = ev.t_s[ev.alarm]
                early += int(np.any(alarms < onset))
                late = alarms[alarms >= onset]
                delays[rec, (kind, size)].append(late[0] - onset if late.size else np.inf)
    print(
        f"detection: {flights} flights of {fly_s:.0f} s, fault from {onset:.0f} s; alarms before it: {early}"
    )
    print("  rate  σ_v    fault               found ≤10 s   median s   p95 s   MDF(10 s) m/s²")
    for rec in RECEIVERS:
        for kind, size in cases:
            d = np.array(delays[rec, (kind, size)])
            label = (
                "z + its MDF"
                if kind == "at the MDF"
                else f"z + {size:g} m/s²"
                if kind == "zero signal"
                else f"z × {1 + size:g}"
            )
            p95 = np.quantile(d, 0.95, method="inverted_cdf")
            print(
                f"  {rec[0]:4.0f}  {rec[1]:.2f}  {label:18s}  {np.sum(d <= 10.0):4d}/{flights:<4d}"
                f"      {np.median(d):6.2f}   {p95:6.2f}   {np.nanmedian(mdf[rec]):.3f}"
            )


def false_alarms(hours: float, flight_s: float) -> None:
    n = max(1, round(hours * 3600.0 / flight_s))
    rates = (10.0, 5.0)
    alarms = dict.fromkeys(rates, 0)
    alarmed = dict.fromkeys(rates, 0)
    judged_h = dict.fromkeys(rates, 0.0)
    for seed in range(n):
        res = simulate(flight_spec(fly=Fly(flight_s), rest_s=REST_S), 500_000 + seed)
        s = res.session
        for rate in rates:
            gt, gv = receiver(res.truth, rate, 0.05, 500_000 + seed)
            ev, mon = thrust_axis_batch(s.t_s, s.accel_mps2, s.gyro_rps, gt, gv)
            alarms[rate] += mon.alarms
            alarmed[rate] += mon.alarms > 0
            judged_h[rate] += np.isfinite(ev.z).sum() / rate / 3600.0
    for rate in rates:
        print(
            f"false alarms at {rate:.0f} Hz: {n} flights, {n * flight_s / 3600:.1f} flight hours "
            f"({judged_h[rate]:.1f} h judged): {alarmed[rate]} flights alarmed ({alarms[rate]} "
            f"alarm epochs); {alarmed[rate] / judged_h[rate]:.4f} per judged hour (design {FALSE_ALARMS_PER_HOUR})"
        )


def cost() -> None:
    res = simulate(flight_spec(fly=Fly(3600.0), rest_s=REST_S), 7)
    s = res.session
    gt, gv = receiver(res.truth, 10.0, 0.05, 7)
    t0 = time.perf_counter()
    thrust_axis_batch(s.t_s, s.accel_mps2, s.gyro_rps, gt, gv)
    batch_s = time.perf_counter() - t0
    monitor = ThrustAxisMonitor(gnss_rate_hz=10.0)
    t0 = time.perf_counter()
    for k in range(0, s.t_s.size, 100):
        sl = slice(k, k + 100)
        monitor.update_imu(s.t_s[sl], s.accel_mps2[sl], s.gyro_rps[sl])
        j = np.searchsorted(gt, s.t_s[sl][[0, -1]])
        monitor.update_gnss(gt[j[0] : j[1]], gv[j[0] : j[1]])
    frames_s = time.perf_counter() - t0
    n = s.t_s.size
    print(
        f"cost, {n / 3600 / 100:.2f} h at 100 Hz + 10 Hz GNSS: batch {batch_s:.2f} s "
        f"({batch_s / n * 1e6:.2f} µs a sample); frames of 100 samples {frames_s:.2f} s "
        f"({frames_s / n * 1e6:.2f} µs a sample, {frames_s / (n / 100) * 1e3:.3f} ms a frame)"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--flights", type=int, default=100)
    p.add_argument("--hours", type=float, default=100.0)
    p.add_argument("--flight-s", type=float, default=900.0, help="length of a false-alarm flight")
    p.add_argument("--short", action="store_true", help="10 flights, 2 hours")
    a = p.parse_args()
    if a.short:
        a.flights, a.hours = 10, 2.0
    cost()
    detection(a.flights, 240.0)
    false_alarms(a.hours, a.flight_s)


if __name__ == "__main__":
    main()
