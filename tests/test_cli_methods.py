"""``ins-health passport tilt|triad|temperature`` and ``ins-health sixpos static|rate`` end to end."""

import json

import numpy as np
import pytest

from estimators.session import ImuSession
from protocols.passport_codec import read_passport_json
from protocols.session_file import load_session, write_csv_session
from service.cli import main


def _run(capsys, *argv):
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def _json(capsys, *argv):
    status, out, err = _run(capsys, *argv, "--json")
    assert err == "", err
    return status, json.loads(out)


@pytest.fixture(scope="module")
def tilt_dir(tmp_path_factory):
    """Two simulated tilt runs written as session files by the command itself."""
    d = tmp_path_factory.mktemp("tilt")
    argv = [
        "passport",
        "tilt",
        "--simulate",
        "--runs",
        "2",
        "--seed",
        "3",
        "--save-sessions",
        str(d),
        "--plot",
        str(d / "checks.png"),
        "--json",
    ]
    assert main(argv) == 0
    return d


def test_tilt_simulate_writes_a_valid_passport_and_reports_the_papers_checks(tmp_path, capsys):
    out = tmp_path / "p.json"
    status, rep = _json(
        capsys,
        "passport",
        "tilt",
        "--simulate",
        "--seed",
        "1",
        "--out",
        out,
        "--report",
        tmp_path / "r.json",
    )
    assert status == 0 and rep["reproducible"]
    assert round(rep["k0_mps2_per_pulse"], 5) == 0.00769
    assert len(rep["runs"]) == 5 and rep["n_angles"] == [60] * 5
    e = rep["error_rms_pulses"]
    assert e["half_pulse"] > 3 * e["in_run_fit"]
    assert rep["without_half_pulse_minus_with"]["zero_offset_mps2"] == pytest.approx(
        -0.5 * rep["k0_mps2_per_pulse"], rel=1e-9
    )
    tp = read_passport_json(out).triads
    (accel,) = tp.values()
    assert (
        accel.nominal[3] == pytest.approx(rep["passport_axis"]["scale_error"])
        and accel.observable[3]
    )
    assert json.loads((tmp_path / "r.json").read_text()) == rep


def test_tilt_from_session_files_matches_the_simulation(tilt_dir, capsys):
    files = sorted(tilt_dir.glob("run*.csv"))
    status, rep = _json(capsys, "passport", "tilt", *[a for f in files for a in ("--session", f)])
    assert status == 0 and rep["n_runs"] == 2 and rep["lsb_mps2"] == pytest.approx(0.0077)
    assert rep["gravity_mps2"] == pytest.approx(load_session(files[0]).gravity_mps2)
    assert rep["n_angles"] == [60, 60]
    assert (tilt_dir / "checks.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tilt_text_report_names_the_checks(capsys):
    status, out, _ = _run(
        capsys, "passport", "tilt", "--simulate", "--runs", "2", "--angles-deg", "10:40:2"
    )
    assert status == 0
    for phrase in (
        "k0 = 2g/(N↑−N↓)",
        "intersection lo",
        "passport value",
        "reproducible across runs: yes",
        "without the half-pulse correction",
    ):
        assert phrase in out


def test_tilt_run_that_moved_fails_the_reproducibility_check(tilt_dir, tmp_path, capsys):
    moved = load_session(tilt_dir / "run2.csv")
    acc = moved.session.accel_mps2.copy()
    acc[:, 0] += 15 * 0.0077  # fifteen pulses of zero offset: another sensor, or a changed one
    write_csv_session(
        tmp_path / "moved.csv",
        ImuSession(moved.session.t_s, acc, None),
        metadata={"gravity_mps2": moved.gravity_mps2},
    )
    status, rep = _json(
        capsys,
        "passport",
        "tilt",
        "--session",
        tilt_dir / "run1.csv",
        "--session",
        tmp_path / "moved.csv",
        "--out",
        tmp_path / "p.json",
    )
    assert status == 1 and rep["not_reproducible"] == ["zero_offset_mps2"]
    (accel,) = read_passport_json(tmp_path / "p.json").triads.values()
    assert not accel.observable[0]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--simulate", "--angles-deg", "5,6,7"], "at least 4 angles"),
        (["--simulate", "--runs", "1"], "--runs must be at least 2"),
        (["--simulate", "--angles-deg", "5:x:1"], "--angles-deg must be"),
    ],
)
def test_tilt_bad_input_says_what_is_missing(capsys, argv, message):
    status, _, err = _run(capsys, "passport", "tilt", *argv)
    assert status == 2 and message in err and err.count("\n") == 1


