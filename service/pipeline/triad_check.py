"""F0 and the diagnosis of one triad against its passport (package docstring, steps 3, 5 and 6):
the state :class:`~service.pipeline.imu_pipeline.ImuPipeline` keeps per triad, F0's configuration
derived from the passport, and the recursive estimator of the diagnosis."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimators.conventions import (
    Triad,
)
from estimators.ninepar import RecursiveNineParam, canonical_triad_matrix
from estimators.passport import TriadPassport
from estimators.scalar import F0Config, Lambda0, derive_lambda0, lambda0_lower_bound
from service.pipeline.options import (
    F0_SHELL_LIMIT,
    PipelineOptions,
)


@dataclass
class TriadCheck:
    """F0 and the diagnosis of one triad against its passport."""

    passport: TriadPassport
    f0: F0Config | None
    lambda0: float
    f0_note: str
    estimator: RecursiveNineParam | None
    since_t_s: float = -math.inf
    f0_failing: bool = False
    f0_fail_t_s: float | None = None
    active: dict[str, float] = field(default_factory=dict)  # predicate -> data time raised
    f0_run: int = 0  # F0 failures in a row at the end of the last batch
    f0_run_onset: tuple[float, float] | None = None  # (t_s, residual) of that run's first sample
    temp_out_edge_c: float | None = (
        None  # range edge crossed while the temperature event is raised, °C
    )
    # [first, last] sample times taken outside the temperature model's range that F0 has not seen yet:
    # the static gate hands samples to F0 up to a window later than the frame that carried them.
    temp_skip_s: list[list[float]] = field(default_factory=list)
    # Largest |x_i|/|x| per axis over the samples F0 tested: the gravity directions its coverage rests on.
    f0_max_abs_u: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # (rate, Hz; F0's per-sample noise σ there) for the coverage's MDF, derived once per rate.
    f0_noise_at: tuple[float, float] | None = None

    def record_temperature_skip(self, t_s: np.ndarray, outside: np.ndarray) -> None:
        """Note the samples (times ``t_s`` (N,), ascending) taken outside the temperature model's range (``outside`` (N,))."""
        if self.temp_skip_s and t_s.size and t_s[0] <= self.temp_skip_s[-1][1]:
            # Time went back: the source restarted (ImuPipeline._source_restart), the old stream is finished.
            self.temp_skip_s.clear()
        edges = np.diff(np.concatenate([[0], outside.astype(np.int8), [0]]))
        first, last = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
        self.temp_skip_s += [
            [float(t_s[a]), float(t_s[b])] for a, b in zip(first, last, strict=True)
        ]

    def take_temperature_skip(self, t_s: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the samples at ``t_s`` (N,), ascending, F0 must skip; forgets the spans F0 has passed."""
        if not self.temp_skip_s or not t_s.size:
            return np.zeros(t_s.shape, dtype=bool)
        spans = np.array(self.temp_skip_s)
        k = np.searchsorted(spans[:, 0], t_s, side="right") - 1
        skip = (k >= 0) & (t_s <= spans[np.maximum(k, 0), 1])
        # F0 sees the samples in time order, so spans ending by the last of these are done.
        self.temp_skip_s = [s for s in self.temp_skip_s if s[1] > t_s[-1]]
        return skip


def _lambda0_inputs(tp: TriadPassport, options: PipelineOptions, rate_hz: float) -> dict[str, Any]:
    """:func:`estimators.scalar.derive_lambda0`'s arguments for one triad at ``rate_hz`` (module docstring step 5)."""
    ref = options.reference(tp.triad)
    # Per-sample white noise scales with the square root of the rate it is sampled at; the
    # audited bias wander (passport.bias_instability_std, docs/audit-xsens.md) does not.
    white = tp.noise_std * math.sqrt(rate_hz / tp.sample_rate_hz)
    noise_norm = np.maximum(np.hypot(white, tp.bias_instability_std) * tp.reference / ref, 1e-12)
    quant = None if tp.quantization_step is None else tp.quantization_step * tp.reference / ref
    tol = tp.tolerance.copy()
    tol[:3] *= tp.reference / ref
    return {
        "noise_std_norm": noise_norm,
        "false_alarm_prob": options.false_alarm_probability,
        "quantization_norm": quant,
        "tolerance_norm": tol,
        "reference_rel_err": options.gravity_rel_err if tp.triad is Triad.ACCEL else 0.0,
    }


def f0_threshold(tp: TriadPassport, options: PipelineOptions, rate_hz: float) -> Lambda0:
    """F0's threshold for one triad at ``rate_hz`` and what it is made of (module docstring step 5)."""
    return derive_lambda0(**_lambda0_inputs(tp, options, rate_hz))


def f0_threshold_bound(tp: TriadPassport, options: PipelineOptions, rate_hz: float) -> float:
    """A lower bound of :func:`f0_threshold`'s λ0 that needs no scipy (:func:`estimators.scalar.lambda0_lower_bound`)."""
    return lambda0_lower_bound(**_lambda0_inputs(tp, options, rate_hz))


def f0_config(
    tp: TriadPassport, options: PipelineOptions, rate_hz: float, *, lower_bound: bool = False
) -> tuple[F0Config | None, float, str]:
    """F0's configuration for one triad (λ0 derived from the passport, module docstring step 5).

    ``lower_bound``: the configuration with λ0's lower bound (:func:`f0_threshold_bound`) in its
    place: every sample F0 fails with the exact λ0 it fails too, and a triad it does not run
    (bound above :data:`F0_SHELL_LIMIT`) the exact λ0 does not run either.
    """
    ref = options.reference(tp.triad)
    nominal = tp.nominal.copy()
    nominal[:3] *= tp.reference / ref
    if lower_bound:
        lambda0 = f0_threshold_bound(tp, options, rate_hz)
    else:
        lambda0 = f0_threshold(tp, options, rate_hz).lambda0
    if lambda0 > F0_SHELL_LIMIT:
        return (
            None,
            lambda0,
            f"F0 {tp.triad.value}: not resolvable (λ0 {lambda0:.3g} > {F0_SHELL_LIMIT:g})",
        )
    cfg = F0Config(
        lambda0=lambda0,
        reference=ref,
        bias_norm=tuple(nominal[:3]),
        matrix=tuple(map(tuple, canonical_triad_matrix(nominal))),
    )
    return cfg, lambda0, f"F0 {tp.triad.value}: λ0 {lambda0:.3g}"


def new_estimator(tp: TriadPassport, options: PipelineOptions) -> RecursiveNineParam | None:
    # A triad whose passport resolves no parameter (a MEMS gyro against Ω) has nothing to diagnose.
    if not np.any(tp.observable):
        return None
    return RecursiveNineParam(tp.triad, reference=options.reference(tp.triad))
