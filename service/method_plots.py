"""Figures of the bench methods (M2 tilt and triad, M3 temperature, M4 rate table), matplotlib Agg.

One small PNG per method: what ``--plot FILE`` of the commands writes and what
``docs/methods/`` shows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes

from estimators.conventions import PARAM_NAMES
from estimators.repeatability import RunSpread
from estimators.sixpos import RateTableFit
from estimators.temperature import TemperatureFit, TemperatureSeries, model_errors
from estimators.tilt import TiltPassportResult, TiltRun
from service.figures import save_figure, subplots

_ARCMIN = np.pi / 180.0 / 60.0
_DPI = 72


def plot_tilt(
    result: TiltPassportResult, runs: list[TiltRun], path: Path, *, truth: np.ndarray | None = None
) -> None:
    """Stabilization of run 1, residuals of every run, per-run intervals and their intersection (M2 checks 1–4).

    ``truth`` (3,) ``[δa, δα, Δk]`` of a simulated bench is drawn on the interval panels.
    """
    sp = result.spread
    k0 = result.k0_mps2
    # Display units: δa in pulses, δα in arc minutes, Δk in ppm.
    unit = np.array([1.0 / k0, 1.0 / _ARCMIN, 1e6])
    labels = ("δa, pulse", "δα, arcmin", "Δk, ppm")
    fig, ax = subplots(2, 3, figsize=(10, 5.6))
    st = result.fits[0].stabilization
    for j in range(3):
        a = ax[0, j]
        v, s = st.values[:, j] * unit[j], st.std[:, j] * unit[j]
        a.fill_between(st.n_equations, v - 2 * s, v + 2 * s, color="0.85", label="±2σ")
        a.plot(st.n_equations, v, "k-", lw=1, label="estimate, run 1")
        a.axvline(st.settled_at[j], color="tab:blue", ls=":", lw=1, label="settled")
        final = v[-1]
        a.set_ylim(final - 8 * s[-1], final + 8 * s[-1])
        a.set_xlabel("equations used")
        a.set_title(f"stabilization: {labels[j]}", fontsize=9)
        if j == 0:
            a.legend(fontsize=7)
    a = ax[1, 0]
    for i, (f, r) in enumerate(zip(result.fits, runs, strict=True)):
        a.plot(
            np.degrees(r.angles_rad), f.residuals_pulses, ".-", ms=3, lw=0.6, label=f"run {i + 1}"
        )
    a.axhline(0, color="k", lw=0.5)
    a.set_xlabel("table angle, deg")
    a.set_title("measured − modelled, pulse", fontsize=9)
    a.legend(fontsize=6, ncol=2)
    for col, j in ((1, 0), (2, 2)):
        _interval_panel(
            ax[1, col],
            sp,
            j,
            scale=unit[j],
            label=labels[j],
            truth=None if truth is None else truth[j],
        )
    save_figure(fig, path, dpi=_DPI)


def plot_triad(spread: RunSpread, path: Path, *, truth: np.ndarray | None = None) -> None:
    """Per-run intervals of the nine parameters of a triad, their intersection and the passport value (M2's checks on M1's estimates).

    ``spread`` over the runs, parameters in ``PARAM_NAMES`` order; ``truth`` (9,) of a simulated unit.
    """
    fig, ax = subplots(3, 3, figsize=(10, 7.2))
    # Display units: zero signals in mg (normalized by g), scale errors in ppm, cosines in mrad.
    scales, units = (1e3, 1e6, 1e3), ("mg", "ppm", "mrad")
    for j, name in enumerate(PARAM_NAMES):
        _interval_panel(
            ax[j // 3, j % 3],
            spread,
            j,
            scale=scales[j // 3],
            label=f"{name}, {units[j // 3]}",
            truth=None if truth is None else truth[j],
            legend=j == 0,
        )
    save_figure(fig, path, dpi=_DPI)


def _interval_panel(
    a: Axes,
    sp: RunSpread,
    j: int,
    *,
    scale: float,
    label: str,
    truth: float | None,
    legend: bool = True,
) -> None:
    """Parameter ``j`` of every run with its interval, their intersection and the passport value."""
    y = np.arange(sp.n_runs) + 1
    a.errorbar(
        sp.values[:, j] * scale,
        y,
        xerr=(sp.upper[:, j] - sp.values[:, j]) * scale,
        fmt="ko",
        ms=3,
        capsize=2,
    )
    if sp.reproducible[j]:
        a.axvspan(
            sp.common_lower[j] * scale,
            sp.common_upper[j] * scale,
            color="tab:green",
            alpha=0.3,
            label="intersection",
        )
    a.axvline(sp.value[j] * scale, color="tab:green", lw=1, label="passport value")
    if truth is not None:
        a.axvline(truth * scale, color="tab:red", ls="--", lw=1, label="simulated truth")
    a.set_yticks(y)
    a.set_ylabel("run")
    a.set_title(f"{round(sp.level * 100)} % intervals: {label}", fontsize=9)
    if legend:
        a.legend(fontsize=7)


def plot_temperature(fit: TemperatureFit, series: TemperatureSeries, path: Path) -> None:
    """Held-out vs training criterion per order, and the bias and scale error with the selected model (M3)."""
    fig, ax = subplots(1, 3, figsize=(10, 3.4))
    orders = [s.order for s in fit.scores]
    ax[0].semilogy(
        orders, [s.regularity for s in fit.scores], "o-", label="held-out (GMDH regularity)"
    )
    ax[0].semilogy(orders, [s.training for s in fit.scores], "s--", label="training residual")
    ax[0].axvline(fit.order, color="tab:green", ls=":", label=f"selected: {fit.order}")
    ax[0].set_xlabel("polynomial order")
    ax[0].set_ylabel("mean squared error / σ²")
    ax[0].legend(fontsize=7)
    t = np.linspace(series.temp_c.min(), series.temp_c.max(), 200)
    b, e = model_errors(fit.model, t)
    g = fit.gravity_mps2
    for i, c in enumerate(("tab:blue", "tab:orange", "tab:red")):
        ax[1].plot(
            series.temp_c,
            series.bias_mps2[:, i] / g * 1e3,
            "o",
            ms=3,
            color=c,
            label=f"{'xyz'[i]} measured",
        )
        ax[1].plot(t, b[:, i] * 1e3, "-", lw=1, color=c)
        ax[2].plot(series.temp_c, series.scale_error[:, i] * 100, "o", ms=3, color=c)
        ax[2].plot(t, e[:, i] * 100, "-", lw=1, color=c)
    ax[1].set_title("bias, mg (lines: model)", fontsize=9)
    ax[2].set_title("scale error, % (lines: model)", fontsize=9)
    ax[1].legend(fontsize=7)
    for a in ax[1:]:
        a.set_xlabel("temperature, °C")
    save_figure(fig, path, dpi=_DPI)


def plot_rate_table(fit: RateTableFit, path: Path) -> None:
    """Gyro output minus table rate on every step, and the residuals of the straight-line fit (M4)."""
    fig, ax = subplots(1, 2, figsize=(8, 3.2))
    r = np.degrees(fit.table_rate_rps)
    ax[0].plot(
        r,
        np.degrees(fit.residuals_rps + fit.bias_rps + fit.scale_error * fit.table_rate_rps),
        "ko",
        ms=3,
    )
    ax[0].plot(
        r,
        np.degrees(fit.bias_rps + fit.scale_error * fit.table_rate_rps),
        "-",
        color="tab:blue",
        label=f"fit: S = {fit.scale_error * 100:.3f} %",
    )
    ax[0].set_xlabel("table rate, °/s")
    ax[0].set_ylabel("gyro − table, °/s")
    ax[0].legend(fontsize=8)
    ax[1].plot(r, np.degrees(fit.residuals_rps) * 3600, "ko", ms=3)
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set_xlabel("table rate, °/s")
    ax[1].set_ylabel("residual, °/h")
    save_figure(fig, path, dpi=_DPI)
