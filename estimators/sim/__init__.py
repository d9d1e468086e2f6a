"""IMU session simulator (methods.md M1, M2): truth, error model, faults.

Typical use::

    from estimators.sim import Grade, multi_position_spec, simulate
    res = simulate(multi_position_spec(grade=Grade.MEMS), seed=7)
    res.session           # estimators.session.ImuSession, SI
    res.truth.accel_params  # the exact nine parameters [b, e, d]

Modules: :mod:`~estimators.sim.motion` (true motion), :mod:`~estimators.sim.errors`
(effect chains, with the effect names of the model audit),
:mod:`~estimators.sim.faults`, :mod:`~estimators.sim.temperature`,
:mod:`~estimators.sim.grades` (MEMS and navigation-grade presets),
:mod:`~estimators.sim.scenarios` (ready-made specs) and
:mod:`~estimators.sim.session` (:func:`simulate`).
"""

from estimators.conventions import Grade

from .errors import (
    EFFECTS,
    Bias,
    BiasDrift,
    BiasInstability,
    ColouredNoise,
    Effect,
    EffectContext,
    EnvironmentEffect,
    ErrorModel,
    GravityMismatch,
    GSensitivity,
    NonOrthogonality,
    NonstaticPositions,
    Quantization,
    Rounding,
    ScaleFactor,
    ScaleNonlinearity,
    TemperatureBias,
    TemperatureScale,
    TriadErrorModel,
    WhiteNoise,
    effect_params,
    half_pulse_correction,
    make_effect,
)
from .faults import Fault, FaultKind
from .grades import GRADES, GradeSpec, TriadGrade, grade_error_model
from .motion import (
    Fly,
    Hold,
    Motion,
    MotionProfile,
    Spin,
    Turn,
    attitude_with_up,
    build_motion,
    eighteen_position_attitudes,
    flight_profile,
    multi_position_profile,
    random_attitudes,
    static_profile,
    tilt_sequence,
)
from .scenarios import (
    PAIR_LEVER_ARM_M,
    PAIR_MOUNT_ZX_DEG,
    OrientationScheme,
    flight_spec,
    multi_position_spec,
    pair_flight_specs,
    position_attitudes,
    second_imu,
    static_spec,
)
from .session import Mounting, SessionSpec, SimResult, Truth, earth_rate_n_rps, simulate
from .temperature import (
    ConstantTemperature,
    CycleTemperature,
    RampTemperature,
    RecordedTemperature,
    TemperatureProfile,
    WarmupTemperature,
)

__all__ = [
    "EFFECTS",
    "GRADES",
    "PAIR_LEVER_ARM_M",
    "PAIR_MOUNT_ZX_DEG",
    "Bias",
    "BiasDrift",
    "BiasInstability",
    "ColouredNoise",
    "ConstantTemperature",
    "CycleTemperature",
    "Effect",
    "EffectContext",
    "EnvironmentEffect",
    "ErrorModel",
    "Fault",
    "FaultKind",
    "Fly",
    "GSensitivity",
    "Grade",
    "GradeSpec",
    "GravityMismatch",
    "Hold",
    "Motion",
    "MotionProfile",
    "Mounting",
    "NonOrthogonality",
    "NonstaticPositions",
    "OrientationScheme",
    "Quantization",
    "RampTemperature",
    "RecordedTemperature",
    "Rounding",
    "ScaleFactor",
    "ScaleNonlinearity",
    "SessionSpec",
    "SimResult",
    "Spin",
    "TemperatureBias",
    "TemperatureProfile",
    "TemperatureScale",
    "TriadErrorModel",
    "TriadGrade",
    "Truth",
    "Turn",
    "WarmupTemperature",
    "WhiteNoise",
    "attitude_with_up",
    "build_motion",
    "earth_rate_n_rps",
    "effect_params",
    "eighteen_position_attitudes",
    "flight_profile",
    "flight_spec",
    "grade_error_model",
    "half_pulse_correction",
    "make_effect",
    "multi_position_profile",
    "multi_position_spec",
    "pair_flight_specs",
    "position_attitudes",
    "random_attitudes",
    "second_imu",
    "simulate",
    "static_profile",
    "static_spec",
    "tilt_sequence",
]
