"""Gross plausibility at rest with no gate (estimators.gross, issue 28 item 2).

A unit at rest whose accelerometer reads 0.35 g or 1.2 g, whatever its noise, and a MEMS gyro 2.9 °/s
off its passport are events of the pipeline, ``replay`` and the offline batch; their fault-free twins,
flights and the shared real logs raise none. Noise per sample is the consumer class's density at the
stream's rate (:mod:`estimators.nominal_passport`), times a factor.
"""

from __future__ import annotations

import dataclasses
import json
import math
from statistics import NormalDist

import numpy as np
import pytest
from real_data import LOGS, SHARED, needs
from replay_support import replay_with_coverage

from estimators.conventions import EARTH_RATE_RPS, N_PARAMS, STANDARD_GRAVITY_MPS2, Grade, Triad
from estimators.gross import (
    GROSS_STATE_VERSION,
    GrossMonitor,
    gross_batch,
    gross_config,
    tolerance_passports,
)
from estimators.ninepar import Method
from estimators.nominal_passport import (
    CLASS_TOLERANCES,
    NOISE_REFERENCE_RATE_HZ,
    SensorClass,
    nominal_passport,
)
from estimators.passport import GRADE_FLOORS, Passport, Provenance, TriadPassport, reference_kind
from estimators.session import ImuSession
from estimators.sim import Fault, FaultKind, flight_spec, multi_position_spec, simulate
from protocols.checkpoint_codec import decode_state, encode_state
from protocols.events import (
    Predicate,
    StreamCause,
    event_from_dict,
    event_from_json,
    event_to_dict,
    make_event,
)
from protocols.frames import SampleBatch
from protocols.logs import write_dataflash_bin
from protocols.mavlink_adapter import STATUSTEXT_MAX_CHARS, alert_text
from protocols.passport_codec import read_passport_json, write_passport_json
from protocols.session_file import load_session, write_csv_session
from protocols.ulog import write_ulog
from service.cli import EXIT_FAULT, EXIT_NO_FAULT, EXIT_UNTESTED, main
from service.pipeline import FleetProcessor, ImuPipeline, PipelineOptions

G = STANDARD_GRAVITY_MPS2
CONSUMER = CLASS_TOLERANCES[SensorClass.CONSUMER_MEMS]
P_FALSE = PipelineOptions().false_alarm_probability


def at_rest(
    magnitude_g: float,
    *,
    rate_hz: float,
    noise_factor: float,
    seed: int,
    duration_s: float = 20.0,
    gyro_rps: tuple[float, float, float] = (0.0, 0.0, 0.0),
    up=(0.0, 0.0, 1.0),
) -> ImuSession:
    """A unit resting with ``up`` along gravity whose accelerometer reads ``magnitude_g`` × g."""
    rng = np.random.default_rng(seed)
    n = round(duration_s * rate_hz)
    per_sample = math.sqrt(rate_hz / NOISE_REFERENCE_RATE_HZ) * noise_factor
    up_b = np.asarray(up, float) / np.linalg.norm(up)
    accel = magnitude_g * G * up_b + rng.normal(
        0.0, CONSUMER.accel.noise_density_si * per_sample, (n, 3)
    )
    gyro = np.asarray(gyro_rps) + rng.normal(
        0.0, CONSUMER.gyro.noise_density_si * per_sample, (n, 3)
    )
    return ImuSession(np.arange(n) / rate_hz + 100.0, accel, gyro)


def run_pipeline(session: ImuSession, passport: Passport | None, *, frame: int = 20, g: float = G):
    """The daemon's chain (a fleet) over ``session`` in frames of ``frame`` samples; its events and pipeline."""
    fleet = FleetProcessor(passports=lambda v, i: passport, options=PipelineOptions(gravity_mps2=g))
    events = []
    for k, i in enumerate(range(0, session.n_samples, frame)):
        sl = slice(i, i + frame)
        batch = SampleBatch(
            "v1", 0, k, session.t_s[sl], session.accel_mps2[sl], session.gyro_rps[sl]
        )
        events += fleet.process(batch, arrival_s=0.0)
    return events + fleet.finish(), fleet.pipelines[("v1", 0)]


def gross_events(events, **match):
    return [
        e
        for e in events
        if e.predicate is Predicate.GROSS and all(getattr(e, k) == v for k, v in match.items())
    ]


