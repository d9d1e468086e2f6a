"""The pipeline's cost per frame, offline: what a frame costs the service's loop before any transport.

A resting unit (the demo passport, 1 kHz) is cut into frames of each size and
fed to one :class:`~service.pipeline.FleetProcessor` as ``--imus`` interleaved
IMUs of one vehicle, one frame of each per group through ``process_queued`` (as
the MAVLink reader hands them over: one batch per IMU every gather). The first
``WARMUP_S`` of the stream set up the chain (rate probe, static detector,
passport checks) and are not timed. Each size is timed ``--repeats`` times on
fresh pipelines, the sizes interleaved; the median is printed with the spread
(min–max) beside it: µs per frame, and samples/s of one core.

A frame's cost is a fixed part (each stage's numpy calls on a few rows) plus a
part per sample (the static detector and the positions, sample by sample below
``positions._MIN_VECTOR`` samples): the fixed part decides how many small-frame
IMUs a core takes (``deploy/SCALING.md``).

Run: ``python benchmarks/bench_pipeline_frames.py [--sizes 5 20 31 100] [--imus 4] [--seconds 10] [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.sim import simulate, static_spec  # noqa: E402
from protocols.frames import SampleBatch  # noqa: E402
from service.demo import demo_passport  # noqa: E402
from service.pipeline import FleetProcessor, PipelineOptions  # noqa: E402

RATE_HZ = 1000.0
WARMUP_S = 3.0
"""Seconds of each stream fed before the timing starts (the chain's set-up is not a frame's cost)."""


def groups_of(session, imus: int, size: int) -> list[list[SampleBatch]]:
    """The session in frames of ``size`` samples, one frame of each IMU per group."""
    out = []
    for k, start in enumerate(range(0, session.n_samples - size + 1, size)):
        sl = slice(start, start + size)
        out.append(
            [
                SampleBatch("bench", imu, k, session.t_s[sl], session.accel_mps2[sl], session.gyro_rps[sl], None)
                for imu in range(imus)
            ]
        )  # fmt: skip
    return out


def time_once(groups: list[list[SampleBatch]], passport, g: float, warmup: int) -> float:
    """Seconds per frame over the groups after ``warmup``, on fresh pipelines."""
    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
    )
    for group in groups[:warmup]:
        fleet.process_queued(group, arrival_s=float(group[-1].t_s[-1]))
    timed = groups[warmup:]
    t0 = time.perf_counter()
    for group in timed:
        fleet.process_queued(group, arrival_s=float(group[-1].t_s[-1]))
    return (time.perf_counter() - t0) / (len(timed) * len(timed[0]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--sizes", type=int, nargs="+", default=[5, 20, 31, 100], help="samples per frame"
    )
    ap.add_argument("--imus", type=int, default=4, help="interleaved IMUs of one vehicle")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds of stream timed per IMU")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    passport, g = demo_passport()
    rest = simulate(
        static_spec(duration_s=WARMUP_S + args.seconds, rate_hz=RATE_HZ, latitude_deg=45.0), seed=2
    ).session
    streams = {size: groups_of(rest, args.imus, size) for size in args.sizes}
    per_frame_s: dict[int, list[float]] = {size: [] for size in args.sizes}
    for r in range(args.repeats):
        for size in args.sizes:
            per_frame_s[size].append(
                time_once(streams[size], passport, g, warmup=int(WARMUP_S * RATE_HZ) // size)
            )
        print(f"  repeat {r + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    print(
        f"pipeline cost per frame, offline: {args.imus} interleaved IMUs of a resting unit at "
        f"{RATE_HZ:.0f} Hz, {args.seconds:g} s timed, median of {args.repeats} (min-max)"
    )
    print("  samples/frame   us/frame (min-max)        samples/s of one core")
    for size in args.sizes:
        v = np.array(per_frame_s[size]) * 1e6
        print(
            f"  {size:13d}   {np.median(v):8.0f} ({v.min():5.0f}-{v.max():5.0f})"
            f"        {size / np.median(v) * 1e6:10.0f}"
        )


if __name__ == "__main__":
    main()
