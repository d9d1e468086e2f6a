"""The sessions people record for other tools: six faces (with and without full turns), noisier
units, joined static parts and lost turns, calibrated into the passport (issue 11)."""

import dataclasses
import itertools
import json

import numpy as np
import pytest
from real_data import XSENS, needs
from service_support import batches_of, run_fleet

from estimators.chain import ChainConfig, calibration_estimates, run_chain
from estimators.conventions import STANDARD_GRAVITY_MPS2, Triad, normal_gravity_mps2
from estimators.ninepar import SOURCE_SCALAR, SOURCE_TURNS, SOURCE_VECTOR, Method, Verdict
from estimators.passport import Passport, PassportError, passport_from_estimates
from estimators.positions import PositionAccumulator, PositionConfig, build_positions
from estimators.session import ImuSession
from estimators.sim import (
    ErrorModel,
    Grade,
    SessionSpec,
    TriadErrorModel,
    WhiteNoise,
    grade_error_model,
    simulate,
)
from estimators.sim.motion import attitude_with_up, multi_position_profile
from estimators.sixpos import accel_vector_nine, ferraris_spec, quantizer_offset
from estimators.static_detector import StaticDetectorConfig, detect_static
from protocols.passport_codec import read_passport_json
from protocols.session_file import read_session, write_csv_session
from service.cli import main
from service.pipeline import FleetProcessor, PipelineOptions, StaticGate

MODEL = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))


def _noisier(model: ErrorModel, k: float) -> ErrorModel:
    def triad(chain: TriadErrorModel) -> TriadErrorModel:
        return TriadErrorModel(
            tuple(
                WhiteNoise(tuple(np.array(e.density_si_per_sqrt_hz) * k))
                if isinstance(e, WhiteNoise)
                else e
                for e in chain.effects
            )
        )

    return ErrorModel(accel=triad(model.accel), gyro=triad(model.gyro))


def _calibrate(session, gravity_mps2):
    config = ChainConfig(
        gravity_mps2=gravity_mps2, detector=StaticDetectorConfig.from_session(session)
    )
    result = run_chain(session, config)
    return result, calibration_estimates(result)


def _truth(res, triad):
    """True nine parameters as the output's user sees them (a FLOOR quantizer's half step is bias)."""
    truth = res.truth.params(triad).copy()
    chain = res.truth.model.triad(triad)
    truth[:3] += quantizer_offset(chain) / res.truth.reference(triad)
    return truth


def test_six_faces_and_full_turns_recover_the_passport_within_its_covariance_over_seeds():
    z_accel, z_gyro = [], []
    for seed in range(16):
        res = simulate(ferraris_spec(MODEL, static_s=8.0), seed=100 + seed)
        result, cal = _calibrate(res.session, res.truth.gravity_mps2)
        assert len(result.positions) == 6 and len(cal.turns) == 3
        acc, gyr = cal.estimates[Triad.ACCEL], cal.estimates[Triad.GYRO]
        assert acc.method is Method.SIX_POSITION and acc.sources[6:] == (SOURCE_VECTOR,) * 3
        assert acc.observable.all()
        assert gyr.sources[3:] == (SOURCE_TURNS,) * 6 and gyr.observable[3:].all()
        z_accel.append((acc.params - _truth(res, Triad.ACCEL)) / acc.sigma)
        z_gyro.append((gyr.params[3:] - _truth(res, Triad.GYRO)[3:]) / gyr.sigma[3:])
    for z in (np.array(z_accel), np.array(z_gyro)):
        # Normalized errors: mean square at most 1 within its sampling spread (χ²₁₆/16 < 2.5 with
        # probability 0.999), and the stated σ not more than about 3× too large.
        ms = np.mean(z**2, axis=0)
        assert np.all(ms < 2.5) and np.all(ms > 0.1), ms
        assert np.max(np.abs(z)) < 4.5


