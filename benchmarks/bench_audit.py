"""Model audit: wall time on the Xsens session, its growth, and the hit rate of hidden effects against their size.

Run: ``python benchmarks/bench_audit.py [--quick]``. Prints

1. the wall time of a full audit of the Xsens session (38 positions, 51,175
   samples) at 5–40 Monte Carlo replicas, and of simulated sessions of growing
   length at a fixed replica count;
2. the hit rate (the audit names exactly the hidden effect) of every kind of
   :data:`estimators.audit.hidden.HIDDEN_KINDS` against its size in detection
   standard errors, and the false-naming rate on effect-free sessions
   (:mod:`estimators.audit.hidden` defines both).
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from estimators.audit import AuditConfig, run_audit
from estimators.audit.hidden import HIDDEN_KINDS, clean_trial, draw, trial
from estimators.chain import ChainConfig
from estimators.sim import Grade, OrientationScheme, multi_position_spec, simulate
from protocols.session_file import load_session

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "xsens-multiposition"
G_XSENS = 9.81744
SIZES = (2.0, 4.0, 6.0, 8.0, 12.0, 16.0)


def _timed(session, gravity, replicas: int) -> float:
    t0 = time.perf_counter()
    run_audit(session, AuditConfig(ChainConfig(gravity_mps2=gravity), replicas=replicas))
    return time.perf_counter() - t0


def wall_times(quick: bool) -> None:
    session = load_session(str(DATA)).session
    print(
        f"Xsens session: {session.n_samples} samples, {session.t_s[-1] - session.t_s[0]:.0f} s, one core"
    )
    for replicas in (5, 10) if quick else (5, 10, 20, 40):
        print(f"  full audit, {replicas:3d} replicas: {_timed(session, G_XSENS, replicas):6.1f} s")
    print("Simulated multi-position sessions (MEMS, 100 Hz, 10 s holds, 4 s turns), 10 replicas:")
    for n in (12, 24) if quick else (12, 24, 48, 96):
        spec = multi_position_spec(
            grade=Grade.MEMS,
            n_positions=n,
            scheme=OrientationScheme.RANDOM,
            orientation_rng=np.random.default_rng(n),
            static_s=10.0,
            transition_s=4.0,
            rate_hz=100.0,
            gravity_mps2=9.80665,
        )
        s = simulate(spec, n).session
        print(f"  {n:3d} positions, {s.n_samples:7d} samples: {_timed(s, 9.80665, 10):6.1f} s")


def _hit(args) -> bool:
    seed, size, kind = args
    return trial(draw(seed, size, kind), seed)


def hit_rates(trials: int, workers: int) -> None:
    print(
        f"Hit rate (exactly the hidden effect named) against size in detection standard errors, {trials} trials each:"
    )
    print("  " + "kind".ljust(34) + "".join(f"{s:>7.0f}" for s in SIZES))
    with ProcessPoolExecutor(workers) as pool:
        for k, kind in enumerate(HIDDEN_KINDS):
            rates = []
            for size in SIZES:
                jobs = [(100_000 + 1000 * k + t, size, kind) for t in range(trials)]
                rates.append(np.mean(list(pool.map(_hit, jobs))))
            print(
                "  "
                + f"{kind[0]} ({kind[1].value})".ljust(34)
                + "".join(f"{r:7.2f}" for r in rates)
            )
        clean = list(pool.map(clean_trial, range(200_000, 200_000 + 5 * trials)))
    print(f"  effect-free sessions naming nothing: {np.mean(clean):.3f} of {len(clean)}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer replica counts, lengths and trials")
    ap.add_argument(
        "--trials", type=int, default=None, help="trials per kind and size (default 40, quick 8)"
    )
    ap.add_argument(
        "--workers", type=int, default=2, help="processes for the hit-rate sweep (default 2)"
    )
    args = ap.parse_args()
    wall_times(args.quick)
    hit_rates(args.trials or (8 if args.quick else 40), args.workers)
