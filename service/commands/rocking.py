"""``ins-health rocking``: gyro scale-factor errors from synchronous rocking (methods.md M5).

Either ``--log FILE [FILE ...]`` (CSV session files with gyro columns
``t,gx,gy,gz`` in rad/s in the paper's axes X forward, Y up, Z right; other
columns are ignored; together one run of each pair roll+pitch, roll+yaw,
pitch+yaw, each with still parts before and after its rocking; runs may
follow one another in one file) or ``--simulate`` (the paper's stand and unit,
options below). Prints the drifts, the X values, δK by the paper's closed
form and by the model-based estimate (the default ``dK``), with their
uncertainty, and the corrected transfer coefficients ``K = K_H/(1 + δK)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimators.conventions import RPS_PER_DPH
from service.cli import UsageError, add_output
from service.method_args import emit
from service.session_args import add_unit_arguments, load_units_checked

if TYPE_CHECKING:
    from estimators.rocking import RockingResult, StandSettings

_SYMBOL = {"gamma": "γ", "psi": "ψ", "theta": "θ"}
PAPER_REL_SIGMA = 0.01
"""estimators.rocking.PAPER_REL_SIGMA, stated here so that the parser does not load scipy
(tests/test_cli_startup.py checks they agree)."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "rocking",
        help="gyro scale-factor errors from attitude drift under two-axis rocking (M5)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--log", nargs="+", type=Path, metavar="FILE", help="CSV record(s) of the three runs"
    )
    src.add_argument(
        "--simulate",
        action="store_true",
        help="simulate the paper's stand and unit (12.2°, 0.53 Hz, its δK)",
    )
    add_unit_arguments(p)
    st = p.add_argument_group("stand")
    st.add_argument(
        "--amplitude-deg",
        type=float,
        help="stand amplitude setting, deg (simulate: 12.2; log: fitted if not given)",
    )
    st.add_argument(
        "--frequency-hz",
        type=float,
        help="stand frequency setting, Hz (simulate: 0.53; log: fitted if not given)",
    )
    st.add_argument(
        "--amplitude-rel-sigma",
        type=float,
        default=PAPER_REL_SIGMA,
        help="stated relative amplitude uncertainty (default 0.01)",
    )
    st.add_argument(
        "--frequency-rel-sigma",
        type=float,
        default=PAPER_REL_SIGMA,
        help="stated relative frequency uncertainty (default 0.01)",
    )
    st.add_argument(
        "--latitude",
        dest="latitude_deg",
        type=float,
        metavar="DEG",
        help="model the Earth rate at this latitude (default: not modelled)",
    )
    st.add_argument(
        "--heading-deg",
        type=float,
        default=0.0,
        help="heading of the stand's X axis from north, deg (default 0)",
    )
    sim = p.add_argument_group("simulation (--simulate)")
    sim.add_argument(
        "--dk",
        type=float,
        nargs=3,
        metavar=("DK1", "DK2", "DK3"),
        help="scale-factor errors of channels 1-3 (default: the paper's)",
    )
    sim.add_argument(
        "--bias-deg-h",
        type=float,
        nargs=3,
        metavar=("B1", "B2", "B3"),
        help="gyro zero signals, deg/h (default 2 -30 5)",
    )
    sim.add_argument(
        "--arw-deg-rth", type=float, help="angle random walk, deg/sqrt(h) (default 0.003)"
    )
    sim.add_argument(
        "--phase-deg",
        type=float,
        help="phase difference of all three runs, deg (default: the paper's +90, -90, +90)",
    )
    sim.add_argument("--rate-hz", type=float, help="sample rate, Hz (default 100)")
    sim.add_argument("--seed", type=int, help="random seed (default 0)")
    add_output(
        sim,
        "--save-csv",
        metavar="FILE",
        help="also write the simulated record (three runs in a row) as a CSV session file",
    )
    out = p.add_argument_group("output")
    out.add_argument(
        "--k-nominal",
        type=float,
        nargs=3,
        default=(1.0, 1.0, 1.0),
        metavar=("K1H", "K2H", "K3H"),
        help="transfer coefficients used in the record, any unit (default 1 1 1: relative)",
    )
    out.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    add_output(out, "--report", help="also write the report as JSON")
    add_output(
        out,
        "--plot",
        metavar="PNG",
        help="plot the drifting angles before and after the correction",
    )
    p.set_defaults(func=run)


