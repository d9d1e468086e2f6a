"""The thresholds of the stream checks (:mod:`estimators.stream_validity`), alone: a session
file's and a passport's plausible sample rates and the service's options are bounded by them,
and reading a session (``calibrate``) needs no stream check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ValidityLimits:
    """Thresholds of the stream checks (defaults follow PX4 and ArduPilot).

    Attributes
    ----------
    timeout_s : no sample for this long → timeout (default 0.5 s: a companion link
        batches frames, so the autopilot's 20 ms would be noise).
    stale_run_samples : identical consecutive values on one axis → stale (default 100, PX4).
    error_window_samples : window of the error density, samples (default 100).
    error_density_max : bad fraction in that window above which the stream is flagged (default 0.1).
    cross_imu_accel_mps2 : mean specific-force disagreement limit, m/s² (default 0.75, ArduPilot).
    cross_imu_gyro_rps : mean angular-rate disagreement limit, rad/s (default 5 °/s = 0.0873, ArduPilot).
    cross_imu_window_s : length of the time bins compared, s (default 0.5).
    cross_imu_persist_windows : consecutive disagreeing bins before a report (default 4, i.e. 2 s).
    min_rate_hz, max_rate_hz : the plausible sample rates, Hz (default 0.5 to 10 kHz); a stream whose
        measured rate lies outside is refused (:func:`plausible_rate_hz`): detector windows and
        position buffers are sized in samples from the rate, so a rate from nonsense time stamps
        (sub-microsecond spacing) would size them in the millions.
    """

    timeout_s: float = 0.5
    stale_run_samples: int = 100
    error_window_samples: int = 100
    error_density_max: float = 0.1
    cross_imu_accel_mps2: float = 0.75
    cross_imu_gyro_rps: float = float(np.radians(5.0))
    cross_imu_window_s: float = 0.5
    cross_imu_persist_windows: int = 4
    min_rate_hz: float = 0.5
    max_rate_hz: float = 10_000.0

    def __post_init__(self) -> None:
        for name in (
            "timeout_s",
            "cross_imu_accel_mps2",
            "cross_imu_gyro_rps",
            "cross_imu_window_s",
            "min_rate_hz",
            "max_rate_hz",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        for name, least in (
            ("stale_run_samples", 2),
            ("error_window_samples", 2),
            ("cross_imu_persist_windows", 1),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        if not 0.0 < self.error_density_max < 1.0:
            raise ValueError(f"error_density_max must be in (0, 1), got {self.error_density_max!r}")
        if not self.min_rate_hz < self.max_rate_hz:
            raise ValueError(
                f"min_rate_hz must be below max_rate_hz, got {self.min_rate_hz!r} and {self.max_rate_hz!r}"
            )
