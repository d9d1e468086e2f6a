"""Time of the rocking method (methods.md M5) and throughput of the strapdown attitude integrator.

Standard bench: the paper's three 150 s runs (12.2°, 0.53 Hz; static, 100 s
rocking, static) of its unit at 100 Hz, 45,000 gyro samples, estimated with
the closed form and the model-based Gauss–Newton solution. The integrator is
timed on one record and on a batch (the model-based estimate integrates
batches). Each figure is the best of three runs. Run:
``taskset -c 0 python benchmarks/bench_rocking.py`` (one core).
"""

from __future__ import annotations

import numpy as np
from stopwatch import best_s

from estimators.rocking import (
    PAPER_DK,
    GyroUnit,
    StandSettings,
    estimate_scale_errors,
    paper_runs,
    simulate_run,
)
from estimators.strapdown import integrate_attitude


def main() -> None:
    rng = np.random.default_rng(1)
    sessions = [simulate_run(r, GyroUnit(), rate_hz=100.0, rng=rng) for r in paper_runs()]
    n_samples = sum(s.n_samples for s in sessions)
    result = estimate_scale_errors(sessions, stand=StandSettings())
    t_method = best_s(lambda: estimate_scale_errors(sessions, stand=StandSettings()), 3)
    print(
        f"rocking method, paper bench (3 runs, {n_samples} samples at 100 Hz): {t_method:.2f} s, "
        f"{result.model.steps} Gauss–Newton steps"
    )
    for name, dk in (("model-based", result.dk), ("closed form", result.closed.dk)):
        print(f"  {name} δK error: " + ", ".join(f"{100 * v:+.3f} %" for v in dk / PAPER_DK - 1))

    n = 200_000
    t = np.arange(n) / 100.0
    w = rng.normal(0.0, 0.5, (n, 3))
    for coning in (True, False):
        dt = best_s(lambda: integrate_attitude(t, w, coning=coning), 3)
        print(
            f"attitude integrator, one record of {n} samples, coning={coning}: {n / dt / 1e6:.2f} M samples/s"
        )
    batch = rng.normal(0.0, 0.5, (16, 20_000, 3))
    dt = best_s(lambda: integrate_attitude(t[:20_000], batch), 3)
    print(
        f"attitude integrator, batch of 16 x 20000 samples: {batch.shape[0] * batch.shape[1] / dt / 1e6:.2f} M samples/s"
    )


if __name__ == "__main__":
    main()
