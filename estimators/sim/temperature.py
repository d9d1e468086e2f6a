"""Temperature profiles of a simulated session (the input of methods.md M3's polynomials).

Each profile is a frozen dataclass with ``temp_c(t_s)``: time ``t_s`` (N,) in
seconds from the session start → temperature (N,) in °C. A profile that is not
monotone in time (:class:`CycleTemperature`) is what separates temperature
effects from time effects (issue 4). :class:`RecordedTemperature` replays a
measured record (the model audit re-simulates a session on its own thermal
history, issue 13).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators._typing import FloatArray


def _finite(name: str, value: float) -> None:
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")


@dataclass(frozen=True)
class ConstantTemperature:
    """``T(t) = temp_c``."""

    temp_c: float = 20.0

    def __post_init__(self) -> None:
        _finite("temp_c", self.temp_c)

    def temp_c_at(self, t_s: FloatArray) -> FloatArray:
        return np.full(np.shape(t_s), float(self.temp_c))


@dataclass(frozen=True)
class RampTemperature:
    """Linear from ``start_c`` at t = 0 at ``rate_c_per_s``."""

    start_c: float = 20.0
    rate_c_per_s: float = 0.01

    def __post_init__(self) -> None:
        _finite("start_c", self.start_c)
        _finite("rate_c_per_s", self.rate_c_per_s)

    def temp_c_at(self, t_s: FloatArray) -> FloatArray:
        return self.start_c + self.rate_c_per_s * np.asarray(t_s, float)


@dataclass(frozen=True)
class WarmupTemperature:
    """Self-heating after switch-on: ``T = final − (final − start)·exp(−t / tau_s)``."""

    start_c: float = 20.0
    final_c: float = 35.0
    tau_s: float = 300.0

    def __post_init__(self) -> None:
        _finite("start_c", self.start_c)
        _finite("final_c", self.final_c)
        if not np.isfinite(self.tau_s) or self.tau_s <= 0:
            raise ValueError(f"tau_s must be positive, got {self.tau_s!r}")

    def temp_c_at(self, t_s: FloatArray) -> FloatArray:
        return self.final_c - (self.final_c - self.start_c) * np.exp(
            -np.asarray(t_s, float) / self.tau_s
        )


@dataclass(frozen=True)
class CycleTemperature:
    """Heat up and cool down: ``T = base + (peak − base)·(1 − cos(2π t / period_s)) / 2``.

    Not monotone: the same temperature recurs at different times.
    """

    base_c: float = 20.0
    peak_c: float = 40.0
    period_s: float = 600.0

    def __post_init__(self) -> None:
        _finite("base_c", self.base_c)
        _finite("peak_c", self.peak_c)
        if not np.isfinite(self.period_s) or self.period_s <= 0:
            raise ValueError(f"period_s must be positive, got {self.period_s!r}")

    def temp_c_at(self, t_s: FloatArray) -> FloatArray:
        phase = 2.0 * np.pi * np.asarray(t_s, float) / self.period_s
        return self.base_c + (self.peak_c - self.base_c) * 0.5 * (1.0 - np.cos(phase))


@dataclass(frozen=True, eq=False)
class RecordedTemperature:
    """A measured temperature record replayed: linear interpolation of ``temp_c`` (K,) at ``t_s`` (K,).

    ``t_s`` is time from the session start, s, strictly increasing; before the
    first and after the last time the record holds its end value (no
    extrapolation of a thermal history nobody measured).
    """

    t_s: FloatArray
    temp_c: FloatArray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        temp = np.asarray(self.temp_c, float)
        if t.ndim != 1 or t.shape != temp.shape or t.size < 1:
            raise ValueError(
                f"t_s and temp_c must be two equal non-empty 1-D arrays, got shapes {t.shape} and {temp.shape}"
            )
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(temp))):
            raise ValueError("a temperature record must be finite")
        if np.any(np.diff(t) <= 0):
            raise ValueError("the times of a temperature record must be strictly increasing")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "temp_c", temp)

    def temp_c_at(self, t_s: FloatArray) -> FloatArray:
        out: FloatArray = np.interp(np.asarray(t_s, float), self.t_s, self.temp_c)
        return out


TemperatureProfile = (
    ConstantTemperature
    | RampTemperature
    | WarmupTemperature
    | CycleTemperature
    | RecordedTemperature
)
