"""Positions from static intervals: averages with an honest covariance, rejects and merges (methods.md M1)."""

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from synthetic_static import (
    G_MPS2,
    Bump,
    Gap,
    Rest,
    Rotate,
    build_scene,
    count_compositions,
    tumble,
)

from estimators.positions import (
    CovarianceMethod,
    Position,
    PositionAccumulator,
    PositionConfig,
    RejectReason,
    _seq_sum_rows,
    build_positions,
)
from estimators.session import ImuSession
from estimators.sim import Grade, RampTemperature, multi_position_spec, simulate
from estimators.static_detector import (
    FinalDecisions,
    StaticDetectorConfig,
    detect_static,
)


def _stream(session: ImuSession, *, rate_hz: float, state_at: int | None = None, **options):
    """Positions and rejections from a PositionAccumulator fed sample by sample (optionally checkpointed)."""
    acc = PositionAccumulator(
        rate_hz=rate_hz,
        has_accel=session.accel_mps2 is not None,
        has_gyro=session.gyro_rps is not None,
        **options,
    )
    n = session.n_samples
    zeros = [[0.0, 0.0, 0.0]] * n
    accel = zeros if session.accel_mps2 is None else session.accel_mps2.tolist()
    gyro = zeros if session.gyro_rps is None else session.gyro_rps.tolist()
    temp = [None] * n if session.temp_c is None else session.temp_c.tolist()
    out = []
    for i, t in enumerate(session.t_s.tolist()):
        if i == state_at:
            acc = PositionAccumulator.from_state_dict(json.loads(json.dumps(acc.state_dict())))
        p = acc.update(t, *accel[i], *gyro[i], temp[i])
        if p is not None:
            out.append(p)
    out += acc.flush()
    return out, acc.drain_rejections()


def _assert_same_positions(got, expected):
    assert len(got) == len(expected)
    for p, q in zip(got, expected, strict=True):
        for name in (
            "t_start_s",
            "t_end_s",
            "n_samples",
            "index_start",
            "index_stop",
            "n_intervals",
        ):
            assert getattr(p, name) == getattr(q, name), name
        for name in (
            "accel_mean_mps2",
            "gyro_mean_rps",
            "accel_cov_mps2",
            "gyro_cov_rps",
            "temp_mean_c",
            "accel_n_eff",
            "gyro_n_eff",
        ):
            a, b = getattr(p, name), getattr(q, name)
            assert (a is None) == (b is None), name
            if a is not None:
                # Running sums of shifted samples vs numpy means: rounding only.
                np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-15, err_msg=name)


# --- a simulated MEMS unit: means agree with the truth within their covariance ----------------------


def test_means_of_a_simulated_unit_are_consistent_with_their_covariance():
    spec = multi_position_spec(
        grade=Grade.MEMS,
        n_positions=18,
        static_s=5.0,
        transition_s=3.0,
        temperature=RampTemperature(20.0, 0.02),
    )
    noisy = simulate(spec, seed=3)
    m = spec.model
    quiet = replace(
        m,
        accel=m.accel.without("white_noise").without("quantization"),
        gyro=m.gyro.without("white_noise").without("quantization"),
    )
    clean = simulate(
        replace(spec, model=quiet), seed=3
    )  # same motion: the seeds of the streams are per effect
    res = build_positions(noisy.session, detect_static(noisy.session))
    assert len(res.positions) == 18 and res.rejections == ()
    chi2, dof = 0.0, 0
    for pos, (t0, t1) in zip(res.positions, noisy.truth.static_intervals_s, strict=True):
        # The truth is the noise-free output in the middle of the true rest, so leakage of the
        # turns into the trimmed interval would show; M2's Entier reads half a count low.
        mid = int(np.searchsorted(noisy.session.t_s, 0.5 * (t0 + t1)))
        for triad, mean, cov in (
            ("accel", pos.accel_mean_mps2, pos.accel_cov_mps2),
            ("gyro", pos.gyro_mean_rps, pos.gyro_cov_rps),
        ):
            step = np.array(m.triad(triad).find("quantization").step_si)
            truth = (clean.session.accel_mps2 if triad == "accel" else clean.session.gyro_rps)[
                mid
            ] - 0.5 * step
            d = mean - truth
            chi2 += d @ np.linalg.solve(cov, d)
            dof += 3
        assert pos.temp_mean_c == pytest.approx(
            noisy.session.temp_c[pos.index_start : pos.index_stop].mean()
        )
    # Batch means never shrink the covariance (τ̂ ≥ 1): χ² may sit a little low, never high.
    assert stats.chi2.ppf(1e-4, dof) < chi2 < stats.chi2.ppf(1 - 1e-4, dof)