def _stand_settings(args: argparse.Namespace) -> StandSettings | None:
    from estimators.rocking import PAPER_AMPLITUDE_RAD, PAPER_FREQUENCY_HZ, StandSettings

    amplitude_deg, frequency_hz = args.amplitude_deg, args.frequency_hz
    if args.simulate:
        amplitude_deg = np.degrees(PAPER_AMPLITUDE_RAD) if amplitude_deg is None else amplitude_deg
        frequency_hz = PAPER_FREQUENCY_HZ if frequency_hz is None else frequency_hz
    if amplitude_deg is None and frequency_hz is None:
        return None
    if amplitude_deg is None or frequency_hz is None:
        raise UsageError(
            "give both --amplitude-deg and --frequency-hz (the stand's settings) or neither (fitted from the record)"
        )
    return StandSettings(
        float(np.radians(amplitude_deg)),
        frequency_hz,
        args.amplitude_rel_sigma,
        args.frequency_rel_sigma,
    )


_SIMULATION_OPTIONS = (
    "dk",
    "bias_deg_h",
    "arw_deg_rth",
    "phase_deg",
    "rate_hz",
    "seed",
    "save_csv",
)


def _records(args: argparse.Namespace, earth_rate_rps) -> tuple[list, list[str]]:
    """The sessions to analyse and notes on how they were obtained."""
    from estimators.rocking import PAPER_DK, GyroUnit, paper_runs, simulate_runs
    from estimators.session import validate_session
    from protocols.session_file import write_csv_session

    if args.simulate:
        rate_hz = 100.0 if args.rate_hz is None else args.rate_hz
        seed = 0 if args.seed is None else args.seed
        if not (np.isfinite(rate_hz) and rate_hz > 0.0):
            raise UsageError(f"--rate-hz must be positive, got {rate_hz!r}")
        unit = GyroUnit(
            scale_err=tuple(PAPER_DK if args.dk is None else args.dk),
            bias_rps=GyroUnit().bias_rps
            if args.bias_deg_h is None
            else tuple(np.asarray(args.bias_deg_h) * RPS_PER_DPH),
            arw_rad_per_sqrt_s=GyroUnit().arw_rad_per_sqrt_s
            if args.arw_deg_rth is None
            else np.radians(args.arw_deg_rth) / 60.0,
        )
        stand = _stand_settings(args)
        if stand is None:
            raise UsageError("--simulate needs the stand's amplitude and frequency")
        runs = paper_runs(
            amplitude_rad=stand.amplitude_rad,
            frequency_hz=stand.frequency_hz,
            phase_rad=None if args.phase_deg is None else float(np.radians(args.phase_deg)),
        )
        session = simulate_runs(
            runs,
            unit,
            rate_hz=rate_hz,
            earth_rate_rps=earth_rate_rps,
            rng=np.random.default_rng(seed),
        )
        notes = [
            f"simulated: δK = {', '.join(f'{v:.7g}' for v in np.asarray(unit.scale_err, dtype=float))}, seed {seed}, {rate_hz:g} Hz"
        ]
        if args.save_csv is not None:
            write_csv_session(
                args.save_csv,
                session,
                comments=(
                    "rocking record (methods.md M5): gyro in rad/s, X forward, Y up, Z right",
                ),
            )
            notes.append(f"record written to {args.save_csv}")
        return [session], notes
    given = [
        f"--{name.replace('_', '-')}"
        for name in _SIMULATION_OPTIONS
        if getattr(args, name) is not None
    ]
    if given:
        raise UsageError(f"{', '.join(given)} only apply to --simulate")
    sessions, notes = [], []
    for path in args.log:
        session, rejected = validate_session(
            load_units_checked(str(path), None, None, args).session
        )
        if session.gyro_rps is None:
            raise UsageError(f"{path}: no gyro columns gx, gy, gz (rad/s)")
        if rejected.total:
            notes.append(f"{path}: dropped {rejected.total} samples {rejected.counts}")
        sessions.append(session)
    return sessions, notes