def replay_json(capsys, path) -> tuple[int, list, str]:
    """Exit status, events and stderr of ``replay --json`` (its last line, the coverage, checked)."""
    status, lines, err, _ = replay_with_coverage(capsys, path, "--json")
    return status, [event_from_json(line) for line in lines], err


# --------------------------------------------------------------------------- the batch form


@pytest.mark.parametrize("rate_hz", [50.0, 200.0])
@pytest.mark.parametrize("noise_factor", [1.0, 3.0])
@pytest.mark.parametrize("magnitude_g", [0.35, 1.2])
def test_rest_off_g_is_found_whatever_the_noise_and_the_twin_is_not(
    rate_hz, noise_factor, magnitude_g
):
    faulty = at_rest(magnitude_g, rate_hz=rate_hz, noise_factor=noise_factor, seed=1)
    res = gross_batch(faulty, None, gravity_mps2=G)
    (change,) = res.changes
    assert change.triad is Triad.ACCEL and change.axis == "z" and change.raised
    assert change.value_si == pytest.approx((magnitude_g - 1.0) * G, abs=6 * change.sigma_si)
    assert abs(change.value_si) > change.bound_si
    assert res.coverage[Triad.ACCEL].source == "nominal consumer_mems"
    twin = gross_batch(
        at_rest(1.0, rate_hz=rate_hz, noise_factor=noise_factor, seed=1), None, gravity_mps2=G
    )
    cov = twin.coverage[Triad.ACCEL]
    assert twin.changes == [] and cov.windows == twin.windows == 40
    assert twin.coverage[Triad.GYRO].windows == 40
    # Per window, the quantiles the coverage's minimum detectable fault takes (module docstring).
    nd = NormalDist()
    assert nd.inv_cdf(1 - cov.window_false_alarm_prob / 2) == pytest.approx(cov.z)
    assert nd.inv_cdf(cov.window_power) == pytest.approx(cov.z_power)
    assert cov.window_false_alarm_prob**cov.persist_windows == pytest.approx(P_FALSE)
    # Gravity along z: only z saw it (what coverage's minimum detectable fault needs).
    assert cov.max_abs_u[2] == pytest.approx(1.0, abs=1e-4) and max(cov.max_abs_u[:2]) < 0.01


def test_a_session_without_gyros_is_tested_on_its_accelerometer_and_says_the_gyro_was_not():
    session = dataclasses.replace(
        at_rest(0.35, rate_hz=100.0, noise_factor=1.0, seed=11), gyro_rps=None
    )
    res = gross_batch(session, None, gravity_mps2=G)
    assert [(c.triad, c.axis, c.raised) for c in res.changes] == [(Triad.ACCEL, "z", True)]
    gyro = res.coverage[Triad.GYRO]
    assert gyro.windows == 0 and all(math.isnan(v) for v in gyro.sigma_mean_si)
    # Shorter than a window: nothing tested, and the coverage says so.
    short = gross_batch(
        at_rest(1.2, rate_hz=100.0, noise_factor=1.0, seed=11, duration_s=0.3), None, gravity_mps2=G
    )
    assert short.changes == [] and short.windows == 0 and short.coverage[Triad.ACCEL].windows == 0


def test_the_noise_used_is_the_streams_own():
    """3× the class noise: the window mean's σ is the stream's, three times the 1× stream's."""
    sig = [
        gross_batch(at_rest(1.0, rate_hz=200.0, noise_factor=f, seed=2), None, gravity_mps2=G)
        .coverage[Triad.ACCEL]
        .sigma_mean_si[2]
        for f in (1.0, 3.0)
    ]
    expected = CONSUMER.accel.noise_density_si * math.sqrt(200.0 / NOISE_REFERENCE_RATE_HZ) / 10.0
    # 40 windows of 99 degrees of freedom pooled: the estimate is within a few % of the truth.
    assert sig[0] == pytest.approx(expected, rel=0.05)
    assert sig[1] == pytest.approx(3 * expected, rel=0.05)


def test_a_flight_and_its_rests_raise_nothing():
    """A healthy MEMS unit resting, flying 120 s of manoeuvres and resting: no gross finding."""
    res = simulate(flight_spec(grade=Grade.MEMS, rest_s=20.0), seed=5)
    out = gross_batch(res.session, None, gravity_mps2=res.spec.assumed_gravity_mps2)
    assert out.changes == []
    # The rests were tested (before and after the flight), the flight was not all taken for rest.
    assert 60 <= out.coverage[Triad.ACCEL].windows < out.windows


