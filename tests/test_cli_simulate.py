"""``ins-health simulate`` end to end: write, read back, compare with the library."""

import json
import re

import numpy as np
import pytest

from estimators.conventions import PARAM_NAMES
from estimators.sim import Fly, Grade, flight_spec, multi_position_spec, simulate, static_spec
from protocols.session_file import load_session
from service.cli import main


def _run(capsys, *argv):
    status = main(["simulate", *map(str, argv)])
    return status, capsys.readouterr().err


def test_default_run_writes_the_library_session_and_a_one_line_summary(tmp_path, capsys):
    out = tmp_path / "s.csv"
    status, err = _run(capsys, "--out", out, "--static-s", 5, "--seed", 3)
    assert status == 0
    assert err.count("\n") == 1 and "simulate: wrote" in err and "18 static interval(s)" in err
    loaded = load_session(out)
    ref = simulate(multi_position_spec(grade=Grade.MEMS, static_s=5.0), 3)
    np.testing.assert_array_equal(loaded.session.t_s, ref.session.t_s)
    np.testing.assert_array_equal(loaded.session.accel_mps2, ref.session.accel_mps2)
    np.testing.assert_array_equal(loaded.session.gyro_rps, ref.session.gyro_rps)
    assert loaded.session.temp_c is None
    assert loaded.gravity_mps2 == ref.truth.gravity_mps2
    assert loaded.metadata["grade"] == "consumer_mems" and loaded.metadata["seed"] == "3"


def test_config_file_with_temperature_faults_and_effects_and_command_line_override(
    tmp_path, capsys
):
    cfg = tmp_path / "sim.toml"
    cfg.write_text(
        """
seed = 1
grade = "navigation"
rate_hz = 50.0
gravity_mps2 = 9.81

[profile]
kind = "multiposition"
positions = 10
static_s = 6.0
transition_s = 2.0

[temperature]
kind = "cycle"
base_c = 15.0
peak_c = 35.0
period_s = 40.0

[[faults]]
kind = "step"
triad = "accel"
index = "ey"
t_start_s = 30.0
magnitude = 0.002

[[effects]]
name = "temperature_bias"
triad = "accel"
coef_si_per_c = [1e-4, 0.0, 0.0]
t_ref_c = 25.0

[[effects]]
name = "gravity_mismatch"
delta_mps2 = 0.002
"""
    )
    out, truth_path = tmp_path / "s.csv", tmp_path / "truth.json"
    status, err = _run(
        capsys,
        "--out",
        out,
        "--config",
        cfg,
        "--truth",
        truth_path,
        "--seed",
        5,
        "--fault",
        "stuck:gyro:z:40:0:5",
    )
    assert status == 0, err
    s = load_session(out).session
    assert s.temp_c is not None and 14.9 < s.temp_c.min() and s.temp_c.max() < 35.1
    assert s.rate_hz == pytest.approx(50.0)
    truth = json.loads(truth_path.read_text())
    assert truth["seed"] == 5  # the command line wins over the file
    assert truth["gravity_mps2"] == 9.81 and truth["gravity_true_mps2"] == pytest.approx(9.812)
    assert [f["kind"] for f in truth["faults"]] == ["step", "stuck"]
    assert truth["faults"][0]["target"] == "ey" and truth["faults"][1]["duration_s"] == 5.0
    assert list(truth["accel_params"]) == list(PARAM_NAMES)
    assert "temperature_bias" in truth["effects"]["accel"] and truth["effects"]["environment"] == [
        "gravity_mismatch"
    ]
    assert len(truth["static_intervals_s"]) == 10
    # The stuck gyro axis is constant from 40 s for 5 s, and only there.
    z = s.gyro_rps[:, 2]
    inside = (s.t_s >= 40.0) & (s.t_s < 45.0)
    assert np.ptp(z[inside]) == 0.0 and np.ptp(z[~inside & (s.t_s > 45.0)]) > 0.0


@pytest.mark.parametrize(
    ("args", "library"),
    [
        (
            ["--profile", "static", "--duration-s", 12, "--grade", "navigation"],
            lambda: static_spec(duration_s=12.0, grade=Grade.NAVIGATION),
        ),
        (
            ["--profile", "flight", "--duration-s", 20, "--rest-s", 3],
            lambda: flight_spec(fly=Fly(20.0), rest_s=3.0),
        ),
    ],
    ids=["static", "flight"],
)
def test_other_profiles(tmp_path, capsys, args, library):
    out = tmp_path / "p.csv"
    status, err = _run(capsys, "--out", out, "--seed", 2, *args)
    assert status == 0, err
    s = load_session(out).session
    ref = simulate(library(), 2).session
    np.testing.assert_array_equal(s.accel_mps2, ref.accel_mps2)
    np.testing.assert_array_equal(s.gyro_rps, ref.gyro_rps)


