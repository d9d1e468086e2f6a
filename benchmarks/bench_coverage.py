"""The minimum detectable fault (MDF, estimators.coverage) per sensor class and session, and the
detection rate against fault size.

1. Table: for each nominal sensor class (estimators.nominal_passport) at 200 Hz, the MDF of F0 on
   an axis that saw gravity (|u_i| = 1) — per sample, so the same for any session length — of the
   gross test on the axis along gravity (z) for :data:`GROSS_REST_S` at rest, and of F1…F9 (zero
   signal of x, scale error of z) for 9 and 18 positions of 5 s and 60 s at rest, in SI and in % of
   the class's tolerance; the accelerometers (a MEMS gyro's F0 and F1…F9 do not apply).
2. Detection rate against fault size (0.5…10 × the MDF), 200 seeded trials per
   point: F0 on a six-face rest session (1 s a face), F1…F9 on 18 positions of 5 s, for the
   consumer-MEMS and tactical classes; and the gross test (window means at rest,
   :mod:`estimators.gross`) on :data:`GROSS_REST_S` at rest with z up.

F0 and F1…F9 are run as the pipeline runs them (λ0 from ``f0_threshold``, persistence 0.02 s,
the refined fit, ``diagnose``). Run: ``python benchmarks/bench_coverage.py``.
"""

from __future__ import annotations

import math

import numpy as np

from estimators.conventions import Triad
from estimators.coverage import CheckCoverage, f0_mdf, ninepar_coverage
from estimators.diagnosis import diagnose
from estimators.gross import gross_batch, tolerance_passports
from estimators.ninepar import estimate_refined, scheme_directions
from estimators.nominal_passport import SensorClass, nominal_passport
from estimators.passport import TriadPassport
from estimators.scalar import F0Config, f0_batch, persistent_failure
from estimators.session import ImuSession
from service.pipeline.options import PipelineOptions
from service.pipeline.triad_check import f0_threshold

