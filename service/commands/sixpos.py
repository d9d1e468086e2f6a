"""``ins-health sixpos static | rate``: six-position and rate-table tests (methods.md M4).

* ``sixpos static``: one session holding the six positions (each axis up,
  then down, in any order). Prints each accelerometer's bias, scale error,
  misalignment and quadratic term, and each gyro's g-independent bias ``Bf``
  and g-sensitivity ``Bg``, with standard deviations. Local gravity comes from
  ``--latitude``/``--height`` (WGS-84 normal gravity) or
  ``--gravity``; the report also shows how much every scale error would
  move if the standard 9.80665 m/s² were assumed instead.
* ``sixpos rate --axis A``: one rate-table session with gyro ``A`` on the
  table axis, the table stepping through a rate profile (default the paper's:
  0, 20, …, 200, 180, …, −200 °/s, in that order). The steps are found as
  plateaus of that gyro and matched to the profile in time order; a
  straight-line fit gives the scale error, the bias and the other gyros'
  cross-coupling.

``--simulate`` replaces ``--session`` with a simulated ADIS16355-like unit at
the paper's site (Guangzhou, g = 9.788 m/s²). ``--json`` prints one JSON
object. Exit status 0; 2 for unusable input.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from estimators.conventions import STANDARD_GRAVITY_MPS2, normal_gravity_mps2
from service.cli import UsageError, add_output
from service.method_args import (
    add_gravity_options,
    add_method_command,
    axis_index,
    emit,
    gravity_from,
    rejected_text,
)
from service.session_args import add_unit_arguments, load_units_checked

_DEG = np.pi / 180.0


def register(subparsers) -> None:
    sub = add_method_command(
        subparsers,
        "sixpos",
        doc=__doc__,
        dest="test",
        metavar="TEST",
        help="six-position accelerometer/gyro test and rate-table gyro scale factor (M4)",
    )
    s = sub.add_parser(
        "static",
        help="six positions: accelerometer scale, bias, misalignment, quadratic term; gyro Bf, Bg",
    )
    _source(s)
    s.add_argument(
        "--static-s",
        type=float,
        default=60.0,
        help="with --simulate: seconds per position (default 60, the paper's)",
    )
    s.set_defaults(func=run_static)
    r = sub.add_parser(
        "rate", help="rate table: gyro scale factor by a straight-line fit over the rate steps"
    )
    _source(r)
    r.add_argument("--axis", choices="xyz", required=True, help="the gyro on the table axis")
    r.add_argument(
        "--max-dps",
        type=float,
        default=200.0,
        help="largest table rate of the profile, °/s (default 200)",
    )
    r.add_argument(
        "--step-dps", type=float, default=20.0, help="rate step of the profile, °/s (default 20)"
    )
    r.add_argument(
        "--hold-s", type=float, default=10.0, help="time the table holds each rate, s (default 10)"
    )
    add_output(r, "--plot", help="write a PNG of the fit and its residuals")
    r.set_defaults(func=run_rate)


def _source(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--session", type=Path, help="CSV session file")
    src.add_argument(
        "--simulate", action="store_true", help="simulate an ADIS16355-like unit at Guangzhou"
    )
    add_unit_arguments(p)
    p.add_argument("--seed", type=int, default=0, help="random seed of --simulate (default 0)")
    add_output(p, "--save-session", help="with --simulate: write the session as CSV")
    add_gravity_options(p)
    add_output(p, "--report", help="also write the report as JSON")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")


def _load(args, make_session):
    """(session, local gravity, latitude or None, simulator model or None, rejected samples by reason)."""
    from estimators.sixpos import GUANGZHOU_HEIGHT_M, GUANGZHOU_LATITUDE_DEG, adis_like_model
    from protocols.session_file import write_csv_session

    if args.simulate:
        g_site = normal_gravity_mps2(GUANGZHOU_LATITUDE_DEG, GUANGZHOU_HEIGHT_M)
        model = adis_like_model()
        session = make_session(model, g_site)
        if args.save_session is not None:
            write_csv_session(
                args.save_session,
                session,
                metadata={"gravity_mps2": repr(g_site), "latitude_deg": GUANGZHOU_LATITUDE_DEG},
            )
        latitude = args.latitude_deg if args.latitude_deg is not None else GUANGZHOU_LATITUDE_DEG
        return session, gravity_from(args, default_mps2=g_site), latitude, model, {}
    from estimators.session import validate_session

    loaded = load_units_checked(args.session, None, None, args)
    clean, dropped = validate_session(loaded.session)
    return (
        clean,
        gravity_from(args, file_gravity_mps2=loaded.gravity_mps2),
        args.latitude_deg,
        None,
        dict(dropped.counts),
    )


def run_static(args: argparse.Namespace) -> int:
    from estimators.sim import simulate
    from estimators.sixpos import (
        ACCEL_TERM_NAMES,
        accel_truth,
        gyro_truth,
        session_positions,
        six_position_accel,
        six_position_spec,
        six_position_test,
    )

    session, g, latitude, model, rejected = _load(
        args,
        lambda model, g_site: (
            simulate(six_position_spec(model, static_s=args.static_s), args.seed).session
        ),
    )
    if session.accel_mps2 is None:
        raise UsageError(
            "the session has no accelerometer columns: the six-position test needs them"
        )
    positions = session_positions(session)
    test = six_position_test(positions, gravity_mps2=g, latitude_deg=latitude)
    acc = test.accel
    standard = six_position_accel(
        np.array([p.accel_mean_mps2 for p in positions]),
        gravity_mps2=STANDARD_GRAVITY_MPS2,
        accel_cov_mps2=np.array([p.accel_cov_mps2 for p in positions]),
    )
    shift = standard.scale_error - acc.scale_error
    report = {
        "method": "M4 six-position test",
        "gravity_mps2": g,
        "n_positions": len(positions),
        "accel": {
            "terms": list(ACCEL_TERM_NAMES),
            "value": acc.values,
            "std": acc.std,
            "misalignment": acc.misalignment,
            "residuals_mps2": acc.residuals_mps2,
        },
        "scale_error_shift_with_standard_gravity": shift,
        # (A↑ − A↓)/2 = (1 + S)·g, so assuming g_n gives 1 + S' = (1 + S)·g/g_n.
        "expected_shift": (1.0 + acc.scale_error) * (g / STANDARD_GRAVITY_MPS2 - 1.0),
        "gyro": None
        if test.gyro is None
        else {
            "bias_rps": test.gyro.bias_rps,
            "g_sensitivity_rps_per_mps2": test.gyro.g_sensitivity,
            "std": test.gyro.std,
            "earth_rate_removed": test.gyro.earth_rate_removed,
        },
        "truth": None
        if model is None
        else {
            "accel": accel_truth(model),
            "gyro_bias_rps": gyro_truth(model)[0],
            "gyro_g_sensitivity": gyro_truth(model)[1],
        },
        "rejected_samples": rejected,
    }
    lines = [
        f"sixpos static: {len(positions)} positions, g = {g:.5f} m/s²",
        "axis  bias [mg]           scale error [%]       misalign [mrad] (two)          quadratic [1/(m/s²)]",
    ]
    for i in range(3):
        v, s = acc.values[i], acc.std[i]
        lines.append(
            f"{'xyz'[i]:<5} {v[0] / g * 1e3:+8.3f} ±{s[0] / g * 1e3:.3f}   {v[1] * 100:+8.4f} ±{s[1] * 100:.4f}   "
            f"{v[2] * 1e3:+7.3f} ±{s[2] * 1e3:.3f} {v[3] * 1e3:+7.3f} ±{s[3] * 1e3:.3f}   {v[4]:+.3e} ±{s[4]:.1e}"
        )
    if model is not None:
        tr = accel_truth(model)
        lines.append(
            "truth "
            + "  ".join(
                f"{'xyz'[i]}: b {tr[i, 0] / g * 1e3:+.3f} mg, S {tr[i, 1] * 100:+.4f} %, Q {tr[i, 4]:+.3e}"
                for i in range(3)
            )
        )
    lines.append(
        f"with g = 9.80665 instead of {g:.5f} every scale error moves by {np.mean(shift) * 100:+.4f} % "
        f"(expected g/9.80665 − 1 = {(g / STANDARD_GRAVITY_MPS2 - 1) * 100:+.4f} %)"
    )
    if test.gyro is not None:
        gy = test.gyro
        lines.append("gyro  Bf [°/s]             Bg x, y, z [°/s per g]")
        for i in range(3):
            gs = gy.g_sensitivity[i] * g / _DEG
            lines.append(
                f"{'xyz'[i]:<5} {gy.bias_rps[i] / _DEG:+.4f} ±{gy.std[i, 0] / _DEG:.4f}   "
                + "  ".join(f"{v:+.4f}" for v in gs)
                + f"   (±{gy.std[i, 1] * g / _DEG:.4f})"
            )
        if model is not None:
            bf, bg = gyro_truth(model)
            lines.append(
                "truth "
                + "  ".join(
                    f"{'xyz'[i]}: Bf {bf[i] / _DEG:+.4f}, Bg {', '.join(f'{v:+.4f}' for v in bg[i] * g / _DEG)}"
                    for i in range(3)
                )
            )
    emit(args, report, "\n".join(lines) + rejected_text(rejected))
    return 0


def run_rate(args: argparse.Namespace) -> int:
    from estimators.sixpos import (
        find_rate_steps,
        paper_rate_profile_rps,
        rate_table_fit,
        rate_table_truth,
        simulate_rate_table,
    )

    axis = axis_index(args.axis)
    try:
        profile = paper_rate_profile_rps(max_dps=args.max_dps, step_dps=args.step_dps)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    session, _, _, model, rejected = _load(
        args,
        lambda model, g_site: simulate_rate_table(
            model,
            axis=axis,
            profile_rps=profile,
            hold_s=args.hold_s,
            gravity_mps2=g_site,
            seed=args.seed,
        ),
    )
    if session.gyro_rps is None:
        raise UsageError("the session has no gyro columns: the rate-table test needs them")
    steps = find_rate_steps(
        session.t_s, session.gyro_rps, axis=axis, profile_rps=profile, min_hold_s=0.5 * args.hold_s
    )
    fit = rate_table_fit(
        profile, steps.gyro_mean_rps, axis=axis, gyro_var_rps=steps.gyro_var_rps[:, axis]
    )
    if args.plot is not None:
        from service.method_plots import plot_rate_table

        plot_rate_table(fit, args.plot)
    truth = None if model is None else rate_table_truth(model)[:, axis]
    report = {
        "method": "M4 rate table",
        "axis": args.axis,
        "n_steps": int(profile.size),
        "table_rate_dps": np.degrees(profile),
        "scale_error": fit.scale_error,
        "scale_error_std": fit.scale_error_std,
        "bias_rps": fit.bias_rps,
        "cross_coupling": fit.cross_coupling,
        "nonlinearity": fit.nonlinearity,
        "residuals_rps": fit.residuals_rps,
        "truth_slopes": truth,
        "rejected_samples": rejected,
    }
    lines = [
        f"sixpos rate: gyro {args.axis}, {profile.size} steps to ±{args.max_dps:g} °/s",
        f"scale error {fit.scale_error * 100:+.4f} % ± {fit.scale_error_std * 100:.4f} %, bias {fit.bias_rps / _DEG:+.4f} °/s",
        "slopes of gyros x, y, z against the table rate: "
        + ", ".join(f"{v:+.5f}" for v in fit.cross_coupling),
        f"nonlinearity (largest residual / full scale) {fit.nonlinearity * 100:.4f} %",
    ]
    if truth is not None:
        lines.append(
            "simulated truth of the slopes:                   "
            + ", ".join(f"{v:+.5f}" for v in truth)
        )
    emit(args, report, "\n".join(lines) + rejected_text(rejected))
    return 0