def test_six_faces_without_turns_give_the_accelerometers_and_no_gyro_passport(tmp_path, capsys):
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=7)
    _, cal = _calibrate(res.session, res.truth.gravity_mps2)
    assert set(cal.estimates) == {Triad.ACCEL} and not cal.turns
    path = tmp_path / "six.csv"
    write_csv_session(path, res.session, metadata={"gravity_mps2": res.truth.gravity_mps2})
    assert main(["calibrate", str(path), "--out", str(tmp_path / "p.json"), "--no-audit"]) == 0
    passport = read_passport_json(tmp_path / "p.json")
    assert set(passport.triads) == {Triad.ACCEL} and passport.schema_version == 3
    prov = passport.triads[Triad.ACCEL].provenance
    assert prov.param_sources == (SOURCE_VECTOR,) * 9 and prov.method is Method.SIX_POSITION
    assert "from M4 six-position vector fit" in capsys.readouterr().err


def test_calibrate_writes_the_gyro_from_full_turns_and_turn_deg_says_which(tmp_path):
    res = simulate(ferraris_spec(MODEL, static_s=8.0), seed=8)
    path = tmp_path / "ferraris.csv"
    write_csv_session(path, res.session, metadata={"gravity_mps2": res.truth.gravity_mps2})
    assert main(["calibrate", str(path), "--out", str(tmp_path / "p.json"), "--no-audit"]) == 0
    gyro = read_passport_json(tmp_path / "p.json").triads[Triad.GYRO]
    assert gyro.provenance.param_sources[3:] == (SOURCE_TURNS,) * 6
    assert gyro.observable[3:].all() and not gyro.observable[:3].any()
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["triads"]["gyro"]["provenance"]["param_sources"][5] == SOURCE_TURNS
    # Declared half turns: the full turns no longer count, the face flips (±x about y, ±y and
    # ±z about x) do; no flip is about z, so e_z is not determined.
    argv = ["calibrate", str(path), "--out", str(tmp_path / "q.json"), "--no-audit"]
    assert main([*argv, "--turn-deg", "180"]) == 0
    half = read_passport_json(tmp_path / "q.json").triads[Triad.GYRO]
    assert half.observable[3:5].all() and not half.observable[5]
    assert main([*argv, "--turn-deg", "-5"]) == 2


def test_param_sources_need_schema_3():
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=9)
    _, cal = _calibrate(res.session, res.truth.gravity_mps2)
    est = cal.estimates[Triad.ACCEL]
    passport = passport_from_estimates(
        cal.estimates,
        unit_id="u",
        sensor_model="m",
        sensor_ids={},
        created="2026-01-01",
        noise_std={Triad.ACCEL: np.full(3, 1e-3)},
        sample_rate_hz=100.0,
        grade=Grade.MEMS,
    )
    back = Passport.from_dict(passport.to_dict())
    assert back.triads[Triad.ACCEL].provenance.param_sources == est.sources
    with pytest.raises(PassportError, match=r"unknown field\(s\) \['param_sources'\]"):
        Passport.from_dict({**passport.to_dict(), "schema_version": 2})
    with pytest.raises(PassportError, match="param_sources needs schema 3"):
        dataclasses.replace(passport, schema_version=2)


def _positions(session):
    det = detect_static(session, config=StaticDetectorConfig.from_session(session))
    return build_positions(session, det).positions


def _true_holds(res):
    return res.truth.static_intervals_s


@pytest.mark.parametrize("noise", [1.0, 10.0, 30.0])
def test_the_same_positions_at_1_10_and_30_times_the_noise_without_options(noise):
    res = simulate(ferraris_spec(_noisier(MODEL, noise), turns=False, static_s=8.0), seed=11)
    positions = _positions(res.session)
    holds = _true_holds(res)
    assert len(positions) == len(holds) == 6
    for p, (t0, t1) in zip(positions, holds, strict=True):
        # Within the hold, up to 0.15 s into a 4 s turn (< 0.05°, under the noise of the mean's
        # direction at 30×).
        assert t0 - 0.15 <= p.t_start_s and p.t_end_s <= t1 + 0.15, (p.t_start_s, t0, t1)


