"""The health report of a replayed log (``ins-health replay LOG --report DIR``): report.json, report.md, plots.

``report.json`` (type ``ins.health.log_report``, schema 1) is deterministic: it
holds only what the log gives (no wall clock, no path beyond the file name),
keys sorted, so the same log gives a byte-identical file. It holds the log
(name, format, what it holds and what was left out), the passport used (a
file's, or the nominal passport of a sensor class with its tolerances and their
source, :mod:`estimators.nominal_passport`), per IMU an object in ``imus``
(:mod:`estimators.log_health` defines each figure; plus ``imu``, ``source``,
``clipped_samples`` as the log counts them — null when it does not — and the
F0 shell and counts of the pipeline), per pair of IMUs their disagreement
(``pairs``), ``firmware``: the health data the autopilot logged itself (ArduPilot ``VIBE`` and
batch sampler, MAVLink ``VIBRATION``, PX4 ``vehicle_imu_status``: :mod:`protocols.firmware_health`),
and ``findings``: the events the service raises on the log, then the firmware's figures against
the firmware's own thresholds, then the report's own checks (vibration and clipping recomputed
from the logged samples, only where the firmware gave none: a recomputation sees below half the
logged rate only, ``vibration.recomputed_below_hz``), each with its severity, text and numbers; ``coverage`` (schema 3): the verdict, what
was not tested and why, and per IMU what each check tested with its minimum
detectable fault (the ``--json`` coverage line of :mod:`service.commands.replay`).

``cross_imu_norm`` (schema 6; null for fewer than two IMUs) is the in-flight norm comparison of
the first two IMUs (:mod:`estimators.cross_imu_norm`): the pair, the CUSUM threshold, seconds
tested, the minimum detectable shifts and the lever arm found with its standard deviations.

``report.md`` shows it as a flight review reads: a table per IMU, |a| − g of
the blocks at rest against F0's shell, the accelerometer and gyro spectra, the
cross-IMU differences over time, the thrust-axis statistic against GNSS and the norm
comparison's CUSUM statistic through the flight against their thresholds
(``gravity_residual.png``, ``spectra.png``, ``cross_imu.png``, ``thrust_axis.png``,
``cross_imu_norm.png``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimators.conventions import AXES
from estimators.cross_imu_norm import NormBlock
from estimators.firmware_health import ARDUPILOT_VIBE_LIMITS_MPS2, ARDUPILOT_VIBE_SOURCE
from estimators.log_health import HealthConfig, ImuHealth, PairDifference
from protocols.events import Event, Severity
from protocols.firmware_health import FirmwareHealth, FirmwareVibration
from protocols.logs import LogStats
from service.commands.replay import log_start
from service.figures import Margins, plain_log_labels, save_figure, subplots
from service.pipeline.norm_check import VehicleNorm
from service.pipeline.thrust_axis import ThrustStatistic

REPORT_TYPE = "ins.health.log_report"
REPORT_SCHEMA_VERSION = 6
"""2: ``log.skipped_bytes`` and ``log.cut_at_byte`` (what a damaged log did not give);
3: ``coverage`` (what each check tested, the verdict); 4: ``log.start_t_s`` (the first sample's
time on the log's clock, from which the plots and the Markdown count) and ``passport.not_applied``
(the IMUs no passport applied to, and why); 5: ``log.clock_restarts`` and per IMU ``runs`` (a
reboot inside the log, :mod:`protocols.logs`), ``firmware`` (the log's own health data,
:mod:`protocols.firmware_health`) and per IMU ``vibration.recomputed_below_hz``; 6: ``cross_imu_norm`` (module docstring)."""
VIBE_WARN_MPS2, VIBE_BAD_MPS2 = ARDUPILOT_VIBE_LIMITS_MPS2
VIBE_SOURCE = ARDUPILOT_VIBE_SOURCE
PLOTS = (
    "gravity_residual.png",
    "spectra.png",
    "cross_imu.png",
    "thrust_axis.png",
    "cross_imu_norm.png",
)


@dataclass(frozen=True)
class ImuF0:
    """What the pipeline's F0 did on one IMU's accelerometers: the shell λ0 (None: not run) and its counts."""

    lambda0: float | None
    tests: int
    fails: int


def event_finding(event: Event) -> dict[str, Any]:
    """A pipeline event as a report finding (severity, text and its numbers)."""
    return {
        "source": "pipeline",
        "severity": event.severity.name.lower(),
        "imu": event.imu,
        "t_s": event.t_s,
        "predicate": event.predicate.value,
        "cause": event.cause.value,
        "triad": None if event.triad is None else event.triad.value,
        "axis": event.axis,
        "estimate": event.estimate,
        "nominal": event.nominal,
        "tolerance": event.tolerance,
        "unit": event.unit,
        "text": event.text,
    }


def health_findings(
    imu: int,
    health: ImuHealth,
    clipped: int | None,
    *,
    firmware_vibration: bool = False,
    firmware_clipping: bool = False,
) -> list[dict[str, Any]]:
    """The report's own checks of one IMU: in-flight vibration (ArduPilot's thresholds) and clipping
    recomputed from the logged samples; ``firmware_vibration``, ``firmware_clipping``: the log has the
    firmware's own figures of this IMU (:func:`firmware_findings`), which these do not repeat."""
    out: list[dict[str, Any]] = []
    if health.vibe_max_mps2 is not None and not firmware_vibration:
        worst = float(health.vibe_max_mps2.max())
        axis = AXES[int(np.argmax(health.vibe_max_mps2))]
        if worst > VIBE_WARN_MPS2:
            severity = Severity.ERROR if worst > VIBE_BAD_MPS2 else Severity.WARNING
            limit = VIBE_BAD_MPS2 if worst > VIBE_BAD_MPS2 else VIBE_WARN_MPS2
            out.append(
                {
                    "source": "report",
                    "severity": severity.name.lower(),
                    "imu": imu,
                    "predicate": "vibration",
                    "axis": axis,
                    "estimate": worst,
                    "tolerance": limit,
                    "unit": "m/s^2",
                    "text": f"IMU{imu} vibration (VIBE) {worst:.1f} m/s² on {axis} in flight, above {limit:g} ({VIBE_SOURCE})",
                }
            )
    if clipped and not firmware_clipping:
        out.append(
            {
                "source": "report",
                "severity": Severity.WARNING.name.lower(),
                "imu": imu,
                "predicate": "clipping",
                "estimate": clipped,
                "tolerance": 0,
                "unit": "samples",
                "text": f"IMU{imu}: {clipped} clipped samples (the sensor saturated: its output is wrong there)",
            }
        )
    if health.rest_s == 0.0:
        # A log too short or too sparse to fill one block is not one that was never at rest.
        too_short = not health.blocks.full.any()
        why = (
            f"{health.n_samples} samples over {health.duration_s:.2f} s at {health.rate_hz:.0f} Hz: "
            f"no {health.config.block_s:g} s block held samples enough to tell rest from motion"
            if too_short
            else "never at rest in the log"
        )
        out.append(
            {
                "source": "report",
                "severity": Severity.INFO.name.lower(),
                "imu": imu,
                "predicate": "too_short" if too_short else "no_rest",
                "text": f"IMU{imu}: {why}: F0 and the diagnosis had nothing to test; noise from the first difference",
            }
        )
    return out


