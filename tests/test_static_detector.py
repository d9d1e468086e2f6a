"""Stationarity and orientation-change detection (methods.md M1: positions of a static unit)."""

import json
import math
import sys

import numpy as np
import pytest
from real_data import XSENS, needs
from scipy.spatial.transform import Rotation
from synthetic_static import Bump, Gap, Rest, Rotate, build_scene, count_compositions, tumble

from estimators.session import ImuSession
from estimators.sim import Grade, multi_position_spec, simulate
from estimators.static_detector import (
    RotationIntegrator,
    StaticDetectorConfig,
    StreamingStaticDetector,
    detect_static,
    direction_change_deg,
    exact_sums,
    is_new_orientation,
)
from protocols.session_file import read_session


def _stream(
    session: ImuSession,
    *,
    config=StaticDetectorConfig(),
    rate_hz: float,
    state_at: int | None = None,
):
    """Feed a session sample by sample: (static mask over input rows, intervals, detector)."""
    det = StreamingStaticDetector(
        config,
        rate_hz=rate_hz,
        has_accel=session.accel_mps2 is not None,
        has_gyro=session.gyro_rps is not None,
    )
    n = session.n_samples
    zeros = [[0.0, 0.0, 0.0]] * n
    accel = zeros if session.accel_mps2 is None else session.accel_mps2.tolist()
    gyro = zeros if session.gyro_rps is None else session.gyro_rps.tolist()
    static = np.zeros(n, bool)
    accepted: list[int] = []
    intervals = []

    def collect(iv):
        static[[accepted[c] for c in range(det.fin_lo, det.fin_split)]] = True
        if iv is not None:
            intervals.append(iv)

    for i, t in enumerate(session.t_s.tolist()):
        if i == state_at:
            det = StreamingStaticDetector.from_state_dict(json.loads(json.dumps(det.state_dict())))
        before = det.n_accepted
        iv = det.update(t, *accel[i], *gyro[i])
        if det.n_accepted != before:
            accepted.append(i)
        collect(iv)
    collect(det.finish())
    return static, intervals, det


@pytest.fixture(scope="module")
def mems_session():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=18, static_s=5.0, transition_s=3.0)
    return simulate(spec, seed=3)


def test_finds_every_simulated_position_and_covers_it(mems_session):
    session, truth = mems_session.session, mems_session.truth
    det = detect_static(session)
    assert len(det.intervals) == len(truth.static_intervals_s) == 18
    assert det.short_runs == ()
    for iv, (t0, t1) in zip(det.intervals, truth.static_intervals_s, strict=True):
        # Every window inside a true rest is quiet (its spread is ~1/3 of the threshold),
        # so the union of quiet windows contains the whole rest.
        assert iv.t_start_s <= t0 and iv.t_end_s >= t1
    # ... and no sample in the middle half of a 3 s turn is static (see test_scalar for the bound).
    t = session.t_s
    t_rest = t[truth.static]
    k = np.clip(np.searchsorted(t_rest, t), 1, t_rest.size - 1)
    from_rest_s = np.minimum(np.abs(t - t_rest[k - 1]), np.abs(t_rest[k] - t))
    assert not np.any(det.static[from_rest_s > 0.75])


def test_streaming_gives_the_batch_decisions_on_messy_data(mems_session):
    s = mems_session.session
    t = s.t_s.copy()
    accel = s.accel_mps2.copy()
    gyro = s.gyro_rps.copy()
    rng = np.random.default_rng(7)
    accel[rng.choice(t.size, 30, replace=False), 0] = np.nan
    gyro[rng.choice(t.size, 10, replace=False), 2] = np.inf
    t[5000] = t[4999]  # duplicate time stamp
    t[9000] = t[8990]  # a step back
    keep = np.ones(t.size, bool)
    keep[1800:1900] = False  # a 1 s gap inside the third position (16–21 s): it splits in two
    messy = ImuSession(t[keep], accel[keep], gyro[keep])
    batch = detect_static(messy, rate_hz=100.0)
    static, intervals, det = _stream(messy, rate_hz=100.0, state_at=6543)
    np.testing.assert_array_equal(static, batch.static)
    assert intervals == list(batch.intervals)
    n_bad = int((~np.isfinite(np.hstack([accel, gyro])).all(axis=1))[keep].sum())
    assert (
        det.rejections.counts
        == batch.rejections.counts
        == {"non_finite": n_bad, "non_monotonic_time": 2}
    )
    assert len(batch.intervals) == 19
    assert [iv.t_end_s for iv in batch.intervals][2] == t[1799]
    assert [iv.t_start_s for iv in batch.intervals][3] == t[1900]


