"""Markdown report and PNG plots of a model audit (``ins-health audit --report DIR``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.audit import AuditResult
from estimators.conventions import AXES, Triad, reference_magnitude
from service.figures import save_figure, subplots

MODELS = (("baseline", "C0"), ("extended", "C1"))
UNIT = {Triad.ACCEL: "m/s²", Triad.GYRO: "rad/s"}
PLOTS = ("residuals.png", "allan.png", "f0_histogram.png", "statistics.png", "headline.png")
"""The PNG files a report with statistics writes, in the order the Markdown shows them (a plot without data is left out)."""


def _simulated(result: AuditResult) -> list[tuple[str, str, dict]]:
    """(model, colour, {Triad: [TriadCurves per replica]}) of the simulations the audit ran."""
    return [
        (name, colour, result.replica_curves[name])
        for name, colour in MODELS
        if name in result.replica_curves
    ]


def _band(curves: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Median and 5–95 % band over replica curves of one length (None without any)."""
    if not curves:
        return None
    a = np.stack(curves)
    return np.median(a, axis=0), np.quantile(a, 0.05, axis=0), np.quantile(a, 0.95, axis=0)


def _residual_plot(result: AuditResult, path: Path) -> bool:
    """Normalized scalar residual per position, measured, with each model's replica band (same position count only)."""
    meas = result.measured_curves[Triad.ACCEL].residual_norm
    if meas is None:
        return False
    k = np.arange(1, meas.size + 1)
    fig, ax = subplots(figsize=(8, 3.6))
    # Extended first: the wider band goes underneath the baseline's.
    for name, colour, curves in reversed(_simulated(result)):
        same = [
            c.residual_norm
            for c in curves[Triad.ACCEL]
            if c.residual_norm is not None and c.residual_norm.size == meas.size
        ]
        band = _band(same)
        if band is not None:
            ax.fill_between(
                k,
                band[1],
                band[2],
                color=colour,
                alpha=0.8 if name == "baseline" else 0.4,
                step="mid",
                label=f"{name} simulation, 5–95 % of {len(same)} replicas",
            )
    ax.plot(k, meas, "ko-", ms=3, lw=0.8, label="measured")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("position (in time order)")
    ax.set_ylabel("scalar residual / predicted σ (–)")
    ax.set_title("Accelerometers: exact scalar equation per position (M1)")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=100)
    return True


def _allan_plot(result: AuditResult, path: Path) -> bool:
    """Allan deviation of the longest position per triad and axis: measured, each model's median and 5–95 % band."""
    triads = [
        t
        for t in (Triad.ACCEL, Triad.GYRO)
        if t in result.measured_curves and result.measured_curves[t].allan_tau_s.size
    ]
    if not triads:
        return False
    fig, axes = subplots(len(triads), 3, figsize=(10, 3.0 * len(triads)), squeeze=False)
    for row, t in zip(axes, triads, strict=True):
        meas = result.measured_curves[t]
        for i, ax in enumerate(row):
            for name, colour, curves in _simulated(result):
                m = min([meas.allan_tau_s.size] + [c.allan_tau_s.size for c in curves[t]])
                band = _band([c.allan_si[:m, i] for c in curves[t]])
                if band is not None:
                    ax.fill_between(
                        meas.allan_tau_s[:m],
                        band[1],
                        band[2],
                        color=colour,
                        alpha=0.3,
                        label=f"{name}: 5–95 %",
                    )
                    ax.plot(
                        meas.allan_tau_s[:m], band[0], color=colour, lw=1.2, label=f"{name}: median"
                    )
            ax.plot(meas.allan_tau_s, meas.allan_si[:, i], "k.-", lw=1, label="measured")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("averaging time τ (s)")
            ax.set_ylabel(f"Allan deviation ({UNIT[t]})")
            ax.set_title(f"{t.value} {AXES[i]}", fontsize=9)
            ax.grid(True, which="both", lw=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Allan deviation within the longest static position", fontsize=10)
    save_figure(fig, path, dpi=90)
    return True


def _f0_plot(result: AuditResult, path: Path) -> bool:
    """Histogram of the F0 statistic of window means, measured against the pooled replicas, with each model's λ0."""
    meas = result.measured_curves[Triad.ACCEL].f0_window
    if meas is None or meas.size == 0:
        return False
    pooled = {
        name: np.concatenate(
            [c.f0_window for c in curves[Triad.ACCEL] if c.f0_window is not None] or [np.zeros(0)]
        )
        for name, _, curves in _simulated(result)
    }
    lam = {name: result.gain.get(f"f0_lambda0_{name}") for name, _ in MODELS}
    top = max(
        [float(np.max(np.abs(v))) for v in (meas, *pooled.values()) if v.size]
        + [v for v in lam.values() if v]
    )
    edges = np.linspace(-1.05 * top, 1.05 * top, 41).tolist()
    fig, ax = subplots(figsize=(7, 3.6))
    for name, colour in MODELS:
        if pooled.get(name, np.zeros(0)).size:
            ax.hist(
                pooled[name],
                bins=edges,
                density=True,
                histtype="step",
                lw=1.5,
                color=colour,
                label=f"{name} simulation ({result.replicas} replicas)",
            )
        lam0 = lam[name]
        if lam0:
            ax.axvline(lam0, color=colour, ls="--", lw=1, label=f"λ0 from the {name} model")
            ax.axvline(-lam0, color=colour, ls="--", lw=1)
    ax.hist(
        meas,
        bins=edges,
        density=True,
        color="k",
        alpha=0.35,
        label=f"measured ({meas.size} windows)",
    )
    ax.set_yscale("log")
    window = result.gain.get("f0_window_samples")
    ax.set_xlabel(f"F0 statistic s = ½(|ã|² − 1) of {window}-sample window means (normalized, –)")
    ax.set_ylabel("probability density (1/unit of s)")
    ax.set_title("F0 statistic on the static data: measured against simulated")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=100)
    return True