def test_stream_and_batch_agree_however_the_samples_are_cut():
    session = at_rest(1.2, rate_hz=100.0, noise_factor=2.0, seed=3, duration_s=30.0)
    session = ImuSession(
        session.t_s, np.concatenate([session.accel_mps2[:1500], session.accel_mps2[1500:] / 1.2]),
        session.gyro_rps,
    )  # fmt: skip
    batch = gross_batch(session, None, gravity_mps2=G)
    assert [(c.raised, c.t_s) for c in batch.changes] == [(True, 100.0), (False, 115.0)]
    cfg = batch.config
    rng = np.random.default_rng(0)
    cuts = np.unique(rng.integers(1, session.n_samples, 200))
    mon = GrossMonitor(cfg)
    changes = []
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, session.n_samples], strict=True):
        changes += mon.update(
            session.t_s[a:b], session.accel_mps2[a:b], session.gyro_rps[a:b]
        ).changes
    assert [(c.raised, c.t_s, c.axis) for c in changes] == [
        (c.raised, c.t_s, c.axis) for c in batch.changes
    ]
    assert mon.tested == {t: batch.coverage[t].windows for t in Triad}


def test_the_figures_are_the_same_bits_however_the_samples_are_cut():
    """The pooled noise behind each window's sigma is a running sum of the quiet windows'
    variances: window by window, in a frame of many windows or across frames, the same additions
    in the same order, so the events' sigma and bound and the coverage agree to the bit (replay
    takes the frames of a lone IMU joined, up to 16,384 samples; the daemon one by one)."""
    session = at_rest(1.2, rate_hz=100.0, noise_factor=2.0, seed=3, duration_s=60.0)
    session = ImuSession(
        session.t_s, np.concatenate([session.accel_mps2[:1500], session.accel_mps2[1500:] / 1.2]),
        session.gyro_rps,
    )  # fmt: skip
    cfg = gross_batch(session, None, gravity_mps2=G).config
    runs = []
    for size in (cfg.window_samples, 100, 4096, session.n_samples):
        mon = GrossMonitor(cfg)
        changes = []
        for i in range(0, session.n_samples, size):
            sl = slice(i, i + size)
            changes += mon.update(
                session.t_s[sl], session.accel_mps2[sl], session.gyro_rps[sl]
            ).changes
        runs.append((changes, mon.coverage()))
    assert len(runs[0][0]) == 2  # raised and cleared: two sigmas that tell the sums apart
    assert all(run == runs[0] for run in runs[1:])


def test_the_state_round_trips_and_resumes_where_it_stopped():
    session = at_rest(0.35, rate_hz=100.0, noise_factor=1.0, seed=4)
    cfg = gross_config(
        None, rate_hz=100.0, gravity_mps2=G, gravity_rel_err=3e-3, false_alarm_prob=P_FALSE
    )
    whole = GrossMonitor(cfg)
    expected = whole.update(session.t_s, session.accel_mps2, session.gyro_rps).changes
    first = GrossMonitor(cfg)
    cut = 437  # mid-window and mid-run (the failure is declared after 500 samples)
    assert (
        first.update(session.t_s[:cut], session.accel_mps2[:cut], session.gyro_rps[:cut]).changes
        == ()
    )
    state = json.loads(json.dumps(first.state_dict()))  # plain values only
    assert state["version"] == GROSS_STATE_VERSION
    resumed = GrossMonitor.from_state(cfg, state)
    rest = resumed.update(
        session.t_s[cut:], session.accel_mps2[cut:], session.gyro_rps[cut:]
    ).changes
    assert rest == expected and len(rest) == 1
    with pytest.raises(ValueError, match="not version"):
        GrossMonitor.from_state(cfg, {**state, "version": GROSS_STATE_VERSION + 1})
    with pytest.raises(ValueError, match="open window"):
        GrossMonitor.from_state(cfg, {**state, "n": cfg.window_samples})


