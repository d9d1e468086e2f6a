"""The thrust axis against GNSS (estimators.thrust_gnss, issue 32).

In flight the accelerometer's ``|f̃|`` is compared with ``|a_n − g_n|`` from the receiver's
velocity, through one kernel on both sides, so a perfect unit and receiver agree through any
manoeuvre; a z zero-signal step of 0.1 m/s² and a z scale step of 1 % mid-flight are found within
10 s; fault-free flights raise nothing; frames give what the whole flight gives at once.

Flights: the project's flight profile (``flight_spec``: rest, ``Fly``, rest) at 240 s of flight,
consumer MEMS, a receiver at 10 Hz (and every second epoch of it: 5 Hz) with 0.05 m/s of white
velocity noise (0.075 m/s vertically) and a latency of 0.15 s. Faults are injected into the
samples (``z + 0.1 m/s²`` or ``z × 1.01`` from mid-flight on), so one simulation serves every case.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.stats import binom

from estimators import thrust_gnss
from estimators.session import ImuSession
from estimators.sim import ErrorModel, Fly, flight_spec, simulate
from estimators.sim.gnss import gnss_velocity
from estimators.thrust_gnss import (
    THRUST_AXIS,
    Exclusion,
    ThrustAxisConfig,
    ThrustAxisMonitor,
    threshold,
    thrust_axis_batch,
    thrust_axis_coverage,
    up_velocity_from_altitude,
)

N_FLIGHTS = 10
FLY_S = 240.0
REST_S = 10.0
ONSET_S = REST_S + FLY_S / 2
LATENCY_S = 0.15
DETECT_WITHIN_S = 10.0


def _flight(seed: int, *, model: ErrorModel | None = None, vel_sd_mps: float = 0.05):
    res = simulate(flight_spec(fly=Fly(FLY_S), rest_s=REST_S, model=model), seed)
    gt, gv = gnss_velocity(
        res.truth,
        rate_hz=10.0,
        vel_sd_mps=vel_sd_mps,
        latency_s=LATENCY_S,
        rng=np.random.default_rng(10_000 + seed),
    )
    return res.session, gt, gv


@pytest.fixture(scope="module")
def flights():
    return [_flight(seed) for seed in range(N_FLIGHTS)]


def _inject(session: ImuSession, kind: str) -> np.ndarray:
    accel = session.accel_mps2.copy()
    after = session.t_s >= ONSET_S
    if kind == "zero signal":
        accel[after, THRUST_AXIS] += 0.1
    else:
        accel[after, THRUST_AXIS] *= 1.01
    return accel


def test_a_perfect_unit_and_receiver_agree_through_manoeuvres():
    """A noise-free unit and receiver: D stays within 3 mm/s² of zero in every window (the
    trapezoids at 100 Hz and the interpolation between samples are what is left; a body-frame
    mean or the receiver's 10 Hz sampling not mirrored on the IMU side left 0.08 m/s² at the
    end of the manoeuvres), and the latency is found within 5 ms."""
    session, gt, gv = _flight(3, model=ErrorModel(), vel_sd_mps=0.0)
    ev, monitor = thrust_axis_batch(session.t_s, session.accel_mps2, session.gyro_rps, gt, gv)
    tested = ev.excluded == Exclusion.TESTED
    assert tested.sum() > 0.7 * FLY_S * 10.0
    assert np.max(np.abs(ev.d_mps2[tested])) < 3e-3
    assert monitor.noise is not None
    assert monitor.noise.latency_s == pytest.approx(LATENCY_S, abs=5e-3)


@pytest.mark.parametrize("rate_hz", [10.0, 5.0])
@pytest.mark.parametrize("kind", ["zero signal", "scale"])
def test_a_thrust_axis_fault_mid_flight_is_found_within_10_s(flights, kind, rate_hz):
    """At least 9 of 10 flights find the fault within 10 s of its onset and none alarms before
    it. benchmarks/bench_thrust_gnss.py finds 100 of 100 at 10 Hz and ≥ 98 of 100 at 5 Hz with
    this receiver; at a detection probability of 0.98, 8 or fewer of 10 has probability 1.6 %."""
    assert binom.cdf(8, N_FLIGHTS, 0.98) < 0.02
    found = 0
    for session, gt, gv in flights:
        step = 1 if rate_hz == 10.0 else 2
        ev, _ = thrust_axis_batch(
            session.t_s, _inject(session, kind), session.gyro_rps, gt[::step], gv[::step]
        )
        alarms = ev.t_s[ev.alarm]
        assert not np.any(alarms < ONSET_S)
        found += bool(np.any(alarms <= ONSET_S + DETECT_WITHIN_S))
    assert found >= 9


def test_fault_free_flights_raise_nothing(flights):
    """Ten fault-free flights at 10 and at 5 Hz, about 0.9 h of judged epochs: no alarm. At the
    design rate of 0.001 false alarms per flight hour the expected count is 0.0009."""
    judged_h = 0.0
    for session, gt, gv in flights:
        for step in (1, 2):
            ev, monitor = thrust_axis_batch(
                session.t_s, session.accel_mps2, session.gyro_rps, gt[::step], gv[::step]
            )
            assert monitor.alarms == 0
            judged_h += np.isfinite(ev.z).sum() / monitor.gnss_rate_hz / 3600.0
    assert judged_h > 0.5


def _altitude(gt: np.ndarray, gv: np.ndarray) -> np.ndarray:
    """The receiver's altitude (the vertical velocity's trapezoids, mm as GPS_RAW_INT has it)."""
    steps = 0.5 * (gv[1:, 2] + gv[:-1, 2]) * np.diff(gt)
    return 100.0 + np.r_[0.0, np.cumsum(steps)]


@pytest.mark.parametrize("glitch", ["altitude steps 0.5 m", "vertical velocity 2 m/s off for 2 s"])
def test_a_gnss_glitch_is_gated_and_a_fault_after_it_still_found(flights, glitch):
    """A receiver's glitch 30 s before the fault (the vertical from altitude differences, as a
    telemetry log and the live link give it): it moved ``D`` on every IMU at once and alarmed
    (both reviewer's flights, issue 32; the accelerometer blamed). Gated as a GNSS outlier, the
    windows holding it are counted and not judged, and the z zero-signal step that follows is
    still found within 10 s."""
    at_s = ONSET_S - 30.0
    for session, gt, gv in flights[:2]:
        alt = _altitude(gt, gv)
        vel = gv.copy()
        if glitch.startswith("altitude"):
            alt = alt + 0.5 * (gt >= at_s)
            vel[:, 2] = up_velocity_from_altitude(gt, np.round(alt, 3))
        else:
            vel[:, 2] = up_velocity_from_altitude(gt, np.round(alt, 3))
            vel[(gt >= at_s) & (gt < at_s + 2.0), 2] += 2.0
        ev, monitor = thrust_axis_batch(
            session.t_s, _inject(session, "zero signal"), session.gyro_rps, gt, vel
        )
        alarms = ev.t_s[ev.alarm]
        assert not np.any(alarms < ONSET_S)
        assert np.any(alarms <= ONSET_S + DETECT_WITHIN_S)
        gated = ev.t_s[ev.excluded == Exclusion.GNSS_OUTLIER]
        assert np.any((gated >= at_s) & (gated <= at_s + monitor.config.span_s))
        assert "GNSS velocity outlier" in thrust_axis_coverage(monitor.summary()).reason


def test_no_window_holding_the_touch_down_is_judged(flights):
    """Rest is declared seconds after the touch-down (the impact's spread decays first); dated at
    the declaration, the windows holding the impact were judged and the altitude path alarmed
    on the reviewer's seed 9 (z 11.7; 2 of 8 flights, issue 32). Dated back to the raw signal's
    last loud sample, no judged epoch reaches the touch-down, and seed 9 stays quiet with the GNSS
    gate off (its outliers would hide the impact here, not on a softer landing)."""
    landing_s = REST_S + FLY_S
    for session, gt, gv in flights:
        ev, _ = thrust_axis_batch(session.t_s, session.accel_mps2, session.gyro_rps, gt, gv)
        assert ev.t_s[ev.excluded == Exclusion.TESTED].max() < landing_s
    res = simulate(flight_spec(fly=Fly(170.0), rest_s=10.0), 9)
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(9)
    )
    vel = gv.copy()
    vel[:, 2] = up_velocity_from_altitude(gt, np.round(_altitude(gt, gv), 3))
    s = res.session
    no_gate = ThrustAxisConfig(gnss_outlier_sigmas=1e6)
    _, monitor = thrust_axis_batch(s.t_s, s.accel_mps2, s.gyro_rps, gt, vel, config=no_gate)
    assert monitor.alarms == 0


def _in_frames(session: ImuSession, accel: np.ndarray, gt: np.ndarray, gv: np.ndarray):
    """The daemon's path: IMU frames of 50 samples, GNSS frames of 7 epochs, interleaved in time;
    the monitor and what each update judged."""
    monitor = ThrustAxisMonitor(gnss_rate_hz=10.0)
    parts = []
    j = 0
    for i in range(0, session.t_s.size, 50):
        sl = slice(i, i + 50)
        parts.append(monitor.update_imu(session.t_s[sl], accel[sl], session.gyro_rps[sl]))
        while j < gt.size and gt[j] <= session.t_s[sl][-1]:
            parts.append(monitor.update_gnss(gt[j : j + 7], gv[j : j + 7]))
            j += 7
    parts.append(monitor.update_gnss(gt[j:], gv[j:]))
    return monitor, parts


def test_frames_give_what_the_whole_flight_gives(flights):
    """The daemon's path judges the same epochs with the same statistic as the batch path."""
    session, gt, gv = flights[0]
    accel = _inject(session, "zero signal")
    batch, _ = thrust_axis_batch(session.t_s, accel, session.gyro_rps, gt, gv)
    monitor, parts = _in_frames(session, accel, gt, gv)
    t = np.concatenate([p.t_s for p in parts])
    z = np.concatenate([p.z for p in parts])
    code = np.concatenate([p.excluded for p in parts])
    np.testing.assert_array_equal(t, batch.t_s)
    np.testing.assert_array_equal(code, batch.excluded)
    np.testing.assert_allclose(z, batch.z, rtol=1e-6, equal_nan=True)
    assert monitor.alarms == np.count_nonzero(batch.alarm) > 0


def test_the_averages_give_the_statistic_lfilter_gives(monkeypatch):
    """The rest detector's and the running noise's exponential averages, first-order low-passes
    solved by estimators.first_order_filter (no scipy.signal to import), judge every epoch as
    scipy.signal.lfilter's did, byte for byte, on a faulty flight taken in the daemon's frames."""

    def oracle(b0, a1, x, zi):
        return lfilter([b0], [1.0, a1], x, axis=0, zi=zi)

    session, gt, gv = _flight(0)
    accel = _inject(session, "zero signal")
    judged = []
    for solver in (thrust_gnss.first_order_filter, oracle):
        monkeypatch.setattr(thrust_gnss, "first_order_filter", solver)
        monitor, parts = _in_frames(session, accel, gt, gv)
        fields = ("t_s", "d_mps2", "z", "excluded", "alarm")
        judged.append([np.concatenate([getattr(p, f) for p in parts]).tobytes() for f in fields])
        assert monitor.alarms > 0
    assert judged[0] == judged[1]


def test_the_coverage_names_the_thrust_axis_and_not_x_y(flights):
    """The specific force stays within about 17° of body z (share of x, y about 0.3): z is tested,
    x and y are stated as not observable; the MDF in 10 s at 10 Hz is below 0.1 m/s²."""
    session, gt, gv = flights[1]
    _, monitor = thrust_axis_batch(session.t_s, session.accel_mps2, session.gyro_rps, gt, gv)
    summary = monitor.summary()
    assert summary.observable.tolist() == [False, False, True]
    assert summary.mdf_10s_mps2 is not None and summary.mdf_10s_mps2 < 0.1
    assert summary.baseline_mps2 == pytest.approx(9.806, abs=0.05)
    assert summary.exclusions["rest"] > 0 and summary.tested_epochs > 1000


def test_clipped_windows_and_a_flight_without_rest_are_not_tested(flights):
    """A clipped sample takes out the windows that hold it; a log cut in the air, no rest in it,
    has no ground baseline and nothing is judged (said, counted as no baseline)."""
    session, gt, gv = flights[2]
    accel = session.accel_mps2.copy()
    accel[(session.t_s > 100.0) & (session.t_s < 100.05), 0] = 200.0
    ev, monitor = thrust_axis_batch(
        session.t_s, accel, session.gyro_rps, gt, gv, config=ThrustAxisConfig(clip_mps2=150.0)
    )
    clipped = ev.t_s[ev.excluded == Exclusion.CLIPPED]
    assert clipped.size and clipped.min() >= 100.0 and clipped.max() <= 100.05 + 20.0
    airborne = (session.t_s > REST_S + 5.0) & (session.t_s < REST_S + FLY_S - 5.0)
    ev, monitor = thrust_axis_batch(
        session.t_s[airborne], session.accel_mps2[airborne], session.gyro_rps[airborne], gt, gv
    )
    assert monitor.baseline_mps2 is None and monitor.summary().tested_epochs == 0
    assert monitor.summary().exclusions["no_baseline"] > 0
    # It flew and was not tested (a daemon restarted in the air is this case): the verdict cannot
    # say "no fault". Only a vehicle that never flew is one the in-flight check does not apply to.
    cut = thrust_axis_coverage(monitor.summary())
    assert cut.missing and "no rest before the flight" in cut.reason
    ground = session.t_s < REST_S
    _, monitor = thrust_axis_batch(
        session.t_s[ground], session.accel_mps2[ground], session.gyro_rps[ground], gt, gv
    )
    assert not thrust_axis_coverage(monitor.summary()).applies


def test_the_threshold_follows_the_false_alarm_rate():
    """h = Φ⁻¹(1 − p/2), p = λ/(3600·r·W): 0.01 /h at 10 Hz over five windows is 5.43."""
    assert threshold(0.01, 10.0, 5) == pytest.approx(5.43, abs=0.01)
    assert threshold(0.01, 5.0, 5) < threshold(0.01, 10.0, 5) < threshold(0.001, 10.0, 5)


def test_bad_input_is_refused_with_the_reason():
    monitor = ThrustAxisMonitor()
    with pytest.raises(ValueError, match="finite"):
        monitor.update_imu(np.array([0.0]), np.array([[np.nan, 0.0, 9.8]]), np.zeros((1, 3)))
    monitor.update_imu(np.array([0.0, 0.01]), np.tile([0.0, 0.0, 9.8], (2, 1)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="increase"):
        monitor.update_imu(np.array([0.005]), np.array([[0.0, 0.0, 9.8]]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"vel_enu_mps \(M, 3\)"):
        monitor.update_gnss(np.array([0.0]), np.zeros(3))


def test_a_receiver_that_stops_does_not_hold_the_imu_history(flights):
    """The daemon's path with GNSS for the first 60 s only: the IMU kept stays within the windows'
    span and the lateness allowed (17.4 + 60 s at 100 Hz, a frame's samples more), where it grew by
    every sample before."""
    session, gt, gv = flights[0]
    monitor = ThrustAxisMonitor(gnss_rate_hz=10.0)
    early = gt < 60.0
    monitor.update_gnss(gt[early], gv[early])
    kept = []
    for i in range(0, session.t_s.size, 100):
        sl = slice(i, i + 100)
        monitor.update_imu(session.t_s[sl], session.accel_mps2[sl], session.gyro_rps[sl])
        kept.append(monitor._imu.t_s.size)
    cfg = monitor.config
    assert max(kept) <= (cfg.span_s + cfg.gnss_late_s + 2.0) * 100.0