def _stat_plot(result: AuditResult, path: Path) -> bool:
    """Measured / median-simulated ratio of every statistic, baseline and extended, with the replicas' 5–95 % band."""
    fig, ax = subplots(figsize=(9, 4))
    for k, (name, cmp, mark) in enumerate(
        (("baseline", result.baseline_cmp, "o"), ("extended", result.extended_cmp, "s"))
    ):
        labels = [
            f"{c.triad.value} {c.statistic}{'' if c.axis is None else ' ' + c.axis}" for c in cmp
        ]
        x = np.arange(len(cmp)) + 0.2 * k
        lo = [c.simulated_p05 / c.simulated_median for c in cmp]
        hi = [c.simulated_p95 / c.simulated_median for c in cmp]
        ax.vlines(x, lo, hi, color=f"C{k}", alpha=0.4, lw=6)
        ax.plot(
            x,
            [c.ratio for c in cmp],
            mark,
            color=f"C{k}",
            label=f"{name}: measured / simulated median (bar: replicas 5–95 %)",
        )
    ax.set_xticks(np.arange(len(labels)), labels, rotation=70, fontsize=7)
    ax.set_yscale("log")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.legend(fontsize=7)
    ax.set_title(f"Measured statistics against {result.replicas} Monte Carlo replicas")
    save_figure(fig, path, dpi=100)
    return True


def _headline_plot(result: AuditResult, path: Path) -> bool:
    """Histogram of the simulated χ²/dof (baseline and extended) with the measured value."""
    fig, ax = subplots(figsize=(6, 3.5))
    for name, k in (("baseline", 0), ("extended", 1)):
        reps = result.replica_stats.get(name, {})
        # The headline's records are those of the first triad with replicas.
        first = next(iter(reps), None)
        vals = (
            [] if first is None else [r["chi2_per_dof"] for r in reps[first] if "chi2_per_dof" in r]
        )
        if vals:
            ax.hist(vals, bins=12, alpha=0.5, color=f"C{k}", label=f"{name} replicas")
    head = result.headline(result.baseline_cmp)
    if head is not None:
        ax.axvline(head.measured, color="k", label="measured")
    ax.set_xlabel("accelerometer χ²/dof of the scalar equation per position (–)")
    ax.set_ylabel("replicas")
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=100)
    return True


MECHANISM_PLOT = "mechanism_{effect}_{where}.png"
"""One plot per named cause a person reads its mechanism from: the residual against time and orientation, or the spectrum."""


TEMPERATURE_EFFECTS = ("temperature_bias", "temperature_scale", "temperature_hysteresis")
SEEN_SHARE = 0.5
"""Smallest |∂f/∂θ| of a position for its residual to stand for the axis' effect in the temperature panel
(≈ |u_i| for a bias, u_i² for a scale): where the axis barely sees the effect the quotient is noise."""


