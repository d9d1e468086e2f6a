"""Model audit (issue 4): measured statistics against the simulation, named causes, extended model, gain.

Public entry points: :func:`run_audit` with :class:`AuditConfig`, and
:func:`effective_noise_std_norm` (the surviving noise model for
:func:`estimators.scalar.derive_lambda0`).
"""

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
from .statistics import MIN_POSITIONS, Comparison, TriadCurves

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
