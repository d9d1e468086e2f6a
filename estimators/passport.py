"""The passport of an IMU: nominal nine parameters per triad with tolerances (methods.md M1, M2).

M1's predicates F1…F9 compare each re-estimated parameter with the unit's
*passport* (nominal value and tolerance λ1…λ9); M2 builds such passports from
calibration runs with confidence intervals. This module is the versioned data
model and its plain-dict form; files and bytes are in
:mod:`protocols.passport_codec`.

Units: every parameter is normalized as in :mod:`estimators.conventions`
(biases divided by the triad's ``reference``, which is stored with it: local g
in m/s² for the accelerometers, Ω in rad/s for the gyros); scale errors and
cosines are dimensionless.

Plain-dict schema, version 3
----------------------------
``type`` = ``"ins.health.passport"``, ``schema_version`` = 3, ``unit_id``,
``sensor_model`` (str), ``sensor_ids`` (map str → str), ``created`` (ISO 8601
date or date-time string, supplied by the caller), ``triads`` (map
``"accel"``/``"gyro"`` → triad map). A triad map: ``param_names`` (the nine
names, checked), ``reference`` (float), ``reference_kind``
(``"gravity_mps2"``/``"earth_rate_rps"``), ``nominal``, ``tolerance``,
``sigma`` (9 floats each), ``observable`` (9 bools), ``noise_std`` (3 floats:
per-sample standard deviation of the normalized output per axis),
``sample_rate_hz`` (0.5 Hz … 10 kHz, :data:`SAMPLE_RATE_RANGE_HZ`),
``quantization_step`` (3 floats, normalized, or null),
``temperature`` (null or ``{reference_temp_c, bias_coeffs, scale_coeffs,
valid_min_c, valid_max_c}``, the last two the temperature range the model was
fitted on, °C) and ``provenance`` (``{method, n_positions, confidence, ci_low,
ci_high, procedure, n_runs, reproducible}`` and, from version 3, an optional
``param_sources``: 9 strings saying how each parameter was obtained — M1's
scalar fit, the M4 six-position vector fit, M4 full turns, the mean of the
static positions, or "not determined"). Unknown keys, wrong shapes, non-finite numbers and
non-numbers where a number belongs (a string such as ``"0.001"``, a boolean, null) are rejected
with the field and the received value; a newer schema version raises
:class:`PassportVersionError`.

Version 2 is version 3 without ``param_sources``; it is read and written back
unchanged. Version 1 is version 2 without ``valid_min_c`` and ``valid_max_c``. It is still
read, and written back unchanged: its temperature models load with no valid
range (``valid_min_c = valid_max_c = None``), which means what version 1 did,
compensation at any temperature. Rejecting those files would take the F0 check
and the diagnosis away from every unit calibrated before the range existed,
and a chamber run cannot be repeated on an installed unit; guessing a range
would invent data. The service states in its status that such a model is
unbounded (:mod:`service.pipeline`); to bound it, set ``schema_version`` to 2
and add the lowest and highest chamber temperature of the fit to each
``temperature`` map, or refit with ``ins-health passport temperature``.

Default tolerance rule (``calibrate``)
--------------------------------------
``λ_j = max(k·σ_j, floor_j)`` with ``k = 3`` and ``σ_j`` the calibration's
standard deviation. The floor is the change a *healthy* sensor of that grade
shows between calibration and use (turn-on and in-run repeatability, per
parameter class, :data:`GRADE_FLOORS`): a tolerance below it would flag normal
behaviour. The ``k·σ`` term keeps the tolerance no tighter than what the
calibration itself resolved: a nominal value known only to ±σ cannot support a
tolerance smaller than its own 3σ interval. (The diagnosis adds the uncertainty
of the new estimate on top: :mod:`estimators.diagnosis`.)
"""

from __future__ import annotations

import datetime as _dt
import math
import numbers
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from statistics import NormalDist
from types import MappingProxyType
from typing import Any, TypeVar

import numpy as np

from estimators._typing import ArrayT, BoolArray, FloatArray
from estimators.conventions import (
    MPS2_PER_MG,
    N_PARAMS,
    PARAM_NAMES,
    RPS_PER_DPH,
    Grade,
    Triad,
    reference_magnitude,
)
from estimators.ninepar import SOURCE_NONE, SOURCE_SCALAR, Estimate, Method, physical
from estimators.positions import Position
from estimators.quantiles import median
from estimators.validity_limits import ValidityLimits

PASSPORT_TYPE = "ins.health.passport"
PASSPORT_SCHEMA_VERSION = 3
SUPPORTED_PASSPORT_VERSIONS = (1, 2, 3)
UNBOUNDED_TEMPERATURE_VERSION = 1
"""The last schema whose temperature models carry no valid range (module docstring)."""
PARAM_SOURCES_VERSION = 3
"""The first schema whose provenance may say how each parameter was obtained (``param_sources``)."""
SAMPLE_RATE_RANGE_HZ = (ValidityLimits.min_rate_hz, ValidityLimits.max_rate_hz)
"""The sample rates a passport may state, Hz: those a session or stream is read at
(:class:`~estimators.stream_validity.ValidityLimits`, as :mod:`protocols.session_file` checks)."""
REFERENCE_REL_TOL = 0.02
"""Largest relative difference between a triad's passport reference and the session's
(:func:`check_references`). Gravity spans 9.76…9.84 m/s² over the Earth (0.8 %), so a passport
made at another site stays inside; one in other units (g, ft/s², °/h) is off by a factor of 3 or more."""