def _who(v: FirmwareVibration) -> str:
    return "the primary accelerometer" if v.instance is None else f"instance {v.instance}"


def firmware_findings(firmware: FirmwareHealth) -> list[dict[str, Any]]:
    """The firmware's own figures against the firmware's own thresholds: vibration levels above the
    warning or error limit, and clipped samples."""
    out: list[dict[str, Any]] = []
    for v in firmware.vibration:
        if not v.accel.max:
            continue
        worst = max(v.accel.max)
        warn, bad = v.limits
        if worst <= warn:
            continue
        limit = bad if worst > bad else warn
        axis = AXES[v.accel.max.index(worst)] if len(v.accel.max) == 3 else None
        on = f" on {axis}" if axis else ""
        out.append(
            {
                "source": "firmware",
                "severity": (Severity.ERROR if worst > bad else Severity.WARNING).name.lower(),
                "imu": v.instance,
                "predicate": "vibration",
                "axis": axis,
                "estimate": worst,
                "tolerance": limit,
                "unit": v.unit,
                "text": f"{v.message} of {_who(v)}: vibration up to {worst:.3g} {v.unit}{on}, above {limit:g} "
                f"in {v.accel.above[f'{limit:g}']} of {v.accel.n} messages ({v.source})",
            }
        )
    for inst, n in sorted(firmware.clipped.items()):
        if n:
            out.append(
                {
                    "source": "firmware",
                    "severity": Severity.WARNING.name.lower(),
                    "imu": inst,
                    "predicate": "clipping",
                    "estimate": n,
                    "tolerance": 0,
                    "unit": "samples",
                    "text": f"accelerometer instance {inst}: {n} clipped samples over the log "
                    f"({firmware.clip_message} counters; {firmware.clip_source})",
                }
            )
    return out