def test_false_alarms_follow_the_stated_probability():
    """A unit at the edge of its tolerance (|a| = g + tol_high): each window fails with p_w/2.

    The per-window test is two-sided at ``p_w = p^(1/P)``; at the upper edge only one side can fail.
    Over 100 seeded trials of 40 windows the failing fraction stays within 5 binomial σ of p_w/2,
    and the healthy unit at g (windows at least tol_high from the bound) never declares a failure.
    """
    cfg = gross_config(
        None, rate_hz=100.0, gravity_mps2=G, gravity_rel_err=3e-3, false_alarm_prob=P_FALSE
    )
    p_window = P_FALSE ** (1.0 / cfg.persist_windows)
    edge = 1.0 + cfg.accel_tol_high_mps2 / G
    fails = windows = declared = 0
    for seed in range(100):
        res = gross_batch(
            at_rest(edge, rate_hz=100.0, noise_factor=1.0, seed=seed), None, gravity_mps2=G
        )
        cov = res.coverage[Triad.ACCEL]
        fails, windows = fails + cov.fail_windows, windows + cov.windows
        healthy = gross_batch(
            at_rest(1.0, rate_hz=100.0, noise_factor=1.0, seed=seed), None, gravity_mps2=G
        )
        declared += len(healthy.changes)
    expected = 0.5 * p_window * windows
    assert abs(fails - expected) <= 5 * math.sqrt(expected * (1 - 0.5 * p_window))
    assert declared == 0


# --------------------------------------------------------------------------- the pipeline, replay


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """0.35 g, 1.2 g and 1 g (the twin) at rest with 1× and 3× the class noise, as ULog (200 Hz),
    DataFlash .bin (50 Hz) and session CSV (100 Hz)."""
    root = tmp_path_factory.mktemp("gross-logs")
    out = {}
    for mag in (0.35, 1.2, 1.0):
        for noise in (1.0, 3.0):
            seed = int(mag * 100 + noise)
            ulg, binlog, csv = (root / f"{mag}-{noise}.{ext}" for ext in ("ulg", "bin", "csv"))
            write_ulog(ulg, {0: at_rest(mag, rate_hz=200.0, noise_factor=noise, seed=seed)})
            write_dataflash_bin(
                binlog, {0: at_rest(mag, rate_hz=50.0, noise_factor=noise, seed=seed)}
            )
            write_csv_session(csv, at_rest(mag, rate_hz=100.0, noise_factor=noise, seed=seed))
            out[mag, noise] = {"ulg": ulg, "bin": binlog, "csv": csv}
    return out


@pytest.mark.parametrize("noise", [1.0, 3.0])
@pytest.mark.parametrize("mag", [0.35, 1.2])
@pytest.mark.parametrize("kind", ["ulg", "bin"])
def test_replay_of_a_log_at_rest_off_g_raises_the_gross_event(capsys, logs, kind, mag, noise):
    status, events, err = replay_json(capsys, logs[mag, noise][kind])
    assert status == EXIT_FAULT
    (event,) = gross_events(events)
    assert event.triad is Triad.ACCEL and event.axis == "z" and event.severity.name == "ERROR"
    assert event.cause is StreamCause.GRAVITY_MAGNITUDE and event.unit == "m/s^2"
    assert abs(event.estimate - (mag - 1.0) * G) < 0.2 and abs(event.estimate) > event.tolerance
    assert "imu0.gross.accel.windows 40" in err and "imu0.gross.accel.fail 40" in err
    twin_status, twin_events, twin_err = replay_json(capsys, logs[1.0, noise][kind])
    # One orientation at rest: F1…F9 cannot run, so the twin is "no finding within coverage".
    assert twin_status == EXIT_UNTESTED and twin_events == []
    assert "imu0.gross.accel.windows 40" in twin_err and "gross.accel.fail" not in twin_err


@pytest.mark.parametrize("noise", [1.0, 3.0])
@pytest.mark.parametrize("mag", [0.35, 1.2])
def test_a_session_file_at_rest_off_g_raises_the_gross_event_in_the_pipeline(logs, mag, noise):
    """No passport at all, as in the daemon: the consumer class's tolerances, said in the status."""
    session = load_session(str(logs[mag, noise]["csv"])).session
    events, pipe = run_pipeline(session, None)
    (event,) = gross_events(events)
    assert event.axis == "z" and "tolerances: nominal consumer_mems" in event.text
    status = pipe.status()
    assert status.state.value == "fault" and "FAILING accel" in status.detail
    assert "gross at rest: nominal consumer_mems (no passport)" in status.detail
    twin_events, twin = run_pipeline(load_session(str(logs[1.0, noise]["csv"])).session, None)
    assert twin_events == [] and twin.counters["gross.accel.windows"] == 40