class PassportError(ValueError):
    """A passport (or its plain dict) that cannot be used; the message names the field and value."""


class PassportVersionError(PassportError):
    """The passport's schema version is not one this build reads."""


class ReferenceKind(StrEnum):
    """What a triad was normalized by."""

    GRAVITY = "gravity_mps2"
    EARTH_RATE = "earth_rate_rps"


def reference_kind(triad: Triad) -> ReferenceKind:
    """g for the accelerometers, Ω for the gyros."""
    return ReferenceKind.GRAVITY if Triad(triad) is Triad.ACCEL else ReferenceKind.EARTH_RATE


GRADE_FLOORS: Mapping[tuple[Triad, Grade], tuple[float, float, float]] = MappingProxyType(
    {
        # (bias in m/s² or rad/s, relative scale error, cosine = rad): typical turn-on/in-run repeatability.
        (Triad.ACCEL, Grade.MEMS): (2.0 * MPS2_PER_MG, 2.0e-3, 1.0e-3),
        (Triad.ACCEL, Grade.TACTICAL): (0.3 * MPS2_PER_MG, 3.0e-4, 2.0e-4),
        (Triad.ACCEL, Grade.NAVIGATION): (0.05 * MPS2_PER_MG, 1.0e-4, 5.0e-5),
        (Triad.GYRO, Grade.MEMS): (20.0 * RPS_PER_DPH, 2.0e-3, 1.0e-3),
        (Triad.GYRO, Grade.TACTICAL): (1.0 * RPS_PER_DPH, 3.0e-4, 2.0e-4),
        (Triad.GYRO, Grade.NAVIGATION): (0.01 * RPS_PER_DPH, 5.0e-5, 2.0e-5),
    }
)
"""Tolerance floors per (triad, grade): bias (SI), scale error, cosine between axes."""


@dataclass(frozen=True, eq=False)
class ToleranceRule:
    """``λ_j = max(k_sigma · σ_j, floor_j)`` (module docstring).

    Attributes
    ----------
    k_sigma : multiple of the calibration standard deviation (default 3).
    floor : (9,) smallest tolerance per parameter, normalized.
    """

    floor: FloatArray
    k_sigma: float = 3.0

    def __post_init__(self) -> None:
        floor = _array(self.floor, (N_PARAMS,), "ToleranceRule.floor")
        if np.any(floor <= 0.0):
            raise PassportError(f"ToleranceRule.floor must be positive, got {floor.tolist()}")
        if not math.isfinite(self.k_sigma) or self.k_sigma <= 0.0:
            raise PassportError(f"ToleranceRule.k_sigma must be positive, got {self.k_sigma!r}")
        object.__setattr__(self, "floor", floor)

    def tolerance(self, sigma: FloatArray) -> FloatArray:
        """(9,) tolerances for calibration standard deviations ``sigma`` (9,)."""
        return np.maximum(self.k_sigma * _array(sigma, (N_PARAMS,), "sigma"), self.floor)


def default_tolerance_rule(
    triad: Triad, grade: Grade, reference: float, *, k_sigma: float = 3.0
) -> ToleranceRule:
    """The documented default rule for ``triad`` of ``grade``; ``reference`` in m/s² or rad/s normalizes the bias floor."""
    if not math.isfinite(reference) or reference <= 0.0:
        raise PassportError(f"reference must be a positive finite number, got {reference!r}")
    bias, scale, nonorth = GRADE_FLOORS[(Triad(triad), Grade(grade))]
    return ToleranceRule(np.repeat([bias / reference, scale, nonorth], 3), k_sigma)