@dataclass(frozen=True)
class TemperaturePanel:
    """A temperature effect of one axis read position by position: ``effect_si`` = −residual / (∂f/∂θ), in the
    effect's units (a bias in SI, a scale relative), with its sd, for the positions that see the axis
    (:data:`SEEN_SHARE`); ``heating`` of each; the fitted curve ``curve_t_c`` → ``curve_si`` (for a hysteresis,
    +h heating and −h cooling, each over the temperatures it was met at)."""

    temp_c: np.ndarray
    effect_si: np.ndarray
    sd_si: np.ndarray
    heating: np.ndarray
    curve_t_c: list[np.ndarray]
    curve_si: list[np.ndarray]
    unit: str


def temperature_panel(cause, st, gravity_mps2: float) -> TemperaturePanel | None:
    """The temperature panel of a named temperature effect on a triad's scalar residual, or None (another
    effect, a triad off the scalar path, no temperature)."""
    if cause.effect not in TEMPERATURE_EFFECTS or cause.axis is None or st.temp_c is None:
        return None
    if st.jac is None or st.heating is None:
        return None
    i = AXES.index(cause.axis)
    p = cause.params
    ref = reference_magnitude(cause.triad, gravity_mps2)
    scale = cause.effect == "temperature_scale"
    d = st.jac[:, 3 + i] if scale else st.jac[:, i]
    seen = np.abs(d) >= SEEN_SHARE
    # The scalar residual is f ≈ J δp − J θ for an effect θ the baseline lacks.
    to_unit = 1.0 if scale else ref
    t = st.temp_c[seen]
    grid = np.linspace(float(st.temp_c.min()), float(st.temp_c.max()), 50)
    dt = grid - float(np.mean(st.temp_c))
    if cause.effect == "temperature_hysteresis":
        h = p["offset_norm"] * ref if cause.triad is Triad.ACCEL else p["offset_rps"]
        sides = [st.heating > 0, st.heating < 0]
        curve_t = [np.array([st.temp_c[k].min(), st.temp_c[k].max()]) for k in sides if k.any()]
        curve = [np.full(2, v) for v, k in zip((h, -h), sides, strict=True) if k.any()]
    elif scale:
        curve_t, curve = [grid], [p["coef_per_c"] * dt]
    elif cause.triad is Triad.ACCEL:
        coefs = [p.get("coef_norm_per_c", 0.0)] + [
            p.get(f"coef{k}_norm_per_c{k}", 0.0) for k in range(2, 4)
        ]
        curve_t, curve = [grid], [ref * sum(c * dt ** (k + 1) for k, c in enumerate(coefs))]
    else:
        curve_t, curve = [grid], [p["coef_rps_per_c"] * dt]
    unit = "–" if scale else UNIT[cause.triad]
    return TemperaturePanel(
        t,
        -st.residual_norm[seen] / d[seen] * to_unit,
        st.sigma_norm[seen] / np.abs(d[seen]) * to_unit,
        st.heating[seen],
        curve_t,
        curve,
        unit,
    )


def _draw_temperature(ax, cause, panel: TemperaturePanel) -> None:
    hyst = cause.effect == "temperature_hysteresis"
    groups = (
        [(panel.heating > 0, "C3", "heating"), (panel.heating < 0, "C0", "cooling")]
        if hyst
        else [(np.ones(panel.temp_c.size, bool), "k", "positions")]
    )
    for k, colour, label in groups:
        ax.errorbar(
            panel.temp_c[k],
            panel.effect_si[k],
            panel.sd_si[k],
            fmt="o",
            ms=3,
            lw=0.6,
            color=colour,
            label=label,
        )
    colours = ("C3", "C0") if hyst else ("C1",)
    for t, v, colour in zip(panel.curve_t_c, panel.curve_si, colours, strict=False):
        ax.plot(t, v, "-", color=colour, lw=1.2)
    ax.plot(
        [], [], "-", color="k" if hyst else "C1", lw=1.2, label="fitted ±h" if hyst else "fitted"
    )
    ax.set_xlabel("temperature of the position (°C)")
    ax.set_ylabel(f"{cause.effect} {cause.axis} ({panel.unit})")
    ax.legend(fontsize=7)