def norm_summary(norm: VehicleNorm | None) -> dict[str, Any] | None:
    """The report's ``cross_imu_norm`` (module docstring) of a vehicle's norm check."""
    if norm is None:
        return None
    r, cov = norm.check.lever_arm()
    mdf_a, mdf_g = norm.check.mdf()
    return {
        "imus": list(norm.pair),
        "block_s": norm.config.block_s,
        "threshold": norm.config.threshold,
        "false_alarms_per_hour": norm.config.false_alarms_per_hour,
        "tested_s": norm.check.tested_s(),
        "mdf_mps2": mdf_a,
        "mdf_rps": mdf_g,
        "lever_arm_m": [float(v) for v in r],
        "lever_arm_sd_m": [float(v) for v in np.sqrt(np.diag(cov))],
    }


def build_report(
    *,
    log_name: str,
    log_format: str,
    stats: LogStats,
    system: str,
    passport: Mapping[str, Any],
    gravity_mps2: float,
    config: HealthConfig,
    healths: Mapping[int, ImuHealth],
    f0: Mapping[int, ImuF0 | None],
    pairs: Sequence[PairDifference],
    events: Sequence[Event],
    coverage: Mapping[str, Any],
    start_t_s: float | None,
    firmware: FirmwareHealth | None = None,
    cross_imu_norm: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The plain-dict report (module docstring); ``coverage``: the replay's coverage map;
    ``start_t_s``: the log's first sample time (None: no sample); ``firmware``: the log's own
    health data (:mod:`protocols.firmware_health`); ``cross_imu_norm``: :func:`norm_summary`."""
    imus = []
    for imu, h in sorted(healths.items()):
        entry = {"imu": imu, "source": stats.sources.get(imu, ""), **h.to_dict()}
        entry["clipped_samples"] = stats.clipped.get(imu)
        # What the recomputation can show: vibration below half the logged rate (the firmware's
        # own figures come from the sensor's kHz samples).
        entry["vibration"]["recomputed_below_hz"] = h.rate_hz / 2.0
        check = f0.get(imu)
        entry["f0_accel"] = (
            None
            if check is None
            else {
                "lambda0": check.lambda0,
                "shell_mps2": None if check.lambda0 is None else check.lambda0 * gravity_mps2,
                "tests": check.tests,
                "fails": check.fails,
            }
        )
        imus.append(entry)
    fw = firmware if firmware is not None else FirmwareHealth()
    findings = [event_finding(e) for e in events] + firmware_findings(fw)
    # The firmware's figures stand for the instances they name (VIBRATION, and VIBE before
    # ArduPilot 4.0: the primary accelerometer, IMU0); any other IMU's recomputed ones are its only.
    vibrations = {0 if v.instance is None else v.instance for v in fw.vibration}
    for imu, h in sorted(healths.items()):
        findings += health_findings(
            imu,
            h,
            stats.clipped.get(imu),
            firmware_vibration=imu in vibrations,
            firmware_clipping=imu in fw.clipped,
        )
    return {
        "type": REPORT_TYPE,
        "schema_version": REPORT_SCHEMA_VERSION,
        "log": {
            "name": log_name,
            "format": log_format,
            "system": system,
            "holds": dict(sorted(stats.held.items())),
            "left_out": dict(sorted(stats.skipped.items())),
            "dropped_samples": dict(sorted(stats.dropped.items())),
            "skipped_bytes": stats.skipped_bytes,
            "cut_at_byte": stats.cut_at_byte,
            "clock_restarts": stats.clock_restarts,
            "start_t_s": start_t_s,
        },
        "passport": dict(passport),
        "gravity_mps2": gravity_mps2,
        "block_s": config.block_s,
        "imus": imus,
        "pairs": [p.to_dict() for p in pairs],
        "cross_imu_norm": None if cross_imu_norm is None else dict(cross_imu_norm),
        "findings": findings,
        "firmware": fw.to_dict(),
        "coverage": dict(coverage),
    }


def write_report(
    report: Mapping[str, Any],
    healths: Mapping[int, ImuHealth],
    pairs: Sequence[PairDifference],
    out_dir: str | Path,
    firmware: FirmwareHealth | None = None,
    thrust: Mapping[int, ThrustStatistic] | None = None,
    norm_blocks: Sequence[NormBlock] = (),
) -> Path:
    """Write report.json, report.md and the plots into ``out_dir`` (created); returns the Markdown
    path. ``firmware``: the batch sampler's spectra join the spectra plot; ``thrust``: per IMU the
    thrust-axis statistic through the flight (None: no GNSS); ``norm_blocks``: the cross-IMU norm
    check's blocks, for its plot."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(
        json.dumps(report, sort_keys=True, indent=1, allow_nan=False) + "\n", encoding="utf-8"
    )
    plots = {
        "gravity_residual.png": _residual_plot(report, healths, out / "gravity_residual.png"),
        "spectra.png": _spectra_plot(healths, firmware or FirmwareHealth(), out / "spectra.png"),
        "cross_imu.png": _cross_plot(report, pairs, out / "cross_imu.png"),
        "thrust_axis.png": _thrust_plot(report, thrust or {}, out / "thrust_axis.png"),
        "cross_imu_norm.png": _norm_plot(report, norm_blocks, out / "cross_imu_norm.png"),
    }
    md = out / "report.md"
    md.write_text(_markdown(report, plots), encoding="utf-8")
    return md