def test_tilt_session_problems_name_the_file(tilt_dir, capsys):
    status, _, err = _run(capsys, "passport", "tilt", "--session", tilt_dir / "run1.csv")
    assert status == 2 and "at least 2 runs" in err
    status, _, err = _run(
        capsys,
        "passport",
        "tilt",
        "--session",
        tilt_dir / "run1.csv",
        "--session",
        tilt_dir / "run2.csv",
        "--angles-deg",
        "5:63:1",
    )
    assert status == 2 and "run1.csv: found 62 holds" in err


def test_triad_passport_from_simulated_runs_and_their_session_files(tmp_path, capsys):
    status, rep = _json(
        capsys,
        "passport",
        "triad",
        "--simulate",
        "--runs",
        "2",
        "--out",
        tmp_path / "t.json",
        "--save-sessions",
        tmp_path,
    )
    assert status == 0 and rep["reproducible"] and rep["n_positions"] == [18, 18]
    (accel,) = read_passport_json(tmp_path / "t.json").triads.values()
    truth = np.array(
        [rep["truth"][n] for n in ("bx", "by", "bz", "ex", "ey", "ez", "d1", "d2", "d3")]
    )
    assert np.all(np.abs(accel.nominal - truth) <= accel.tolerance)
    status, again = _json(
        capsys,
        "passport",
        "triad",
        "--session",
        tmp_path / "run1.csv",
        "--session",
        tmp_path / "run2.csv",
    )
    assert status == 0 and again["passport_value"] == pytest.approx(
        rep["passport_value"], rel=1e-9, abs=1e-15
    )


def test_temperature_passport_carries_the_selected_model(tmp_path, capsys):
    status, rep = _json(
        capsys,
        "passport",
        "temperature",
        "--simulate",
        "--static-s",
        "8",
        "--out",
        tmp_path / "m.json",
        "--save-session",
        tmp_path / "chamber.csv",
    )
    assert status == 0 and rep["order"] == 4
    assert (
        rep["truth_max_errors"]["zero_error_after_g"]
        < 2e-4
        < rep["truth_max_errors"]["zero_error_before_g"]
    )
    assert (
        rep["truth_max_errors"]["scale_error_after"]
        < 5e-4
        < rep["truth_max_errors"]["scale_error_before"]
    )
    (accel,) = read_passport_json(tmp_path / "m.json").triads.values()
    assert accel.temperature.order == 4 and accel.temperature.reference_temp_c == 20.0
    # The same chamber read back from its CSV gives the same model.
    status, again = _json(capsys, "passport", "temperature", "--session", tmp_path / "chamber.csv")
    assert status == 0 and again["order"] == 4
    np.testing.assert_allclose(
        again["model"]["bias_coeffs"], rep["model"]["bias_coeffs"], rtol=1e-6, atol=1e-15
    )


