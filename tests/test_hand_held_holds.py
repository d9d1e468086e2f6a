"""Hand-held holds are positions (issue 30, item 3; the rule: estimators/static_detector.py,
"Hand-held holds"): a bench rest then poses held in the hand with tremor, 1.5–7 s each.

The oracles: the simulator's schedule for a generated session (tests/hand_held.py), and for the
shared MPU-6050 session the static intervals its author's own tool found (Tedaldi's method,
``static_intervals.csv``: start and end rows).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimators.sim import Grade, multi_position_spec, simulate
from estimators.static_detector import StaticDetectorConfig, detect_static
from protocols.session_file import SessionUnits, load_session
from tests.hand_held import HOLDS_S, hand_posed_session
from tests.real_data import MPU6050, MPU6050_SESSION, needs

MPU_UNITS = SessionUnits("g", "deg/s", None, 1 / 16384, 1 / 131)
"""SOURCE.md: ±2 g at 16,384 counts per g, ±250 °/s at 131 counts per °/s."""


def _one_to_one(found: list[tuple[float, float]], truth: list[tuple[float, float]]) -> bool:
    """Each true hold lies inside exactly one found interval, and each found interval holds one."""
    inside = np.array([[f0 <= t0 and t1 <= f1 for f0, f1 in found] for t0, t1 in truth])
    return bool(np.all(inside.sum(axis=0) == 1) and np.all(inside.sum(axis=1) == 1))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_every_trembling_hold_of_a_generated_session_is_a_static_interval(seed):
    """Ten orientations, the holds trimmed by the window (half a window at each end, as a bench
    rest's): every one found, one interval each, and nothing in the turns."""
    sim = hand_posed_session(seed)
    detection = detect_static(sim.session, config=StaticDetectorConfig.from_session(sim.session))
    found = [(iv.t_start_s, iv.t_end_s) for iv in detection.intervals]
    trimmed = [(t0 + 0.25, t1 - 0.25) for t0, t1 in sim.truth.static_intervals_s.tolist()]
    assert len(found) == len(HOLDS_S) == 10
    assert _one_to_one(found, trimmed)


@needs(MPU6050_SESSION)
def test_the_mpu6050_session_gives_its_ten_orientations_as_its_author_found_them():
    """Without options: ten intervals, each of the author's inside one of ours (his tool keeps
    only the stretches its own threshold passes: 0.02–34.6 s of holds of 2–37 s)."""
    session = load_session(MPU6050_SESSION, units=MPU_UNITS).session
    detection = detect_static(session, config=StaticDetectorConfig.from_session(session))
    starts, ends = np.loadtxt(MPU6050 / "static_intervals.csv", delimiter=",")
    theirs = [(float(a), float(b)) for a, b in zip(starts, ends, strict=True)]
    ours = [(float(iv.start), float(iv.stop - 1)) for iv in detection.intervals]
    assert len(ours) == len(theirs) == 10
    assert _one_to_one(ours, theirs)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_knock_on_the_bench_is_no_tremor(seed):
    """A bench session (navigation grade, 18 rests of 10 s) whose gyros shake for 0.6 s in one rest
    (0.005 rad/s, the accelerometers untouched): two windows of one rest, no hold that trembles.
    The thresholds stay the bench's; taken for tremor they rose 37-fold for the whole session and
    the gyro fit lost its observability (seed 1) or its residual grew 40-fold (seed 2)."""
    sim = simulate(multi_position_spec(grade=Grade.NAVIGATION, static_s=10.0, n_positions=18), seed)
    s = sim.session
    t0 = sim.truth.static_intervals_s[5][0] + 3.0
    knock = (s.t_s >= t0) & (s.t_s < t0 + 0.6)
    gyro = s.gyro_rps.copy()
    gyro[knock] += np.random.default_rng(seed).normal(scale=0.005, size=(knock.sum(), 3))
    bench = StaticDetectorConfig.from_session(s)
    knocked = StaticDetectorConfig.from_session(dataclasses.replace(s, gyro_rps=gyro))
    # The knock's windows move the median of the quiet windows' spreads by < 0.1 %.
    assert knocked.gyro_std_rps == pytest.approx(bench.gyro_std_rps, rel=1e-2)
    assert knocked.gyro_rate_rps == pytest.approx(bench.gyro_rate_rps, rel=1e-2)