def test_nan_sample_is_a_counted_rejection_that_leaves_the_state_alone():
    det = StreamingStaticDetector(rate_hz=100.0)
    for k in range(80):
        det.update(0.01 * k, 0.0, 0.0, 9.8, 0.0, 0.0, 0.0)
    before = det.state_dict()
    assert det.update(0.8, math.nan, 0.0, 9.8, 0.0, 0.0, 0.0) is None
    assert det.update(0.79, 0.0, 0.0, 9.8, 0.0, 0.0, 0.0) is None
    after = det.state_dict()
    assert after.pop("n_input") == before.pop("n_input") + 2
    assert after.pop("rejections") == {"non_finite": 1, "non_monotonic_time": 1}
    before.pop("rejections")
    assert after == before
    assert det.static_now


def test_batch_without_a_triad_the_detector_has_is_a_clear_error():
    det = StreamingStaticDetector(rate_hz=100.0)
    for k in range(80):
        det.update(0.01 * k, 0.0, 0.0, 9.8, 0.0, 0.0, 0.0)
    t = 0.8 + 0.01 * np.arange(5)
    with pytest.raises(ValueError, match="gyro_rps is required"):
        det.clean_batch(t, np.tile([0.0, 0.0, 9.8], (5, 1)), None)
    with pytest.raises(ValueError, match="accel_mps2 is required"):
        det.update_batch(t, None, np.zeros((5, 3)))


def test_one_triad_is_enough(mems_session):
    s = mems_session.session
    full = detect_static(s).intervals
    for session in (ImuSession(s.t_s, s.accel_mps2, None), ImuSession(s.t_s, None, s.gyro_rps)):
        det = detect_static(session)
        assert len(det.intervals) == 18
        static, intervals, _ = _stream(session, rate_hz=100.0)
        np.testing.assert_array_equal(static, det.static)
        assert intervals == list(det.intervals)
        # One triad alone is no stricter than both.
        for iv, ref in zip(det.intervals, full, strict=True):
            assert iv.t_start_s <= ref.t_start_s and iv.t_end_s >= ref.t_end_s
    with pytest.raises(ValueError, match="neither"):
        detect_static(ImuSession(s.t_s, None, None))


@needs(XSENS)
def test_xsens_session_has_its_initial_rest_and_37_positions():
    # SOURCE.md: about 50 s static, then about 37 short static positions, 100 Hz.
    session = read_session(XSENS)
    det = detect_static(session)
    durations = np.array([iv.duration_s for iv in det.intervals])
    assert len(det.intervals) == 38
    assert 45.0 < durations[0] < 55.0
    assert np.all((durations[1:] > 3.0) & (durations[1:] < 15.0))
    # The only other quiet run is a 0.7 s pause inside a turn, shorter than min_static_s.
    assert [round(r.duration_s, 1) for r in det.short_runs] == [0.7]
    static, intervals, _ = _stream(session, rate_hz=det.rate_hz)
    np.testing.assert_array_equal(static, det.static)
    assert intervals == list(det.intervals)