def _mechanism_plot(result: AuditResult, cause, path: Path) -> bool:
    """A named cause's evidence: a line's spectrum over its floor; a low-pass's spectrum with the fitted response;
    any other cause of a triad on a scalar path,
    that triad's scalar residual per position against time (the change's turn marked) and against the
    orientation of the cause's axis (for the triad's cross-axis term, ``u_x u_y u_z``); a temperature effect
    also against temperature with its fitted curve (:func:`temperature_panel`; a hysteresis heating and cooling
    apart)."""
    p = cause.params
    if cause.effect == "spectral_line":
        fig, ax = subplots(figsize=(8, 3.4))
        for key, style, label in (
            ("spectrum_psd_si2_per_hz", "k-", "static samples"),
            ("floor_psd_si2_per_hz", "C1--", "noise floor (running median)"),
        ):
            ax.semilogy(p["spectrum_freq_hz"], p[key], style, lw=0.8, label=label)
        ax.axvline(
            p["freq_hz"],
            color="C3",
            lw=0.6,
            label=f"line {p['freq_hz']:.4g} Hz, amplitude {p['amplitude_si']:.3g}",
        )
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel(f"PSD ({UNIT[cause.triad]}²/Hz)")
        ax.set_title(f"{cause.triad.value} {cause.axis}: spectrum of the static samples")
        ax.legend(fontsize=7)
        save_figure(fig, path, dpi=100)
        return True
    if cause.effect == "lowpass":
        fig, ax = subplots(figsize=(8, 3.4))
        f = p["spectrum_freq_hz"]
        for i, ax_name in enumerate(AXES):
            ax.semilogy(
                f, p["spectrum_si2"][i], f"C{i}-", lw=0.7, label=f"{ax_name} static samples"
            )
            ax.semilogy(f, p["fitted_si2"][i], f"C{i}--", lw=1.0)
        ax.axvline(
            p["cutoff_hz"],
            color="k",
            lw=0.6,
            label=f"order {p['order']} at {p['cutoff_hz']:.3g} Hz "
            f"({p['cutoff_low_hz']:.3g}–{p['cutoff_high_hz']:.3g}); dashed: the fitted response",
        )
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel(f"periodogram ({UNIT[cause.triad]}² per sample)")
        ax.set_title(
            f"{cause.triad.value}: the static noise's spectrum through the firmware low-pass"
        )
        ax.legend(fontsize=7)
        save_figure(fig, path, dpi=100)
        return True
    st = next((x for x in result.structure if x.triad is cause.triad), None)
    if st is None:
        return False
    z = st.residual_norm / st.sigma_norm
    panel = temperature_panel(cause, st, result.gravity_mps2)
    fig, axes = subplots(1, 2 if panel is None else 3, figsize=(10 if panel is None else 15, 3.4))
    a_t, a_u = axes[0], axes[1]
    if panel is not None:
        _draw_temperature(axes[2], cause, panel)
    a_t.plot(st.t_mid_s, z, "ko-", ms=3, lw=0.6)
    if "t_change_s" in p:
        a_t.axvspan(
            p["t_change_s"] - p["t_change_se_s"],
            p["t_change_s"] + p["t_change_se_s"],
            color="C3",
            alpha=0.3,
            label="the change's turn",
        )
        a_t.legend(fontsize=7)
    a_t.set_xlabel("time of the position (s)")
    a_t.set_ylabel("scalar residual / σ within positions (–)")
    axis = cause.axis or p.get("fitted_axis")
    # The direction of the triad's own reference: gravity for the accelerometers, the Earth rate for a gyro.
    on = "gravity" if cause.triad is Triad.ACCEL else "the Earth rate"
    if axis is None:
        u, label = np.prod(st.up, axis=1), "u_x u_y u_z"
    else:
        u, label = st.up[:, AXES.index(axis)], f"u_{axis} ({on} on the axis)"
    a_u.plot(u, z, "ko", ms=3)
    a_u.set_xlabel(label)
    for a in axes:
        a.axhline(0.0, color="k", lw=0.5)
    fig.suptitle(
        f"{cause.effect} ({cause.triad.value}{'' if cause.axis is None else ' ' + cause.axis}): baseline residual per position"
    )
    save_figure(fig, path, dpi=100)
    return True


def _mechanism_plots(result: AuditResult, d: Path) -> list[str]:
    """:func:`_mechanism_plot` of every named cause that has one; the file names written."""
    out = []
    for c in result.named:
        name = MECHANISM_PLOT.format(effect=c.effect, where=f"{c.triad.value}_{c.axis or 'triad'}")
        if _mechanism_plot(result, c, d / name):
            out.append(name)
    return out