def test_a_dead_accelerometer_under_a_still_gyro_is_found(capsys, tmp_path):
    """The ArduRover case: 50 Hz, 107 s, gyros still (|ω| ≈ 0.008 rad/s), |a| ≈ 3.4 m/s², noise 1.5× the class."""
    session = at_rest(
        3.4 / G,
        rate_hz=50.0,
        noise_factor=1.5,
        seed=9,
        duration_s=107.0,
        gyro_rps=(0.005, -0.005, 0.004),
    )
    log = tmp_path / "rover.bin"
    write_dataflash_bin(log, {0: session})
    _, events, _ = replay_json(capsys, log)
    (event,) = gross_events(events)
    assert event.estimate == pytest.approx(3.4 - G, abs=0.05) and event.t_s == pytest.approx(100.0)


def mems_gyro_passport(accel: TriadPassport, gyro_bias_rps: np.ndarray) -> Passport:
    """The unit's passport with a gyro triad: its zero signal known, tolerance the MEMS grade's floor."""
    bias_si, scale, cross = GRADE_FLOORS[(Triad.GYRO, Grade.MEMS)]
    nominal = np.zeros(N_PARAMS)
    nominal[:3] = gyro_bias_rps / EARTH_RATE_RPS
    gyro = TriadPassport(
        triad=Triad.GYRO, reference=EARTH_RATE_RPS, reference_kind=reference_kind(Triad.GYRO),
        nominal=nominal, tolerance=np.repeat([bias_si / EARTH_RATE_RPS, scale, cross], 3),
        sigma=np.zeros(N_PARAMS), observable=np.zeros(N_PARAMS, bool),
        noise_std=np.full(3, CONSUMER.gyro.noise_density_si / EARTH_RATE_RPS), sample_rate_hz=2.0,
        provenance=Provenance(Method.LINEAR, 0, 0.95, nominal, nominal, procedure="static means (test)"),
    )  # fmt: skip
    return Passport("mems-1", "sim MEMS", {}, "2026-01-01", {Triad.ACCEL: accel, Triad.GYRO: gyro})


@pytest.fixture(scope="module")
def eighteen(tmp_path_factory):
    """A MEMS unit's 18-position session, its passport (accelerometer from ``ins-health calibrate``,
    gyro zero signal from the simulated truth) and a twin session whose gyro x reads +0.05 rad/s more."""
    clean = simulate(multi_position_spec(grade=Grade.MEMS, static_s=10.0), seed=3)
    g = clean.spec.assumed_gravity_mps2
    csv = tmp_path_factory.mktemp("eighteen") / "clean.csv"
    write_csv_session(csv, clean.session)
    out = csv.with_suffix(".json")
    assert main(["calibrate", str(csv), "--out", str(out), "--no-audit", "--gravity", str(g)]) == 0
    accel = read_passport_json(out).triads[Triad.ACCEL]
    passport = mems_gyro_passport(accel, clean.truth.gyro_params[:3] * EARTH_RATE_RPS)
    off = Fault(FaultKind.STEP, Triad.GYRO, 0, 0.0, 0.05 / EARTH_RATE_RPS)
    spec = lambda faults: multi_position_spec(grade=Grade.MEMS, static_s=10.0, faults=faults)  # noqa: E731
    return passport, g, simulate(spec([]), seed=4).session, simulate(spec([off]), seed=4).session


def test_a_mems_gyro_2_9_deg_s_off_its_passport_is_found_on_18_positions(eighteen):
    passport, g, twin, faulty = eighteen
    events, pipe = run_pipeline(faulty, passport, frame=50, g=g)
    (event,) = gross_events(events)
    assert event.triad is Triad.GYRO and event.axis == "x" and event.cause.value == "zero_signal"
    assert event.estimate - event.nominal == pytest.approx(0.05, abs=2e-3)
    assert event.tolerance < 1e-3 and "deg/s" in event.text
    assert len(alert_text(event)) <= STATUSTEXT_MAX_CHARS
    assert pipe.counters["gross.gyro.fail"] > 0 and pipe.state.value == "fault"
    twin_events, twin_pipe = run_pipeline(twin, passport, frame=50, g=g)
    assert gross_events(twin_events) == [] and twin_pipe.counters["gross.gyro.windows"] >= 18 * 10
    batch = gross_batch(faulty, passport, gravity_mps2=g)
    assert [(c.triad, c.axis, c.raised) for c in batch.changes] == [(Triad.GYRO, "x", True)]