@dataclass(frozen=True, eq=False)
class TemperatureModel:
    """Polynomial temperature model of bias and scale per axis (methods.md M3).

    ``b_i(t) = Σ_k bias_coeffs[i, k]·(t − reference_temp_c)^k`` (normalized) and
    ``e_i(t) = Σ_k scale_coeffs[i, k]·(t − reference_temp_c)^k``, valid for
    ``valid_min_c ≤ t ≤ valid_max_c``: the temperatures of the chamber tests it
    was fitted on. Outside them the polynomial is not evaluated
    (:func:`estimators.temperature.model_errors` holds it at the nearer edge).

    Attributes
    ----------
    reference_temp_c : temperature the polynomials are centred on, °C (inside the range).
    bias_coeffs : (3, order+1) normalized bias coefficients, per °C^k.
    scale_coeffs : (3, order+1) relative scale-error coefficients, per °C^k.
    valid_min_c, valid_max_c : the range the model was fitted on, °C (keyword-only);
        both None only for a model read from a schema-1 passport, which recorded no
        range (module docstring): then the polynomial is used at any temperature.

    Raises
    ------
    PassportError
        Non-finite values, wrong shapes, a range with ``valid_min_c ≥ valid_max_c``,
        one bound without the other, or ``reference_temp_c`` outside the range.
    """

    reference_temp_c: float
    bias_coeffs: FloatArray
    scale_coeffs: FloatArray
    valid_min_c: float | None = field(kw_only=True)
    valid_max_c: float | None = field(kw_only=True)

    def __post_init__(self) -> None:
        ref = _number(self.reference_temp_c, "temperature.reference_temp_c")
        bias = _numbers(
            self.bias_coeffs, "temperature.bias_coeffs", "numbers of shape (3, order+1)"
        )
        if bias.ndim != 2 or bias.shape[0] != 3 or bias.shape[1] < 1:
            raise PassportError(
                f"temperature.bias_coeffs must have shape (3, order+1), got {np.shape(self.bias_coeffs)}: {_short(self.bias_coeffs)}"
            )
        object.__setattr__(self, "bias_coeffs", _array(bias, bias.shape, "temperature.bias_coeffs"))
        object.__setattr__(
            self, "scale_coeffs", _array(self.scale_coeffs, bias.shape, "temperature.scale_coeffs")
        )
        if self.valid_min_c is None and self.valid_max_c is None:
            return
        if self.valid_min_c is None or self.valid_max_c is None:
            raise PassportError(
                f"temperature.valid_min_c and valid_max_c go together, got {self.valid_min_c!r} and {self.valid_max_c!r}"
            )
        lo = _number(self.valid_min_c, "temperature.valid_min_c")
        hi = _number(self.valid_max_c, "temperature.valid_max_c")
        if not lo < hi:
            raise PassportError(
                f"temperature.valid_min_c must be below valid_max_c, got {lo!r} ≥ {hi!r}"
            )
        if not lo <= ref <= hi:
            raise PassportError(
                f"temperature.reference_temp_c {ref!r} °C is outside the valid range {lo!r}…{hi!r} °C"
            )
        object.__setattr__(self, "valid_min_c", lo)
        object.__setattr__(self, "valid_max_c", hi)

    @property
    def order(self) -> int:
        return int(self.bias_coeffs.shape[1]) - 1

    @property
    def bounded(self) -> bool:
        """False for a schema-1 model, which records no valid range."""
        return self.valid_min_c is not None

    def in_range(self, temp_c: FloatArray) -> BoolArray:
        """(N,) bool: which of ``temp_c`` (N,), °C, lie in the valid range (all, for an unbounded model)."""
        t = np.asarray(temp_c, dtype=float).reshape(-1)
        if not self.bounded:
            return np.ones(t.shape, dtype=bool)
        return (t >= self.valid_min_c) & (t <= self.valid_max_c)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "reference_temp_c": float(self.reference_temp_c),
            "bias_coeffs": self.bias_coeffs.tolist(),
            "scale_coeffs": self.scale_coeffs.tolist(),
        }
        if self.bounded:
            out["valid_min_c"] = self.valid_min_c
            out["valid_max_c"] = self.valid_max_c
        return out

    @classmethod
    def from_dict(
        cls, obj: Any, *, schema_version: int = PASSPORT_SCHEMA_VERSION
    ) -> TemperatureModel:
        """The model of a passport of ``schema_version`` (1: no range keys, read unbounded; 2: the range is required)."""
        keys = ("reference_temp_c", "bias_coeffs", "scale_coeffs")
        if schema_version <= UNBOUNDED_TEMPERATURE_VERSION:
            obj = _map(obj, "temperature", keys)
            return cls(_number(obj["reference_temp_c"], "temperature.reference_temp_c"), obj["bias_coeffs"], obj["scale_coeffs"],
                       valid_min_c=None, valid_max_c=None)  # fmt: skip
        obj = _map(obj, "temperature", (*keys, "valid_min_c", "valid_max_c"))
        return cls(
            _number(obj["reference_temp_c"], "temperature.reference_temp_c"),
            obj["bias_coeffs"],
            obj["scale_coeffs"],
            valid_min_c=_number(obj["valid_min_c"], "temperature.valid_min_c"),
            valid_max_c=_number(obj["valid_max_c"], "temperature.valid_max_c"),
        )


