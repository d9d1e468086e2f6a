"""Wall time of the full audit of the Xsens session and its growth with the replica count."""

import time
from pathlib import Path

from estimators.audit import AuditConfig, run_audit
from estimators.chain import ChainConfig
from protocols.session_file import load_session

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "xsens-multiposition"

if __name__ == "__main__":
    session = load_session(str(DATA)).session
    for replicas in (5, 10, 20, 40):
        t0 = time.perf_counter()
        run_audit(session, AuditConfig(ChainConfig(gravity_mps2=9.81744), replicas=replicas))
        print(f"xsens audit, {session.n_samples} samples, {replicas:3d} replicas: {time.perf_counter() - t0:6.1f} s")