def test_diagnose_names_the_gyro_2_9_deg_s_off_and_says_what_it_tested(eighteen, tmp_path, capsys):
    """The issue's case offline: 18 positions, gyro x 2.9 deg/s off its passport. It was 'no fault
    (not diagnosed: gyro)', exit 0; the gross test names it (exit 1) and the coverage states each
    check with its minimum detectable fault. The twin: no gross fault, and the gyro's F0 and F1…F9
    do not apply (a MEMS gyro cannot see the Earth rate), so nothing the verdict rests on is missing."""
    passport, g, twin, faulty = eighteen
    pj = tmp_path / "p.json"
    write_passport_json(passport, pj)
    verdicts = {}
    for name, session in (("faulty", faulty), ("twin", twin)):
        csv = tmp_path / f"{name}.csv"
        write_csv_session(csv, session)
        status = main(["diagnose", str(csv), "--passport", str(pj), "--gravity", str(g), "--json"])
        out = json.loads(capsys.readouterr().out)
        assert out["exit_status"] == status
        verdicts[name] = status, out
    status, out = verdicts["faulty"]
    (fault,) = [f for f in out["faults"] if f["predicate"] == "gross"]
    assert status == EXIT_FAULT and (fault["triad"], fault["axis"]) == ("gyro", "x")
    assert fault["cause"] == "zero_signal" and fault["estimate"] - fault["nominal"] > 0.045
    checks = {(c["triad"], c["check"]): c for c in out["coverage"]["checks"]}
    gyro_gross, accel_f19 = checks["gyro", "gross"], checks["accel", "F1-F9"]
    # Its MDF: the MEMS floor's zero-signal tolerance plus a few window-mean σ, under the fault.
    assert gyro_gross["ran"] and gyro_gross["samples"] >= 18 * 10
    assert all(
        tol < m < 0.05
        for m, tol in zip(gyro_gross["mdf_bias_si"], gyro_gross["tolerance_bias_si"], strict=True)
    )
    assert accel_f19["ran"] and accel_f19["positions"] == 18
    assert not checks["gyro", "F1-F9"]["applies"]
    twin_status, twin_out = verdicts["twin"]
    assert not [f for f in twin_out["faults"] if f["predicate"] == "gross"]
    assert twin_status in (EXIT_NO_FAULT, EXIT_UNTESTED)
    csv = tmp_path / "faulty.csv"
    assert main(["diagnose", str(csv), "--passport", str(pj), "--gravity", str(g)]) == EXIT_FAULT
    text = capsys.readouterr().out
    assert "FAULT gross: gyro x zero_signal" in text and "coverage: IMU0 gyro gross: ran on" in text


def test_a_checkpoint_keeps_a_raised_failure_and_its_recovery_comes_once():
    """The pipeline's state saved mid-failure: the resumed one raises no second event, recovers once."""
    bad = at_rest(1.2, rate_hz=100.0, noise_factor=1.0, seed=6, duration_s=20.0)
    good = at_rest(1.0, rate_hz=100.0, noise_factor=1.0, seed=7, duration_s=20.0)
    good = dataclasses.replace(good, t_s=good.t_s + 20.0)
    events, pipe = run_pipeline(bad, None)
    assert len(gross_events(events)) == 1
    state = decode_state(encode_state(pipe.state_dict()))
    resumed = ImuPipeline("v1", 0, passport=None, options=PipelineOptions())
    resumed.load_state(state)
    later = []
    for k, i in enumerate(range(0, good.n_samples, 20)):
        sl = slice(i, i + 20)
        batch = SampleBatch("v1", 0, 1000 + k, good.t_s[sl], good.accel_mps2[sl], good.gyro_rps[sl])
        later += resumed.process(batch, arrival_s=0.0)
    (recovered,) = gross_events(later)
    assert recovered.cause is StreamCause.RECOVERED and recovered.t_s == pytest.approx(120.0)
    # A checkpoint from before the gross test (no "gross" key) still loads: the test starts afresh.
    old = {k: v for k, v in state.items() if k != "gross"}
    ImuPipeline("v1", 0, passport=None, options=PipelineOptions()).load_state(old)