def test_temperature_at_one_temperature_says_what_is_missing(tmp_path, capsys):
    assert (
        main(
            [
                "sixpos",
                "static",
                "--simulate",
                "--static-s",
                "6",
                "--save-session",
                str(tmp_path / "s.csv"),
                "--json",
            ]
        )
        == 0
    )
    capsys.readouterr()
    session = load_session(tmp_path / "s.csv").session
    write_csv_session(
        tmp_path / "t.csv",
        ImuSession(
            session.t_s, session.accel_mps2, session.gyro_rps, np.full(session.n_samples, 21.0)
        ),
        metadata={"gravity_mps2": 9.788},
    )
    status, _, err = _run(capsys, "passport", "temperature", "--session", tmp_path / "t.csv")
    assert status == 2 and "4 or more different temperatures, got 1" in err
    status, _, err = _run(
        capsys, "passport", "temperature", "--session", tmp_path / "s.csv", "--gravity", "9.788"
    )
    assert status == 2 and "no temperature column" in err


def test_sixpos_static_reports_terms_and_the_standard_gravity_shift(capsys):
    status, rep = _json(capsys, "sixpos", "static", "--simulate", "--static-s", "20")
    assert status == 0 and rep["n_positions"] == 6
    value, std, truth = (
        np.array(rep["accel"]["value"]),
        np.array(rep["accel"]["std"]),
        np.array(rep["truth"]["accel"]),
    )
    assert np.all(np.abs(value - truth) < 4.5 * std)
    np.testing.assert_allclose(
        rep["scale_error_shift_with_standard_gravity"], rep["expected_shift"], atol=1e-12
    )
    np.testing.assert_allclose(rep["expected_shift"], -0.0019, atol=1e-4)


def test_sixpos_static_on_a_session_missing_a_face(tmp_path, capsys):
    assert (
        main(
            [
                "sixpos",
                "static",
                "--simulate",
                "--static-s",
                "6",
                "--save-session",
                str(tmp_path / "s.csv"),
                "--json",
            ]
        )
        == 0
    )
    capsys.readouterr()
    s = load_session(tmp_path / "s.csv").session
    acc = s.accel_mps2.copy()
    acc[100:103, 1] = np.nan  # three broken samples inside the first position: dropped and counted
    write_csv_session(tmp_path / "broken.csv", ImuSession(s.t_s, acc, s.gyro_rps))
    status, rep = _json(
        capsys,
        "sixpos",
        "static",
        "--session",
        tmp_path / "broken.csv",
        "--latitude",
        "23.13",
        "--height",
        "20",
    )
    assert status == 0 and rep["n_positions"] == 6 and rep["gyro"]["earth_rate_removed"]
    assert rep["rejected_samples"] == {"non_finite": 3}
    cut = s.t_s < s.t_s[-1] - 8.0  # drop the last position (z down)
    write_csv_session(tmp_path / "five.csv", s.select(cut))
    status, _, err = _run(
        capsys, "sixpos", "static", "--session", tmp_path / "five.csv", "--latitude", "23.13"
    )
    assert status == 2 and "missing: -z up" in err
    status, _, err = _run(capsys, "sixpos", "static", "--session", tmp_path / "five.csv")
    assert status == 2 and "--latitude" in err


def test_sixpos_rate_simulate_and_a_wrong_axis(tmp_path, capsys):
    status, rep = _json(
        capsys,
        "sixpos",
        "rate",
        "--simulate",
        "--axis",
        "z",
        "--hold-s",
        "6",
        "--save-session",
        tmp_path / "r.csv",
    )
    assert status == 0 and rep["n_steps"] == 31
    assert abs(rep["scale_error"] - (rep["truth_slopes"][2] - 1)) < 4 * rep["scale_error_std"]
    status, again = _json(
        capsys, "sixpos", "rate", "--session", tmp_path / "r.csv", "--axis", "z", "--hold-s", "6"
    )
    assert status == 0 and again["scale_error"] == pytest.approx(rep["scale_error"], rel=1e-9)
    status, _, err = _run(
        capsys, "sixpos", "rate", "--session", tmp_path / "r.csv", "--axis", "x", "--hold-s", "6"
    )
    assert status == 2 and "constant-rate steps of gyro x" in err
