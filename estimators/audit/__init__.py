"""Model audit (issue 4): measured statistics against the simulation, named causes, extended model, gain.

Public entry points: :func:`run_audit` with :class:`AuditConfig`, and
:func:`effective_noise_std_norm` (the surviving noise model for
:func:`estimators.scalar.derive_lambda0`).

The submodules load on first use of one of their names: ``calibrate`` asks
:data:`MIN_POSITIONS` (defined here, so that asking loads none of them) before it runs the
audit, and a six-position session, too few for it, does not pay for importing the
simulator, nor the statistics and their noise analysis.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .audit import (
        DEFAULT_REPLICAS,
        AuditConfig,
        AuditResult,
        TriadBaseline,
        effective_noise_std_norm,
        extend_model,
        find_candidates,
        fit_baseline,
        fit_baselines,
        run_audit,
        same_session_spec,
    )
    from .candidates import CANDIDATE_NAMES, FAMILY_ALPHA, Candidate
    from .statistics import Comparison, TriadCurves

MIN_POSITIONS = 12
"""Positions needed for the accelerometer statistics (9 parameters plus a few degrees of freedom)."""

__all__ = [
    "CANDIDATE_NAMES",
    "DEFAULT_REPLICAS",
    "FAMILY_ALPHA",
    "MIN_POSITIONS",
    "AuditConfig",
    "AuditResult",
    "Candidate",
    "Comparison",
    "TriadBaseline",
    "TriadCurves",
    "effective_noise_std_norm",
    "extend_model",
    "find_candidates",
    "fit_baseline",
    "fit_baselines",
    "run_audit",
    "same_session_spec",
]

_NOT_IN_AUDIT = {
    "CANDIDATE_NAMES": "candidates",
    "FAMILY_ALPHA": "candidates",
    "Candidate": "candidates",
    "Comparison": "statistics",
    "TriadCurves": "statistics",
}


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = importlib.import_module(f".{_NOT_IN_AUDIT.get(name, 'audit')}", __name__)
    return getattr(module, name)