@dataclass(frozen=True, eq=False)
class Provenance:
    """Where the nominal values come from (methods.md M2: confidence intervals of the calibration).

    Attributes
    ----------
    method : estimator used.
    n_positions : positions (or equations) used.
    confidence : confidence level of the intervals, in (0, 1).
    ci_low, ci_high : (9,) interval bounds, normalized.
    procedure : the calibration procedure (free text, e.g. "M1 multi-position",
        "M2 tilt table", "M3 temperature chamber").
    n_runs : independent runs behind the values (M2's reproducibility check needs ≥ 2).
    reproducible : (9,) bool, the parameters whose run intervals intersect
        (M2), or None when only one run was made.
    param_sources : (9,) how each parameter was obtained (``Estimate.sources``: M1's
        scalar fit, the M4 six-position vector fit, M4 full turns, …), or None (schema ≥ 3).
    """

    method: Method
    n_positions: int
    confidence: float
    ci_low: FloatArray
    ci_high: FloatArray
    procedure: str = "M1 multi-position"
    n_runs: int = 1
    reproducible: BoolArray | None = None
    param_sources: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", _enum(Method, self.method, "provenance.method"))
        if self.param_sources is not None:
            src = self.param_sources
            if not (
                isinstance(src, (list, tuple))
                and len(src) == N_PARAMS
                and all(isinstance(v, str) and v.strip() for v in src)
            ):
                raise PassportError(
                    f"provenance.param_sources must be {N_PARAMS} non-empty strings or null, got {_short(src)}"
                )
            object.__setattr__(self, "param_sources", tuple(src))
        if type(self.n_positions) is not int or self.n_positions < 0:
            raise PassportError(
                f"provenance.n_positions must be a non-negative int, got {self.n_positions!r}"
            )
        if not (isinstance(self.confidence, (int, float)) and 0.0 < self.confidence < 1.0):
            raise PassportError(f"provenance.confidence must be in (0, 1), got {self.confidence!r}")
        low = _array(self.ci_low, (N_PARAMS,), "provenance.ci_low")
        high = _array(self.ci_high, (N_PARAMS,), "provenance.ci_high")
        if np.any(low > high):
            raise PassportError(
                f"provenance.ci_low must not exceed ci_high, got {low.tolist()} > {high.tolist()}"
            )
        object.__setattr__(self, "ci_low", low)
        object.__setattr__(self, "ci_high", high)
        if not isinstance(self.procedure, str) or not self.procedure.strip():
            raise PassportError(
                f"provenance.procedure must be a non-empty string, got {_short(self.procedure)}"
            )
        if type(self.n_runs) is not int or self.n_runs < 1:
            raise PassportError(f"provenance.n_runs must be a positive int, got {self.n_runs!r}")
        if self.reproducible is not None:
            rep = np.asarray(self.reproducible)
            if rep.shape != (N_PARAMS,) or rep.dtype != bool:
                raise PassportError(
                    f"provenance.reproducible must be 9 booleans or null, got {_short(self.reproducible)}"
                )
            object.__setattr__(self, "reproducible", _readonly(rep.copy()))

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method.value,
            "n_positions": self.n_positions,
            "confidence": float(self.confidence),
            "ci_low": self.ci_low.tolist(),
            "ci_high": self.ci_high.tolist(),
            "procedure": self.procedure,
            "n_runs": self.n_runs,
            "reproducible": None if self.reproducible is None else self.reproducible.tolist(),
        } | ({} if self.param_sources is None else {"param_sources": list(self.param_sources)})

    @classmethod
    def from_dict(cls, obj: Any, *, schema_version: int = PASSPORT_SCHEMA_VERSION) -> Provenance:
        keys: tuple[str, ...] = ("method", "n_positions", "confidence", "ci_low", "ci_high", "procedure", "n_runs", "reproducible")  # fmt: skip
        if schema_version >= PARAM_SOURCES_VERSION and isinstance(obj, dict):
            keys += ("param_sources",)
            obj = {"param_sources": None, **obj}
        obj = _map(obj, "provenance", keys)
        rep = obj["reproducible"]
        if rep is not None and not (
            isinstance(rep, list) and all(isinstance(v, bool) for v in rep)
        ):
            raise PassportError(
                f"provenance.reproducible must be a list of booleans or null, got {_short(rep)}"
            )
        return cls(
            obj["method"],
            obj["n_positions"],
            _number(obj["confidence"], "provenance.confidence"),
            obj["ci_low"],
            obj["ci_high"],
            obj["procedure"],
            obj["n_runs"],
            None if rep is None else np.array(rep, dtype=bool),
            obj.get("param_sources"),
        )


