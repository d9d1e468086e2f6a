"""The Xsens half-to-half spreads against the extended model's replicas, per triad (issue 13, item 4).

Run: ``python benchmarks/bench_audit_halves.py [--replicas N] [--seed S] [--z-gm SIGMA_G TAU_S]``. Prints,
for the measured session and for the replicas of the extended model as the audit fits it (and of the same
model without the z wander, without the accelerometer wanders' loadings on other axes, and with ``--z-gm``
a z Gauss–Markov bias of σ in g and τ in s instead), for the accelerometers and the gyros:

1. the level at which 0.5 s means shrink (:func:`estimators.noise.batch_means_sd`) per axis, over every
   position and over the positions the audit does not flag as disturbed, and the median per-position
   batch-means factor ``m·var(batch means)/var(samples)`` per axis;
2. the half-to-half statistic ``rms(d / 2σ)`` per axis with σ from the chain's batch-means factor pooled
   over the three axes (what the audit compares, ``estimators.positions``) and from a factor per axis,
   over every position and without the disturbed ones: measured, the replicas' ratio (measured / median),
   the tail (share of replicas ≥ measured) and whether the measured value is inside their 5–95 % band;
3. the correlation of the x and z half-to-half differences over the undisturbed positions (a wander common
   to both axes shows there).

A pooled factor lets one axis' wander inside the 0.5 s batches raise the others' σ; the per-axis factor
does not, so an axis still outside with it has an excess of its own.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from estimators.audit import extend_model, find_candidates, fit_baselines, same_session_spec
from estimators.audit.audit import triad_model, triad_samples
from estimators.audit.statistics import position_span, position_table
from estimators.chain import ChainConfig, ChainResult, run_chain
from estimators.conventions import EARTH_RATE_RPS, Triad
from estimators.noise import batch_means_sd
from estimators.session import validate_session
from estimators.sim import ErrorModel, simulate
from estimators.sim.errors import BiasInstability
from estimators.static_detector import StaticDetectorConfig
from protocols.session_file import load_session

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "xsens-multiposition"
G_XSENS = 9.81744
BATCH = 50
"""0.5 s at the session's 100 Hz: the chain's batch length."""


def spans(chain: ChainResult, skip: set[int]) -> list[tuple[int, int]]:
    return [
        position_span(p)
        for k, p in enumerate(chain.positions)
        if k not in skip and p.n_intervals == 1
    ]


def figures(x: np.ndarray, chain: ChainResult, skip: set[int]) -> dict[str, np.ndarray]:
    """Batch levels, median batch factor and the half-to-half statistic (pooled / per-axis factor)."""
    out: dict[str, np.ndarray] = {
        "level_all": batch_means_sd([x[a:b] for a, b in spans(chain, set())], BATCH),
        "level_kept": batch_means_sd([x[a:b] for a, b in spans(chain, skip)], BATCH),
    }
    for label, drop in (("all", set()), ("kept", skip)):
        factor, pooled, per_axis = [], [], []
        for a, b in spans(chain, drop):
            y = x[a:b]
            nb = y.shape[0] // BATCH
            var = y.var(axis=0, ddof=1)
            var_b = y[: nb * BATCH].reshape(nb, BATCH, 3).mean(axis=1).var(axis=0, ddof=1)
            h = (a + b) // 2
            d2 = (x[a:h].mean(axis=0) - x[h:b].mean(axis=0)) ** 2
            factor.append(BATCH * var_b / var)
            pooled.append(d2 / (4.0 * var * max(1.0, BATCH * var_b.sum() / var.sum()) / y.shape[0]))
            per_axis.append(d2 / (4.0 * var * np.maximum(1.0, BATCH * var_b / var) / y.shape[0]))
        out[f"factor_{label}"] = np.median(factor, axis=0)
        out[f"halves_pooled_{label}"] = np.sqrt(np.mean(pooled, axis=0))
        out[f"halves_per_axis_{label}"] = np.sqrt(np.mean(per_axis, axis=0))
    d = np.array(
        [
            x[a : (a + b) // 2].mean(axis=0) - x[(a + b) // 2 : b].mean(axis=0)
            for a, b in spans(chain, skip)
        ]
    )
    out["halves_corr_xz_kept"] = np.array([np.corrcoef(d[:, 0], d[:, 2])[0, 1]])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicas", type=int, default=100)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--z-gm", type=float, nargs=2, metavar=("SIGMA_G", "TAU_S"))
    args = ap.parse_args()
    session = load_session(str(DATA)).session
    config = replace(
        ChainConfig(gravity_mps2=G_XSENS, detector=StaticDetectorConfig.from_session(session)),
        bias_instability_std=None,
    )
    session, _ = validate_session(
        session, accel_limit_mps2=config.accel_limit_mps2, gyro_limit_rps=config.gyro_limit_rps
    )
    chain = run_chain(session, config)
    base = fit_baselines(session, chain)
    model = ErrorModel(
        accel=triad_model(base[Triad.ACCEL], G_XSENS),
        gyro=triad_model(base[Triad.GYRO], EARTH_RATE_RPS),
    )
    cands = find_candidates(session, chain, base)
    tab = position_table(
        chain, triad_samples(session, Triad.ACCEL), session.t_s, Triad.ACCEL, session.temp_c
    )
    ext, _ = extend_model(model, base, cands, tab, G_XSENS)
    skip = set(
        next(c for c in cands if c.effect == "nonstatic_positions").params.get(
            "disturbed_positions", []
        )
    )
    fitted = ext.accel.find(BiasInstability)
    assert fitted is not None, "the audit names no accelerometer wander on this session"
    sigma, tau = np.array(fitted.gm_sigma_si), np.array(fitted.gm_tau_s)
    loading = np.array(fitted.gm_loading)
    variants = {"extended (as fitted)": ext}
    for label, z in (("without the z wander", (0.0, tau[2])), ("--z-gm", args.z_gm)):
        if z is not None:
            s, t = sigma.copy(), tau.copy()
            s[2], t[2] = z[0] * (G_XSENS if label == "--z-gm" else 1.0), z[1]
            variants[f"{label}: z σ {s[2]:.3g} m/s², τ {t[2]:.3g} s"] = ext.with_effect(
                BiasInstability(gm_sigma_si=s, gm_tau_s=t, gm_loading=loading), Triad.ACCEL
            )
    if not np.array_equal(loading, np.eye(3)):
        variants["without the wanders' loadings on other axes"] = ext.with_effect(
            BiasInstability(gm_sigma_si=sigma, gm_tau_s=tau), Triad.ACCEL
        )
    samples = {Triad.ACCEL: lambda s: s.accel_mps2, Triad.GYRO: lambda s: s.gyro_rps}
    measured = {tri: figures(get(session), chain, skip) for tri, get in samples.items()}
    print(f"Xsens; disturbed positions left out of 'kept': {sorted(skip)}")
    print(
        f"fitted accelerometer wander: σ {' / '.join(f'{v:.3g}' for v in sigma)} m/s², "
        f"τ {' / '.join(f'{v:.3g}' for v in tau)} s (x / y / z), loading (columns: the axis' wander) "
        f"{np.round(loading, 3).tolist()}"
    )
    for tri, figs in measured.items():
        for key, value in figs.items():
            print(
                f"measured {tri.value:5s} {key:22s} x/y/z {' / '.join(f'{v:.4g}' for v in value)}"
            )
    for label, mdl in variants.items():
        spec = same_session_spec(chain, session, mdl)
        reps: dict[Triad, list[dict[str, np.ndarray]]] = {tri: [] for tri in samples}
        for r in range(args.replicas):
            sim = simulate(spec, np.random.SeedSequence([args.seed, r]).generate_state(1)[0])
            sim_chain = run_chain(sim.session, config)
            for tri, get in samples.items():
                reps[tri].append(figures(get(sim.session), sim_chain, skip))
        print(f"\n{label}, {args.replicas} replicas")
        for tri, figs in measured.items():
            for key, value in figs.items():
                sim_v = np.array([rep[key] for rep in reps[tri]])
                med = np.median(sim_v, axis=0)
                p05, p95 = np.quantile(sim_v, [0.05, 0.95], axis=0)
                cells = [
                    f"{m / s:.2f} (tail {tl:.2f}, {'in' if lo <= m <= hi else 'OUT'})"
                    for m, s, tl, lo, hi in zip(
                        value, med, np.mean(sim_v >= value, axis=0), p05, p95, strict=True
                    )
                ]
                print(
                    f"  {tri.value:5s} median {key:22s} {' / '.join(f'{v:.4g}' for v in med)}   "
                    f"ratio {' / '.join(cells)}"
                )


if __name__ == "__main__":
    main()
