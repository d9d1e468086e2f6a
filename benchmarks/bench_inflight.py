"""The cross-IMU norm check in flight (estimators.cross_imu_norm): detection time, false alarms, cost.

Two simulated IMUs on one vehicle (the project's flight profile, ``flight_spec``: 10 s at rest, a
``Fly`` segment, 10 s at rest; MEMS grade, 100 Hz); IMU 1 sits 7.8 cm from IMU 0, turned (body z
on its y axis, 30° of yaw), with noise of its own. Printed:

1. detection time against the size of a scale fault of IMU 1's thrust-carrying axis (from a random
   time 40–80 s into a 100 s flight): the fraction found within 5 s over ``--flights`` seeded flights
   (100 at 0.5 %, the issue's size), the median and 95th percentile delay;
2. false alarms per flight hour: ``--hours`` fault-free flights of one hour each (IMU 1 turned a
   further 10°), with the 95 % upper bound of the rate (3.0 / hours when none);
3. the cost per sample of the streaming path (frames of 50 samples per IMU, the daemon's per-frame
   path) and of the batch path (replay);
4. the thresholds at the check's false-alarm rate against ArduPilot's and PX4's cross-IMU limits.

Run: ``python benchmarks/bench_inflight.py [--flights 100] [--hours 100]``; ``--short`` runs 20
flights and 2 hours.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from statistics import NormalDist

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scipy.spatial.transform import Rotation  # noqa: E402
from stopwatch import best_s  # noqa: E402

from estimators.conventions import STANDARD_GRAVITY_MPS2, Triad  # noqa: E402
from estimators.cross_imu_norm import (  # noqa: E402
    N_ONE_SIDED,
    CrossImuNorm,
    NormChannel,
    NormCheckConfig,
    NormTrace,
    cross_imu_norm_sessions,
)
from estimators.session import ImuSession  # noqa: E402
from estimators.sim import (  # noqa: E402
    PAIR_MOUNT_ZX_DEG,
    Fault,
    FaultKind,
    pair_flight_specs,
    simulate,
)

MOUNT = Rotation.from_euler("zx", PAIR_MOUNT_ZX_DEG, degrees=True).as_matrix()
TURNED = Rotation.from_euler("x", 10.0, degrees=True).as_matrix() @ MOUNT
THRUST_AXIS = int(np.argmax(np.abs(MOUNT[:, 2])))
REST_S = 10.0
AUTOPILOTS = (
    ("ArduPilot (arming, INS_*)", 0.75, math.radians(5.0)),
    ("PX4 (COM_ARM_IMU_ACC/GYR)", 0.7, 0.25),
)


def pair(
    seed: int, fly_s: float, faults: tuple[Fault, ...] = (), mat_sb: np.ndarray = MOUNT
) -> tuple[ImuSession, ImuSession]:
    spec0, spec1 = pair_flight_specs(fly_s=fly_s, rest_s=REST_S, mat_sb=mat_sb, faults=faults)
    return simulate(spec0, seed).session, simulate(spec1, seed).session


def batch(s0: ImuSession, s1: ImuSession) -> NormTrace:
    return cross_imu_norm_sessions(s0, s1)


def detection(scale: float, flights: int) -> tuple[float, float, float, float]:
    """Fraction found within 5 s, median and 95th percentile delay (s; inf when missed), median σ̂."""
    rng = np.random.default_rng(32)
    delays, sigmas = [], []
    for seed in range(flights):
        onset = REST_S + float(rng.uniform(40.0, 80.0))
        fault = Fault(FaultKind.STEP, Triad.ACCEL, 3 + THRUST_AXIS, onset, scale)
        trace = batch(*pair(seed, 100.0, (fault,)))
        alarms = [
            a.t_s - onset for a in trace.alarms if a.channel is NormChannel.ACCEL and a.t_s > onset
        ]
        delays.append(alarms[0] if alarms else math.inf)
        sigmas.append(np.median([b.accel.sigma_si for b in trace.blocks[30:]]))
    d = np.array(delays)
    return (
        float(np.mean(d <= 5.0)),
        float(np.median(d)),
        float(np.percentile(d, 95)),
        float(np.median(sigmas)),
    )


def false_alarms(hours: int) -> tuple[int, float, float]:
    """Alarms in ``hours`` one-hour fault-free flights, and the median σ̂ of each channel."""
    alarms, sig_a, sig_g = 0, [], []
    for seed in range(1000, 1000 + hours):
        trace = batch(*pair(seed, 3600.0 - 2 * REST_S, mat_sb=TURNED))
        alarms += len(trace.alarms)
        sig_a.append(np.median([b.accel.sigma_si for b in trace.blocks[60:]]))
        sig_g.append(np.median([b.gyro.sigma_si for b in trace.blocks[60:]]))
    return alarms, float(np.median(sig_a)), float(np.median(sig_g))


def cost(s0: ImuSession, s1: ImuSession) -> tuple[float, float]:
    """µs per sample pair of the streaming path (frames of 50) and of the batch path."""
    n = s0.t_s.size

    def stream() -> None:
        check = CrossImuNorm()
        for k in range(0, n, 50):
            sl = slice(k, k + 50)
            check.add(0, s0.t_s[sl], s0.accel_mps2[sl], s0.gyro_rps[sl])
            check.add(1, s1.t_s[sl], s1.accel_mps2[sl], s1.gyro_rps[sl])

    return 1e6 * best_s(stream, 3) / n, 1e6 * best_s(lambda: batch(s0, s1), 3) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=100)
    ap.add_argument("--hours", type=int, default=100)
    ap.add_argument("--short", action="store_true", help="20 flights and 2 hours")
    args = ap.parse_args()
    flights, hours = (20, 2) if args.short else (args.flights, args.hours)
    cfg = NormCheckConfig()
    print(
        f"CUSUM k = {cfg.k_sigma:g}, h = {cfg.threshold:.3f} at {cfg.false_alarms_per_hour:g} false alarms per flight hour; MDF = {cfg.mdf_sigmas:.2f} sigma (5 s mean delay)"
    )
    print("\n1. IMU 1 thrust-axis scale fault: found within 5 s, delay (median, 95th percentile)")
    for scale in (0.002, 0.003, 0.005, 0.01):
        n = flights if scale == 0.005 else max(flights // 5, 10)
        frac, med, p95, sigma = detection(scale, n)
        print(
            f"   {100 * scale:4.1f} % ({scale * STANDARD_GRAVITY_MPS2:.3f} m/s² in hover): {frac * n:.0f}/{n} within 5 s, median {med:.1f} s, 95th pct {p95:.1f} s (block noise {sigma:.4f} m/s²)"
        )
    print(f"\n2. false alarms: {hours} fault-free flights of 1 h, IMU 1 turned 10° more")
    n_alarms, sig_a, sig_g = false_alarms(hours)
    bound = (3.0 if n_alarms == 0 else n_alarms + 2.0 * math.sqrt(n_alarms)) / hours
    print(
        f"   {n_alarms} alarms in {hours} flight hours ({n_alarms / hours:.3g} per hour; 95 % upper bound {bound:.3g}); block noise {sig_a:.4f} m/s², {sig_g:.2e} rad/s"
    )
    s0, s1 = pair(0, 300.0)
    per_stream, per_batch = cost(s0, s1)
    print(
        f"\n3. cost per sample pair: streaming (frames of 50) {per_stream:.1f} µs, batch {per_batch:.2f} µs"
    )
    # A one-block test at the same rate: z such that 2 channels x 2 sides x 3600 blocks/h alarm 1e-4 times.
    z = NormalDist().inv_cdf(1.0 - cfg.false_alarms_per_hour * cfg.block_s / (N_ONE_SIDED * 3600.0))
    print(
        f"\n4. thresholds at {cfg.false_alarms_per_hour:g} false alarms per flight hour (simulated MEMS flights)"
    )
    print("   | check | accelerometer | gyro | needs the mounting |")
    print("   |---|---|---|---|")
    for name, acc, gyr in AUTOPILOTS:
        print(f"   | {name}: vector difference | {acc:.2f} m/s² | {gyr:.3f} rad/s | yes |")
    print(
        f"   | norm, one 1 s block (z = {z:.2f}) | {z * sig_a:.3f} m/s² | {z * sig_g:.4f} rad/s | no |"
    )
    mdf = cfg.mdf_sigmas
    print(
        f"   | norm, CUSUM MDF (5 s mean delay) | {mdf * sig_a:.3f} m/s² | {mdf * sig_g:.4f} rad/s | no |"
    )


if __name__ == "__main__":
    main()