@dataclass(frozen=True, eq=False)
class TriadPassport:
    """Passport of one triad (methods.md M1: nominal values and tolerances λ1…λ9).

    Attributes
    ----------
    triad : which triad.
    reference : normalizing value, m/s² (accel, local g) or rad/s (gyro, Ω).
    reference_kind : :class:`ReferenceKind`, must match the triad.
    nominal : (9,) nominal parameters, normalized.
    tolerance : (9,) tolerances λ (> 0), normalized.
    sigma : (9,) standard deviation of the nominal values (≥ 0).
    observable : (9,) bool, whether the calibration resolved each parameter.
    noise_std : (3,) per-sample standard deviation of the normalized output per axis.
    sample_rate_hz : sample rate the noise refers to, Hz.
    quantization_step : (3,) normalized step of one count per axis, or None.
    temperature : :class:`TemperatureModel` or None.
    provenance : :class:`Provenance`.
    bias_instability_std : (3,) normalized standard deviation of the bias wander that
        does not average down within a position (the model audit's ``bias_instability``,
        ``ins-health calibrate --audit``); zeros when the white-noise model was not audited.
        Thresholds and position covariances add it to the white noise
        (:meth:`effective_noise_std`, :meth:`position_cov_floor`).
    """

    triad: Triad
    reference: float
    reference_kind: ReferenceKind
    nominal: FloatArray
    tolerance: FloatArray
    sigma: FloatArray
    observable: BoolArray
    noise_std: FloatArray
    sample_rate_hz: float
    provenance: Provenance
    quantization_step: FloatArray | None = None
    temperature: TemperatureModel | None = None
    bias_instability_std: FloatArray = field(default_factory=lambda: np.zeros(3))

    def effective_noise_std(self, n_avg: int = 1) -> FloatArray:
        """(3,) per-sample normalized noise for windows of ``n_avg`` samples.

        :func:`estimators.scalar.derive_lambda0` divides the variance by ``n_avg``; the
        bias wander must survive that division: ``σ_eff² = σ_white² + n_avg·σ_bi²``.
        """
        return np.sqrt(self.noise_std**2 + n_avg * self.bias_instability_std**2)

    def position_cov_floor(self) -> FloatArray:
        """(3, 3) covariance, in the triad's SI unit squared, that a position mean carries beyond its white noise."""
        return np.diag((self.bias_instability_std * self.reference) ** 2)

    def __post_init__(self) -> None:
        triad = _enum(Triad, self.triad, "triad")
        where = f"triads.{triad.value}"
        kind = _enum(ReferenceKind, self.reference_kind, f"{where}.reference_kind")
        if kind is not reference_kind(triad):
            raise PassportError(
                f"{where}.reference_kind must be {reference_kind(triad).value!r} for the {triad.value} triad, got {kind.value!r}"
            )
        if _number(self.reference, f"{where}.reference") <= 0.0:
            raise PassportError(f"{where}.reference must be positive, got {self.reference!r}")
        lo, hi = SAMPLE_RATE_RANGE_HZ
        # The pipeline scales the noise by √(session rate / this rate): 0 Hz or 1 GHz would void λ0.
        if not lo <= _number(self.sample_rate_hz, f"{where}.sample_rate_hz") <= hi:
            raise PassportError(
                f"{where}.sample_rate_hz must be a sample rate sessions are read at, {lo:g}…{hi:g} Hz, "
                f"got {self.sample_rate_hz!r}"
            )
        nominal = _array(self.nominal, (N_PARAMS,), f"{where}.nominal")
        arrays: dict[str, FloatArray | BoolArray] = {
            "nominal": nominal,
            "tolerance": _array(self.tolerance, (N_PARAMS,), f"{where}.tolerance"),
            "sigma": _array(self.sigma, (N_PARAMS,), f"{where}.sigma"),
            "noise_std": _array(self.noise_std, (3,), f"{where}.noise_std"),
            "bias_instability_std": _array(
                self.bias_instability_std, (3,), f"{where}.bias_instability_std"
            ),
        }
        if np.any(arrays["tolerance"] <= 0.0):
            raise PassportError(
                f"{where}.tolerance must be positive, got {arrays['tolerance'].tolist()}"
            )
        # Outside it the scalar model has no meaning: the pipeline and diagnose failed on such a
        # passport in their linear algebra ('Matrix is not positive definite').
        if not physical(nominal):
            raise PassportError(
                f"{where}.nominal {nominal.tolist()} is no working triad: a gain 1 + e outside "
                "(0.1, 10) or sensitive axes nearly coplanar (cosines d1..d3)"
            )
        for name in ("sigma", "noise_std", "bias_instability_std"):
            if np.any(arrays[name] < 0.0):
                raise PassportError(
                    f"{where}.{name} must not be negative, got {arrays[name].tolist()}"
                )
        obs = np.asarray(self.observable)
        if obs.shape != (N_PARAMS,) or obs.dtype != bool:
            raise PassportError(
                f"{where}.observable must be {N_PARAMS} booleans, got {_short(self.observable)}"
            )
        arrays["observable"] = _readonly(obs)
        if self.quantization_step is not None:
            step = _array(self.quantization_step, (3,), f"{where}.quantization_step")
            if np.any(step <= 0.0):
                raise PassportError(
                    f"{where}.quantization_step must be positive, got {step.tolist()}"
                )
            arrays["quantization_step"] = step
        if self.temperature is not None and not isinstance(self.temperature, TemperatureModel):
            raise PassportError(
                f"{where}.temperature must be a TemperatureModel or None, got {type(self.temperature).__name__}"
            )
        if not isinstance(self.provenance, Provenance):
            raise PassportError(
                f"{where}.provenance must be a Provenance, got {type(self.provenance).__name__}"
            )
        object.__setattr__(self, "triad", triad)
        object.__setattr__(self, "reference_kind", kind)
        object.__setattr__(self, "reference", float(self.reference))
        object.__setattr__(self, "sample_rate_hz", float(self.sample_rate_hz))
        for name, arr in arrays.items():
            object.__setattr__(self, name, arr)

    def to_dict(self) -> dict[str, Any]:
        return {
            "param_names": list(PARAM_NAMES),
            "reference": self.reference,
            "reference_kind": self.reference_kind.value,
            "nominal": self.nominal.tolist(),
            "tolerance": self.tolerance.tolist(),
            "sigma": self.sigma.tolist(),
            "observable": [bool(v) for v in self.observable],
            "noise_std": self.noise_std.tolist(),
            "bias_instability_std": self.bias_instability_std.tolist(),
            "sample_rate_hz": self.sample_rate_hz,
            "quantization_step": None
            if self.quantization_step is None
            else self.quantization_step.tolist(),
            "temperature": None if self.temperature is None else self.temperature.to_dict(),
            "provenance": self.provenance.to_dict(),
        }

    @classmethod
    def from_dict(
        cls, triad: Triad, obj: Any, *, schema_version: int = PASSPORT_SCHEMA_VERSION
    ) -> TriadPassport:
        """Validate and build one triad of a passport of ``schema_version`` (it decides the temperature map's keys)."""
        where = f"triads.{Triad(triad).value}"
        keys = ("param_names", "reference", "reference_kind", "nominal", "tolerance", "sigma", "observable", "noise_std",
                "bias_instability_std", "sample_rate_hz", "quantization_step", "temperature", "provenance")  # fmt: skip
        obj = _map(obj, where, keys)
        if obj["param_names"] != list(PARAM_NAMES):
            raise PassportError(
                f"{where}.param_names must be {list(PARAM_NAMES)}, got {_short(obj['param_names'])}"
            )
        observable = obj["observable"]
        if not isinstance(observable, list) or not all(isinstance(v, bool) for v in observable):
            raise PassportError(
                f"{where}.observable must be a list of booleans, got {_short(observable)}"
            )
        return cls(
            triad=triad,
            reference=_number(obj["reference"], f"{where}.reference"),
            reference_kind=obj["reference_kind"],
            nominal=obj["nominal"],
            tolerance=obj["tolerance"],
            sigma=obj["sigma"],
            observable=np.array(observable, dtype=bool),
            noise_std=obj["noise_std"],
            bias_instability_std=obj["bias_instability_std"],
            sample_rate_hz=_number(obj["sample_rate_hz"], f"{where}.sample_rate_hz"),
            quantization_step=obj["quantization_step"],
            temperature=None
            if obj["temperature"] is None
            else TemperatureModel.from_dict(obj["temperature"], schema_version=schema_version),
            provenance=Provenance.from_dict(obj["provenance"], schema_version=schema_version),
        )


