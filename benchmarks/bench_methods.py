"""Time of each bench method (M2, M3, M4) on its standard bench size.

Standard sizes (the papers' protocols):

* M2 tilt: 5 runs × (60 angles × 30 s + up/down 2 × 60 s) at 50 Hz = 480,000
  samples (510,500 with the table's moves in the session form); timed: simulating the samples, the passport (5 least-squares fits with
  their stabilization series, intervals, intersection), and the passport from
  session samples (plateau finding on 5 × 102,100 samples plus the passport).
* M3 temperature: 25 chamber temperatures (−45…+75 °C) × six positions × 20 s at
  100 Hz; timed: static positions of the chamber session, the 25 six-position
  tests, and the GMDH comparison of orders 1–5 with the final fit.
* M4: one six-position session (6 × 60 s at 100 Hz, the paper's), positions and
  both fits; one rate-table record (31 steps × 10 s at 100 Hz), step finding and
  fit.

Each figure is the best of three runs. Run: ``python benchmarks/bench_methods.py``.
"""

from __future__ import annotations

import numpy as np
from stopwatch import best_s

from estimators.conventions import normal_gravity_mps2
from estimators.sim import simulate
from estimators.sixpos import (
    GUANGZHOU_HEIGHT_M,
    GUANGZHOU_LATITUDE_DEG,
    adis_like_model,
    find_rate_steps,
    paper_rate_profile_rps,
    rate_table_fit,
    session_positions,
    simulate_rate_table,
    six_position_spec,
    six_position_test,
)
from estimators.temperature import (
    PAPER_TEMPS_C,
    fit_temperature_model,
    hidden_quartic_model,
    simulate_chamber,
    temperature_series,
)
from estimators.tilt import (
    TiltBench,
    bench_session,
    run_from_session,
    runs_from_samples,
    simulate_samples,
    tilt_passport,
)


def _row(name: str, seconds: float, size: str) -> None:
    print(f"{name:<52} {seconds * 1e3:9.1f} ms   {size}")


def main() -> None:
    print(f"{'step':<52} {'time':>12}   size")

    bench = TiltBench()
    samples = simulate_samples(bench, np.random.default_rng(1))
    t = best_s(lambda: simulate_samples(bench, np.random.default_rng(1)), 3)
    n = sum(s.up.size + s.down.size + s.angles.size for s in samples)
    _row("M2 simulate the bench (whole pulses)", t, f"{n:,} samples")
    runs = runs_from_samples(bench, samples)
    t = best_s(lambda: tilt_passport(runs, gravity_mps2=bench.gravity_mps2), 3)
    _row(
        "M2 passport (5 runs: LS, stabilization, intervals)",
        t,
        f"{len(runs)} runs × {len(bench.angles_deg)} angles",
    )
    sessions = [bench_session(bench, s, rng=np.random.default_rng(2)) for s in samples]
    angles = np.radians(bench.angles_deg)

    def from_sessions():
        return tilt_passport(
            [run_from_session(s, angles_rad=angles)[0] for s in sessions],
            gravity_mps2=bench.gravity_mps2,
        )

    t = best_s(from_sessions, 3)
    _row("M2 passport from session samples", t, f"{sum(s.n_samples for s in sessions):,} samples")

    g = normal_gravity_mps2(45.0, 0.0)
    chamber = simulate_chamber(
        hidden_quartic_model(gravity_mps2=g), PAPER_TEMPS_C, seed=1, static_s=20.0
    )
    positions = session_positions(chamber)
    t = best_s(lambda: session_positions(chamber), 3)
    _row("M3 static positions of the chamber session", t, f"{chamber.n_samples:,} samples")
    series = temperature_series(positions, gravity_mps2=g)
    t = best_s(lambda: temperature_series(positions, gravity_mps2=g), 3)
    _row("M3 six-position tests at every temperature", t, f"{series.temp_c.size} temperatures")

    def gmdh():
        return fit_temperature_model(
            series.temp_c,
            series.bias_mps2,
            series.scale_error,
            bias_std_mps2=series.bias_std_mps2,
            scale_std=series.scale_std,
            gravity_mps2=g,
        )

    fit = gmdh()
    t = best_s(gmdh, 3)
    _row(f"M3 GMDH orders 1-5 and fit (selected {fit.order})", t, "6 series")

    g_site = normal_gravity_mps2(GUANGZHOU_LATITUDE_DEG, GUANGZHOU_HEIGHT_M)
    model = adis_like_model()
    six = simulate(six_position_spec(model), 1).session
    pos6 = session_positions(six)
    t = best_s(lambda: session_positions(six), 3)
    _row("M4 static positions of a six-position session", t, f"{six.n_samples:,} samples")
    t = best_s(
        lambda: six_position_test(pos6, gravity_mps2=g_site, latitude_deg=GUANGZHOU_LATITUDE_DEG), 3
    )
    _row("M4 six-position accelerometer + gyro Bf/Bg fits", t, f"{len(pos6)} positions")
    profile = paper_rate_profile_rps()
    rate = simulate_rate_table(model, axis=0, profile_rps=profile, gravity_mps2=g_site, seed=1)

    def rate_fit():
        steps = find_rate_steps(rate.t_s, rate.gyro_rps, axis=0, profile_rps=profile)
        return rate_table_fit(
            profile, steps.gyro_mean_rps, axis=0, gyro_var_rps=steps.gyro_var_rps[:, 0]
        )

    t = best_s(rate_fit, 3)
    _row("M4 rate-table steps and fit", t, f"{rate.n_samples:,} samples, {profile.size} steps")


if __name__ == "__main__":
    main()
