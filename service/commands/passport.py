"""``ins-health passport tilt | triad | temperature``: make a passport on a bench (methods.md M2, M1, M3).

* ``tilt``: one accelerometer axis on a tilt table (M2): repeated runs of axis
  up, axis down and a list of table angles; least squares per run, per-run
  confidence intervals, their intersection as the passport value and the
  reproducibility check. ``--simulate`` runs the paper's bench
  (:class:`estimators.tilt.TiltBench`); ``--session FILE`` (once per run)
  reads CSV session files whose axis column holds whole pulses times the
  logger's pulse weight.
* ``triad``: the nine parameters of the accelerometer triad from repeated
  multi-position sessions (M1's estimator), with M2's methodology: per-run
  intervals, intersection, tolerances from the runs' envelope.
* ``temperature``: six-position tests at many temperatures (M3): bias and scale
  error per axis as polynomials in temperature, the order chosen by the GMDH
  held-out criterion; the passport carries the temperature model.

Every subcommand prints a text report (``--json``: one JSON object), writes the
passport with ``--out`` and the report with ``--report``. Exit status 0; 1 if
a parameter is not reproducible across runs (the passport is still written,
with that parameter marked not observable); 2 for unusable input.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimators.conventions import PARAM_NAMES, Grade, Triad
from service.cli import UsageError, add_output
from service.grades import FLOOR_GRADE, SENSOR_CLASSES, grade_name
from service.method_args import (
    add_gravity_options,
    add_method_command,
    add_passport_options,
    add_rejections,
    axis_index,
    emit,
    gravity_from,
    load_valid,
    parse_angles_deg,
    rejected_text,
    write_passport,
)
from service.session_args import add_unit_arguments

if TYPE_CHECKING:
    from estimators.passport import TriadPassport

# The estimators' defaults the parser shows, stated here so that it does not load scipy
# (tests/test_cli_startup.py checks they agree with estimators.sim and estimators.temperature).
ROUNDINGS = ("floor", "toward_zero", "nearest")
"""The values of estimators.sim.Rounding."""
DEFAULT_ROUNDING = "toward_zero"
ORDERS = (1, 2, 3, 4, 5)
DEFAULT_REFERENCE_TEMP_C = 20.0

_ARCMIN = np.pi / 180.0 / 60.0


def register(subparsers) -> None:
    sub = add_method_command(
        subparsers,
        "passport",
        doc=__doc__,
        dest="method",
        metavar="METHOD",
        help="make a passport on a bench: tilt table (M2), repeated triad sessions, temperature model (M3)",
    )

    t = sub.add_parser("tilt", help="single-axis accelerometer on a tilt table (M2)")
    _source_options(
        t,
        runs_default=5,
        session_help="CSV session file of one run (repeat the option for each run)",
    )
    t.add_argument("--axis", choices="xyz", default="x", help="the tested axis column (default x)")
    t.add_argument(
        "--angles-deg",
        help="table angles in measuring order, START:STOP:STEP or a list (default 5:64:1)",
    )
    t.add_argument(
        "--hold-s", type=float, default=30.0, help="time held at each angle, s (default 30)"
    )
    t.add_argument(
        "--lsb-mps2",
        type=float,
        help="pulse weight the logger wrote the CSV with (default: found from the data)",
    )
    t.add_argument(
        "--rounding",
        choices=ROUNDINGS,
        default=DEFAULT_ROUNDING,
        help="how the converter makes whole pulses (default toward_zero, the paper's)",
    )
    t.add_argument(
        "--no-half-pulse",
        action="store_true",
        help="omit the half-pulse correction (to see the bias it removes)",
    )
    t.add_argument(
        "--save-sessions", type=Path, help="with --simulate: write each run as DIR/run<N>.csv"
    )
    _common_options(t)
    t.set_defaults(func=run_tilt)

    r = sub.add_parser(
        "triad",
        help="accelerometer triad from repeated multi-position sessions (M1 with M2's checks)",
    )
    _source_options(
        r,
        runs_default=3,
        session_help="CSV multi-position session of one run (repeat for each run)",
    )
    r.add_argument(
        "--save-sessions", type=Path, help="with --simulate: write each run as DIR/run<N>.csv"
    )
    _common_options(r)
    r.set_defaults(func=run_triad)

    m = sub.add_parser(
        "temperature", help="temperature model from six-position tests at many temperatures (M3)"
    )
    src = m.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--session",
        type=Path,
        help="CSV session with a temp column: six-position tests at several temperatures",
    )
    src.add_argument(
        "--simulate",
        action="store_true",
        help="simulate the paper's chamber: −45…+75 °C, hidden 4th-order dependence",
    )
    m.add_argument("--seed", type=int, default=0, help="random seed of --simulate (default 0)")
    add_unit_arguments(m)
    m.add_argument(
        "--static-s",
        type=float,
        default=20.0,
        help="with --simulate: seconds per position (default 20)",
    )
    add_output(m, "--save-session", help="with --simulate: write the chamber session as CSV")
    m.add_argument(
        "--orders",
        default=",".join(map(str, ORDERS)),
        help="polynomial orders to compare (default 1,2,3,4,5)",
    )
    m.add_argument(
        "--reference-temp-c",
        type=float,
        default=DEFAULT_REFERENCE_TEMP_C,
        help="T_ref of the polynomials, °C (default 20)",
    )
    m.add_argument(
        "--tolerance-c",
        type=float,
        default=2.0,
        help="positions within this of each other are one test temperature, °C",
    )
    _common_options(m)
    m.set_defaults(func=run_temperature)


def _source_options(p: argparse.ArgumentParser, *, runs_default: int, session_help: str) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--session", type=Path, action="append", help=session_help)
    src.add_argument(
        "--simulate", action="store_true", help="simulate the bench instead of reading files"
    )
    p.add_argument(
        "--runs",
        type=int,
        default=runs_default,
        help=f"with --simulate: number of runs (default {runs_default})",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of --simulate (default 0)")
    add_unit_arguments(p)


def _common_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--level", type=float, default=0.95, help="confidence level of the intervals (default 0.95)"
    )
    add_gravity_options(p)
    add_passport_options(p)
    p.add_argument(
        "--grade",
        type=grade_name,
        choices=SENSOR_CLASSES,
        default=SENSOR_CLASSES[0],
        help="sensor class for the default tolerances (default consumer_mems; both MEMS classes "
        "take the MEMS floors; 'mems' is taken as consumer_mems)",
    )
    add_output(p, "--plot", help="write a PNG figure of the method's checks")


def _check_runs(args) -> None:
    if args.simulate and args.runs < 2:
        raise UsageError(f"--runs must be at least 2 to check reproducibility, got {args.runs}")


# --- tilt (M2) -------------------------------------------------------------------------------------


def run_tilt(args: argparse.Namespace) -> int:
    from estimators.sim import Rounding
    from estimators.tilt import (
        TILT_PARAM_NAMES,
        HalfPulse,
        TiltBench,
        bench_session,
        half_pulse_bias,
        run_from_session,
        runs_from_samples,
        simulate_samples,
        tilt_passport,
        tilt_triad_passport,
    )
    from protocols.session_file import write_csv_session

    _check_runs(args)
    axis = axis_index(args.axis)
    angles_deg = None if args.angles_deg is None else parse_angles_deg(args.angles_deg)
    correction = HalfPulse.OMIT if args.no_half_pulse else HalfPulse.APPLY
    truth = None
    rejected: dict[str, int] = {}
    if args.simulate:
        bench = TiltBench(n_runs=args.runs, rounding=Rounding(args.rounding))
        if angles_deg is not None:
            bench = replace(bench, angles_deg=tuple(angles_deg))
        rng = np.random.default_rng(args.seed)
        samples = simulate_samples(bench, rng)
        runs = runs_from_samples(bench, samples)
        g = gravity_from(args, default_mps2=bench.gravity_mps2)
        lsb, rate_hz = bench.lsb_mps2, bench.rate_hz
        truth = dict(zip(TILT_PARAM_NAMES, bench.true_params, strict=True))
        if args.save_sessions is not None:
            args.save_sessions.mkdir(parents=True, exist_ok=True)
            for i, s in enumerate(samples):
                write_csv_session(
                    args.save_sessions / f"run{i + 1}.csv",
                    bench_session(bench, s, axis=axis, rng=rng),
                    metadata={
                        "gravity_mps2": repr(bench.gravity_mps2),
                        "rate_hz": bench.rate_hz,
                        "method": "tilt",
                        "run": i + 1,
                    },
                    comments=(
                        f"simulated tilt-table run {i + 1}: axis up, axis down, angles {bench.angles_deg[0]:g}..{bench.angles_deg[-1]:g} deg",
                    ),
                )
    else:
        angles = np.radians(np.arange(5.0, 65.0) if angles_deg is None else angles_deg)
        runs, lsbs, gravities, rates = [], [], [], []
        for path in args.session:
            loaded, clean, dropped = load_valid(path, args)
            add_rejections(rejected, dropped)
            try:
                run, lsb = run_from_session(
                    clean,
                    angles_rad=angles,
                    axis=axis,
                    hold_s=args.hold_s,
                    lsb_mps2=args.lsb_mps2,
                    rounding=Rounding(args.rounding),
                )
            except ValueError as exc:
                raise UsageError(f"{path}: {exc}") from None
            runs.append(run)
            lsbs.append(lsb)
            gravities.append(loaded.gravity_mps2)
            rates.append(clean.rate_hz)
        if len(runs) < 2:
            raise UsageError(
                "the tilt passport needs at least 2 runs (give --session once per run) to check reproducibility"
            )
        if max(lsbs) - min(lsbs) > 1e-9 * max(lsbs):
            raise UsageError(
                f"the runs were written with different pulse weights {sorted(set(lsbs))}: give --lsb-mps2"
            )
        lsb, rate_hz = lsbs[0], float(np.median(rates))
        g = gravity_from(args, file_gravity_mps2=gravities[0])
    result = tilt_passport(runs, gravity_mps2=g, correction=correction, level=args.level)
    bias = half_pulse_bias(runs, gravity_mps2=g, level=args.level)
    tp = tilt_triad_passport(
        result,
        axis=axis,
        lsb_mps2=lsb,
        sample_rate_hz=rate_hz,
        grade=Grade(FLOOR_GRADE[args.grade]),
    )
    write_passport(args, tp)
    if args.plot is not None:
        from service.method_plots import plot_tilt

        plot_tilt(
            result, runs, args.plot, truth=None if truth is None else np.array(list(truth.values()))
        )
    report = {
        **_tilt_report(result, bias, tp, axis=axis, lsb=lsb, truth=truth),
        "rejected_samples": rejected,
    }
    emit(args, report, _tilt_text(result, bias, lsb, truth, args) + rejected_text(rejected))
    return 0 if result.spread.all_reproducible else 1


def _spread_report(sp) -> dict:
    names = sp.names
    per = lambda arr: dict(zip(names, arr, strict=True))  # noqa: E731
    return {
        "level": sp.level,
        "runs": [
            {
                "value": per(sp.values[r]),
                "std": per(sp.std[r]),
                "ci_low": per(sp.lower[r]),
                "ci_high": per(sp.upper[r]),
            }
            for r in range(sp.n_runs)
        ],
        "across_runs": {
            "mean": per(sp.mean),
            "std": per(sp.spread),
            "mean_ci_low": per(sp.mean_lower),
            "mean_ci_high": per(sp.mean_upper),
        },
        "intersection": {
            "low": per(sp.common_lower),
            "high": per(sp.common_upper),
            "non_empty": per(sp.reproducible),
        },
        "passport_value": per(sp.value),
        "tolerance": per(sp.tolerance),
        "consistency_p_value": per(sp.p_value),
        "reproducible": sp.all_reproducible,
        "not_reproducible": list(sp.not_reproducible()),
    }


def _tilt_report(result, bias, tp: TriadPassport, *, axis: int, lsb: float, truth) -> dict:
    from estimators.tilt import TILT_PARAM_NAMES

    e = result.errors
    return {
        "method": "M2 tilt table",
        "axis": "xyz"[axis],
        "gravity_mps2": result.gravity_mps2,
        "k0_mps2_per_pulse": result.k0_mps2,
        "scale_mps2_per_pulse": result.scale_mps2,
        "lsb_mps2": lsb,
        "half_pulse_correction": result.correction.value,
        "n_runs": result.spread.n_runs,
        "n_angles": [int(f.fit.residuals.size) for f in result.fits],
        "settled_at": [
            dict(zip(TILT_PARAM_NAMES, f.stabilization.settled_at, strict=True))
            for f in result.fits
        ],
        "residual_rms_pulses": [
            float(np.sqrt(np.mean(f.residuals_pulses**2))) for f in result.fits
        ],
        **_spread_report(result.spread),
        "error_rms_pulses": {
            "raw": e.raw,
            "half_pulse": e.half_pulse,
            "in_run_fit": e.in_run,
            "passport": e.passport,
        },
        "without_half_pulse_minus_with": dict(zip(TILT_PARAM_NAMES, bias, strict=True)),
        "passport_axis": {
            "bias_norm": tp.nominal[axis],
            "scale_error": tp.nominal[3 + axis],
            "tolerance_bias_norm": tp.tolerance[axis],
            "tolerance_scale_error": tp.tolerance[3 + axis],
        },
        "truth": truth,
    }


def _tilt_text(result, bias, lsb, truth, args) -> str:
    from estimators.tilt import TILT_PARAM_NAMES

    sp, k0 = result.spread, result.k0_mps2
    fmt = (
        lambda v: f"{v * 1e3:+8.3f}",
        lambda v: f"{v / _ARCMIN:+7.3f}",
        lambda v: f"{v * 1e6:+8.1f}",
    )
    head = "               δa [mm/s²]   δα [′]    Δk [ppm]"
    lines = [
        f"passport tilt: {sp.n_runs} runs × {result.fits[0].fit.residuals.size} angles, axis {args.axis}, g = {result.gravity_mps2:.5f} m/s²",
        f"k0 = 2g/(N↑−N↓) = {k0:.7f} m/s²/pulse; passport k* = k0(1+Δk) = {result.scale_mps2:.7f}; logger pulse weight {lsb:.7g}",
        head,
    ]
    for r in range(sp.n_runs):
        vals = "  ".join(f(sp.values[r, j]) for j, f in enumerate(fmt))
        half = "  ".join(
            f(sp.upper[r, j] - sp.values[r, j]).replace("+", "±") for j, f in enumerate(fmt)
        )
        lines.append(f"run {r + 1:<3}       {vals}   ({half})")
    lines.append(f"mean            {'  '.join(f(sp.mean[j]) for j, f in enumerate(fmt))}")
    lines.append(
        f"std             {'  '.join(f(sp.spread[j]).replace('+', ' ') for j, f in enumerate(fmt))}"
    )
    lines.append(f"intersection lo {'  '.join(f(sp.common_lower[j]) for j, f in enumerate(fmt))}")
    lines.append(f"intersection hi {'  '.join(f(sp.common_upper[j]) for j, f in enumerate(fmt))}")
    lines.append(f"passport value  {'  '.join(f(sp.value[j]) for j, f in enumerate(fmt))}")
    if truth is not None:
        lines.append(
            f"simulated truth {'  '.join(f(truth[n]) for f, n in zip(fmt, TILT_PARAM_NAMES, strict=True))}"
        )
    lines.append(
        "reproducible across runs: yes"
        if sp.all_reproducible
        else f"NOT reproducible across runs: {', '.join(sp.not_reproducible())}"
    )
    e = result.errors
    lines.append(
        f"error RMS: raw {e.raw:.2f} pulse, half-pulse corrected {e.half_pulse:.2f} → with the passport {e.passport:.2f} (in-run fit {e.in_run:.2f})"
    )
    lines.append(
        f"without the half-pulse correction the passport would move by δa {bias[0] * 1e3:+.3f} mm/s² ({bias[0] / k0:+.2f} pulse), "
        f"δα {bias[1] / _ARCMIN:+.3f}′, Δk {bias[2] * 1e6:+.1f} ppm"
    )
    if args.out is not None:
        lines.append(f"passport written to {args.out}")
    return "\n".join(lines)


# --- triad (M1 estimates, M2 methodology) ---------------------------------------------------------------


def run_triad(args: argparse.Namespace) -> int:
    from estimators.passport import per_sample_noise_std
    from estimators.repeatability import passport_from_runs, triad_runs
    from estimators.sim import multi_position_spec, simulate
    from estimators.sixpos import quantizer_offset, session_positions
    from protocols.session_file import write_csv_session

    _check_runs(args)
    sessions, file_gravity = [], None
    rejected: dict[str, int] = {}
    if args.simulate:
        for i in range(args.runs):
            res = simulate(multi_position_spec(grade=Grade.MEMS), args.seed + i)
            sessions.append((f"run {i + 1}", res.session))
            file_gravity = res.truth.gravity_mps2
            if args.save_sessions is not None:
                args.save_sessions.mkdir(parents=True, exist_ok=True)
                write_csv_session(
                    args.save_sessions / f"run{i + 1}.csv",
                    res.session,
                    metadata={"gravity_mps2": repr(res.truth.gravity_mps2)},
                )
        # The simulator's truth excludes the converter's mean rounding offset, which
        # is part of the bias the data show.
        truth = res.truth.accel_params.copy()
        truth[0:3] += quantizer_offset(res.truth.model.accel) / res.truth.gravity_true_mps2
    else:
        for path in args.session:
            loaded, clean, dropped = load_valid(path, args)
            add_rejections(rejected, dropped)
            sessions.append((str(path), clean))
            file_gravity = file_gravity or loaded.gravity_mps2
        truth = None
    if len(sessions) < 2:
        raise UsageError(
            "the triad passport needs at least 2 sessions (give --session once per run) to check reproducibility"
        )
    g = gravity_from(args, file_gravity_mps2=file_gravity)
    positions = []
    for name, session in sessions:
        if session.accel_mps2 is None:
            raise UsageError(f"{name}: the session has no accelerometer columns")
        positions.append(session_positions(session, min_static_s=2.0))
    try:
        runs = triad_runs(positions, Triad.ACCEL, g, level=args.level)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    all_positions = [p for run in positions for p in run]
    tp = passport_from_runs(
        runs,
        noise_std=per_sample_noise_std(all_positions, Triad.ACCEL, g),
        sample_rate_hz=float(np.median([s.rate_hz for _, s in sessions])),
    )
    write_passport(args, tp)
    sp = runs.spread
    if args.plot is not None:
        from service.method_plots import plot_triad

        plot_triad(sp, args.plot, truth=truth)
    report = {
        "method": "M1 nine parameters from repeated sessions, M2 reproducibility",
        "triad": "accel",
        "gravity_mps2": g,
        "n_positions": [e.n_positions for e in runs.estimates],
        "settled_at": [
            dict(zip(PARAM_NAMES, s.settled_at, strict=True)) for s in runs.stabilizations
        ],
        **_spread_report(sp),
        "observable": dict(zip(PARAM_NAMES, tp.observable, strict=True)),
        "truth": None if truth is None else dict(zip(PARAM_NAMES, truth, strict=True)),
        "rejected_samples": rejected,
    }
    lines = [
        f"passport triad: {sp.n_runs} runs, positions {report['n_positions']}, g = {g:.5f} m/s²",
        "param      value        tolerance    intersection                 reproducible"
        + ("   truth" if truth is not None else ""),
    ]
    for j, name in enumerate(PARAM_NAMES):
        row = f"{name:<6} {sp.value[j]:+.4e}  {sp.tolerance[j]:.3e}   [{sp.common_lower[j]:+.4e}, {sp.common_upper[j]:+.4e}]  {'yes' if sp.reproducible[j] else 'NO'}"
        lines.append(row + (f"   {truth[j]:+.4e}" if truth is not None else ""))
    if args.out is not None:
        lines.append(f"passport written to {args.out}")
    emit(args, report, "\n".join(lines) + rejected_text(rejected))
    return 0 if sp.all_reproducible else 1


# --- temperature (M3) ------------------------------------------------------------------------------------


def _orders(text: str) -> tuple[int, ...]:
    try:
        orders = tuple(sorted({int(v) for v in text.split(",") if v.strip()}))
    except ValueError:
        raise UsageError(f"--orders must be a comma list of integers, got {text!r}") from None
    if not orders or min(orders) < 0 or max(orders) > 8:
        raise UsageError(f"--orders must be polynomial degrees between 0 and 8, got {text!r}")
    return orders


def run_temperature(args: argparse.Namespace) -> int:
    from estimators.sixpos import session_positions
    from estimators.temperature import (
        PAPER_TEMPS_C,
        fit_temperature_model,
        hidden_quartic_model,
        model_errors,
        simulate_chamber,
        temperature_series,
        temperature_truth,
    )
    from protocols.session_file import write_csv_session

    orders = _orders(args.orders)
    model = None
    rejected: dict[str, int] = {}
    if args.simulate:
        g = gravity_from(args, default_mps2=9.80619)
        model = hidden_quartic_model(gravity_mps2=g, t_ref_c=args.reference_temp_c)
        session = simulate_chamber(model, PAPER_TEMPS_C, seed=args.seed, static_s=args.static_s)
        if args.save_session is not None:
            write_csv_session(
                args.save_session,
                session,
                metadata={"gravity_mps2": repr(g)},
                comments=("simulated chamber: six positions at -45..75 degC",),
            )
    else:
        loaded, session, dropped = load_valid(args.session, args)
        add_rejections(rejected, dropped)
        g = gravity_from(args, file_gravity_mps2=loaded.gravity_mps2)
        if session.accel_mps2 is None:
            raise UsageError(f"{args.session}: the session has no accelerometer columns")
    positions = session_positions(session)
    series = temperature_series(positions, gravity_mps2=g, tolerance_c=args.tolerance_c)
    fit = fit_temperature_model(
        series.temp_c,
        series.bias_mps2,
        series.scale_error,
        bias_std_mps2=series.bias_std_mps2,
        scale_std=series.scale_std,
        gravity_mps2=g,
        orders=orders,
        reference_temp_c=args.reference_temp_c,
    )
    tp = _temperature_passport(
        fit, series, positions, g, Grade(FLOOR_GRADE[args.grade]), args.level, session.rate_hz
    )
    write_passport(args, tp)
    if args.plot is not None:
        from service.method_plots import plot_temperature

        plot_temperature(fit, series, args.plot)
    b_fit, e_fit = model_errors(fit.model, series.temp_c)
    b_ref, e_ref = model_errors(fit.model, np.array([fit.model.reference_temp_c]))
    measured = {
        "zero_error_before_g": float(np.max(np.abs(series.bias_mps2 / g - b_ref))),
        "zero_error_after_g": float(np.max(np.abs(series.bias_mps2 / g - b_fit))),
        "scale_error_before": float(np.max(np.abs(series.scale_error - e_ref))),
        "scale_error_after": float(np.max(np.abs(series.scale_error - e_fit))),
    }
    truth = None
    if model is not None:
        grid = np.linspace(PAPER_TEMPS_C[0], PAPER_TEMPS_C[-1], 481)
        bt, et = temperature_truth(model, grid)
        b0, e0 = temperature_truth(model, np.array([args.reference_temp_c]))
        bm, em = model_errors(fit.model, grid)
        truth = {
            "hidden_order": 4,
            "zero_error_before_g": float(np.max(np.abs(bt - b0)) / g),
            "zero_error_after_g": float(np.max(np.abs(bt / g - bm))),
            "scale_error_before": float(np.max(np.abs(et - e0))),
            "scale_error_after": float(np.max(np.abs(et - em))),
        }
    report = {
        "method": "M3 temperature model",
        "gravity_mps2": g,
        "temperatures_c": series.temp_c,
        "scores": [
            {
                "order": s.order,
                "heldout_criterion": s.regularity,
                "heldout_se": s.regularity_se,
                "training_criterion": s.training,
            }
            for s in fit.scores
        ],
        "order": fit.order,
        "reason": fit.reason,
        "model": fit.model.to_dict(),
        "measured_max_errors": measured,
        "truth_max_errors": truth,
        "rejected_samples": rejected,
    }
    lines = [
        f"passport temperature: {series.temp_c.size} test temperatures {series.temp_c.min():g}…{series.temp_c.max():g} °C, g = {g:.5f} m/s²",
        "order   held-out criterion (±se)   training residual",
    ]
    for s in fit.scores:
        mark = "  ← selected" if s.order == fit.order else ""
        lines.append(
            f"{s.order:>5}   {s.regularity:>12.4g} (±{s.regularity_se:.2g})   {s.training:>12.4g}{mark}"
        )
    lines.append(fit.reason)
    lines.append(
        f"measured: zero error {measured['zero_error_before_g']:.2e} g → {measured['zero_error_after_g']:.2e} g, "
        f"scale error {measured['scale_error_before'] * 100:.3f} % → {measured['scale_error_after'] * 100:.4f} % (largest over the test temperatures)"
    )
    if truth is not None:
        lines.append(
            f"against the simulated truth (hidden order 4, dense grid): zero error {truth['zero_error_before_g']:.2e} g → {truth['zero_error_after_g']:.2e} g, "
            f"scale error {truth['scale_error_before'] * 100:.2f} % → {truth['scale_error_after'] * 100:.5f} %"
        )
    if args.out is not None:
        lines.append(f"passport written to {args.out}")
    emit(args, report, "\n".join(lines) + rejected_text(rejected))
    return 0


def _temperature_passport(
    fit, series, positions, g: float, grade: Grade, level: float, rate_hz: float
) -> TriadPassport:
    """The accelerometer passport at T_ref: nominal bias and scale from the model's constant terms,
    non-orthogonality from the six-position tests (mean over temperatures), the temperature model attached."""
    from estimators.ninepar import Method
    from estimators.passport import (
        Provenance,
        TriadPassport,
        default_tolerance_rule,
        per_sample_noise_std,
        reference_kind,
    )
    from estimators.repeatability import t_quantile

    nine = np.mean([t.nine_params() for t in series.tests], axis=0)
    nine[0:3] = fit.model.bias_coeffs[:, 0]
    nine[3:6] = fit.model.scale_coeffs[:, 0]
    sigma = np.concatenate(
        [
            np.sqrt(fit.bias_cov[:, 0, 0]),
            np.sqrt(fit.scale_cov[:, 0, 0]),
            np.std([t.nine_params()[6:] for t in series.tests], axis=0),
        ]
    )
    z = float(t_quantile(level, np.inf))
    rule = default_tolerance_rule(Triad.ACCEL, grade, g)
    return TriadPassport(
        triad=Triad.ACCEL,
        reference=g,
        reference_kind=reference_kind(Triad.ACCEL),
        nominal=nine,
        tolerance=rule.tolerance(sigma),
        sigma=sigma,
        observable=np.ones(9, dtype=bool),
        noise_std=per_sample_noise_std(positions, Triad.ACCEL, g),
        sample_rate_hz=rate_hz,
        provenance=Provenance(
            Method.LINEAR,
            len(positions),
            level,
            nine - z * sigma,
            nine + z * sigma,
            procedure="M3 temperature chamber, six-position tests",
        ),
        temperature=fit.model,
    )
