"""Resident memory of the pipeline over one hour of 1 kHz data (it must stay flat).

One IMU, 3.6 million samples, replayed through the daemon's pipeline
(:class:`service.pipeline.FleetProcessor`, arrival clock = data time, as
``ins-health replay`` does) in frames of 1000 samples. The hour is simulated a
minute at a time (ten static positions per minute, the MEMS unit of the demo),
so the generator's own memory does not grow either. Printed: resident set size
(RSS, from ``/proc/self/statm``) every ten minutes of data, its slope over the
second half hour, the positions accumulated, and the size of the unit's
checkpoint (the per-IMU state).

Run: ``python benchmarks/bench_replay_memory.py``.
"""

from __future__ import annotations

import gc
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.sim import Grade as SimGrade  # noqa: E402
from estimators.sim import Hold, MotionProfile, SessionSpec, grade_error_model, simulate  # noqa: E402
from estimators.sim.motion import eighteen_position_attitudes  # noqa: E402
from protocols.checkpoint_codec import encode_state  # noqa: E402
from protocols.frames import SampleBatch  # noqa: E402
from service.demo import DEMO_LATITUDE_DEG, demo_passport, handling_segments  # noqa: E402
from service.pipeline import FleetProcessor, PipelineOptions  # noqa: E402

RATE_HZ = 1000.0
MINUTES = 60
FRAME = 1000


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def minute(k: int):
    """Minute ``k`` of the hour: ten positions of the 18-position scheme (6 s, then 4 s each after 2 s turns), from 60 k s."""
    att = eighteen_position_attitudes(heading_rad=0.3 * k)
    segments = [Hold(6.0), *handling_segments(att[1:10], hold_s=4.0, turn_s=2.0)]
    spec = SessionSpec(MotionProfile(att[0], tuple(segments)), grade_error_model(SimGrade.MEMS), rate_hz=RATE_HZ,
                       latitude_deg=DEMO_LATITUDE_DEG, t0_s=60.0 * k)  # fmt: skip
    return simulate(spec, seed=100 + k).session


def main() -> None:
    passport, g = demo_passport()
    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
    )
    samples, events, seq = 0, 0, 0
    marks = []
    t0 = time.perf_counter()
    for k in range(MINUTES):
        s = minute(k)
        keep = s.t_s < 60.0 * (k + 1)  # each minute ends before the next begins
        for i in range(0, int(keep.sum()), FRAME):
            sl = slice(i, min(int(keep.sum()), i + FRAME))
            batch = SampleBatch("hour", 0, seq, s.t_s[sl], s.accel_mps2[sl], s.gyro_rps[sl])
            events += len(fleet.process(batch, arrival_s=float(batch.t_s[-1])))
            seq += 1
        samples += int(keep.sum())
        del s
        gc.collect()
        marks.append((k + 1, rss_mb()))
    wall = time.perf_counter() - t0
    pipe = fleet.pipelines[("hour", 0)]
    state = encode_state(pipe.state_dict())
    minutes = np.array([m for m, _ in marks], dtype=float)
    rss = np.array([r for _, r in marks])
    half = minutes > MINUTES / 2
    slope = np.polyfit(minutes[half], rss[half], 1)[0] * 60.0
    print(
        f"one hour of 1 kHz data through the pipeline ({samples:,} samples, frames of {FRAME}, one IMU)"
    )
    print(
        "  RSS by minutes of data: "
        + "  ".join(f"{m:.0f}: {r:.1f} MB" for m, r in marks if m % 10 == 0 or m == 1)
    )
    print(
        f"  slope over the second half hour: {slope:+.2f} MB per hour of data (flat: |slope| well under 1 MB/h)"
    )
    print(
        f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.1f} MB; {pipe.n_positions} positions kept in the estimate, {events} events"
    )
    print(f"  per-IMU state (checkpoint, msgpack): {len(state) / 1024:.1f} kB")
    print(f"  wall {wall:.0f} s ({samples / wall / 1e3:.1f} k samples/s, simulation included)")


if __name__ == "__main__":
    main()