@dataclass(frozen=True, eq=False)
class Passport:
    """Passport of one IMU: identity and one :class:`TriadPassport` per triad.

    Attributes
    ----------
    unit_id : identity of the IMU (non-empty).
    sensor_model : model name.
    sensor_ids : per-sensor identities (e.g. serial numbers by triad), str → str.
    created : ISO 8601 date or date-time string given by the caller (estimators read no clock).
    triads : :class:`Triad` → :class:`TriadPassport` (at least one).
    schema_version : one of :data:`SUPPORTED_PASSPORT_VERSIONS`, :data:`PASSPORT_SCHEMA_VERSION` by default;
        a passport read from a schema-1 file keeps 1 and is written back as schema 1 (module docstring).
    """

    unit_id: str
    sensor_model: str
    sensor_ids: Mapping[str, str]
    created: str
    triads: Mapping[Triad, TriadPassport]
    schema_version: int = PASSPORT_SCHEMA_VERSION

    def __post_init__(self) -> None:
        _check_version(self.schema_version)
        for name in ("unit_id", "sensor_model", "created"):
            if not isinstance(getattr(self, name), str):
                raise PassportError(f"{name} must be a string, got {_short(getattr(self, name))}")
        if not self.unit_id.strip():
            raise PassportError(f"unit_id must not be empty, got {self.unit_id!r}")
        try:
            _dt.datetime.fromisoformat(self.created)
        except ValueError:
            raise PassportError(
                f"created must be an ISO 8601 date or date-time, got {self.created!r}"
            ) from None
        if not isinstance(self.sensor_ids, Mapping) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in self.sensor_ids.items()
        ):
            raise PassportError(
                f"sensor_ids must map strings to strings, got {_short(self.sensor_ids)}"
            )
        if not isinstance(self.triads, Mapping) or not self.triads:
            raise PassportError(f"triads must be a non-empty mapping, got {_short(self.triads)}")
        triads = {}
        for key, value in self.triads.items():
            triad = _enum(Triad, key, "triads key")
            if not isinstance(value, TriadPassport) or value.triad is not triad:
                raise PassportError(
                    f"triads[{triad.value!r}] must be the TriadPassport of that triad, got {_short(value)}"
                )
            triads[triad] = value
            if (
                value.provenance.param_sources is not None
                and self.schema_version < PARAM_SOURCES_VERSION
            ):
                raise PassportError(
                    f"triads[{triad.value!r}].provenance.param_sources needs schema {PARAM_SOURCES_VERSION}, "
                    f"this passport is schema {self.schema_version}"
                )
            model = value.temperature
            # The schema decides whether a temperature map has range keys: a mismatch could not be written back.
            if model is not None and model.bounded != (
                self.schema_version > UNBOUNDED_TEMPERATURE_VERSION
            ):
                raise PassportError(
                    f"triads[{triad.value!r}].temperature: a schema-{self.schema_version} passport needs a temperature model "
                    + (
                        "without a valid range (schema 1 has none)"
                        if model.bounded
                        else "with its valid range (valid_min_c, valid_max_c)"
                    )
                )
        object.__setattr__(self, "sensor_ids", MappingProxyType(dict(self.sensor_ids)))
        object.__setattr__(self, "triads", MappingProxyType(triads))

    def to_dict(self) -> dict[str, Any]:
        """The plain-dict form (JSON and msgpack ready; schema in the module docstring)."""
        return {
            "type": PASSPORT_TYPE,
            "schema_version": self.schema_version,
            "unit_id": self.unit_id,
            "sensor_model": self.sensor_model,
            "sensor_ids": dict(self.sensor_ids),
            "created": self.created,
            "triads": {
                t.value: tp.to_dict()
                for t, tp in sorted(self.triads.items(), key=lambda kv: kv[0].value)
            },
        }

    @classmethod
    def from_dict(cls, obj: Any) -> Passport:
        """Validate and build; raises :class:`PassportError` (or :class:`PassportVersionError`)."""
        if not isinstance(obj, dict):
            raise PassportError(f"a passport must be a map, got {type(obj).__name__}")
        if obj.get("type") != PASSPORT_TYPE:
            raise PassportError(f"type tag {_short(obj.get('type'))} is not {PASSPORT_TYPE!r}")
        _check_version(obj.get("schema_version"))
        obj = _map(
            obj,
            "passport",
            (
                "type",
                "schema_version",
                "unit_id",
                "sensor_model",
                "sensor_ids",
                "created",
                "triads",
            ),
        )
        triads_obj = obj["triads"]
        if not isinstance(triads_obj, dict):
            raise PassportError(f"triads must be a map, got {_short(triads_obj)}")
        triads = {}
        for key, value in triads_obj.items():
            triad = _enum(Triad, key, "triads key")
            triads[triad] = TriadPassport.from_dict(
                triad, value, schema_version=obj["schema_version"]
            )
        sensor_ids = obj["sensor_ids"]
        if not isinstance(sensor_ids, dict):
            raise PassportError(f"sensor_ids must be a map, got {_short(sensor_ids)}")
        return cls(
            unit_id=obj["unit_id"],
            sensor_model=obj["sensor_model"],
            sensor_ids=sensor_ids,
            created=obj["created"],
            triads=triads,
            schema_version=obj["schema_version"],
        )