def test_fixed_default_thresholds_lose_the_noisy_unit():
    # What the derived thresholds fix: the defaults see no static window at 10× MEMS noise.
    res = simulate(ferraris_spec(_noisier(MODEL, 10.0), turns=False, static_s=8.0), seed=11)
    assert len(detect_static(res.session).intervals) == 0


def _joined(res, keep):
    s = res.session
    n = int(np.count_nonzero(keep))
    t = s.t_s[0] + np.arange(n) / res.spec.rate_hz
    return ImuSession(t, s.accel_mps2[keep], s.gyro_rps[keep])


def _assert_faces(positions, res):
    assert len(positions) == 6
    truth = res.truth
    for p, (t0, t1) in zip(positions, truth.static_intervals_s, strict=True):
        inside = (truth.t_s >= t0) & (truth.t_s <= t1)
        true_f = truth.specific_force_b_mps2[inside].mean(axis=0)
        assert (
            np.degrees(
                np.arccos(
                    p.accel_mean_mps2
                    @ true_f
                    / np.linalg.norm(p.accel_mean_mps2)
                    / np.linalg.norm(true_f)
                )
            )
            < 1.0
        )


def test_static_parts_joined_without_transitions_give_the_six_positions():
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=12)
    joined = _joined(res, res.truth.static)
    # One continuous run for the old rule (the union of quiet windows spans the jumps).
    assert len(detect_static(joined).intervals) == 6
    positions = _positions(joined)
    # Map the joined times back: the k-th position is the k-th hold.
    assert len(positions) == 6
    for p, (t0, t1) in zip(positions, res.truth.static_intervals_s, strict=True):
        held = t1 - t0
        assert p.t_end_s - p.t_start_s > 0.5 * held


def test_a_turn_lost_from_the_log_ends_the_position_with_or_without_a_time_gap():
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=13)
    truth = res.truth
    t_end_hold, t_next = truth.static_intervals_s[2][1], truth.static_intervals_s[3][0]
    lost = (truth.t_s > t_end_hold) & (truth.t_s < t_next)
    s = res.session
    with_gap = ImuSession(s.t_s[~lost], s.accel_mps2[~lost], s.gyro_rps[~lost])
    _assert_faces(_positions(with_gap), res)
    restamped = _joined(res, ~lost)
    positions = _positions(restamped)
    assert len(positions) == 6
    assert len(build_positions(restamped, detect_static(restamped)).positions) == 6


def test_units_of_g_need_no_rescaling_of_the_thresholds():
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=14)
    assert STANDARD_GRAVITY_MPS2 > 9.8 and len(_positions(res.session)) == 6


@needs(XSENS)
def test_the_measured_xsens_session_keeps_its_38_positions_and_passport():
    session = read_session(XSENS)
    g = normal_gravity_mps2(45.0)
    old = run_chain(session, ChainConfig(gravity_mps2=g))  # the fixed thresholds of before
    new = run_chain(
        session, ChainConfig(gravity_mps2=g, detector=StaticDetectorConfig.from_session(session))
    )
    assert len(old.positions) == len(new.positions) == 38
    for a, b in zip(old.positions, new.positions, strict=True):
        assert abs(a.t_start_s - b.t_start_s) < 1.0 and abs(a.t_end_s - b.t_end_s) < 1.0
    est_old, est_new = old.triads[Triad.ACCEL].estimate, new.triads[Triad.ACCEL].estimate
    assert est_new.verdict is est_old.verdict
    # The passport values move by a fraction of their standard deviation (the positions lose or
    # gain a few tenths of a second at their ends).
    np.testing.assert_array_less(np.abs(est_new.params - est_old.params), 0.5 * est_old.sigma)
    cal = calibration_estimates(new)
    assert set(cal.estimates) == {Triad.ACCEL} and not cal.turns
    assert cal.estimates[Triad.ACCEL].sources == (SOURCE_SCALAR,) * 9