def _unplotted(result: AuditResult, written: list[str]) -> list[str]:
    """A line per named cause without a mechanism plot, and why: silence is never a plot that was left out."""
    out = []
    for c in result.named:
        where = f"{c.triad.value}_{c.axis or 'triad'}"
        if MECHANISM_PLOT.format(effect=c.effect, where=where) in written:
            continue
        path = result.grade_paths.get(c.triad, {}).get("path", "no scalar")
        out.append(
            f"- no mechanism plot for {c.effect} ({_where(c.triad.value, c.axis)}): the {c.triad.value} took the "
            f"`{path}` path, which has no scalar residual per position to plot; its fit is under Named causes"
        )
    return out


def _fmt(v) -> str:
    """A parameter value for the report: numbers to 3 significant digits, lists element-wise, a
    mapping as its keys with their values ("none" when empty): never a Python repr."""
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items()) or "none"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.3g}"
    return str(v)


PLOTTED_ONLY = (
    "spectrum_freq_hz",
    "spectrum_psd_si2_per_hz",
    "floor_psd_si2_per_hz",
    "spectrum_si2",
    "fitted_si2",
)
"""Parameters that are a plot's data (the mechanism plot shows them), not a figure for the text."""


def _fitted(params: dict) -> str:
    """A cause's fitted parameters, each with its standard error (``<name>_se``) when it has one."""
    return "; ".join(
        f"{k} {_fmt(v)}" + (f" ± {_fmt(params[k + '_se'])}" if k + "_se" in params else "")
        for k, v in params.items()
        if not (k.endswith("_se") and k[: -len("_se")] in params) and k not in PLOTTED_ONLY
    )


GAIN_ROWS = {
    "heldout_rms_norm": "held-out residual rms (of the reference)",
    "heldout_chi2": "held-out χ²/dof",
    "f0_lambda0": "F0 threshold λ0",
    "f0_false_alarm_rate": "F0 false-alarm rate on the session's rest",
    "f0_tests": "F0 tests",
}
"""The gain's figures compared between the baseline and the extended model, as the table names them."""


def _gain_lines(gain: dict) -> list[str]:
    """The gain as a table, baseline against extended, and its settings in a sentence."""
    lines = ["| figure | baseline | extended |", "|---|---|---|"]
    stems = [k[: -len("_baseline")] for k in gain if k.endswith("_baseline")]
    for stem in stems:
        lines.append(
            f"| {GAIN_ROWS.get(stem, stem)} | {_fmt(gain[stem + '_baseline'])} | "
            f"{_fmt(gain.get(stem + '_extended', '–'))} |"
        )
    paired = {f"{stem}_{side}" for stem in stems for side in ("baseline", "extended")}
    rest = {k: v for k, v in gain.items() if k not in paired}
    if rest:
        lines += ["", "With " + "; ".join(f"{k} {_fmt(v)}" for k, v in rest.items()) + "."]
    return lines


def _where(triad: str, axis: str | None) -> str:
    return triad if axis is None else f"{triad} {axis}"