def test_batch_means_cover_correlated_noise_where_the_sample_covariance_does_not():
    # AR(1) noise, φ = 0.9: the variance of a long mean is τ = (1 + φ)/(1 − φ) = 19 times σ²/n.
    rng = np.random.default_rng(17)
    scene = build_scene(tumble(100, rest_s=20.0, rng=rng), rng=rng, phi=0.9, accel_noise_mps2=0.005)
    det = detect_static(scene.session)
    coverage = {}
    for method in CovarianceMethod:
        # Batches of 2 s are 200 samples ≫ the 19-sample correlation time.
        res = build_positions(
            scene.session, det, config=PositionConfig(batch_s=2.0, covariance=method)
        )
        assert len(res.positions) == 100
        z = []
        for pos in res.positions:
            k = scene.rest_index[pos.index_start]
            truth = G_MPS2 * scene.up_b[scene.rest_index == k][0]
            z.append((pos.accel_mean_mps2 - truth) / np.sqrt(np.diag(pos.accel_cov_mps2)))
        coverage[method] = np.mean(np.abs(np.concatenate(z)) < 3.0)
        if method is CovarianceMethod.BATCH_MEANS:
            n_eff = np.array([p.accel_n_eff / p.n_samples for p in res.positions])
            assert 1 / 19 * 0.7 < np.median(n_eff) < 1 / 19 * 1.3
    # τ̂ from 3 × 9 degrees of freedom: z is about t(27)-distributed, P(|t| < 3) = 0.994;
    # over 300 values fewer than 97 % covered has probability < 1e-3.
    assert coverage[CovarianceMethod.BATCH_MEANS] >= 0.97
    # σ/√n is √19 ≈ 4.4 times too small: |z| < 3 only for |N(0,1)| < 0.69, about half.
    assert coverage[CovarianceMethod.SAMPLE] < 0.7


# --- rejections and merges, batch = streaming -----------------------------------------------------------


def _scene_segments():
    return [
        Rest(5.0),
        Bump(0.6),
        Rest(4.0),  # a bump splits one position: merged
        # The union of quiet windows reaches ~0.25 s into the slow ends of each turn:
        Rotate(2.0, (1, 0, 0), 90.0),
        Rest(0.3),  # a run of 0.6–0.8 s: too short for an interval
        Rotate(2.0, (0, 0, 1), 60.0),
        Rest(0.8),  # 1.1–1.4 s: an interval, < 100 samples once trimmed
        Rotate(2.0, (1, 1, 0), 80.0),
        Rest(4.0),
        Gap(2.0),
        Rest(3.0),  # same direction across a gap
        Rotate(2.0, None, 90.0),
        Rest(3.0),  # heading change: same specific force, new position
    ]


def _scene(rng):
    return build_scene(_scene_segments(), rng=rng, temp_c=25.0)


CFG = PositionConfig(trim_s=0.3, min_samples=100)


