"""A generated hand-posed multi-position session, as a user makes one with a cheap IMU and no
fixture: a bench rest, then nine poses held in the hand (1.5–7 s each), ten orientations in all
(the six faces and four tilts), the shape of the shared MPU-6050 session (``../shared/data/field/mpu6050-multiposition``).

The hand's tremor is the simulator's :class:`~estimators.sim.errors.NonstaticPositions` (a
wobble of 1 mrad RMS at 1–6 Hz: gyro window spreads of about 0.02 rad/s, as that session's holds
show); the bench rest is the same session simulated without it (the simulator draws each effect
from its own stream, so the two differ by the tremor alone), spliced in mid-way through the first
turn.
"""

from __future__ import annotations

import numpy as np

from estimators.sim import Grade, NonstaticPositions, SessionSpec, SimResult, simulate
from estimators.sim.grades import grade_error_model
from estimators.sim.motion import attitude_with_up, multi_position_profile

UP_VECTORS = (
    (0.01, -0.05, 1),
    (0.08, 0.02, -1),
    (1, -0.04, -0.06),
    (-1, -0.06, -0.18),
    (0.02, -1, -0.05),
    (0.06, 1, -0.11),
    (0.02, 1, 0.93),
    (-0.03, -0.86, 1),
    (-1, -0.04, 0.41),
    (0.67, -0.02, 1),
)
"""Ten orientations, as the MPU-6050 session's (its mean specific-force directions, rounded): the
bench rest (z up), then the other five faces, posed by hand 3–10° off, and four tilts."""
HOLDS_S = (30.0, 2.5, 1.5, 3.5, 4.0, 2.0, 4.0, 5.0, 3.0, 7.0)
TURN_S = 3.0
TREMOR = NonstaticPositions(angle_rms_rad=1e-3, band_hz=(1.0, 6.0), ramp_s=0.2)


def hand_posed_session(
    seed: int,
    *,
    grade: Grade = Grade.MEMS,
    tremor: bool = True,
    poses: slice = slice(None),
) -> SimResult:
    """The session with a quiet bench rest and trembling holds (``tremor``; else all quiet), of
    the ``poses`` of :data:`UP_VECTORS`; ``truth`` is the trembling one's."""
    attitudes = np.stack([attitude_with_up(u) for u in UP_VECTORS[poses]])
    holds = np.array(HOLDS_S[poses])
    profile = multi_position_profile(attitudes, static_s=holds, transition_s=TURN_S)
    model = grade_error_model(grade)
    quiet = simulate(SessionSpec(profile, model), seed)
    if not tremor:
        return quiet
    shaky = simulate(SessionSpec(profile, model.with_effect(TREMOR)), seed)
    cut = int(np.searchsorted(shaky.session.t_s, HOLDS_S[0] + 0.5 * TURN_S))
    for name in ("accel_mps2", "gyro_rps"):
        getattr(shaky.session, name)[:cut] = getattr(quiet.session, name)[:cut]
    return shaky