# --------------------------------------------------------------------------- plots

_MARGINS = Margins()
"""The plots' margins (8 inches wide; tick labels of six characters at most, ``1e−05`` or ``−0.025``,
axis labels of one line; the axes off the figure's middle by 0.3 inch at most, so the time label
of a log on Unix time, 7.4 inches, stays in the figure), set rather than measured: ``tight_layout``
took 0.09 s of the 0.30 s the five-minute log's two plots took."""
_TITLED = Margins(top=0.45)


def _residual_plot(report: Mapping[str, Any], healths: Mapping[int, ImuHealth], path: Path) -> bool:
    g = float(report["gravity_mps2"])
    shells = {e["imu"]: (e["f0_accel"] or {}).get("shell_mps2") for e in report["imus"]}
    if not any(h.blocks.rest.any() for h in healths.values()):
        return False
    fig, ax = subplots(figsize=(8, 3.6))
    for imu, h in sorted(healths.items()):
        b = h.blocks
        t = (b.k[b.rest] + 0.5) * report["block_s"] - _start(report)
        ax.plot(t, np.linalg.norm(b.accel_mean[b.rest], axis=1) - g, ".", ms=3, label=f"IMU{imu}")
        shell = shells.get(imu)
        if shell is not None:
            ax.axhline(shell, color="k", lw=0.8, ls="--")
            ax.axhline(-shell, color="k", lw=0.8, ls="--")
    return _finish_in_time(fig, ax, report, path, "|a| − g at rest, m/s²", "Blocks at rest against F0's shell (dashed)")  # fmt: skip


def _finish_in_time(fig: Any, ax: Any, report: Mapping[str, Any], path: Path, ylabel: str, title: str) -> bool:  # fmt: skip
    """Label a plot against the log's time, save it: True (it was written)."""
    ax.set_xlabel(_time_label(report))
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=90, margins=_TITLED)
    return True


