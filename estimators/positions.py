"""Static positions: the averaged outputs of one static interval (methods.md M1).

M1 averages the outputs of each fixed position so the noise mean vanishes, and
stacks one scalar equation per position. A :class:`Position` carries that
average together with what the estimators and the audit need to weigh it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Position:
    """One static position of the unit.

    Attributes
    ----------
    t_start_s, t_end_s : time span of the static interval, s.
    n_samples : number of samples averaged.
    accel_mean_mps2 : (3,) mean specific force, m/s², sensor axes (None without that triad).
    accel_cov_mps2 : (3, 3) covariance of that *mean*, (m/s²)².
    gyro_mean_rps : (3,) mean angular rate, rad/s (None without that triad).
    gyro_cov_rps : (3, 3) covariance of that mean, (rad/s)².
    temp_mean_c : mean temperature, °C, or None.
    """

    t_start_s: float
    t_end_s: float
    n_samples: int
    accel_mean_mps2: np.ndarray | None
    accel_cov_mps2: np.ndarray | None
    gyro_mean_rps: np.ndarray | None
    gyro_cov_rps: np.ndarray | None
    temp_mean_c: float | None = None

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s