def _faces_posed_thrice():
    """18 positions, each of the six faces three times, tilted by up to 15° (within the 20° of a
    face, ``MAX_FACE_TILT_RAD``): a session of faces only, which M1's fit resolves whole."""
    ups = []
    for axis, sign in itertools.product(range(3), (1.0, -1.0)):
        others = [k for k in range(3) if k != axis]
        for tilt in ((0.0, 0.0), (0.2, 0.1), (-0.1, 0.25)):
            up = np.zeros(3)
            up[axis], up[others[0]], up[others[1]] = sign, *tilt
            ups.append(attitude_with_up(up))
    return SessionSpec(multi_position_profile(np.stack(ups), static_s=8.0), MODEL)


def test_several_geometries_combine_into_one_estimate_with_one_covariance():
    # A session of faces (the vector fit's only): M1's fit resolves everything. Declare its
    # cosines unresolved, as a weaker geometry would leave them, and the vector fit supplies them.
    res = simulate(_faces_posed_thrice(), seed=5)
    g = res.truth.gravity_mps2
    result = run_chain(
        res.session,
        ChainConfig(gravity_mps2=g, detector=StaticDetectorConfig.from_session(res.session)),
    )
    m1 = result.triads[Triad.ACCEL].estimate
    keep = np.arange(9) < 6
    partial = dataclasses.replace(m1, observable=keep, verdict=Verdict.PARTIALLY_OBSERVABLE)
    result.triads[Triad.ACCEL] = dataclasses.replace(result.triads[Triad.ACCEL], estimate=partial)
    est = calibration_estimates(result).estimates[Triad.ACCEL]
    assert est.method is Method.COMBINED
    assert est.sources == (SOURCE_SCALAR,) * 6 + (SOURCE_VECTOR,) * 3
    vector = accel_vector_nine(result.positions, gravity_mps2=g)
    assert vector is not None
    np.testing.assert_array_equal(est.params[:6], m1.params[:6])
    np.testing.assert_allclose(est.params[6:], vector[0][6:], rtol=0, atol=1e-12)
    # The combination's covariance by the delta method over the position means reproduces
    # M1's own covariance on the parameters it kept, and it is one positive definite matrix.
    np.testing.assert_allclose(est.cov[:6, :6], m1.cov[:6, :6], rtol=0.05, atol=1e-14)
    assert np.linalg.eigvalsh(est.cov)[0] > 0
    # M1's parameters are the truth's; the vector fit's cosines carry the faces' tilts (6–15°),
    # which its model takes for misalignment: why it is kept to sessions of faces.
    truth = _truth(res, Triad.ACCEL)
    assert np.all(np.abs(est.params - truth)[:6] < 4.5 * est.sigma[:6])


# --- the same rule streamed: per sample, or in frames cut anywhere (the daemon and replay) ----------


def _joined_and_lost():
    """A six-face session with its static parts joined, and one whose turn 3 → 4 was lost with
    uniform time stamps (no time gap at either jump)."""
    res = simulate(ferraris_spec(MODEL, turns=False, static_s=8.0), seed=12)
    truth = res.truth
    t_end_hold, t_next = truth.static_intervals_s[2][1], truth.static_intervals_s[3][0]
    lost = (truth.t_s > t_end_hold) & (truth.t_s < t_next)
    return {"joined": _joined(res, truth.static), "lost_turn": _joined(res, ~lost)}