def _spectra_plot(healths: Mapping[int, ImuHealth], firmware: FirmwareHealth, path: Path) -> bool:
    batches = [b for b in firmware.batches if b.stream.freq_hz.size]
    if not any(h.freq_hz.size for h in healths.values()) and not batches:
        return False
    fig, axes = subplots(2, 1, figsize=(8, 6), sharex=True)
    for imu, h in sorted(healths.items()):
        if not h.freq_hz.size:
            continue
        for ax, psd in zip(axes, (h.accel_psd, h.gyro_psd), strict=True):
            for k, axis in enumerate(AXES):
                ax.semilogy(h.freq_hz[1:], psd[1:, k], lw=0.8, label=f"IMU{imu} {axis}")
    for b in batches:
        ax = axes[0 if b.sensor == "accel" else 1]
        for k, axis in enumerate(AXES):
            label = f"batch {b.sensor}{b.instance} {axis} ({b.stream.rate_hz:.0f} Hz)"
            ax.semilogy(b.stream.freq_hz[1:], b.stream.psd[1:, k], lw=0.6, ls="--", label=label)
    axes[0].set_ylabel("accel PSD, (m/s²)²/Hz")
    axes[1].set_ylabel("gyro PSD, (rad/s)²/Hz")
    axes[1].set_xlabel("frequency, Hz")
    for ax in axes:
        if ax.get_yscale() == "log":  # an axis with no spectrum stays linear
            plain_log_labels(ax)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, ncol=3)
    save_figure(fig, path, dpi=90, margins=_MARGINS)
    return True


def _start(report: Mapping[str, Any]) -> float:
    """The time the report's plots count from: the log's first sample, s of its clock."""
    return float(report["log"]["start_t_s"] or 0.0)


def _time_label(report: Mapping[str, Any]) -> str:
    return f"time from the log's start, s (start: {log_start(report['log']['start_t_s'])})"


def _cross_plot(report: Mapping[str, Any], pairs: Sequence[PairDifference], path: Path) -> bool:
    if not pairs:
        return False
    fig, axes = subplots(2, 1, figsize=(8, 5), sharex=True)
    for p in pairs:
        label = f"IMU{p.imus[0]}−IMU{p.imus[1]}"
        # A run after the clock started again goes back in time: its line starts apart.
        cuts = np.flatnonzero(np.diff(p.run)) + 1
        t = np.insert(p.t_s - _start(report), cuts, np.nan)
        axes[0].plot(t, np.insert(p.accel_mps2, cuts, np.nan), lw=0.8, label=label)
        axes[1].plot(t, np.insert(p.gyro_rps, cuts, np.nan), lw=0.8, label=label)
    axes[0].set_ylabel("|Δa|, m/s²")
    axes[1].set_ylabel("|Δω|, rad/s")
    axes[1].set_xlabel(_time_label(report))
    axes[0].legend(fontsize=8)
    save_figure(fig, path, dpi=90, margins=_MARGINS)
    return True


def _thrust_plot(
    report: Mapping[str, Any], thrust: Mapping[int, ThrustStatistic], path: Path
) -> bool:
    if not any(np.isfinite(s.z).any() for s in thrust.values()):
        return False
    fig, ax = subplots(figsize=(8, 3.6))
    for imu, s in sorted(thrust.items()):
        ax.plot(s.t_s - _start(report), s.z, lw=0.8, label=f"IMU{imu}")
        ax.axhline(s.threshold, color="k", lw=0.8, ls="--")
    return _finish_in_time(fig, ax, report, path, "max over windows |D_L| / σ_L", "In flight: |f| against GNSS, the statistic and its threshold (dashed)")  # fmt: skip


def _norm_plot(report: Mapping[str, Any], blocks: Sequence[NormBlock], path: Path) -> bool:
    norm = report.get("cross_imu_norm")
    if norm is None or not blocks:
        return False
    t = np.array([b.t_s for b in blocks]) - _start(report)
    fig, axes = subplots(2, 1, figsize=(8, 5), sharex=True)
    channels = ((axes[0], "accel", "|f|"), (axes[1], "gyro", "|ω|"))
    for ax, name, word in channels:
        stat = [max(getattr(b, name).cusum_pos, getattr(b, name).cusum_neg) for b in blocks]
        ax.plot(
            t, stat, lw=0.8, label=f"CUSUM of {word}{norm['imus'][1]} − {word}{norm['imus'][0]}"
        )
        ax.axhline(norm["threshold"], color="k", lw=0.8, ls="--", label="threshold")
        alarms = [
            a.t_s - _start(report) for b in blocks for a in b.alarms if a.channel.value == name
        ]
        for x in alarms:
            ax.axvline(x, color="r", lw=1.0)
        ax.set_ylabel(f"{name} CUSUM, σ")
        ax.legend(fontsize=7, loc="upper left")
    r, sd = norm["lever_arm_m"], norm["lever_arm_sd_m"]
    axes[0].set_title(
        "Lever arm found: "
        + ", ".join(f"{100 * v:.1f} ± {100 * e:.1f} cm" for v, e in zip(r, sd, strict=True)),
        fontsize=9,
    )
    axes[1].set_xlabel(_time_label(report))
    save_figure(fig, path, dpi=90, margins=_TITLED)
    return True