def test_gross_events_are_schema_version_2_and_others_stay_version_1():
    events, _ = run_pipeline(at_rest(0.35, rate_hz=100.0, noise_factor=1.0, seed=8), None)
    gross = gross_events(events)[0]
    d = event_to_dict(gross)
    assert d["v"] == 2 and event_from_dict(d) == gross
    with pytest.raises(Exception, match="needs event schema version 2"):
        event_from_dict({**d, "v": 1})
    f0 = make_event(
        vehicle="v1", imu=0, t_s=1.0, predicate=Predicate.F0, cause=StreamCause.OUT_OF_SHELL,
        severity=4, triad=Triad.ACCEL, estimate=0.3,
    )  # fmt: skip
    assert event_to_dict(f0)["v"] == 1 and event_from_dict(event_to_dict(f0)) == f0
    assert alert_text(gross).startswith("IMU0 ACC Z |a|-g -6.")


# --------------------------------------------------------------------------- real logs keep their verdicts

REAL_LOGS = [
    LOGS / "px4-events.ulg",
    LOGS / "ardupilot-test.BIN",
    LOGS / "ardupilot-sitl-vtol.tlog",
    *sorted((SHARED / "data" / "field").glob("*.ulg")),
    *sorted((SHARED / "data" / "field").glob("*.bin")),
]


@needs(LOGS)
@needs(SHARED / "data" / "field")
def test_real_logs_are_tested_and_raise_no_gross_event(capsys):
    """The shared real logs keep their verdict (no event) and the test ran on every one long enough
    for its windows (the 45- and 10-sample DataFlash cuts hold none)."""
    for path in REAL_LOGS:
        status, events, err = replay_json(capsys, path)
        assert status == EXIT_UNTESTED and events == [], path.name
        if path.name not in ("ardupilot-test.BIN", "ardupilot-copter462-cut.bin"):
            assert ".gross.accel.windows" in err and ".gross.accel.fail" not in err, path.name