def test_constant_rate_turn_about_the_vertical_needs_the_mean_rate_bound():
    rng = np.random.default_rng(2)
    scene = build_scene(
        [Rest(5.0), Rotate(10.0, (0, 0, 1), 90.0, constant_rate=True), Rest(5.0)], rng=rng
    )
    plain = detect_static(scene.session)
    # Variance only: the turn (0.157 rad/s, constant) looks static — a documented blind spot;
    # its start and end are rate steps that no quiet window spans, so they end the runs.
    assert plain.static[~scene.rest].all()
    spans = [(iv.t_start_s, iv.t_end_s) for iv in plain.intervals]
    np.testing.assert_allclose(spans, [(0.0, 4.99), (5.0, 14.99), (15.0, 19.99)], atol=1e-9)
    cfg = StaticDetectorConfig(gyro_rate_rps=0.05)
    bounded = detect_static(scene.session, config=cfg)
    assert len(bounded.intervals) == 2
    assert not np.any(bounded.static[~scene.rest])
    static, intervals, _ = _stream(scene.session, config=cfg, rate_hz=100.0)
    np.testing.assert_array_equal(static, bounded.static)
    assert intervals == list(bounded.intervals)


def test_short_runs_are_reported_apart():
    rng = np.random.default_rng(4)
    scene = build_scene([Rest(3.0), Bump(1.0), Rest(0.8), Bump(1.0), Rest(3.0)], rng=rng)
    det = detect_static(scene.session)
    assert [round(iv.duration_s, 2) for iv in det.intervals] == [2.99, 2.99]
    assert [round(iv.duration_s, 2) for iv in det.short_runs] == [0.79]


def test_from_noise_sets_thresholds_at_a_multiple_of_the_white_noise_spread():
    cfg = StaticDetectorConfig.from_noise(
        accel_noise_mps2=0.01, gyro_noise_rps=0.001, base=StaticDetectorConfig(window_s=1.0)
    )
    assert cfg.accel_std_mps2 == pytest.approx(3 * math.sqrt(3) * 0.01)
    assert cfg.gyro_std_rps == pytest.approx(3 * math.sqrt(3) * 0.001)
    assert cfg.window_s == 1.0
    with pytest.raises(ValueError, match="accel_std_mps2"):
        StaticDetectorConfig(accel_std_mps2=-1.0)
    with pytest.raises(ValueError, match="rate_hz"):
        cfg.window_samples(0.0)
    with pytest.raises(ValueError, match="invalid StreamingStaticDetector state"):
        StreamingStaticDetector.from_state_dict({"config": {}})


# --- orientation changes ---------------------------------------------------------------------------


def test_direction_change_is_exact_at_small_and_right_angles():
    assert direction_change_deg([0, 0, 9.8], [9.8, 0, 0]) == pytest.approx(90.0)
    tiny = 1e-7  # rad: arccos of the dot product would lose it entirely
    assert direction_change_deg([0, 0, 1], [0, math.sin(tiny), math.cos(tiny)]) == pytest.approx(
        math.degrees(tiny), rel=1e-9
    )


def test_rotation_integrator_composes_like_rotation_matrices():
    rng = np.random.default_rng(6)
    rates = rng.normal(0, 1.0, (500, 3))
    dt = 0.01
    bias = (0.01, -0.02, 0.005)
    rot = RotationIntegrator(bias)
    for w in rates.tolist():
        rot.add(*w, dt)
    expected = Rotation.identity()
    for w in rates:
        expected = expected * Rotation.from_rotvec((w - bias) * dt)
    assert rot.angle_deg == pytest.approx(np.degrees(expected.magnitude()), abs=1e-9)
    # Four quarter turns x, y, −x, −y do not cancel: their commutator is a 120° rotation.
    rot.reset()
    for axis in ((1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0)):
        for _ in range(100):
            rot.add(*(np.array(axis) * (math.pi / 2)).tolist(), 0.01)
    assert rot.angle_deg == pytest.approx(120.0, abs=1e-9)
    again = RotationIntegrator.from_state_dict(json.loads(json.dumps(rot.state_dict())))
    assert again.q == rot.q and again.bias_rps == rot.bias_rps