def _statistics_table(result: AuditResult) -> list[str]:
    """Measured statistics against both simulations: ratio (measured / median) and tail (replicas ≥ measured).

    The extended comparison's measured value is its own where it leaves positions out (both sides alike).
    """
    ext = {(c.triad, c.statistic, c.axis): c for c in result.extended_cmp}
    lines = [
        "| triad | statistic | axis | measured | baseline ratio | baseline tail | measured, extended comparison | extended ratio | extended tail | extended inside 5–95 % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in result.baseline_cmp:
        e = ext.get((c.triad, c.statistic, c.axis), c)
        without = (
            f" (without {', '.join(f'#{k}' for k in e.positions_left_out)})"
            if e.positions_left_out
            else ""
        )
        lines.append(
            f"| {c.triad.value} | {c.statistic} | {c.axis or ''} | {c.measured:.3g} | {c.ratio:.2f} | {c.tail_prob:.2f} | "
            f"{e.measured:.3g}{without} | {e.ratio:.2f} | {e.tail_prob:.2f} | {'yes' if e.inside else 'no'} |"
        )
    if result.left_out:
        lines += [
            "",
            f"Extended comparison: {result.left_out_reason}. The baseline's keeps every position.",
        ]
    return lines


def _model_table(result: AuditResult) -> list[str]:
    """The surviving noise model of each triad (SI, per axis)."""
    lines = [
        "| triad | noise sd per sample | of it, colour: σ at τ (s) | level of long averages, colour (sd) | noise for averages (sd) | grid step | Gauss–Markov bias σ | its τ (s) | moves other axes | wander between positions (sd) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t, m in result.extended_model.items():
        scale = reference_magnitude(t, result.gravity_mps2)
        gm = [f"{v * scale:.3g}" if v > 0 else "–" for v in m.gm_sigma_norm]
        tau = [
            f"{v:.3g}" if s > 0 else "–" for s, v in zip(m.gm_sigma_norm, m.gm_tau_s, strict=True)
        ]
        wander = [f"{v * scale:.3g}" if v > 0 else "–" for v in m.excess_sd_norm]
        shared = ", ".join(
            f"{AXES[i]} → {AXES[j]} × {m.gm_loading[j, i]:.2g}"
            for i in range(3)
            for j in range(3)
            if i != j and m.gm_loading[j, i] != 0 and m.gm_sigma_norm[i] > 0
        )
        step = "none" if m.quant_step_si is None else _fmt(list(m.quant_step_si))
        colour = "; ".join(
            " + ".join(f"{sd:.3g} at {tc:.3g}" for sd, tc in zip(sds, taus, strict=True) if sd > 0)
            or "–"
            for sds, taus in zip(m.colour_sigma_si, m.colour_tau_s, strict=True)
        )
        lines.append(
            f"| {t.value} ({UNIT[t]}) | {_fmt(list(m.white_sd_si))} | {colour} | {_fmt(list(m.colour_level_sd_si))} | "
            f"{_fmt(list(m.mean_noise_sd_si))} | {step} | "
            f"[{', '.join(gm)}] | [{', '.join(tau)}] | {shared or '–'} | [{', '.join(wander)}] |"
        )
    return lines


def write_report(result: AuditResult, out_dir: str | Path, *, title: str) -> Path:
    """Write ``audit.md`` and its PNGs into ``out_dir``; returns the Markdown path."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    lines = [f"# Model audit: {title}", ""]
    lines += [f"- {s}" for s in result.statements] + ([""] if result.statements else [])
    if result.baseline_cmp:
        written = [
            name
            for name, plot in zip(
                PLOTS,
                (_residual_plot, _allan_plot, _f0_plot, _stat_plot, _headline_plot),
                strict=False,
            )
            if plot(result, d / name)
        ] + _mechanism_plots(result, d)
        data = result.to_dict()
        lines += [f"Positions: {result.n_positions}; Monte Carlo replicas: {result.replicas}.", ""]
        lines += [
            f"- {triad} candidates on the `{p['path']}` path: {p['reason']}"
            for triad, p in data["grade_paths"].items()
        ] + [""]
        if data["baseline"]["ratio"] is not None and data["extended"]["ratio"] is not None:
            lines += [
                f"Headline (accelerometer χ²/dof of the scalar equation per position): baseline ratio {data['baseline']['ratio']:.2f} "
                f"(tail {data['baseline']['tail_prob']:.2f}), extended ratio {data['extended']['ratio']:.2f} (tail {data['extended']['tail_prob']:.2f}).",
                "",
            ]
        lines += ["## What the simulation gets wrong", "", *_statistics_table(result), ""]
        lines += ["## Named causes", ""]
        for c in data["named_causes"]:
            lines.append(
                f"- **{c['effect']}** ({_where(c['triad'], c['axis'])}): {c['evidence']}. "
                f"Fitted: {_fitted(c['params'])}."
            )
        if not data["named_causes"]:
            lines.append("- none: the baseline explains the data")
        lines += ["", "Not identifiable on this session:", ""]
        lines += sorted(
            {
                f"- {c['effect']} ({_where(c['triad'], c['axis'])}): {c['reason']}"
                for c in data["candidates"]
                if not c["identifiable"]
            }
        ) or ["- (every candidate was tested)"]
        lines += ["", "## Extended model (surviving noise per triad)", "", *_model_table(result)]
        lines += ["", "## Gain", "", *_gain_lines(data["gain"])]
        lines += ["", "## Plots", ""] + [f"![{Path(name).stem}]({name})\n" for name in written]
        lines += _unplotted(result, written)
    path = d / "audit.md"
    path.write_text("\n".join(lines) + "\n")
    return path