def report_of(result: RockingResult, k_nominal) -> dict:
    """The JSON report (also the source of the text output)."""
    from estimators.strapdown import ANGLE_NAMES

    x_sigma = np.sqrt(np.diag(result.closed.x_cov))
    drifts, runs = {}, {}
    for e, c, f in zip(result.episodes, result.corrected, result.fitted, strict=True):
        name, k = e.pair.x_name, e.drift_axis
        i, j = e.pair.lead_axis, e.pair.lag_axis
        drifts[name] = {
            "static": e.drift_static_rps[k] / RPS_PER_DPH,
            "rocking": e.drift_rocking_rps[k] / RPS_PER_DPH,
            "rocking_minus_static": e.drift_rps / RPS_PER_DPH,
            "after_correction": c.drift_rps / RPS_PER_DPH,
        }
        window = e.t_s[slice(*e.segments.window)]
        runs[name] = {
            "pair": e.pair.value,
            "window_s": [window[0], window[-1]],
            "amplitude_deg": np.degrees(f.stand.amplitude_rad[[i, j]]),
            "frequency_hz": f.stand.frequency_hz,
            "phase_deg": np.degrees(f.phase_diff_rad),
        }
    stand = result.stand
    return {
        "method": "M5 synchronous rocking",
        "X": {n: result.closed.x[a] for a, n in enumerate(ANGLE_NAMES)},
        "X_sigma": {n: x_sigma[a] for a, n in enumerate(ANGLE_NAMES)},
        "dK": result.dk,
        "dK_sigma": result.dk_sigma,
        "dK_method": "model-based",
        "dK_closed": result.closed.dk,
        "dK_closed_sigma": np.sqrt(np.diag(result.closed.dk_cov)),
        "dK_closed_bound": result.closed.dk_bound,
        "K_nominal": np.asarray(k_nominal, float),
        "K_corrected": result.corrected_coefficients(k_nominal),
        "drift_deg_per_h": drifts,
        "runs": runs,
        "stand": None
        if stand is None
        else {
            "amplitude_deg": np.degrees(stand.amplitude_rad),
            "frequency_hz": stand.frequency_hz,
            "amplitude_rel_sigma": stand.amplitude_rel_sigma,
            "frequency_rel_sigma": stand.frequency_rel_sigma,
        },
        "gauss_newton_steps": result.model.steps,
    }