RATE_HZ = 200.0
OPTIONS = PipelineOptions()
G = OPTIONS.gravity_mps2
PERSIST = max(1, round(OPTIONS.f0_persistence_s * RATE_HZ))
TRIALS = 200
FACTORS = (0.5, 0.75, 0.9, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
FACES = np.vstack([np.eye(3), -np.eye(3)])
GROSS_REST_S = 6.0
"""Rest of the gross test's sessions: 12 windows of 0.5 s, two more than a declared failure needs."""


def _accel(cls: SensorClass) -> TriadPassport:
    return nominal_passport(cls, gravity_mps2=G).triads[Triad.ACCEL]


def _sample_sd(tp: TriadPassport) -> float:
    """Per-sample noise of the normalized output at RATE_HZ (worst axis)."""
    return float(tp.noise_std.max() * math.sqrt(RATE_HZ / tp.sample_rate_hz))


def _f0(tp: TriadPassport) -> tuple[F0Config, tuple[float, ...], tuple[float, ...]]:
    lam = f0_threshold(tp, OPTIONS, RATE_HZ)
    bias, scale = f0_mdf(
        lambda0=lam.lambda0,
        noise_std=lam.noise_std,
        persist=PERSIST,
        max_abs_u=(1, 1, 1),
        reference=G,
    )
    return F0Config(lambda0=lam.lambda0, reference=G), bias, scale


def _positions(tp: TriadPassport, n_positions: int, seconds: float):
    """Directions and per-position covariance (normalized) of a rest session."""
    u = scheme_directions(n_positions)
    var = _sample_sd(tp) ** 2 / (seconds * RATE_HZ)
    return u, np.broadcast_to(var * np.eye(3), (n_positions, 3, 3)).copy()


def _ninepar_mdf(tp: TriadPassport, n_positions: int, seconds: float, rng) -> tuple[float, float]:
    u, cov = _positions(tp, n_positions, seconds)
    means = u + rng.standard_normal(u.shape) * np.sqrt(cov[:, 0, 0])[:, None]
    diag = diagnose(estimate_refined(means, cov, Triad.ACCEL, reference=G), tp)
    cov_ = ninepar_coverage(
        diag, positions=n_positions, reference=G, passport_observable=tp.observable
    )
    assert cov_.mdf_bias_si is not None and cov_.mdf_scale is not None
    return cov_.mdf_bias_si[0], cov_.mdf_scale[2]


def _gross_rest(
    cls: SensorClass, seed: int, bias_z: float = 0.0, scale_z: float = 0.0
) -> ImuSession:
    """A unit of the class resting z up for GROSS_REST_S, its z accelerometer off by ``bias_z`` m/s²
    and ``scale_z`` (relative); white noise of the class at RATE_HZ."""
    passport = nominal_passport(cls, gravity_mps2=G)
    rng = np.random.default_rng(seed)
    n = round(GROSS_REST_S * RATE_HZ)
    sd = {
        t: float(tp.noise_std.max() * tp.reference * math.sqrt(RATE_HZ / tp.sample_rate_hz))
        for t, tp in passport.triads.items()
    }
    accel = rng.normal(0.0, sd[Triad.ACCEL], (n, 3))
    accel[:, 2] += G * (1.0 + scale_z) + bias_z
    gyro = rng.normal(0.0, sd[Triad.GYRO], (n, 3))
    return ImuSession(np.arange(n) / RATE_HZ, accel, gyro)


def _gross_found(cls: SensorClass, session: ImuSession) -> bool:
    res = gross_batch(session, nominal_passport(cls, gravity_mps2=G), gravity_mps2=G)
    return any(c.raised and c.triad is Triad.ACCEL for c in res.changes)


def _gross_mdf(cls: SensorClass) -> CheckCoverage:
    """The gross test's coverage of the accelerometers, from a fault-free rest of the class."""
    passport = nominal_passport(cls, gravity_mps2=G)
    res = gross_batch(_gross_rest(cls, 10_000), passport, gravity_mps2=G)
    tps, _ = tolerance_passports(passport, gravity_mps2=G)
    return res.coverage[Triad.ACCEL].check(
        tps[Triad.ACCEL], gravity_mps2=G, total_windows=res.windows
    )


def table() -> None:
    print(
        f"Minimum detectable fault of the accelerometers, {RATE_HZ:g} Hz (probability 0.95; % of the class tolerance)"
    )
    print(
        "| class | F0 zero signal | F0 scale | gross zero signal z / scale z, 6 s at rest "
        "| F1…F9 zero signal x / scale z: 9 × 5 s | 9 × 60 s | 18 × 5 s | 18 × 60 s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(1)
    for cls in SensorClass:
        tp = _accel(cls)
        tol_b, tol_e = tp.tolerance[0] * G, tp.tolerance[5]
        _, bias, scale = _f0(tp)
        cells = [
            f"{bias[0]:.3g} m/s² ({100 * bias[0] / tol_b:.0f} %)",
            f"{100 * scale[0]:.3g} % ({100 * scale[0] / tol_e:.0f} %)",
        ]
        gross = _gross_mdf(cls)
        assert gross.mdf_bias_si is not None and gross.mdf_scale is not None
        gb, ge, tol_bz = gross.mdf_bias_si[2], gross.mdf_scale[2], tp.tolerance[2] * G
        cells.append(
            f"{gb:.3g} m/s² ({100 * gb / tol_bz:.0f} %) / {100 * ge:.3g} % ({100 * ge / tol_e:.0f} %)"
        )
        for n, s in ((9, 5.0), (9, 60.0), (18, 5.0), (18, 60.0)):
            b, e = _ninepar_mdf(tp, n, s, rng)
            cells.append(
                f"{b:.3g} m/s² ({100 * b / tol_b:.0f} %) / {100 * e:.3g} % ({100 * e / tol_e:.0f} %)"
            )
        print(f"| {cls.value} | " + " | ".join(cells) + " |")


def f0_curve(cls: SensorClass) -> None:
    tp = _accel(cls)
    config, bias, scale = _f0(tp)
    sd = _sample_sd(tp) * G
    u = np.repeat(FACES, int(RATE_HZ), axis=0)
    rng = np.random.default_rng(2)
    static = np.ones(u.shape[0], bool)
    row_b, row_e = [], []
    for factor in FACTORS:
        found_b = found_e = 0
        for _ in range(TRIALS):
            noise = rng.normal(0.0, sd, u.shape)
            for kind in ("b", "e"):
                x = u * G + noise
                if kind == "b":
                    x[:, 0] += factor * bias[0]
                else:
                    x[:, 2] += factor * scale[2] * u[:, 2] * G
                hit = persistent_failure(f0_batch(x, static, config).state, 0, PERSIST)[0] >= 0
                found_b += hit and kind == "b"
                found_e += hit and kind == "e"
        row_b.append(found_b)
        row_e.append(found_e)
    print(
        f"| F0 {cls.value}, zero signal x (MDF {bias[0]:.3g} m/s²) | "
        + " | ".join(f"{n}/{TRIALS}" for n in row_b)
        + " |"
    )
    print(
        f"| F0 {cls.value}, scale z (MDF {100 * scale[2]:.3g} %) | "
        + " | ".join(f"{n}/{TRIALS}" for n in row_e)
        + " |"
    )


def ninepar_curve(cls: SensorClass) -> None:
    tp = _accel(cls)
    rng = np.random.default_rng(3)
    mdf_b, mdf_e = _ninepar_mdf(tp, 18, 5.0, rng)
    u, cov = _positions(tp, 18, 5.0)
    sd = np.sqrt(cov[:, 0, 0])[:, None]
    rows = {"F1": [], "F6": []}
    for factor in FACTORS:
        for name, j in (("F1", 0), ("F6", 5)):
            truth = u.copy()
            if j == 0:
                truth[:, 0] += factor * mdf_b / G
            else:
                truth[:, 2] *= 1.0 + factor * mdf_e
            found = 0
            for _ in range(TRIALS):
                means = truth + rng.standard_normal(u.shape) * sd
                diag = diagnose(estimate_refined(means, cov, Triad.ACCEL, reference=G), tp)
                found += name in {f.predicate for f in diag.findings}
            rows[name].append(found)
    print(
        f"| F1…F9 {cls.value}, F1 zero signal x (MDF {mdf_b:.3g} m/s²) | "
        + " | ".join(f"{n}/{TRIALS}" for n in rows["F1"])
        + " |"
    )
    print(
        f"| F1…F9 {cls.value}, F6 scale z (MDF {100 * mdf_e:.3g} %) | "
        + " | ".join(f"{n}/{TRIALS}" for n in rows["F6"])
        + " |"
    )


def gross_curve(cls: SensorClass) -> None:
    mdf = _gross_mdf(cls)
    assert mdf.mdf_bias_si is not None and mdf.mdf_scale is not None
    bias, scale = mdf.mdf_bias_si[2], mdf.mdf_scale[2]
    rows = {
        "zero signal z": [
            sum(_gross_found(cls, _gross_rest(cls, s, bias_z=f * bias)) for s in range(TRIALS))
            for f in FACTORS
        ],
        "scale z": [
            sum(_gross_found(cls, _gross_rest(cls, s, scale_z=f * scale)) for s in range(TRIALS))
            for f in FACTORS
        ],
    }
    for name, size in (("zero signal z", f"{bias:.3g} m/s²"), ("scale z", f"{100 * scale:.3g} %")):
        print(
            f"| gross {cls.value}, {name} (MDF {size}) | "
            + " | ".join(f"{n}/{TRIALS}" for n in rows[name])
            + " |"
        )


def main() -> None:
    table()
    print()
    print(f"Detection rate against fault size (× MDF), {TRIALS} seeded trials per point")
    print("| check | " + " | ".join(f"{f:g}×" for f in FACTORS) + " |")
    print("|---|" + "---|" * len(FACTORS))
    for cls in (SensorClass.CONSUMER_MEMS, SensorClass.TACTICAL):
        f0_curve(cls)
    for cls in (SensorClass.CONSUMER_MEMS, SensorClass.TACTICAL):
        ninepar_curve(cls)
    for cls in (SensorClass.CONSUMER_MEMS, SensorClass.TACTICAL):
        gross_curve(cls)


if __name__ == "__main__":
    main()