def test_rotation_integrator_add_many_is_add_sample_by_sample_to_the_bit():
    # Rates at rest (θ = |ω − bias|·dt below 1e-4 rad: the series) and in turns (the sine),
    # and both sides of the switch, in pieces of every size the positions hand over.
    rng = np.random.default_rng(61)
    scale = rng.choice([2e-3, 0.09, 0.11, 3.0], size=(4000, 1))
    rates = rng.normal(0.0, 1.0, (4000, 3)) * scale
    dts = rng.uniform(0.5e-3, 1.5e-3, 4000)
    bias = (0.01, -0.02, 0.005)
    one, many = RotationIntegrator(bias), RotationIntegrator(bias)
    q = (1.0, 0.0, 0.0, 0.0)  # the oracle: exp(½ (ω − bias) dt) composed on the right, written out
    for (wx, wy, wz), dt in zip(rates.tolist(), dts.tolist(), strict=True):
        one.add(wx, wy, wz, dt)
        rx, ry, rz = (wx - bias[0]) * dt, (wy - bias[1]) * dt, (wz - bias[2]) * dt
        th = math.sqrt(rx * rx + ry * ry + rz * rz)
        s = math.sin(0.5 * th) / th if th > 1e-4 else 0.5 - th * th / 48.0
        dw, dx, dy, dz = math.cos(0.5 * th), rx * s, ry * s, rz * s
        w, x, y, z = q
        q = (
            w * dw - x * dx - y * dy - z * dz,
            w * dx + x * dw + y * dz - z * dy,
            w * dy - x * dz + y * dw + z * dx,
            w * dz + x * dy - y * dx + z * dw,
        )
    assert one.q == q
    k = 0
    for size in [0, 1, *rng.integers(1, 700, size=40).tolist()]:
        many.add_many(rates[k : k + size], dts[k : k + size])
        k += size
    many.add_many(rates[k:], dts[k:])
    assert many.q == q


def test_rotation_integrator_composes_add_many_when_read_and_never_what_a_reset_drops(monkeypatch):
    # The positions integrate a static run's first samples in case it is rejected; an accepted run
    # resets the rotation: those samples are then never composed (a Python step per sample).
    rng = np.random.default_rng(62)
    rates = rng.normal(0.0, 0.5, (3000, 3))
    dts = np.full(3000, 1e-3)
    composed = count_compositions(monkeypatch)
    rot, ref = RotationIntegrator((0.01, 0.0, 0.0)), RotationIntegrator((0.01, 0.0, 0.0))
    rot.add_many(rates[:300], dts[:300])
    rot.add_many(rates[300:600], dts[300:600])
    rot.reset()
    assert composed == []
    monkeypatch.setattr(RotationIntegrator, "DEFERRED_SAMPLES", 1000)
    # The mark waits too, and is composed alone when read; reads past the bound (composed at 1,000
    # waiting) and after a sample by sample add: the same rotations to the bit as one call each.
    rot.reset((0.01, 0.0, 0.0))
    rot.add_many(rates[:700], dts[:700])
    rot.set_mark()
    rot.add_many(rates[700:900], dts[700:900])
    assert composed == []
    mark = rot.mark
    assert composed == [700]
    rot.add_many(rates[900:1500], dts[900:1500])
    rot.add_many(rates[1500:2500], dts[1500:2500])
    assert composed == [700, 1800]
    rot.add(*rates[2500].tolist(), 1e-3)
    rot.add_many(rates[2501:], dts[2501:])
    assert composed == [700, 1800, 1]
    q = rot.q
    assert composed == [700, 1800, 1, 499]
    ref.add_many(rates[:700], dts[:700])
    assert mark == ref.q
    ref.add_many(rates[700:], dts[700:])
    assert q == ref.q


def test_new_orientation_needs_a_change_in_any_available_measure():
    cfg = StaticDetectorConfig(orientation_change_deg=1.0)
    assert not is_new_orientation(cfg, direction_deg=0.5, rotation_deg=0.5)
    assert is_new_orientation(
        cfg, direction_deg=0.5, rotation_deg=90.0
    )  # a turn about the vertical
    assert is_new_orientation(cfg, direction_deg=30.0, rotation_deg=None)
    assert not is_new_orientation(cfg, direction_deg=None, rotation_deg=0.2)
    assert is_new_orientation(cfg, direction_deg=None, rotation_deg=None)