# --------------------------------------------------------------------------- Markdown


def _f(v: Any, spec: str = ".4g") -> str:
    if v is None:
        return "—"
    if isinstance(v, list):
        return ", ".join(_f(x, spec) for x in v)
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _imu_table(e: Mapping[str, Any]) -> list[str]:
    vib = e["vibration"]
    vibe = vib["ardupilot_vibe_mps2"]
    grav = e["gravity_residual_mps2"]
    temp = e["temperature_c"]
    f0 = e["f0_accel"]
    settling = (
        f"; {e['settling_blocks']} settling block(s) left out" if e["settling_blocks"] else ""
    )
    below = f" from the logged samples (sees below {vib['recomputed_below_hz']:.0f} Hz only)"
    rows = [
        ("source", e["source"]),
        ("samples", e["n_samples"]),
        ("runs (the clock started again in between)", e["runs"]),
        ("rate (median), Hz", _f(e["rate_hz"])),
        ("duration, s", _f(e["duration_s"])),
        ("gaps (count, longest s)", f"{e['gaps']['count']}, {_f(e['gaps']['longest_s'])}"),
        ("at rest, s (blocks of spread ≤ accel, gyro)", f"{_f(e['rest_s'])} ({_f(e['rest_test']['accel_spread_mps2'])} m/s², {_f(e['rest_test']['gyro_spread_rps'])} rad/s)"),
        (f"accel noise x, y, z, m/s² ({e['noise_method']}{settling})", _f(e["accel_noise_mps2"])),
        (f"gyro noise x, y, z, rad/s ({e['noise_method']}{settling})", _f(e["gyro_noise_rps"])),
        ("|a| − g at rest (median, max abs), m/s²", "—" if grav is None else f"{_f(grav['median'])}, {_f(grav['max_abs'])}"),
        ("gyro bias at rest x, y, z, rad/s", _f(e["gyro_bias_rps"])),
        (f"VIBE recomputed in flight{below} x, y, z (median / max), m/s²", "—" if vibe is None else f"{_f(vibe['median'], '.3g')} / {_f(vibe['max'], '.3g')}"),
        (f"PX4 accel vibration metric recomputed{below} (median / max), m/s", "—" if vib["px4_accel_vibration_metric_mps"] is None else f"{_f(vib['px4_accel_vibration_metric_mps']['median'])} / {_f(vib['px4_accel_vibration_metric_mps']['max'])}"),
        (f"PX4 gyro vibration metric recomputed{below} (median / max), rad", "—" if vib["px4_gyro_vibration_metric_rad"] is None else f"{_f(vib['px4_gyro_vibration_metric_rad']['median'])} / {_f(vib['px4_gyro_vibration_metric_rad']['max'])}"),
        ("clipped samples", _f(e["clipped_samples"])),
        ("temperature (min, max), °C", "—" if temp is None else f"{_f(temp['min'])}, {_f(temp['max'])}"),
        ("F0 shell λ0 (|a| − g, m/s²); tests, fails", "not run" if f0 is None or f0["lambda0"] is None else f"{_f(f0['lambda0'])} ({_f(f0['shell_mps2'])}); {f0['tests']}, {f0['fails']}"),
    ]  # fmt: skip
    return ["| | |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)]


def _tolerances(pp: Mapping[str, Any]) -> str:
    """The nominal passport's tolerances, in the units its datasheets state them."""
    return (
        f"Tolerances: accelerometer bias {_f(pp['accel_bias_mg'])} mg, scale {_f(pp['accel_scale_pct'])} %, "
        f"cross-axis {_f(pp['accel_cross_axis_pct'])} %, noise {_f(pp['accel_noise_ug_per_rthz'])} µg/√Hz; "
        f"gyro bias {_f(pp['gyro_bias_dph'])} °/h, scale {_f(pp['gyro_scale_pct'])} %, "
        f"cross-axis {_f(pp['gyro_cross_axis_pct'])} %, noise {_f(pp['gyro_noise_dps_per_rthz'])} °/s/√Hz."
    )


def _coverage_section(coverage: Mapping[str, Any]) -> list[str]:
    """The verdict, what was not tested, and each check's coverage (one line each)."""
    from estimators.coverage import ImuCoverage

    lines = ["## Verdict and coverage", "", f"**{coverage['verdict']}**."]
    if coverage["untested"]:
        lines += ["", "Not tested:", *(f"- {u}" for u in coverage["untested"])]
    lines += ["", "What each check tested (minimum detectable fault at probability 0.95):", ""]
    for imu in coverage["imus"]:
        lines += [f"- {line}" for line in ImuCoverage.from_dict(imu).lines()]
    return lines


def _passport_lines(pp: Mapping[str, Any], *, n_imus: int) -> list[str]:
    """What passport applied: none (stream checks only) where the replay applied none, and why."""
    not_applied = list(pp.get("not_applied", []))
    if not_applied and len(not_applied) >= n_imus:
        return [f"No passport applied, stream checks only: {'; '.join(not_applied)}."]
    lines = [
        f"Passport: {pp.get('kind')}"
        + (f", class `{pp['class']}` ({pp['source']})" if pp.get("class") else "")
        + "."
    ]
    if pp.get("class"):
        lines.append(_tolerances(pp))
    if not_applied:
        lines.append(f"Not applied (stream checks only): {'; '.join(not_applied)}.")
    return lines


def _levels(summary: Mapping[str, Any] | None, unit: str | None) -> str:
    if summary is None or not summary["n"]:
        return "—"
    return f"{_f(summary['median'], '.3g')} / {_f(summary['max'], '.3g')} {unit or ''}".strip()


def _firmware_section(fw: Mapping[str, Any]) -> list[str]:
    """The log's own health data: vibration and clipping as the firmware measured them, the batch sampler."""
    if not (fw["vibration"] or fw["clipped"] or fw["batches"] or fw["unread"]):
        return []
    lines = ["", "## The firmware's own health data", ""]
    if fw["unread"]:
        lines.append(f"Not read: {fw['unread']}.")
    if fw["vibration"]:
        lines += [
            "Measured by the autopilot on the sensor's own samples (what the logged samples' rate cannot show).",
            "",
            "| message | instance | vibration (median / max) | above warning, error (messages) | gyro vibration | coning | clipping x, y, z | rates, Hz |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for v in fw["vibration"]:
            above = ", ".join(f"{n} > {k}" for k, n in v["accel"]["above"].items())
            rates = (
                ", ".join(f"{k.removesuffix('_hz')} {x:.0f}" for k, x in v["rates_hz"].items())
                or "—"
            )
            inst = "primary" if v["instance"] is None else v["instance"]
            lines.append(
                f"| {v['message']} | {inst} | {_levels(v['accel'], v['unit'])} | {above} | "
                f"{_levels(v['gyro'], v['gyro_unit'])} | {_levels(v['coning'], 'rad²')} | {_f(v['clipping_axes'])} | {rates} |"
            )
        lines += [
            "",
            "Thresholds: "
            + "; ".join(
                sorted(
                    {
                        f"{v['source']}: {v['limits'][0]:g}, {v['limits'][1]:g} {v['unit']}"
                        for v in fw["vibration"]
                    }
                )
            )
            + ".",
        ]
    if fw["clipped"]:
        clipped = ", ".join(f"instance {k} {n}" for k, n in fw["clipped"].items())
        before = ", ".join(f"instance {k} {n}" for k, n in fw["clipped_before_log"].items() if n)
        since = f"; before the log's first message the counters held {before} (since boot)"
        lines += [
            "",
            f"Clipped samples over the log ({fw['clip_message']} counters): {clipped}"
            + (since if before else "")
            + ".",
        ]
    if fw["batches"]:
        lines += [
            "",
            "Batch sampler (ISBH/ISBD: the sensor's raw samples at its own rate):",
            "",
            "| sensor | instance | samples (blocks) | rate, Hz | noise x, y, z (first difference) | saturated samples |",
            "|---|---|---|---|---|---|",
        ]
        for b in fw["batches"]:
            lines.append(
                f"| {b['sensor']} | {b['instance']} | {b['samples']} ({b['blocks']}) | {_f(b['rate_hz'], '.0f')} | "
                f"{_f(b['noise'])} {b['unit']} | {b['saturated']} |"
            )
    return lines


def _markdown(report: Mapping[str, Any], plots: Mapping[str, bool]) -> str:
    log, pp = report["log"], report["passport"]
    lines = [
        f"# IMU health of {log['name']}",
        "",
        f"Format `{log['format']}`" + (f", system {log['system']}" if log["system"] else "") + ".",
        f"Starts at {log_start(log['start_t_s'])}; the times below count from there.",
        *_passport_lines(pp, n_imus=len(report["imus"])),
        f"Local gravity {report['gravity_mps2']:.5f} m/s².",
        "",
    ]  # fmt: skip
    if log["left_out"]:
        lines += ["Left out: " + "; ".join(f"{k} {v}" for k, v in log["left_out"].items()), ""]
    damage = [f"{k} {n}" for k, n in log["dropped_samples"].items()]
    if log["skipped_bytes"]:
        damage.append(f"{log['skipped_bytes']} bytes that start no message")
    if log["cut_at_byte"] is not None:
        damage.append(f"the file is cut mid-message at byte {log['cut_at_byte']}")
    if damage:
        lines += ["Not read: " + "; ".join(damage) + ".", ""]
    if log["clock_restarts"]:
        lines += [
            f"The time of the samples started again {log['clock_restarts']} time(s) (an autopilot reboot, "
            "or logs joined end to end): each IMU's runs are taken apart; in the plots each run keeps its own clock.",
            "",
        ]
    lines += ["## Findings", ""]
    if report["findings"]:
        lines += [f"- **{f['severity']}** {f['text']}" for f in report["findings"]]
    else:
        lines.append("None.")
    lines += _firmware_section(report["firmware"])
    lines += ["", *_coverage_section(report["coverage"])]
    for e in report["imus"]:
        lines += ["", f"## IMU{e['imu']}", "", *_imu_table(e)]
    if report["pairs"]:
        lines += ["", "## Cross-IMU disagreement (block means)", "", "| pair | accel p99 / max flight, m/s² | at rest | gyro p99 / max flight, rad/s | at rest |", "|---|---|---|---|---|"]  # fmt: skip
        for p in report["pairs"]:

            def pm(d: Mapping[str, Any] | None) -> str:
                return "—" if d is None else f"{_f(d['p99'])} / {_f(d['max'])}"

            lines.append(
                f"| IMU{p['imus'][0]}–IMU{p['imus'][1]} | {pm(p['accel_mps2']['flight'])} | {pm(p['accel_mps2']['rest'])} "
                f"| {pm(p['gyro_rps']['flight'])} | {pm(p['gyro_rps']['rest'])} |"
            )
    if (norm := report.get("cross_imu_norm")) is not None:
        i0, i1 = norm["imus"]
        lines += [
            "",
            "## Cross-IMU norm in flight",
            "",
            f"IMU{i1} against IMU{i0}, rotation-invariant (no mounting needed): tested on "
            f"{norm['tested_s']:.0f} s, minimum detectable shift {_f(norm['mdf_mps2'], '.2g')} m/s² "
            f"and {_f(norm['mdf_rps'], '.2g')} rad/s (5 s mean delay) at {norm['false_alarms_per_hour']:g} "
            f"false alarms per flight hour (CUSUM threshold {norm['threshold']:.3g} σ). Lever arm found "
            "(IMU0's axes): "
            + ", ".join(
                f"{100 * v:.1f} ± {100 * e:.1f} cm"
                for v, e in zip(norm["lever_arm_m"], norm["lever_arm_sd_m"], strict=True)
            )
            + ".",
        ]
    titles = {
        "gravity_residual.png": "|a| − g at rest against the F0 shell",
        "spectra.png": "Accelerometer and gyro spectra",
        "cross_imu.png": "Cross-IMU differences over time",
        "thrust_axis.png": "Thrust axis against GNSS in flight",
        "cross_imu_norm.png": "Cross-IMU norm: CUSUM through the flight against its threshold",
    }
    for name in PLOTS:
        if plots.get(name):
            lines += ["", f"## {titles[name]}", "", f"![{titles[name]}]({name})"]
    return "\n".join(lines) + "\n"
