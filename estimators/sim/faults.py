"""Faults injected into a simulated session at a given time.

A fault is data (:class:`Fault`); the simulator applies it and the truth keeps
it. Two families:

* parameter faults (:attr:`FaultKind.STEP`, :attr:`FaultKind.RAMP`) change one
  of the nine parameters of a triad (order :data:`estimators.conventions.PARAM_NAMES`,
  units of that parameter: normalized bias, relative scale error, cosine between
  sensitive axes) from ``t_start_s`` on; the error model applies the change where
  the parameter acts (see :mod:`estimators.sim.errors`);
* output faults act on one sensor axis of the output: a stuck axis, a noise
  burst, saturation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from estimators._typing import BoolArray, FloatArray
from estimators.conventions import N_PARAMS, PARAM_NAMES, Triad


class FaultKind(StrEnum):
    """What a fault does (``magnitude`` unit in brackets)."""

    STEP = "step"
    """Parameter ``index`` changes by ``magnitude`` (its own unit) at ``t_start_s``, for ``duration_s``."""
    RAMP = "ramp"
    """Parameter ``index`` drifts linearly by ``magnitude`` over ``duration_s`` (finite), then holds."""
    STUCK = "stuck"
    """Axis ``index`` holds the output it had at onset, plus ``magnitude`` (SI), for ``duration_s``."""
    NOISE_BURST = "noise_burst"
    """Axis ``index`` gets extra white noise of standard deviation ``magnitude`` (SI) for ``duration_s``."""
    SATURATION = "saturation"
    """Axis ``index`` is clipped to ±``magnitude`` (SI, full scale, > 0) for ``duration_s``."""


PARAMETER_FAULTS = (FaultKind.STEP, FaultKind.RAMP)


@dataclass(frozen=True)
class Fault:
    """One injected fault.

    Attributes
    ----------
    kind : what happens (:class:`FaultKind`).
    triad : the triad hit.
    index : parameter index 0…8 for STEP/RAMP, sensor axis 0…2 otherwise.
    t_start_s : onset, s (session time).
    magnitude : size, in the unit :class:`FaultKind` states.
    duration_s : how long it lasts, s (``inf``: to the end); a RAMP's rise time.
    """

    kind: FaultKind
    triad: Triad
    index: int
    t_start_s: float
    magnitude: float
    duration_s: float = math.inf

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", FaultKind(self.kind))
        object.__setattr__(self, "triad", Triad(self.triad))
        limit = N_PARAMS if self.kind in PARAMETER_FAULTS else 3
        if not isinstance(self.index, (int, np.integer)) or not 0 <= self.index < limit:
            raise ValueError(
                f"{self.kind.value} fault index must be an integer in [0, {limit}), got {self.index!r}"
            )
        object.__setattr__(self, "index", int(self.index))
        if not np.isfinite(self.t_start_s):
            raise ValueError(f"fault t_start_s must be finite, got {self.t_start_s!r}")
        if not np.isfinite(self.magnitude):
            raise ValueError(f"fault magnitude must be finite, got {self.magnitude!r}")
        if not self.duration_s > 0:
            raise ValueError(f"fault duration_s must be positive, got {self.duration_s!r}")
        if self.kind is FaultKind.RAMP and not np.isfinite(self.duration_s):
            raise ValueError("a ramp fault needs a finite duration_s (its rise time)")
        if self.kind in (FaultKind.SATURATION, FaultKind.NOISE_BURST) and self.magnitude <= 0:
            raise ValueError(
                f"{self.kind.value} fault magnitude must be positive, got {self.magnitude!r}"
            )

    @property
    def target(self) -> str:
        """The parameter name (STEP/RAMP) or axis name hit."""
        return PARAM_NAMES[self.index] if self.kind in PARAMETER_FAULTS else "xyz"[self.index]

    def active(self, t_s: FloatArray) -> BoolArray:
        """(N,) True where the fault acts (a RAMP holds its end value after the rise)."""
        t = np.asarray(t_s, float)
        if self.kind is FaultKind.RAMP:
            return t >= self.t_start_s
        return (t >= self.t_start_s) & (t < self.t_start_s + self.duration_s)

    def profile(self, t_s: FloatArray) -> FloatArray:
        """(N,) size of the fault at each time (0 where inactive)."""
        t = np.asarray(t_s, float)
        if self.kind is FaultKind.RAMP:
            return self.magnitude * np.clip((t - self.t_start_s) / self.duration_s, 0.0, 1.0)
        return np.where(self.active(t), self.magnitude, 0.0)


def faults_of(faults: tuple[Fault, ...], triad: Triad) -> tuple[Fault, ...]:
    return tuple(f for f in faults if f.triad is Triad(triad))


def param_deltas(faults: tuple[Fault, ...], triad: Triad, t_s: FloatArray) -> FloatArray | None:
    """(N, 9) change of the nine parameters of ``triad`` at each sample, or None without parameter faults."""
    mine = [f for f in faults_of(faults, triad) if f.kind in PARAMETER_FAULTS]
    if not mine:
        return None
    out = np.zeros((np.size(t_s), N_PARAMS))
    for f in mine:
        out[:, f.index] += f.profile(t_s)
    return out


def add_noise_bursts(
    y: FloatArray, faults: tuple[Fault, ...], t_s: FloatArray, rng: np.random.Generator
) -> FloatArray:
    """``y`` (N, 3) with the NOISE_BURST faults' extra noise added (a new array)."""
    out = y.copy()
    for f in faults:
        if f.kind is FaultKind.NOISE_BURST:
            m = f.active(t_s)
            out[m, f.index] += f.magnitude * rng.standard_normal(int(m.sum()))
    return out


def apply_output_faults(y: FloatArray, faults: tuple[Fault, ...], t_s: FloatArray) -> FloatArray:
    """``y`` (N, 3) with STUCK and SATURATION faults applied, in the order given (a new array).

    A stuck axis holds the last output before onset (the first sample's if the
    fault starts at or before it).
    """
    out = y.copy()
    for f in faults:
        m = f.active(t_s)
        if not m.any():
            continue
        if f.kind is FaultKind.STUCK:
            first = int(np.argmax(m))
            out[m, f.index] = out[max(first - 1, 0), f.index] + f.magnitude
        elif f.kind is FaultKind.SATURATION:
            out[m, f.index] = np.clip(out[m, f.index], -f.magnitude, f.magnitude)
    return out
