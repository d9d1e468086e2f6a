"""The conclusion of the audit on the real Xsens session (docs/audit-xsens.md)."""

from pathlib import Path

from estimators.audit import AuditConfig, run_audit
from estimators.chain import ChainConfig
from estimators.conventions import Triad
from protocols.session_file import load_session

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "xsens-multiposition"


def test_xsens_bias_instability_explains_the_headline():
    res = run_audit(load_session(str(DATA)).session, AuditConfig(ChainConfig(gravity_mps2=9.81744), replicas=10, seed=0))
    named = {(c.effect, c.triad) for c in res.named}
    assert ("bias_instability", Triad.ACCEL) in named
    assert not any(c.effect in ("bias_drift", "scale_nonlinearity") and c.triad is Triad.ACCEL for c in res.named)
    base, ext = res.headline(res.baseline_cmp), res.headline(res.extended_cmp)
    assert base.measured > base.simulated_p95  # the white-noise model cannot produce χ²/dof ≈ 8.6
    assert ext.simulated_p05 <= ext.measured <= ext.simulated_p95