def test_gaps_split_segments_and_windows_never_span_them():
    rng = np.random.default_rng(9)
    scene = build_scene(
        [Rest(3.0), Gap(2.0), Rest(3.0), *tumble(3, rest_s=3.0, rng=rng)[1:]], rng=rng
    )
    det = detect_static(scene.session)
    assert len(det.intervals) == 4
    assert det.segment_start.sum() == 2
    static, intervals, _ = _stream(scene.session, rate_hz=100.0)
    assert intervals == list(det.intervals)
    np.testing.assert_array_equal(static, det.static)


@pytest.mark.parametrize(
    ("rest_s", "max_batch"),
    # Batches of up to 300 samples (6 windows), and up to 1,600: 12 or more windows of 50 samples
    # between re-summations, whose running sums go side by side (SIDE_BY_SIDE_SUMS).
    [(3.0, 300), (12.0, 1600)],
)
def test_update_batch_gives_update_s_decisions_and_state_bit_for_bit(rest_s, max_batch):
    rng = np.random.default_rng(5)
    s = build_scene(tumble(4, rest_s=rest_s, rng=rng), rng=rng).session
    t, accel, gyro = s.t_s, s.accel_mps2, s.gyro_rps
    rows = np.column_stack([t, accel, gyro]).tolist()  # update takes plain floats
    config = StaticDetectorConfig(gyro_rate_rps=0.05)
    ref = StreamingStaticDetector(config, rate_hz=100.0)
    det = StreamingStaticDetector(config, rate_hz=100.0)
    i = 0
    while not det.steady():
        det.update(*rows[i])
        ref.update(*rows[i])
        i += 1
    closed = 0
    for size in rng.integers(1, max_batch, size=200).tolist():
        sl = slice(i, min(t.size, i + size))
        assert det.clean_batch(t[sl], accel[sl], gyro[sl])
        static, closes = det.update_batch(t[sl], accel[sl], gyro[sl])
        expected = []
        for k in range(sl.start, sl.stop):
            ref.update(*rows[k])
            expected.append(ref.fin_split > ref.fin_lo)
            if ref.closed_run is not None:
                assert closes[k - i] == (ref.closed_run, ref.closed_run_short)
                closed += 1
        assert static.tolist() == expected
        assert json.dumps(det.state_dict()) == json.dumps(ref.state_dict())
        assert (det.fin_lo, det.fin_split, det.fin_hi, det.static_now) == (
            ref.fin_lo,
            ref.fin_split,
            ref.fin_hi,
            ref.static_now,
        )
        i = sl.stop
        if i == t.size:
            break
    assert closed == 3  # the fourth rest ends with the data
    assert not det.clean_batch(np.array([t[-1]]), accel[:1], gyro[:1])  # time not increasing
    bad = accel[:3].copy()
    bad[1, 0] = np.nan
    assert not det.clean_batch(t[-1] + np.array([0.01, 0.02, 0.03]), bad, gyro[:3])
    assert not det.clean_batch(
        t[-1] + np.array([0.01, 1.0]), accel[:2], gyro[:2]
    )  # a gap ends the segment


