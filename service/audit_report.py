"""Markdown report and PNG plots of a model audit (``ins-health audit --report DIR``)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from estimators.audit import AuditResult  # noqa: E402


def _stat_plot(result: AuditResult, path: Path) -> None:
    """Measured / median-simulated ratio of every statistic, baseline and extended, with the replicas' 5–95 % band."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for k, (name, cmp, mark) in enumerate((("baseline", result.baseline_cmp, "o"), ("extended", result.extended_cmp, "s"))):
        labels = [f"{c.triad.value} {c.statistic}{'' if c.axis is None else ' ' + c.axis}" for c in cmp]
        x = np.arange(len(cmp)) + 0.2 * k
        lo = [c.simulated_p05 / c.simulated_median for c in cmp]
        hi = [c.simulated_p95 / c.simulated_median for c in cmp]
        ax.vlines(x, lo, hi, color=f"C{k}", alpha=0.4, lw=6)
        ax.plot(x, [c.ratio for c in cmp], mark, color=f"C{k}", label=f"{name}: measured / simulated median (bar: replicas 5–95 %)")
    ax.set_xticks(np.arange(len(labels)), labels, rotation=70, fontsize=7)
    ax.set_yscale("log")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.legend(fontsize=7)
    ax.set_title(f"Measured statistics against {result.replicas} Monte Carlo replicas")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _headline_plot(result: AuditResult, path: Path) -> None:
    """Histogram of the simulated χ²/dof (baseline and extended) with the measured value."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, k in (("baseline", 0), ("extended", 1)):
        reps = result.replica_stats.get(name, {})
        vals = [r["chi2_per_dof"] for r in reps.get(next(iter(reps), None), []) if "chi2_per_dof" in r] if reps else []
        if vals:
            ax.hist(vals, bins=12, alpha=0.5, color=f"C{k}", label=f"{name} replicas")
    head = result.headline(result.baseline_cmp)
    if head is not None:
        ax.axvline(head.measured, color="k", label="measured")
    ax.set_xlabel("accelerometer χ²/dof of the scalar equation per position")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(result: AuditResult, out_dir: str | Path, *, title: str) -> Path:
    """Write ``audit.md`` and its PNGs into ``out_dir``; returns the Markdown path."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    lines = [f"# Model audit: {title}", ""]
    lines += [f"- {s}" for s in result.statements]
    if result.baseline_cmp:
        _stat_plot(result, d / "statistics.png")
        _headline_plot(result, d / "headline.png")
        data = result.to_dict()
        lines += [
            f"Positions: {result.n_positions}; Monte Carlo replicas: {result.replicas}.", "",
            f"Headline (accelerometer χ²/dof): baseline ratio {data['baseline']['ratio']:.2f} (tail {data['baseline']['tail_prob']:.2f}),"
            f" extended ratio {data['extended']['ratio']:.2f} (tail {data['extended']['tail_prob']:.2f}).", "",
            "## Named causes", "",
        ]
        lines += [f"- **{c['effect']}** ({c['triad']}{'' if c['axis'] is None else ' ' + c['axis']}): {c['evidence']}; params {c['params']}" for c in data["named_causes"]] or ["- none"]
        lines += ["", "## Gain", ""] + [f"- {k}: {v:.4g}" for k, v in data["gain"].items()]
        lines += ["", "![statistics](statistics.png)", "", "![headline](headline.png)", ""]
    path = d / "audit.md"
    path.write_text("\n".join(lines) + "\n")
    return path