_REFERENCE_WORDS = {
    Triad.ACCEL: ("accelerometer", "m/s²", "the session's gravity", "a passport in g units"),
    Triad.GYRO: ("gyro", "rad/s", "Earth's rotation rate", "a passport in °/h or °/s"),
}


def check_references(passport: Passport, *, gravity_mps2: float) -> None:
    """Raise :class:`PassportError` when a triad's ``reference`` does not fit the session's.

    Biases are normalized by the reference and rescaled by ``passport.reference / reference``
    when compared (:mod:`estimators.diagnosis`), so a reference in other units would turn every
    bias into a fault. Within :data:`REFERENCE_REL_TOL` the passport may come from another site.

    Parameters
    ----------
    gravity_mps2 : the session's local gravity, m/s² (the gyros' reference is Earth's rate).
    """
    for triad, tp in passport.triads.items():
        expected = reference_magnitude(triad, gravity_mps2)
        if abs(tp.reference - expected) > REFERENCE_REL_TOL * expected:
            sensor, unit, what, hint = _REFERENCE_WORDS[triad]
            raise PassportError(
                f"the passport's {sensor} reference is {tp.reference!r} {unit} but {what} is "
                f"{expected:.6g} {unit}: {hint}, or of another quantity? (a passport from another "
                f"site differs by less than {REFERENCE_REL_TOL:.0%})"
            )


def per_sample_noise_std(
    positions: Sequence[Position], triad: Triad, reference: float
) -> FloatArray:
    """(3,) per-sample standard deviation of the normalized output per axis.

    Each position's covariance of the mean times its effective sample count
    (``n_eff``, :mod:`estimators.positions`; ``n_samples`` when not recorded)
    is a per-sample variance: the covariance of the mean is ``Σ·τ/n`` and
    ``n_eff = n/τ``, so the correlation factor ``τ`` cancels. The median over
    positions resists a disturbed one.

    Parameters
    ----------
    positions : static positions (SI covariances of the means).
    triad : which triad.
    reference : g in m/s² or Ω in rad/s, the normalizing value.
    """
    triad = Triad(triad)
    variances = []
    for k, pos in enumerate(positions):
        cov = pos.cov(triad)
        if cov is None:
            raise PassportError(f"position {k} has no {triad.value} covariance")
        n_eff = pos.accel_n_eff if triad is Triad.ACCEL else pos.gyro_n_eff
        variances.append(
            np.diag(np.asarray(cov, dtype=float)) * (pos.n_samples if n_eff is None else n_eff)
        )
    if not variances:
        raise PassportError("no positions to estimate the noise from")
    return np.sqrt(median(np.array(variances), axis=0)) / reference


def passport_from_estimates(
    estimates: Mapping[Triad, Estimate],
    *,
    unit_id: str,
    sensor_model: str,
    sensor_ids: Mapping[str, str],
    created: str,
    noise_std: Mapping[Triad, FloatArray],
    sample_rate_hz: float,
    grade: Grade | Mapping[Triad, Grade],
    quantization_step: Mapping[Triad, FloatArray] | None = None,
    tolerance_rules: Mapping[Triad, ToleranceRule] | None = None,
    confidence: float = 0.95,
    bias_instability_std: Mapping[Triad, FloatArray] | None = None,
) -> Passport:
    """A passport from calibration estimates of a fault-free session.

    Nominal = the estimate; sigma = its standard deviation; tolerance by the
    default rule for ``grade`` (or ``tolerance_rules``); confidence intervals
    ``nominal ± z σ`` at ``confidence`` (two-sided normal). Parameters that the
    estimate flags as not observable keep its value but are marked so, and the
    diagnosis does not evaluate them.

    Parameters
    ----------
    estimates : per triad, an estimate with params and a known ``reference``.
    noise_std : per triad, (3,) per-sample normalized noise (:func:`per_sample_noise_std`).
    sample_rate_hz : sample rate of the session, Hz.
    grade : sensor grade for the default tolerance floors, one for all triads or per triad.
    quantization_step : per triad, (3,) normalized count step, when known.
    bias_instability_std : per triad, (3,) normalized bias wander from the model audit (default: none).
    """
    if not 0.0 < confidence < 1.0:
        raise PassportError(f"confidence must be in (0, 1), got {confidence!r}")
    z = NormalDist().inv_cdf(0.5 + 0.5 * confidence)
    triads = {}
    for key, est in estimates.items():
        triad = Triad(key)
        sigma = est.sigma
        if est.params is None or sigma is None:
            raise PassportError(f"cannot build the {triad.value} passport: {est.reason}")
        if est.reference is None:
            raise PassportError(
                f"the {triad.value} estimate does not record its reference (use estimate_triad or pass reference=)"
            )
        triad_grade = grade.get(triad) if isinstance(grade, Mapping) else grade
        if triad_grade is None or triad not in noise_std:
            raise PassportError(
                f"the {triad.value} triad needs a grade and a noise_std to build its passport"
            )
        rule = (tolerance_rules or {}).get(triad) or default_tolerance_rule(
            triad, triad_grade, est.reference
        )
        triads[triad] = TriadPassport(
            triad=triad,
            reference=est.reference,
            reference_kind=reference_kind(triad),
            nominal=est.params,
            tolerance=rule.tolerance(sigma),
            sigma=sigma,
            observable=np.asarray(est.observable, dtype=bool),
            noise_std=noise_std[triad],
            sample_rate_hz=sample_rate_hz,
            quantization_step=None if quantization_step is None else quantization_step.get(triad),
            bias_instability_std=np.zeros(3)
            if bias_instability_std is None
            else bias_instability_std.get(triad, np.zeros(3)),
            provenance=Provenance(
                est.method,
                est.n_positions,
                confidence,
                est.params - z * sigma,
                est.params + z * sigma,
                procedure=_procedure(est),
                param_sources=est.sources,
            ),
        )
    return Passport(
        unit_id=unit_id,
        sensor_model=sensor_model,
        sensor_ids=dict(sensor_ids),
        created=created,
        triads=triads,
    )