@pytest.mark.parametrize(("step_mps2", "runs"), [(3.0, 2), (0.002, 1)])
def test_the_streaming_detector_ends_a_run_where_the_data_jump_as_the_batch_one(step_mps2, runs):
    # Two rests joined without a transition or a time gap: a jump far above the noise (σ = 0.005 m/s²)
    # ends the run in both detectors; one the noise explains does not.
    rng = np.random.default_rng(31)
    n = 600
    accel = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0.0, 0.005, (n, 3))
    accel[n // 2 :, 0] += step_mps2
    gyro = rng.normal(0.0, 0.001, (n, 3))
    session = ImuSession(np.arange(n) / 100.0, accel, gyro)
    batch = detect_static(session)
    assert len(batch.intervals) == runs and batch.short_runs == ()
    for state_at in (None, n // 2 + 10):
        static, intervals, _ = _stream(session, rate_hz=100.0, state_at=state_at)
        assert intervals == list(batch.intervals)
        np.testing.assert_array_equal(static, batch.static)


def test_exact_sums_are_math_fsum_bit_for_bit():
    """The re-summations' vectorized fsum against math.fsum (the oracle) on windows of the
    detector's size: noise and its squares, float32 read-outs, values over 600 decades, exact
    cancellations, ties of the rounding and sums just past them, signed zeros, subnormals, sums near overflow."""
    rng = np.random.default_rng(8)
    noise = rng.normal(0.0, 0.05, (8, 500, 6))
    cancel = rng.normal(0.0, 1.0, (4, 500, 6))
    cancel[:, 250:] = -cancel[:, :250]
    cancel[1, 0, :] += 1e-300
    ties = np.ones((2, 500, 6))
    ties[:, 0] = 2.0**53
    quarter = rng.integers(-(2**20), 2**20, (2, 500, 6)) * 2.0**-30
    quarter[:, 0] = 1.5 * 2.0**52
    # Just past or short of a tie: 1 + 2⁻⁵³ ± k·2⁻¹⁰⁶, where rounding the sum of the errors first
    # lands on the tie and rounds to even.
    past = np.zeros((2, 500, 6))
    past[:, 0], past[:, 1] = 1.0, 2.0**-53
    past[:, 2] = np.array([[1, 2, 3, -1, -2, -3], [5, 7, -5, -7, 1, -1]]) * 2.0**-106
    zeros = np.zeros((2, 500, 6))
    zeros[0] = -0.0
    zeros[1, 0] = -0.0
    tiny = np.full((2, 500, 6), 5e-324)
    tiny[:, ::2] *= -1.0
    tiny[1, 3] = 5e-324
    huge = rng.normal(0.0, 1e306, (2, 500, 6))
    huge[1, :, 0] = 1.7e308
    huge[1, 1::2, 0] = -1.7e308
    huge[1, 0, 0] = 1.6e308
    windows = [
        noise,
        noise**2,
        noise.astype(np.float32).astype(float),
        rng.normal(0.0, 1.0, (4, 500, 6)) * 10.0 ** rng.integers(-300, 300, (4, 500, 6)),
        cancel,
        ties,
        past,
        quarter,
        zeros,
        tiny,
    ]
    # All of them at once (252 columns: side by side, SIDE_BY_SIDE_SUMS), and the partials near
    # overflow on their own (they send every column of their call to fsum).
    windows += [np.concatenate(windows), huge]
    for x in windows:
        got = exact_sums(x)
        want = [[math.fsum(x[r, :, k].tolist()) for k in range(6)] for r in range(x.shape[0])]
        assert [[(v, math.copysign(1.0, v)) for v in row] for row in got.tolist()] == [
            [(v, math.copysign(1.0, v)) for v in row] for row in want
        ]


def test_exact_sums_raise_as_math_fsum_where_its_partial_sums_overflow():
    """At the largest double a quarter of its ulp (2⁹⁶⁹) added twice leaves every running sum of
    ``cumsum`` at the largest double, whose upper half-ulp is infinite: the rounding looks certain.
    fsum's own partial sum reaches 2¹⁰²⁴ there and it raises, whether the exact sum then comes back
    under the largest double (−2⁹⁶⁹, −the largest) or not (+2⁻¹⁰⁷⁴): exact_sums is fsum, so it raises too."""
    big, quarter = sys.float_info.max, 2.0**969
    for tail in (-quarter, -big, 5e-324):
        column = [big, quarter, quarter, tail]
        with pytest.raises(OverflowError):
            math.fsum(column)
        for sign in (1.0, -1.0):
            x = np.zeros((2, len(column), 3))
            x[1, :, 2] = np.multiply(sign, column)
            with pytest.raises(OverflowError):
                exact_sums(x)
