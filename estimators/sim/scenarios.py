"""Ready-made session specs: multi-position calibration, long static, flight.

These are what the tests, the demo and the benchmarks start from; every
argument is keyword-only and has a typical default.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray
from estimators.conventions import Grade

from .errors import ErrorModel
from .faults import Fault
from .grades import grade_error_model
from .motion import (
    Fly,
    MotionProfile,
    eighteen_position_attitudes,
    flight_profile,
    multi_position_profile,
    random_attitudes,
    static_profile,
)
from .session import Mounting, SessionSpec
from .temperature import TemperatureProfile


class OrientationScheme(StrEnum):
    """How the positions of a multi-position session are chosen."""

    EIGHTEEN = "eighteen"
    """The 18-position scheme (6 faces and 12 edges at 45°), first ``n`` of them."""
    RANDOM = "random"
    """Attitudes uniform over the rotation group."""


def position_attitudes(
    n_positions: int,
    *,
    scheme: OrientationScheme = OrientationScheme.EIGHTEEN,
    heading_rad: float = 0.0,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """(n, 3, 3) attitudes of ``n_positions`` positions.

    EIGHTEEN allows up to 18 positions, with ``heading_rad`` about the up axis;
    RANDOM needs ``rng``.
    """
    scheme = OrientationScheme(scheme)
    if scheme is OrientationScheme.EIGHTEEN:
        if not 1 <= n_positions <= 18:
            raise ValueError(f"the 18-position scheme has 1 to 18 positions, got {n_positions}")
        return eighteen_position_attitudes(heading_rad)[:n_positions]
    if rng is None:
        raise ValueError("random orientations need a numpy Generator (rng)")
    return random_attitudes(n_positions, rng)


def _spec(
    profile: MotionProfile,
    grade: Grade,
    model: ErrorModel | None,
    rate_hz: float,
    latitude_deg: float,
    height_m: float,
    gravity_mps2: float | None,
    temperature: TemperatureProfile | None,
    faults: Sequence[Fault],
) -> SessionSpec:
    """``profile`` as a :class:`SessionSpec`, with the grade's fixed preset unless ``model`` is given."""
    return SessionSpec(
        profile,
        grade_error_model(grade) if model is None else model,
        rate_hz=rate_hz,
        latitude_deg=latitude_deg,
        height_m=height_m,
        gravity_mps2=gravity_mps2,
        temperature=temperature,
        faults=tuple(faults),
    )


def multi_position_spec(
    *,
    grade: Grade = Grade.MEMS,
    model: ErrorModel | None = None,
    n_positions: int = 18,
    scheme: OrientationScheme = OrientationScheme.EIGHTEEN,
    orientation_rng: np.random.Generator | None = None,
    heading_rad: float = 0.0,
    static_s: float | FloatArray = 20.0,
    transition_s: float | FloatArray = 4.0,
    first_static_s: float | None = None,
    rate_hz: float = 100.0,
    latitude_deg: float = 45.0,
    height_m: float = 0.0,
    gravity_mps2: float | None = None,
    temperature: TemperatureProfile | None = None,
    faults: Sequence[Fault] = (),
) -> SessionSpec:
    """A multi-position session (methods.md M1's diagnosis geometry).

    ``model`` defaults to the grade's fixed preset
    (:func:`~estimators.sim.grades.grade_error_model`); lengths as in
    :func:`~estimators.sim.motion.multi_position_profile`. With the defaults: 18
    positions of 20 s, 4 s turns, 100 Hz: 428 s, 42,800 samples.
    """
    att = position_attitudes(
        n_positions, scheme=scheme, heading_rad=heading_rad, rng=orientation_rng
    )
    profile = multi_position_profile(
        att, static_s=static_s, transition_s=transition_s, first_static_s=first_static_s
    )
    return _spec(
        profile, grade, model, rate_hz, latitude_deg, height_m, gravity_mps2, temperature, faults
    )


def static_spec(
    *,
    duration_s: float = 600.0,
    grade: Grade = Grade.MEMS,
    model: ErrorModel | None = None,
    mat_nb: FloatArray | None = None,
    rate_hz: float = 100.0,
    latitude_deg: float = 45.0,
    height_m: float = 0.0,
    gravity_mps2: float | None = None,
    temperature: TemperatureProfile | None = None,
    faults: Sequence[Fault] = (),
) -> SessionSpec:
    """One long static interval (noise studies, Allan deviation, warm-up)."""
    return _spec(
        static_profile(duration_s, mat_nb),
        grade,
        model,
        rate_hz,
        latitude_deg,
        height_m,
        gravity_mps2,
        temperature,
        faults,
    )


def flight_spec(
    *,
    fly: Fly = Fly(120.0),
    rest_s: float = 10.0,
    grade: Grade = Grade.MEMS,
    model: ErrorModel | None = None,
    rate_hz: float = 100.0,
    latitude_deg: float = 45.0,
    height_m: float = 0.0,
    gravity_mps2: float | None = None,
    temperature: TemperatureProfile | None = None,
    faults: Sequence[Fault] = (),
) -> SessionSpec:
    """Rest level, fly the :class:`~estimators.sim.motion.Fly` segment ``fly``, rest again."""
    return _spec(
        flight_profile(fly, rest_s=rest_s),
        grade,
        model,
        rate_hz,
        latitude_deg,
        height_m,
        gravity_mps2,
        temperature,
        faults,
    )


def second_imu(
    spec: SessionSpec,
    *,
    lever_arm_b_m: ArrayLike,
    mat_sb: ArrayLike,
    model: ErrorModel | None = None,
    faults: Sequence[Fault] = (),
    unit: str = "imu1",
) -> SessionSpec:
    """A second IMU on the vehicle of ``spec``: the same motion (same seed), its own place and turn
    (:class:`~estimators.sim.session.Mounting`), errors (``model``, default ``spec``'s) and faults, and
    noise of its own (``unit``)."""
    return replace(
        spec,
        mounting=Mounting(lever_arm_b_m, mat_sb),
        unit=unit,
        model=spec.model if model is None else model,
        faults=tuple(faults),
    )


PAIR_LEVER_ARM_M = (0.06, -0.04, 0.03)
"""The two-IMU flight's lever arm, m, body axes (7.8 cm)."""
PAIR_MOUNT_ZX_DEG = (30.0, 90.0)
"""The two-IMU flight's second unit turned 30° about body z, then 90° about x: body z (the thrust)
falls on its y axis."""


def pair_flight_specs(
    *,
    fly_s: float,
    rest_s: float = 10.0,
    mat_sb: ArrayLike | None = None,
    faults: Sequence[Fault] = (),
) -> tuple[SessionSpec, SessionSpec]:
    """Two IMUs on one vehicle flying :func:`flight_spec` (MEMS, 100 Hz): IMU 0 at the body point,
    IMU 1 at :data:`PAIR_LEVER_ARM_M` turned by ``mat_sb`` (default :data:`PAIR_MOUNT_ZX_DEG`) with
    ``faults`` and noise of its own; :func:`~estimators.sim.session.simulate` both with the same seed."""
    from scipy.spatial.transform import Rotation

    if mat_sb is None:
        mat_sb = Rotation.from_euler("zx", PAIR_MOUNT_ZX_DEG, degrees=True).as_matrix()
    spec0 = flight_spec(fly=Fly(fly_s), rest_s=rest_s)
    return spec0, second_imu(spec0, lever_arm_b_m=PAIR_LEVER_ARM_M, mat_sb=mat_sb, faults=faults)