@pytest.mark.network
def test_the_daemon_raises_the_gross_event_of_a_unit_without_passport_over_zenoh(tmp_path):
    """A vehicle with no passport in the store streams a unit at rest reading 1.2 g: the gross event
    arrives at a ground station, and the status says the class tolerances were used."""
    import zenoh
    from service_support import (
        ServiceThread,
        batches_of,
        service_config,
        wait_subscribed,
        wait_until,
        zenoh_client_config,
        zenoh_router,
    )

    from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key, subscribe_status

    session = at_rest(1.2, rate_hz=100.0, noise_factor=1.0, seed=12)
    with zenoh_router() as port:
        cfg = service_config(
            tmp_path, port=port, passport_dir=tmp_path / "empty-store", validity={"timeout_s": 60.0}
        )
        with (
            ServiceThread(cfg),
            zenoh.open(zenoh_client_config(port)) as vehicle,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            got, statuses = [], []
            with EventReceiver(ground, got.append):
                subscribe_status(ground, statuses.append)
                wait_subscribed(vehicle, frame_key("uav-7", 0))
                with FramePublisher(
                    vehicle, "uav-7", 0, congestion_control=zenoh.CongestionControl.BLOCK
                ) as pub:
                    for b in batches_of(session, vehicle="uav-7", imu=0, batch_samples=50):
                        pub.publish(b)
                wait_until(lambda: gross_events(got), timeout_s=60, what="the gross event")
                wait_until(
                    lambda: any(s.imus and "gross at rest" in s.imus[0].detail for s in statuses),
                    timeout_s=30,
                    what="a status naming the gross test",
                )
    (event,) = gross_events(got)
    assert event.triad is Triad.ACCEL and event.axis == "z" and event.estimate > event.tolerance
    detail = next(s for s in reversed(statuses) if s.imus).imus[0].detail
    # The daemon gives the unit its class's nominal passport ([service] default_grade), whose
    # tolerances the gross test takes.
    assert "passport: nominal consumer_mems" in detail
    assert "gross at rest: passport nominal-consumer_mems" in detail


# --------------------------------------------------------------------------- its minimum detectable fault


def tight_passport(tolerance: float) -> Passport:
    """The consumer class's nominal passport with every tolerance at ``tolerance`` (normalized): the
    window mean's noise, not the tolerance, then sizes the minimum detectable fault."""
    base = nominal_passport(SensorClass.CONSUMER_MEMS, gravity_mps2=G)
    triads = {
        t: dataclasses.replace(tp, tolerance=np.full(N_PARAMS, tolerance))
        for t, tp in base.triads.items()
    }
    return dataclasses.replace(base, triads=triads)


@pytest.mark.parametrize(
    ("name", "tolerance"), [("consumer class", None), ("tolerance below the noise", 1e-6)]
)
def test_faults_at_1_5x_the_stated_mdf_are_found_and_at_0_5x_rarely(name, tolerance):
    """The issue's check of a printed minimum detectable fault against simulation: a zero signal on
    z (the axis along gravity, whose MDF is finite), a scale error on z (accelerometer) and a zero
    signal on x (gyro), each at 1.5× the MDF the fault-free session states, are declared in at least
    95 of 100 seeded trials, and at 0.5× in at most 20. The sessions hold 12 windows, 2 more than the
    10 a declared failure needs. With the class's tolerances the tolerance dominates the bound; with
    tolerances far below the noise, the window mean's noise does (the reference's error left out)."""
    passport = None if tolerance is None else tight_passport(tolerance)
    tps, _ = tolerance_passports(passport, gravity_mps2=G)

    def run(accel_bias=0.0, accel_scale=0.0, gyro_bias=0.0, seed=0):
        s = at_rest(1.0, rate_hz=50.0, noise_factor=1.0, seed=seed, duration_s=6.0)
        accel = s.accel_mps2 * np.array([1.0, 1.0, 1.0 + accel_scale])
        accel += np.array([0.0, 0.0, accel_bias])
        gyro = s.gyro_rps + np.array([gyro_bias, 0.0, 0.0])
        return gross_batch(
            ImuSession(s.t_s, accel, gyro), passport, gravity_mps2=G, gravity_rel_err=0.0
        )

    healthy = run(seed=10_000)
    mdf = {
        t: healthy.coverage[t].check(tps[t], gravity_mps2=G, total_windows=healthy.windows)
        for t in (Triad.ACCEL, Triad.GYRO)
    }
    assert healthy.windows == 12 and not healthy.changes
    cases = {
        "accel zero signal z": ("accel_bias", mdf[Triad.ACCEL].mdf_bias_si[2], Triad.ACCEL),
        "accel scale z": ("accel_scale", mdf[Triad.ACCEL].mdf_scale[2], Triad.ACCEL),
        "gyro zero signal x": ("gyro_bias", mdf[Triad.GYRO].mdf_bias_si[0], Triad.GYRO),
    }
    for case, (kind, size, triad) in cases.items():
        assert math.isfinite(size), case
        found = {
            k: sum(
                any(c.raised and c.triad is triad for c in run(**{kind: k * size}, seed=s).changes)
                for s in range(100)
            )
            for k in (0.5, 1.5)
        }
        assert found[1.5] >= 95 and found[0.5] <= 20, (name, case, size, found)


def test_a_gyro_resting_off_zero_within_its_tolerance_leaves_the_accelerometer_tested():
    """The measured Xsens unit's gyro rests 0.05 rad/s off 0 (inside its class's 20 °/s): a 'still'
    gyro demanded within 0.05 rad/s of the passport's zero left its accelerometer untested (0 windows
    of 1023). A gyro 0.07 rad/s off on x and z, no passport: the accelerometer reading 1.2 g is found;
    beyond the widened band (0.15 rad/s) the gyro is not still, and the accelerometer is not tested."""
    off = at_rest(1.2, rate_hz=100.0, noise_factor=1.0, seed=8, gyro_rps=(0.07, 0.0, 0.07))
    res = gross_batch(off, None, gravity_mps2=G)
    assert res.coverage[Triad.ACCEL].windows == res.windows
    assert [(c.triad, c.raised) for c in res.changes] == [(Triad.ACCEL, True)]
    turning = at_rest(1.2, rate_hz=100.0, noise_factor=1.0, seed=8, gyro_rps=(0.15, 0.0, 0.0))
    res = gross_batch(turning, None, gravity_mps2=G)
    assert res.coverage[Triad.ACCEL].windows == 0 and not res.changes
