"""Sessions as other tools and damaged recorders write them: each is read for what it is, or refused
with the reason, never calibrated as if it were whole."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import TURN_MAX_S, position_gaps_s, simulated_timing
from estimators.chain import ChainConfig, run_chain
from estimators.session import ImuSession, SessionError, validate_session
from estimators.sim import Grade, grade_error_model, multi_position_spec, simulate
from estimators.static_detector import StaticDetectorConfig, detect_static
from protocols.session_file import SessionUnits, UnitsError, check_units, write_csv_session
from service.cli import main

G = 9.80665


@pytest.fixture(scope="module")
def session() -> ImuSession:
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    return simulate(multi_position_spec(model=model), seed=40).session


def _rows(s: ImuSession, rows: np.ndarray) -> ImuSession:
    assert s.accel_mps2 is not None and s.gyro_rps is not None
    return ImuSession(s.t_s[rows], s.accel_mps2[rows], s.gyro_rps[rows])


def test_thresholds_from_a_session_with_repeated_and_nan_time_stamps_are_those_of_its_valid_samples(
    session,
):
    n = session.n_samples
    # Every row written twice (a logger that flushed twice), and ten time stamps lost.
    dirty = _rows(session, np.repeat(np.arange(n), 2))
    t = dirty.t_s.copy()
    t[np.arange(1, 2 * n, 2 * n // 10)[:10] + 1] = np.nan
    dirty = replace(dirty, t_s=t)
    clean = validate_session(dirty)[0]
    assert StaticDetectorConfig.from_session(dirty) == StaticDetectorConfig.from_session(clean)


def test_a_session_left_with_one_usable_sample_is_refused_naming_the_rejections(session):
    backwards = replace(session, t_s=session.t_s[::-1].copy())
    with pytest.raises(SessionError, match=r"1 usable sample.*non_monotonic_time"):
        StaticDetectorConfig.from_session(backwards)


def test_one_finite_spike_costs_only_the_rest_it_falls_in(session):
    config = StaticDetectorConfig.from_session(session)
    before = detect_static(session, config=config).intervals
    spike = (before[0].start + before[0].stop) // 2
    accel = session.accel_mps2.copy()
    accel[spike, 0] = 1e9  # a corrupt record: its square is 1e18
    after = detect_static(replace(session, accel_mps2=accel), config=config).intervals
    untouched = [iv for iv in before if not iv.start <= spike < iv.stop]
    assert len(untouched) == len(before) - 1
    assert set(untouched) <= set(after)


def test_a_value_beyond_any_sensor_is_rejected_and_counted(session):
    accel = session.accel_mps2.copy()
    accel[1000:1010] = 1e300
    clean, rejected = validate_session(replace(session, accel_mps2=accel))
    assert rejected.counts == {"implausible_value": 10}
    assert clean.n_samples == session.n_samples - 10
    result = run_chain(replace(session, accel_mps2=accel), ChainConfig(gravity_mps2=G))
    assert len(result.positions) == len(run_chain(session, ChainConfig(gravity_mps2=G)).positions)


def test_time_stamps_in_ms_that_nothing_declares_are_refused_and_declared_ones_read(session):
    # 1 kHz stamps written in ms and read as seconds: 1 Hz, a session that calibrates without a word.
    stamped = replace(session, t_s=np.arange(session.n_samples) * 1.0)
    units = SessionUnits().resolved()
    with pytest.raises(UnitsError, match=r"1 Hz read as s but 1000 Hz read as ms"):
        check_units(stamped, units, time_declared=False)
    check_units(stamped, units, time_declared=True)
    # A usual rate in seconds is not ambiguous.
    check_units(session, units, time_declared=False)


def test_calibrate_says_the_time_gaps_and_the_samples_never_tested(session, tmp_path, capsys):
    # The recorder fell to a tenth of its rate half way: the second half's samples are 0.1 s apart.
    n = session.n_samples
    rows = np.concatenate([np.arange(n // 2), np.arange(n // 2, n, 10)])
    write_csv_session(tmp_path / "slowed.csv", _rows(session, rows))
    capsys.readouterr()
    code = main(
        [
            "calibrate",
            str(tmp_path / "slowed.csv"),
            "--out",
            str(tmp_path / "pp.json"),
            "--no-audit",
        ]
    )
    err = capsys.readouterr().err
    assert code in (0, 2), err
    second_half = len(rows) - n // 2  # its first sample follows the first half's last at 0.01 s
    assert f"time gaps: {second_half - 1} step(s)" in err
    assert f"{second_half - 1} samples lie between gaps" in err


def test_a_break_in_the_recording_is_simulated_as_a_bounded_turn_and_said(session):
    t = session.t_s.copy()
    t[session.n_samples // 2 :] += 1000.0  # the bench left overnight, say
    broken = replace(session, t_s=t)
    chain = run_chain(broken, ChainConfig(gravity_mps2=G))
    assert position_gaps_s(chain).max() > 999.0
    assert simulated_timing(chain)[1].max() == TURN_MAX_S
    heard: list[str] = []
    res = run_audit(
        broken, AuditConfig(ChainConfig(gravity_mps2=G), replicas=2), progress=heard.append
    )
    assert heard[:2] == [f"baseline model: {k} of 2 replicas simulated" for k in (1, 2)]
    assert any(
        s.startswith("1 break(s) in the recording") and f"turns in {TURN_MAX_S:.0f} s" in s
        for s in res.statements
    ), res.statements


def test_a_stuck_channel_is_named_instead_of_a_covariance(session, tmp_path, capsys):
    accel = session.accel_mps2.copy()
    accel[:, 1] = 0.25  # the y accelerometer's output stuck at one value
    write_csv_session(tmp_path / "stuck.csv", replace(session, accel_mps2=accel))
    capsys.readouterr()
    assert main(["calibrate", str(tmp_path / "stuck.csv"), "--out", str(tmp_path / "pp.json")]) == 2
    assert (
        "accel: position 0: axis y has no spread at all (a stuck channel" in capsys.readouterr().err
    )