def _text(report: dict, notes: list[str], earth: bool) -> str:
    lines = [f"ins-health rocking (methods.md M5){'; Earth rate modelled' if earth else ''}"]
    lines += [f"  {n}" for n in notes]
    lines.append("")
    lines.append(
        "drift of the third angle, deg/h       static   rocking  rocking-static  after correction"
    )
    for name in ("psi", "theta", "gamma"):
        d, r = report["drift_deg_per_h"][name], report["runs"][name]
        lines.append(
            f"  {_SYMBOL[name]} ({r['pair']:>10}, Δφ {r['phase_deg']:+6.1f}°)  {d['static']:9.2f} {d['rocking']:9.2f} "
            f"{d['rocking_minus_static']:14.2f} {d['after_correction']:17.3f}"
        )
    lines.append("")
    stand = report["stand"]
    used = (
        f"stand settings {stand['amplitude_deg']:.3g}° ± {100 * stand['amplitude_rel_sigma']:.3g} %, "
        f"{stand['frequency_hz']:.4g} Hz ± {100 * stand['frequency_rel_sigma']:.3g} %"
        if stand is not None
        else "fitted stand motion"
    )
    lines.append(f"X (M5 eq. 4, {used}):")
    lines.append(
        "  "
        + "   ".join(
            f"X{_SYMBOL[n]} = {report['X'][n]:.6f} ± {report['X_sigma'][n]:.6f}"
            for n in ("psi", "theta", "gamma")
        )
    )
    lines.append(
        "δK, %                         channel 1 (X)        channel 2 (Y)        channel 3 (Z)"
    )
    lines.append(
        "  closed form (M5 eq. 5)  "
        + "".join(
            f"  {100 * v:9.5f} ± {100 * s:8.5f}"
            for v, s in zip(report["dK_closed"], report["dK_closed_sigma"], strict=True)
        )
    )
    lines.append(
        "    worst case of the stand"
        + "".join(f"       ± {100 * b:8.5f}  " for b in report["dK_closed_bound"])
    )
    lines.append(
        "  model-based (dK)        "
        + "".join(
            f"  {100 * v:9.5f} ± {100 * s:8.5f}"
            for v, s in zip(report["dK"], report["dK_sigma"], strict=True)
        )
    )
    lines.append(f"    Gauss–Newton steps: {report['gauss_newton_steps']}")
    lines.append("corrected coefficients K = K_H / (1 + δK) (M5 eq. 6):")
    lines.append(
        "  "
        + "   ".join(
            f"K{c + 1} = {k:.7g} (K{c + 1}H = {kh:.7g})"
            for c, (k, kh) in enumerate(
                zip(report["K_corrected"], report["K_nominal"], strict=True)
            )
        )
    )
    lines.append("stand motion fitted to the corrected records (what the model simulates):")
    for name in ("psi", "theta", "gamma"):
        r = report["runs"][name]
        lines.append(
            f"  {r['pair']:>10}: window {r['window_s'][0]:.1f}–{r['window_s'][1]:.1f} s, amplitudes "
            f"{r['amplitude_deg'][0]:.4f}°, {r['amplitude_deg'][1]:.4f}°, {r['frequency_hz']:.5f} Hz, Δφ {r['phase_deg']:+.2f}°"
        )
    return "\n".join(lines)


def plot_drifts(result: RockingResult, path: Path) -> None:
    """The third angle of each run as recorded and after the correction (the paper's Figs. 1 and 2)."""
    from service.figures import save_figure, subplots

    fig, axes = subplots(1, 3, figsize=(9.6, 3.0))
    for a, k in zip(axes, (1, 2, 0), strict=True):  # ψ, θ, γ: the paper's order
        e, c, f = result.episodes[k], result.corrected[k], result.fitted[k]
        step = max(1, e.t_s.size // 1500)
        t = e.t_s[::step] - e.t_s[0]
        win = e.t_s[slice(*e.segments.window)] - e.t_s[0]
        a.axvspan(win[0], win[-1], color="0.92", lw=0)
        a.plot(
            t, np.degrees(e.drift_angle_rad[::step]), color="tab:red", lw=0.8, label="as recorded"
        )
        a.plot(
            t,
            np.degrees(c.drift_angle_rad[::step]),
            color="tab:blue",
            lw=0.8,
            label="K = K_H/(1+δK)",
        )
        name = e.pair.x_name
        a.set_title(
            f"{_SYMBOL[name]} under {e.pair.value} (Δφ {np.degrees(f.phase_diff_rad):+.0f}°)",
            fontsize=9,
        )
        a.set_xlabel("time, s", fontsize=8)
        a.tick_params(labelsize=7)
    axes[0].set_ylabel("computed angle, deg", fontsize=8)
    axes[0].legend(fontsize=7, loc="upper left")
    save_figure(fig, path, dpi=80)


def run(args: argparse.Namespace) -> int:
    from estimators.rocking import earth_rate_stand_rps, estimate_scale_errors

    earth = (
        None
        if args.latitude_deg is None
        else earth_rate_stand_rps(args.latitude_deg, args.heading_deg)
    )
    sessions, notes = _records(args, earth)
    result = estimate_scale_errors(sessions, stand=_stand_settings(args), earth_rate_rps=earth)
    report = report_of(result, args.k_nominal)
    if args.plot is not None:
        plot_drifts(result, args.plot)
    emit(args, report, _text(report, notes, earth is not None))
    return 0