def test_random_errors_draw_from_the_grade(tmp_path, capsys):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for path, seed in ((a, 1), (b, 2)):
        status, err = _run(
            capsys,
            "--out",
            tmp_path / "x.csv",
            "--static-s",
            2,
            "--positions",
            9,
            "--random-errors",
            "--seed",
            seed,
            "--truth",
            path,
        )
        assert status == 0, err
    assert json.loads(a.read_text())["accel_params"] != json.loads(b.read_text())["accel_params"]


@pytest.mark.parametrize(
    ("argv", "config", "match"),
    [
        (["--fault", "step:accel:bx:10"], None, r"--fault step:accel:bx:10: expected KIND:TRIAD"),
        (["--fault", "tilt:accel:bx:10:1"], None, "fault kind must be one of"),
        (["--fault", "step:accel:q9:10:1"], None, "fault index for step must be 0-8"),
        (["--fault", "stuck:gyro:x:10:1:-1"], None, "duration_s must be positive"),
        (["--temperature", "sauna"], None, "temperature kind must be one of"),
        (
            ["--temperature", "cycle:peak=40"],
            None,
            "temperature cycle: .*unexpected keyword argument 'peak'",
        ),
        (["--positions", 19], None, "1 to 18 positions"),
        ([], "grade = 'consumer'\n", "grade must be one of"),
        ([], "[[effects]]\nname = 'magic'\ntriad = 'accel'\n", "unknown effect 'magic'"),
        ([], "[[effects]]\nname = 'bias'\n", "effect bias triad must be one of"),
        (
            [],
            "[[effects]]\nname = 'g_sensitivity'\ntriad = 'accel'\n",
            "does not apply to the accel triad",
        ),
        ([], "[profile]\nkind = 'orbit'\n", "profile kind must be one of"),
        (
            ["--profile", "flight", "--rest-s", "0"],
            None,
            r"--rest-s \(setting rest_s\) must be a positive finite number, got 0.0",
        ),
        (
            ["--rate-hz", "nan"],
            None,
            r"--rate-hz \(setting rate_hz\) must be a positive finite number",
        ),
        (
            [],
            "[profile]\nstatic_s = -1\n",
            r"--static-s \(setting static_s\) must be a positive finite number",
        ),
        (
            [],
            "[profile]\nkind = 'flight'\nrest_s = 'ten'\n",
            r"--rest-s \(setting rest_s\) must be a positive finite number, got 'ten'",
        ),
        (
            [],
            "[profile]\nkind = 'flight'\nrest_s = [1, 2]\n",
            r"--rest-s \(setting rest_s\) must be",
        ),
        ([], "[profile]\nkind = 'flight'\nrest_s = true\n", r"--rest-s \(setting rest_s\) must be"),
        ([], "seed = [\n", "not valid TOML"),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, argv, config, match):
    args = ["--out", tmp_path / "x.csv", *argv]
    if config is not None:
        cfg = tmp_path / "c.toml"
        cfg.write_text(config)
        args += ["--config", cfg]
    status, err = _run(capsys, *args)
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("ins-health simulate: ")
    assert re.search(match, err), err
    assert not (tmp_path / "x.csv").exists()


def test_one_grade_vocabulary_and_the_earlier_spelling_taken_with_a_note(tmp_path, capsys):
    """Issue 34: three vocabularies for one idea (simulate {mems, navigation}, calibrate {mems,
    tactical, navigation}, replay {consumer_mems, …}). Every command takes the sensor classes;
    ``mems`` is still taken, as consumer_mems, and said."""
    out = tmp_path / "s.csv"
    assert _run(capsys, "--out", out, "--static-s", 5, "--grade", "consumer_mems")[0] == 0
    same = tmp_path / "same.csv"
    status, err = _run(capsys, "--out", same, "--static-s", 5, "--grade", "mems")
    assert status == 0 and "--grade mems is spelled consumer_mems now" in err
    assert load_session(same).metadata["grade"] == "consumer_mems"
    assert same.read_text() == out.read_text()
    cal = ["calibrate", str(out), "--no-audit"]
    assert main([*cal, "--out", str(tmp_path / "i.json"), "--grade", "industrial_mems"]) == 0
    assert main([*cal, "--out", str(tmp_path / "m.json"), "--grade", "mems"]) == 0
    # Both MEMS classes take the MEMS tolerance floors, as 'mems' did.
    assert (tmp_path / "i.json").read_text() == (tmp_path / "m.json").read_text()