def _cuts(n, sizes, rng, jumps):
    """Frame boundaries: random frame lengths in ``sizes``, plus a cut exactly at each jump."""
    cuts = np.cumsum(rng.integers(*sizes, size=n // sizes[0] + 2))
    return np.unique(np.concatenate([[0, n], cuts[cuts < n], jumps]))


def _stream(session, config, cuts):
    """Positions, and the final static decisions, from a PositionAccumulator fed ``cuts`` frames
    (frames of one sample go through ``update``, as the daemon's per-sample path does)."""
    rate = session.rate_hz
    acc = PositionAccumulator(rate_hz=rate, detector_config=config)
    out, steps = [], []
    decisions = None
    for a, b in itertools.pairwise(cuts.tolist()):
        if b - a == 1:
            p = acc.update(session.t_s[a], *session.accel_mps2[a], *session.gyro_rps[a])
            out += [] if p is None else [p]
            d = acc.detector.last_step()
        else:
            got, d = acc.update_batch(
                session.t_s[a:b], session.accel_mps2[a:b], session.gyro_rps[a:b]
            )
            out += got
        decisions = d if decisions is None else decisions.then(d)
        steps.append(d)
    out += acc.flush()
    return out, decisions, steps, acc.detector


@pytest.mark.parametrize("case", ["joined", "lost_turn"])
def test_streamed_positions_split_at_jumps_as_the_batch_ones_however_the_stream_is_cut(case):
    session = _joined_and_lost()[case]
    config = StaticDetectorConfig.from_session(session)
    detection = detect_static(session, config=config)
    expected = build_positions(session, detection).positions
    assert len(expected) == 6
    # The jumps: neighbouring samples whose specific force differs by far more than the noise.
    step = np.linalg.norm(np.diff(session.accel_mps2, axis=0), axis=1)
    jumps = np.flatnonzero(step > 2.0) + 1
    assert 1 <= jumps.size <= 5
    rng = np.random.default_rng(21)
    for sizes in ((1, 2), (1, 9), (60, 400), (300, 3000)):
        got, _, _, _ = _stream(session, config, _cuts(session.n_samples, sizes, rng, jumps))
        assert len(got) == len(expected), sizes
        for p, q in zip(got, expected, strict=True):
            for name in ("index_start", "index_stop", "n_samples", "n_intervals"):
                assert getattr(p, name) == getattr(q, name), (sizes, name)
            np.testing.assert_allclose(p.accel_mean_mps2, q.accel_mean_mps2, rtol=1e-9)
            np.testing.assert_allclose(p.gyro_mean_rps, q.gyro_mean_rps, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("case", ["joined", "lost_turn"])
def test_f0_s_static_gate_does_not_erode_at_a_jump(case):
    # The positions end at a jump; F0 does not: a step fault of a resting unit is a jump, and F0
    # tests the samples right after it. The gate's flags are the static samples with ``margin``
    # static neighbours on both sides, jumps or not, whatever frames the stream came in.
    session = _joined_and_lost()[case]
    config = StaticDetectorConfig.from_session(session)
    static = detect_static(session, config=config).static
    margin = PositionConfig().trim_samples(session.rate_hz)
    windows = np.lib.stride_tricks.sliding_window_view(static, 2 * margin + 1)
    expected = np.zeros(session.n_samples, dtype=bool)
    expected[margin:-margin] = windows.all(axis=1)
    step = np.linalg.norm(np.diff(session.accel_mps2, axis=0), axis=1)
    jumps = np.flatnonzero(step > 2.0) + 1
    assert expected[jumps].all() and expected[jumps - 1].all()
    rng = np.random.default_rng(22)
    for sizes in ((1, 2), (1, 9), (60, 400)):
        cuts = _cuts(session.n_samples, sizes, rng, jumps)
        gate = StaticGate(margin)
        _, _, steps, detector = _stream(session, config, cuts)
        released = []
        for (a, b), d in zip(itertools.pairwise(cuts.tolist()), steps, strict=True):
            *_, flags = gate.push(
                session.t_s[a:b], session.accel_mps2[a:b], session.gyro_rps[a:b], d
            )
            released.append(flags)
        # The last window's decisions come with flush (finish): push them too.
        *_, flags = gate.push(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), detector.last_step())
        released.append(flags)
        got = np.concatenate(released)
        assert got.size >= session.n_samples - margin
        assert np.array_equal(got, expected[: got.size]), sizes


@pytest.mark.parametrize("case", ["joined", "lost_turn"])
def test_the_service_s_pipeline_finds_the_six_faces_of_a_joined_stream(case):
    # What the daemon and replay do with such a recording: frames of any size, no time gap.
    session = _joined_and_lost()[case]
    for frame in (1, 7, 333):
        fleet = FleetProcessor(
            passports=lambda v, i: None, options=PipelineOptions(gravity_mps2=9.81)
        )
        run_fleet(fleet, batches_of(session, vehicle="v", imu=0, batch_samples=frame))
        assert fleet.pipelines[("v", 0)].n_positions == 6, frame
