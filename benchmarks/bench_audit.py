"""Model audit: wall and CPU time on the Xsens session, its growth, and the hit rate of hidden effects against their size.

Run: ``python benchmarks/bench_audit.py [--quick] [--no-times | --no-rates]``. Prints

1. the wall and CPU time of a full audit of the Xsens session (38 positions, 51,175
   samples) at 5–40 Monte Carlo replicas, and of simulated sessions of growing
   length at a fixed replica count;
2. per grade (MEMS, navigation), the hit rate (the audit names exactly the
   hidden effect) of every kind of :func:`estimators.audit.hidden.kinds_of`
   against its size in detection standard errors (2–10), with and without the
   temperature column; the coarse grid against its step in noise sd; and the
   false-naming rate on effect-free sessions (:mod:`estimators.audit.hidden`
   defines them); ``--table`` runs this part alone (``--grade`` and ``--size`` select);
3. the two-effect pairs of :data:`estimators.audit.hidden.PAIRS` at 10 standard errors each
   (both named, nothing else);
4. the 50 Hz line on 200 Hz sessions (:data:`estimators.audit.hidden.LINE_KIND`) against its
   amplitude in noise sd, and effect-free 200 Hz sessions naming nothing;
5. a gyro drift on each side of the chain's nine-parameter σ limit (the gyro's path is continuous),
   and a quadratic accelerometer temperature bias (its order chosen on held-out temperatures);
6. ``--mechanisms``: only the deterministic classes of both triads at 10 standard errors (the
   accelerometer's on MEMS sessions, the gyro's where it resolves the Earth rate, g-sensitivity at both
   grades), each named as its mechanism on its axis, and the effect-free sessions of both grades.
7. issue 31's effect-free session shapes (:data:`estimators.audit.hidden.SHAPES`: 12 positions at 200 Hz,
   30 at 50 Hz, MEMS and navigation, with and without the temperature column, and with the firmware's
   20 Hz low-pass, which must then be named on both triads and nothing else). ``--shapes`` runs this
   part alone (``--trials`` per shape, default 40).
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from estimators.audit import AuditConfig, run_audit
from estimators.audit.hidden import (
    GYRO_MECHANISM_KINDS,
    LINE_KIND,
    LINE_RATE_HZ,
    MECHANISM_KINDS,
    NEAR_LIMIT_GYRO_SD_RPS,
    PAIRS,
    SHAPES,
    clean_trial,
    draw,
    hide,
    hide_pair,
    kinds_of,
    near_limit_drift_named,
    pair_trial,
    quadratic_temperature_named,
    shape_trial,
    trial,
)
from estimators.chain import ChainConfig
from estimators.conventions import AXES, Triad
from estimators.sim import Grade, OrientationScheme, multi_position_spec, simulate
from protocols.session_file import load_session

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "xsens-multiposition"
G_XSENS = 9.81744
SIZES = (2.0, 4.0, 6.0, 8.0, 10.0)
COARSE_STEPS = (2.5, 3.0, 3.5, 4.0)
"""Coarse-grid rows: the step in white-noise sd (noise below half a step; hidden size = 10 × this)."""


def _timed(session, gravity, replicas: int) -> str:
    """Wall and CPU seconds of one audit: on a shared machine the CPU time is the figure."""
    t0, c0 = time.perf_counter(), time.process_time()
    run_audit(session, AuditConfig(ChainConfig(gravity_mps2=gravity), replicas=replicas))
    return f"{time.perf_counter() - t0:6.1f} s wall, {time.process_time() - c0:6.1f} s CPU"


def wall_times(quick: bool) -> None:
    session = load_session(str(DATA)).session
    print(
        f"Xsens session: {session.n_samples} samples, {session.t_s[-1] - session.t_s[0]:.0f} s, one core"
    )
    for replicas in (5, 10) if quick else (5, 10, 20, 40):
        print(f"  full audit, {replicas:3d} replicas: {_timed(session, G_XSENS, replicas)}")
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
        print(f"  {n:3d} positions, {s.n_samples:7d} samples: {_timed(s, 9.80665, 10)}")


def _hit(args) -> bool:
    seed, size, kind, grade, temperature = args
    if kind[0] == "quantization" and size > 20.0:
        h = hide(seed, "quantization", kind[1], None, size, grade=grade)
    else:
        h = draw(seed, size, kind, grade)
    return trial(h, seed, temperature=temperature)


def _clean(args) -> bool:
    seed, grade, temperature = args
    return clean_trial(seed, temperature=temperature, grade=grade)


def hit_rates(
    trials: int, workers: int, grades: tuple[Grade, ...], sizes: tuple[float, ...] = SIZES
) -> None:
    print(
        f"Hit rate (exactly the hidden effect named) against size in detection standard errors, {trials} trials each:"
    )
    with ProcessPoolExecutor(workers) as pool:
        for grade in grades:
            print(f"  {grade.value} grade".ljust(50) + "".join(f"{s:>7.0f}" for s in sizes))
            for k, kind in enumerate(kinds_of(grade)):
                for temperature in (True, False):
                    if kind[0].startswith("temperature") and not temperature:
                        continue
                    rates = []
                    for size in sizes:
                        jobs = [
                            (100_000 + 1000 * k + t, size, kind, grade, temperature)
                            for t in range(trials)
                        ]
                        rates.append(np.mean(list(pool.map(_hit, jobs))))
                    label = (
                        f"{kind[0]} ({kind[1].value}){'' if temperature else ', no temp column'}"
                    )
                    print("    " + label.ljust(46) + "".join(f"{r:7.2f}" for r in rates))
            print(
                "    coarse grid, step in noise sd".ljust(50)
                + "".join(f"{s:>7.1f}" for s in COARSE_STEPS)
            )
            for temperature in (True, False):
                rates = []
                for step in COARSE_STEPS:
                    jobs = [
                        (
                            300_000 + t,
                            10.0 * step,
                            ("quantization", Triad.ACCEL),
                            grade,
                            temperature,
                        )
                        for t in range(trials)
                    ]
                    rates.append(np.mean(list(pool.map(_hit, jobs))))
                label = f"quantization (accel){'' if temperature else ', no temp column'}"
                print("    " + label.ljust(46) + "".join(f"{r:7.2f}" for r in rates))
            for temperature in (True, False):
                jobs = [(200_000 + t, grade, temperature) for t in range(5 * trials)]
                clean = list(pool.map(_clean, jobs))
                print(
                    f"    effect-free sessions naming nothing{'' if temperature else ', no temp column'}: "
                    f"{np.mean(clean):.3f} of {len(clean)}"
                )


def _pair(args) -> bool:
    seed, k = args
    return pair_trial(hide_pair(seed, *PAIRS[k], 10.0), seed)


def pair_rates(trials: int, workers: int) -> None:
    print(
        f"Two effects at 10 standard errors each (MEMS), both named and nothing else, {trials} trials:"
    )
    with ProcessPoolExecutor(workers) as pool:
        for k, (a, b) in enumerate(PAIRS):
            hits = list(pool.map(_pair, [(400_000 + 1000 * k + t, k) for t in range(trials)]))
            label = f"{a[0]} ({a[1].value} {a[2]}) + {b[0]} ({b[1].value} {b[2]})"
            print("    " + label.ljust(70) + f"{np.mean(hits):7.2f}")


LINE_SIZES = (0.5, 1.0, 1.5, 2.0)
"""Line amplitudes in per-sample noise sd (the issue's case: 1.5)."""


def _line(args) -> bool:
    seed, size = args
    return trial(draw(seed, size, LINE_KIND), seed)


def _clean_line_rate(seed: int) -> bool:
    return clean_trial(seed, temperature=seed % 2 == 0, rate_hz=LINE_RATE_HZ)


def line_rates(trials: int, workers: int) -> None:
    print(
        f"50 Hz line on accel, 200 Hz sessions, {trials} trials, against its amplitude in noise sd:"
    )
    with ProcessPoolExecutor(workers) as pool:
        rates = [
            np.mean(list(pool.map(_line, [(500_000 + t, size) for t in range(trials)])))
            for size in LINE_SIZES
        ]
        print("    " + "".join(f"{s:>7.1f}" for s in LINE_SIZES))
        print("    " + "".join(f"{r:7.2f}" for r in rates))
        clean = list(pool.map(_clean_line_rate, range(600_000, 600_000 + 2 * trials)))
        print(
            f"    effect-free 200 Hz sessions naming nothing: {np.mean(clean):.3f} of {len(clean)}"
        )


NEAR_LIMIT_SIZES = (4.0, 6.0, 10.0)
QUADRATIC_COEFS = (2.5e-5, 5e-5, 1e-4)
"""Quadratic temperature bias trials, m/s² per °C² about 30 °C (1e-4: 0.01 m/s² at the cycle's ends)."""


def _near_limit(args) -> tuple[bool, bool]:
    return near_limit_drift_named(*args)


def _quadratic(args) -> bool:
    seed, coef = args
    return quadratic_temperature_named(seed, AXES[seed % 3], coef)


def gyro_path_and_temperature_order_rates(trials: int, workers: int) -> None:
    print(
        f"Gyro x drift on each side of the nine-parameter σ limit (navigation unit, gyro noise "
        f"{NEAR_LIMIT_GYRO_SD_RPS[0]:g} and {NEAR_LIMIT_GYRO_SD_RPS[1]:g} rad/s), {trials} trials, against "
        "its size in the first's standard errors:"
    )
    with ProcessPoolExecutor(workers) as pool:
        for size in NEAR_LIMIT_SIZES:
            hits = np.array(
                list(pool.map(_near_limit, [(700_000 + t, size) for t in range(trials)]))
            )
            print(
                f"    {size:4.0f} SE: {hits[:, 0].mean():.2f} below the limit, {hits[:, 1].mean():.2f} above"
            )
        print(f"Quadratic accelerometer temperature bias (MEMS, 20–40 °C), {trials} trials:")
        for coef in QUADRATIC_COEFS:
            hits = list(pool.map(_quadratic, [(710_000 + t, coef) for t in range(trials)]))
            print(
                f"    {coef:g} m/s² per °C²: {np.mean(hits):.2f} named temperature_bias on its axis"
            )


MECHANISM_TABLE = (
    *((k, Grade.MEMS) for k in MECHANISM_KINDS),
    (("g_sensitivity", Triad.GYRO), Grade.MEMS),
    *((k, Grade.NAVIGATION) for k in (*GYRO_MECHANISM_KINDS, ("g_sensitivity", Triad.GYRO))),
)
"""The deterministic classes of issue 31 and the grade each is hidden at (a gyro's at the grade that resolves the Earth rate)."""


def mechanism_rates(trials: int, workers: int) -> None:
    print(
        f"Deterministic classes at 10 standard errors, named as their mechanism on their axis, {trials} trials:"
    )
    with ProcessPoolExecutor(workers) as pool:
        for k, (kind, grade) in enumerate(MECHANISM_TABLE):
            jobs = [(800_000 + 1000 * k + t, 10.0, kind, grade, True) for t in range(trials)]
            hits = list(pool.map(_hit, jobs))
            label = f"{kind[0]} ({kind[1].value}, {grade.value})"
            print("    " + label.ljust(50) + f"{np.mean(hits):7.2f}")
        for grade in (Grade.MEMS, Grade.NAVIGATION):
            clean = list(pool.map(_clean, [(200_000 + t, grade, True) for t in range(2 * trials)]))
            print(
                f"    effect-free {grade.value} sessions naming nothing: {sum(clean)} of {len(clean)}"
            )


def _shape(args) -> bool:
    k, seed = args
    return shape_trial(SHAPES[k], seed)


def shape_rates(trials: int, workers: int) -> None:
    print(
        f"Issue 31's session shapes, {trials} seeded sessions each: exactly what the shape holds named "
        "(nothing; the low-pass on both triads where it has one):"
    )
    with ProcessPoolExecutor(workers) as pool:
        for k, shape in enumerate(SHAPES):
            t0 = time.perf_counter()
            hits = list(pool.map(_shape, [(k, 800_000 + 1000 * k + t) for t in range(trials)]))
            print(
                "    "
                + shape.label.ljust(58)
                + f"{sum(hits):4d} of {trials}  ({time.perf_counter() - t0:.0f} s)"
            )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer replica counts, lengths and trials")
    ap.add_argument(
        "--trials", type=int, default=None, help="trials per kind and size (default 40, quick 8)"
    )
    ap.add_argument(
        "--workers", type=int, default=2, help="processes for the hit-rate sweep (default 2)"
    )
    ap.add_argument(
        "--grade",
        choices=[g.value for g in (Grade.MEMS, Grade.NAVIGATION)],
        action="append",
        help="grade of the hit-rate sweep (repeatable; default both)",
    )
    ap.add_argument(
        "--size",
        type=float,
        action="append",
        help="size of the hit-rate sweep in standard errors (repeatable; default 2-10)",
    )
    ap.add_argument("--no-times", action="store_true", help="skip the wall-time part")
    ap.add_argument("--no-rates", action="store_true", help="skip the hit-rate sweep")
    ap.add_argument(
        "--mechanisms",
        action="store_true",
        help="only the deterministic classes at 10 standard errors (default 20 trials) and effect-free sessions",
    )
    ap.add_argument(
        "--shapes",
        action="store_true",
        help="only issue 31's session shapes (--trials each, default 40)",
    )
    ap.add_argument(
        "--table",
        action="store_true",
        help="only the hit-rate table (classes, coarse grid, effect-free sessions; docs/audit-xsens.md)",
    )
    args = ap.parse_args()
    if args.mechanisms:
        mechanism_rates(args.trials or 20, args.workers)
        raise SystemExit(0)
    if args.shapes:
        shape_rates(args.trials or 40, args.workers)
        raise SystemExit(0)
    grades = tuple(Grade(g) for g in args.grade) if args.grade else (Grade.MEMS, Grade.NAVIGATION)
    sizes = tuple(args.size) if args.size else SIZES
    if args.table:
        hit_rates(args.trials or 40, args.workers, grades, sizes)
        raise SystemExit(0)
    if not args.no_times:
        wall_times(args.quick)
    if not args.no_rates:
        hit_rates(args.trials or (8 if args.quick else 40), args.workers, grades, sizes)
        pair_rates(args.trials or (8 if args.quick else 20), args.workers)
        line_rates(args.trials or (8 if args.quick else 20), args.workers)
        gyro_path_and_temperature_order_rates(
            args.trials or (8 if args.quick else 20), args.workers
        )
        shape_rates(args.trials or (8 if args.quick else 40), args.workers)