def test_short_sparse_and_duplicate_intervals_are_recorded_with_their_reason():
    rng = np.random.default_rng(1)
    scene = _scene(rng)
    det = detect_static(scene.session)
    res = build_positions(scene.session, det, config=CFG)
    assert [p.n_intervals for p in res.positions] == [2, 2, 1]
    assert [r.reason for r in res.rejections] == [
        RejectReason.MERGED,
        RejectReason.SHORT_INTERVAL,
        RejectReason.TOO_FEW_SAMPLES,
        RejectReason.MERGED,
    ]
    t = scene.session.t_s
    # Each record spans the rest it stands for (rests 1, 2, 3, 5 of the scene).
    for rec, k in zip(res.rejections, (1, 2, 3, 5), strict=True):
        rest_t = t[scene.rest_index == k]
        assert rec.t_start_s <= rest_t[rest_t.size // 2] <= rec.t_end_s
    assert res.rejections[1].t_end_s - res.rejections[1].t_start_s < 1.0
    assert (
        "rotation" in res.rejections[0].detail and "rotation" not in res.rejections[3].detail
    )  # gap: rotation unknown
    # Merged: both intervals minus 0.3 s (30 samples) at each of their four ends.
    first, (iv0, iv1) = res.positions[0], det.intervals[:2]
    assert first.n_samples == iv0.n_samples + iv1.n_samples - 4 * 30
    assert first.t_start_s == pytest.approx(iv0.t_start_s + 0.3) and first.t_end_s == pytest.approx(
        iv1.t_end_s - 0.3
    )
    np.testing.assert_allclose(
        first.accel_mean_mps2, G_MPS2 * scene.up_b[0], atol=5 * 0.01 / np.sqrt(first.n_samples)
    )
    assert first.temp_mean_c == pytest.approx(25.0, abs=0.05)
    # The heading change leaves the specific force alone; the gyros saw it.
    m1, m2 = res.positions[1].accel_mean_mps2, res.positions[2].accel_mean_mps2
    assert (
        np.degrees(np.arccos(np.clip(m1 @ m2 / np.linalg.norm(m1) / np.linalg.norm(m2), -1, 1)))
        < 0.5
    )


def test_streaming_accumulator_gives_the_batch_positions_through_a_checkpoint():
    rng = np.random.default_rng(1)
    scene = _scene(rng)
    s = scene.session
    temp = s.temp_c.copy()
    temp[rng.choice(temp.size, 50, replace=False)] = (
        np.nan
    )  # unknown temperature: the sample still counts
    accel = s.accel_mps2.copy()
    accel[[100, 2000, 2001]] = np.nan  # bad samples: counted, skipped
    session = ImuSession(s.t_s, accel, s.gyro_rps, temp)
    batch = build_positions(session, detect_static(session, rate_hz=100.0), config=CFG)
    for state_at in (None, 1234, 2150):
        got, rejections = _stream(session, rate_hz=100.0, config=CFG, state_at=state_at)
        _assert_same_positions(got, batch.positions)
        assert rejections == list(batch.rejections)


@pytest.mark.parametrize(
    ("triads", "n_intervals"),
    [
        # Gyros only: across the gap the rotation is unknown, so no merge there.
        ("gyro", [2, 1, 1, 1]),
        # Accelerometers only: the heading change is invisible (not even a break in stationarity),
        # harmless for them: the specific force did not change.
        ("accel", [2, 2]),
    ],
)
def test_one_triad_merges_by_what_it_can_see(triads, n_intervals):
    rng = np.random.default_rng(1)
    s = _scene(rng).session
    session = ImuSession(
        s.t_s, s.accel_mps2 if triads == "accel" else None, s.gyro_rps if triads == "gyro" else None
    )
    det = detect_static(session)
    res = build_positions(session, det, config=CFG)
    assert [p.n_intervals for p in res.positions] == n_intervals
    got, rejections = _stream(session, rate_hz=100.0, config=CFG, detector_config=det.config)
    _assert_same_positions(got, res.positions)
    assert rejections == list(res.rejections)


def test_position_round_trips_through_a_plain_dict():
    rng = np.random.default_rng(1)
    scene = _scene(rng)
    pos = build_positions(scene.session, detect_static(scene.session), config=CFG).positions[0]
    again = Position.from_dict(json.loads(json.dumps(pos.to_dict())))
    _assert_same_positions([again], [pos])
    with pytest.raises(ValueError, match="accel_mean_mps2 must have shape"):
        Position.from_dict({**pos.to_dict(), "accel_mean_mps2": [1.0, 2.0]})


def test_bad_configs_and_states_are_clear_errors():
    with pytest.raises(ValueError, match="min_samples"):
        PositionConfig(min_samples=1)
    with pytest.raises(ValueError, match="trim_s"):
        PositionConfig(trim_s=-0.1)
    with pytest.raises(ValueError, match="invalid PositionAccumulator state"):
        PositionAccumulator.from_state_dict({"detector": {}})
    session = ImuSession(np.arange(10.0), np.zeros((10, 3)), None)
    other = ImuSession(np.arange(11.0), np.zeros((11, 3)), None)
    with pytest.raises(ValueError, match="detection covers"):
        build_positions(session, detect_static(other, rate_hz=1.0))


# --- update_batch: the per-sample results, bit for bit, however the stream is cut -------------------


def _per_sample(acc: PositionAccumulator, s):
    """Positions and per-sample decisions of ``update`` (the service's loop)."""
    n = s.t_s.size
    zeros = np.zeros((n, 3))
    rows = np.column_stack(
        [
            s.t_s,
            zeros if s.accel_mps2 is None else s.accel_mps2,
            zeros if s.gyro_rps is None else s.gyro_rps,
            np.full(n, np.nan) if s.temp_c is None else s.temp_c,
        ]
    ).tolist()
    out, steps = [], []
    det = acc.detector
    for t, ax, ay, az, gx, gy, gz, tc in rows:
        p = acc.update(t, ax, ay, az, gx, gy, gz, None if tc != tc else tc)
        if p is not None:
            out.append(p)
        if det.fin_hi > det.fin_lo:
            steps.append((det.fin_lo, det.fin_split, det.fin_hi, det.fin_break))
    return out, FinalDecisions.from_steps(0, steps)


def _batched(acc: PositionAccumulator, s, cuts):
    out, decisions = [], FinalDecisions.empty(0)
    for a, b in itertools.pairwise(cuts):
        part = [None if v is None else v[a:b] for v in (s.accel_mps2, s.gyro_rps, s.temp_c)]
        p, d = acc.update_batch(s.t_s[a:b], *part)
        out += p
        decisions = decisions.then(d)
    return out, decisions


def _assert_identical(p: Position, q: Position):
    for name, a in p.__dict__.items():
        b = getattr(q, name)
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, name


def _messy(rng):
    """The scene of _scene plus tumbles, with NaN/Inf values, repeated time stamps and unknown temperatures."""
    s = build_scene(
        _scene_segments() + tumble(4, rest_s=3.0, rng=rng), rng=rng, temp_c=25.0
    ).session
    t, accel, gyro, temp = s.t_s.copy(), s.accel_mps2.copy(), s.gyro_rps.copy(), s.temp_c.copy()
    accel[rng.choice(t.size, 8, replace=False), 1] = np.nan
    gyro[rng.choice(t.size, 4, replace=False), 2] = np.inf
    dup = rng.choice(t.size - 1, 8, replace=False)
    t[dup + 1] = t[dup]
    temp[rng.choice(t.size, 60, replace=False)] = np.nan
    return ImuSession(t, accel, gyro, temp)


@pytest.mark.parametrize("case", ["clean", "messy", "sim400", "accel", "gyro", "rate_bound"])
def test_update_batch_equals_update_bit_for_bit_for_any_cut(case):
    rng = np.random.default_rng(7)
    s = build_scene(
        _scene_segments() + tumble(4, rest_s=3.0, rng=rng), rng=rng, temp_c=25.0
    ).session
    rate, options = 100.0, {"config": CFG}
    if case == "messy":
        s = _messy(rng)
    elif case == "sim400":
        s = simulate(
            multi_position_spec(
                grade=Grade.MEMS, n_positions=5, static_s=3.0, transition_s=2.0, rate_hz=400.0
            ),
            3,
        ).session
        rate, options = 400.0, {}
    elif case in ("accel", "gyro"):
        s = ImuSession(
            s.t_s, s.accel_mps2 if case == "accel" else None, s.gyro_rps if case == "gyro" else None
        )
    elif case == "rate_bound":
        options["detector_config"] = StaticDetectorConfig(gyro_rate_rps=0.05)
    kw = dict(
        rate_hz=rate, has_accel=s.accel_mps2 is not None, has_gyro=s.gyro_rps is not None, **options
    )
    ref = PositionAccumulator(**kw)
    expected, expected_decisions = _per_sample(ref, s)
    ref_state = json.dumps(ref.state_dict())
    ref_flush = ref.flush()
    ref_rejections = ref.drain_rejections()
    assert len(expected) + len(ref_flush) >= 3
    for sizes in ((1, 9), (60, 400), (300, 3000)):
        n = s.t_s.size
        cuts = np.unique(
            np.concatenate([[0, n], np.cumsum(rng.integers(*sizes, size=n // sizes[0] + 1))])
        )
        cuts = cuts[cuts <= n]
        acc = PositionAccumulator(**kw)
        got, decisions = _batched(acc, s, cuts)
        assert np.array_equal(decisions.static, expected_decisions.static) and np.array_equal(
            decisions.brk, expected_decisions.brk
        )
        assert len(got) == len(expected)
        for p, q in zip(got, expected, strict=True):
            _assert_identical(p, q)
        assert json.dumps(acc.state_dict()) == ref_state
        for p, q in zip(acc.flush(), ref_flush, strict=True):
            _assert_identical(p, q)
        assert acc.drain_rejections() == ref_rejections
    if case == "messy":
        assert ref.detector.rejections.counts == {"non_finite": 12, "non_monotonic_time": 8}


def test_update_batch_composes_the_rotation_only_where_the_specific_force_cannot_tell_a_turn(
    monkeypatch,
):
    # Turns about horizontal axes move the specific force by 90°: a new position whatever the gyros
    # say, so the rotation (a Python step per sample) is never composed. A turn about the vertical
    # leaves the specific force where it was: only the integrated gyros tell the positions apart.
    composed = count_compositions(monkeypatch)
    rng = np.random.default_rng(71)
    for turns, about_vertical in (([(1, 0, 0), (0, 0, 1)], False), ([None], True)):
        segments = [Rest(6.0)]
        for axis in turns:
            segments += [Rotate(2.0, axis, 90.0), Rest(6.0)]
        s = build_scene(segments, rng=rng).session
        acc = PositionAccumulator(rate_hz=100.0, has_accel=True, has_gyro=True)
        got = acc.update_batch(s.t_s, s.accel_mps2, s.gyro_rps)[0] + acc.flush()
        assert len(got) == len(turns) + 1
        assert bool(composed) == about_vertical
        composed.clear()


def test_seq_sum_rows_adds_the_rows_in_turn_in_any_memory_order():
    # numpy sums pairwise along the fast axis: rows in Fortran order (a fancy index of columns gives
    # them) or one column would be summed pairwise, not as the running += of the per-sample path.
    rng = np.random.default_rng(72)
    for k in (1, 2, 21):
        rows = rng.normal(0.0, 1.0, (3000, k)) * rng.choice([1e-6, 1.0, 1e6], (3000, 1))
        start = rng.normal(0.0, 1.0, k)
        expected = start.tolist()
        for row in rows.tolist():
            expected = [a + b for a, b in zip(expected, row, strict=True)]
        for order in ("C", "F"):
            assert _seq_sum_rows(start, np.asarray(rows, order=order)).tolist() == expected


def test_update_batch_checkpoints_mid_stream_and_rejects_bad_shapes():
    rng = np.random.default_rng(8)
    s = build_scene(tumble(3, rest_s=4.0, rng=rng), rng=rng).session
    ref = PositionAccumulator(rate_hz=100.0, config=CFG)
    expected, _ = _per_sample(ref, s)
    expected += ref.flush()
    acc = PositionAccumulator(rate_hz=100.0, config=CFG)
    got = acc.update_batch(s.t_s[:777], s.accel_mps2[:777], s.gyro_rps[:777])[0]
    acc = PositionAccumulator.from_state_dict(json.loads(json.dumps(acc.state_dict())))
    got += acc.update_batch(s.t_s[777:], s.accel_mps2[777:], s.gyro_rps[777:])[0] + acc.flush()
    assert len(got) == len(expected) == 3
    for p, q in zip(got, expected, strict=True):
        _assert_identical(p, q)
    with pytest.raises(ValueError, match="gyro_rps is required"):
        acc.update_batch(s.t_s[:5], s.accel_mps2[:5], None)
    with pytest.raises(ValueError, match="shape"):
        acc.update_batch(s.t_s[:5], s.accel_mps2[:4], s.gyro_rps[:5])