def _procedure(est: Estimate) -> str:
    """The provenance's procedure: M1 multi-position, or the methods that supplied the parameters."""
    if est.sources is None or set(est.sources) <= {SOURCE_SCALAR}:
        return "M1 multi-position"
    return " + ".join(dict.fromkeys(s for s in est.sources if s != SOURCE_NONE))


# --------------------------------------------------------------------------- validation helpers


def _check_version(version: Any) -> None:
    if type(version) is int and version in SUPPORTED_PASSPORT_VERSIONS:
        return
    if type(version) is int and version > PASSPORT_SCHEMA_VERSION:
        raise PassportVersionError(
            f"passport schema version {version} is newer than this build reads ({list(SUPPORTED_PASSPORT_VERSIONS)}); "
            "upgrade ins-health, or re-create the passport with this version's `ins-health calibrate`"
        )
    raise PassportVersionError(
        f"passport schema version {_short(version)} is not supported (this build reads {list(SUPPORTED_PASSPORT_VERSIONS)}); "
        "the file is not an ins-health passport or is damaged"
    )


def _map(obj: Any, where: str, keys: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise PassportError(f"{where} must be a map, got {_short(obj)}")
    missing = [k for k in keys if k not in obj]
    if missing:
        raise PassportError(f"{where} lacks field(s) {missing}")
    unknown = sorted(str(k) for k in obj if k not in keys)
    if unknown:
        raise PassportError(f"{where} has unknown field(s) {unknown}")
    return obj


# One rule for every number of a passport, scalar or array: a real number, never a bool or a
# string. float() and np.array(dtype=float) would turn "0.001" and true into numbers, so a
# hand-edited or foreign file would pass with values nobody wrote as numbers.


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _leaves(value: Any) -> Iterator[Any]:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        for item in value:
            yield from _leaves(item)
    else:
        yield value


def _numbers(value: Any, name: str, expected: str) -> FloatArray:
    """``value`` (nested lists or an array of numbers) as a float array of its own shape."""
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise PassportError(f"{name} must be {expected}, got {_short(value)}")
    bad = [v for v in _leaves(value) if not _is_number(v)]
    if bad:
        kind = (
            "booleans"
            if isinstance(bad[0], (bool, np.bool_))
            else f"{type(bad[0]).__name__} {bad[0]!r}"
        )
        raise PassportError(f"{name} must be numbers, got {kind}: {_short(value)}")
    try:
        return np.array(value, dtype=float)
    except ValueError:  # ragged nesting
        raise PassportError(f"{name} must be {expected}, got {_short(value)}") from None


def _array(value: Any, shape: tuple[int, ...], name: str) -> FloatArray:
    arr = _numbers(value, name, f"numbers of shape {shape}")
    if arr.shape != shape:
        raise PassportError(
            f"{name} must have shape {shape}, got shape {arr.shape}: {_short(value)}"
        )
    if not np.isfinite(arr).all():
        raise PassportError(f"{name} must be finite, got {_short(value)}")
    return _readonly(arr)


def _number(value: Any, name: str) -> float:
    if not _is_number(value):
        raise PassportError(f"{name} must be a number, got {_short(value)}")
    out = float(value)
    if not math.isfinite(out):
        raise PassportError(f"{name} must be finite, got {value!r}")
    return out


_EnumT = TypeVar("_EnumT", bound=Enum)


def _enum(kind: type[_EnumT], value: Any, name: str) -> _EnumT:
    try:
        return kind(value)
    except ValueError:
        raise PassportError(
            f"{name} is {_short(value)}, expected one of {[m.value for m in kind]}"
        ) from None


def _readonly(arr: ArrayT) -> ArrayT:
    out = arr.copy(order="K")
    out.setflags(write=False)
    return out


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
