"""``ins-health calibrate`` and ``diagnose`` on session files, and the real Xsens session."""

import json

import numpy as np
import pytest
from real_data import XSENS, needs

from estimators.conventions import Triad
from estimators.sim import Fault, FaultKind, Grade, grade_error_model, multi_position_spec, simulate
from protocols.passport_codec import read_passport_json
from protocols.session_file import write_csv_session
from service.cli import main


@pytest.fixture(scope="module")
def unit_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("unit")
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    write_csv_session(d / "clean.csv", simulate(multi_position_spec(model=model), seed=30).session)
    assert (
        main(["calibrate", str(d / "clean.csv"), "--out", str(d / "pp.json"), "--latitude", "45"])
        == 0
    )
    tol = read_passport_json(d / "pp.json").triads[Triad.ACCEL].tolerance[4]
    fault = Fault(FaultKind.STEP, Triad.ACCEL, 4, 0.0, 5.0 * tol)
    write_csv_session(
        d / "faulty.csv",
        simulate(multi_position_spec(model=model, faults=(fault,)), seed=31).session,
    )
    return d


def _diagnose_json(capsys, *argv, status=0):
    """diagnose --json; exit 0 by default: everything that applies tested (the MEMS gyro of these
    sessions cannot see the Earth rate: its F0 and F1…F9 do not apply, the gross test ran)."""
    capsys.readouterr()
    assert main(["diagnose", *argv, "--json", "--latitude", "45"]) == status
    return json.loads(capsys.readouterr().out)


def test_calibrate_writes_a_passport_of_the_resolvable_triads(unit_files):
    passport = read_passport_json(unit_files / "pp.json")
    assert set(passport.triads) == {Triad.ACCEL}  # a MEMS gyro cannot see Ω
    assert passport.triads[Triad.ACCEL].provenance.n_positions == 18
    # The audit (on by default) finds nothing beyond white noise in a white-noise simulation.
    assert not passport.triads[Triad.ACCEL].bias_instability_std.any()


def test_diagnose_json_names_the_fault(unit_files, capsys):
    out = _diagnose_json(
        capsys, str(unit_files / "faulty.csv"), "--passport", str(unit_files / "pp.json"), status=1
    )
    assert len(out["positions"]) == 18
    accel = out["triads"]["accel"]
    assert len(accel["estimate"]["params"]) == len(accel["estimate"]["sigma"]) == 9
    assert [p["outcome"] for p in accel["predicates"]["predicates"]].count("fail") == 1
    # F1…F9 name it; the gross test sees |a| off g where y points up (its own tests: test_gross.py).
    named = [f for f in out["faults"] if f["predicate"] != "gross"]
    assert [(f["triad"], f["axis"], f["cause"]) for f in named] == [("accel", "y", "scale_factor")]
    assert {(f["triad"], f["axis"]) for f in out["faults"] if f["predicate"] == "gross"} <= {
        ("accel", "y")
    }
    assert set(named[0]) >= {
        "triad",
        "axis",
        "cause",
        "estimate",
        "nominal",
        "tolerance",
        "sigma",
    }


def test_diagnose_of_the_clean_session_has_no_fault(unit_files, capsys):
    out = _diagnose_json(
        capsys, str(unit_files / "clean.csv"), "--passport", str(unit_files / "pp.json")
    )
    assert out["faults"] == []


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        ("", "empty"),
        ("t,ax,ay\n0,1,2\n", "missing"),
        ("t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,x\n", "line 2"),
    ],
)
def test_unusable_input_exits_2_with_a_one_line_reason(
    unit_files, tmp_path, capsys, content, reason
):
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    capsys.readouterr()
    assert main(["diagnose", str(bad), "--passport", str(unit_files / "pp.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and reason in err.lower()


def test_saturated_samples_are_rejected_and_counted_given_the_full_scale(
    unit_files, tmp_path, capsys
):
    # A ±2 g accelerometer that sat on its rail for 25 samples inside the third position.
    full_scale = 2.0 * 9.80665
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    session = simulate(multi_position_spec(model=model), seed=32).session
    session.accel_mps2[5000:5025, 0] = full_scale
    write_csv_session(tmp_path / "railed.csv", session)
    args = (str(tmp_path / "railed.csv"), "--passport", str(unit_files / "pp.json"))
    out = _diagnose_json(capsys, *args, "--accel-range", str(full_scale))
    assert out["rejected_samples"] == {"saturated_accel": 25}
    assert len(out["positions"]) == 18 and out["faults"] == []
    assert _diagnose_json(capsys, *args)["rejected_samples"] == {}
    assert main(["diagnose", *args, "--accel-range", "-1"]) == 2
    assert "accel_limit_mps2 must be a positive full-scale range" in capsys.readouterr().err


def test_a_navigation_grade_gyro_calibrates_with_thresholds_from_its_own_noise(tmp_path, capsys):
    # Fixed MEMS thresholds would let the slow end of each turn into the positions, which a gyro
    # that resolves Ω sees; the session's own noise (or the stated one) sets them at 3× its spread.
    model = grade_error_model(Grade.NAVIGATION, rng=np.random.default_rng(4))
    res = simulate(multi_position_spec(model=model), seed=33)
    write_csv_session(tmp_path / "nav.csv", res.session)
    noise = {t: model.triad(t).find("white_noise").sample_sd(res.spec.rate_hz).max() for t in Triad}
    argv = ["calibrate", str(tmp_path / "nav.csv"), "--grade", "navigation", "--latitude", "45"]
    assert main([*argv, "--out", str(tmp_path / "default.json")]) == 0
    derived = read_passport_json(tmp_path / "default.json").triads[Triad.GYRO]
    assert derived.observable.all() and derived.provenance.n_positions == 18
    noise_args = ["--accel-noise", str(noise[Triad.ACCEL]), "--gyro-noise", str(noise[Triad.GYRO])]
    assert main([*argv, "--out", str(tmp_path / "nav.json"), *noise_args]) == 0
    gyro = read_passport_json(tmp_path / "nav.json").triads[Triad.GYRO]
    assert gyro.observable.all() and gyro.provenance.n_positions == 18
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "x.json"), "--gyro-noise", "0"]) == 2
    assert "--gyro-noise must be a positive noise level" in capsys.readouterr().err


def test_missing_passport_exits_2(unit_files, tmp_path, capsys):
    assert (
        main(["diagnose", str(unit_files / "clean.csv"), "--passport", str(tmp_path / "none.json")])
        == 2
    )
    assert "none.json" in capsys.readouterr().err


@needs(XSENS)
def test_xsens_session_calibrates_from_its_38_positions(tmp_path, capsys):
    # SOURCE.md: a ~50 s initial static interval and ~37 short positions.
    assert (
        main(["calibrate", str(XSENS), "--out", str(tmp_path / "xs.json"), "--json", "--no-audit"])
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert len(out["positions"]) == 38
    first = out["positions"][0]
    assert first["t_end_s"] - first["t_start_s"] > 40.0
    accel = out["triads"]["accel"]
    assert accel["estimate"]["verdict"] == "observable"
    # The residuals are reported; on this real unit they exceed the white-noise
    # prediction (χ²/dof ≫ 1) — what the model audit explains (docs/audit-xsens.md).
    assert len(accel["residuals"]) == 38
    assert accel["estimate"]["chi2_per_dof"] > 2.0
    assert out["triads"]["gyro"]["estimate"]["params"] is None
    assert set(read_passport_json(tmp_path / "xs.json").triads) == {Triad.ACCEL}


@needs(XSENS)
def test_audited_calibration_of_xsens_carries_the_bias_instability_that_explains_its_residuals(
    tmp_path, capsys
):
    # docs/audit-xsens.md: the white-noise model leaves χ²/dof ≈ 8.6; the audited wander brings it near 1.
    assert (
        main(
            [
                "calibrate",
                str(XSENS),
                "--out",
                str(tmp_path / "xs.json"),
                "--audit",
                "--replicas",
                "5",
                "--json",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["triads"]["accel"]["estimate"]["chi2_per_dof"] < 2.0
    tp = read_passport_json(tmp_path / "xs.json").triads[Triad.ACCEL]
    assert (
        tp.bias_instability_std.max() > 5e-5
    )  # ≈ 0.1 mg of wander on at least one axis (docs/audit-xsens.md)


def test_a_triad_whose_fit_leaves_the_physical_domain_is_suspect_not_no_fault(
    unit_files, tmp_path, capsys
):
    """The unit's accelerometer x gain halved (a fault far beyond the scheme's): its eighteen positions
    determine the parameters but the fit leaves the physical domain. diagnose said "no fault" with
    exit 0 when another triad was diagnosed, and blamed the noise; now SUSPECT, and F0's persistent
    failure is a FAULT: exit 1 (a fault outranks what could not be fitted)."""
    fault = Fault(FaultKind.STEP, Triad.ACCEL, 3, 0.0, -0.5)
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    path = tmp_path / "halved.csv"
    write_csv_session(
        path, simulate(multi_position_spec(model=model, faults=(fault,)), seed=31).session
    )
    capsys.readouterr()
    argv = ["diagnose", str(path), "--passport", str(unit_files / "pp.json"), "--latitude", "45"]
    assert main(argv) == 1
    text = capsys.readouterr().out
    assert "SUSPECT accel: its positions determine the nine parameters" in text
    assert "  FAULT F0: accel leaves the shell" in text and "mid-session" not in text
    assert "  no fault" not in text.splitlines()
    assert main([*argv, "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["triads"]["accel"]["suspect"] is True
    assert out["triads"]["accel"]["estimate"]["fit_left_domain"] is True


@needs(XSENS)
def test_a_swapped_xsens_pair_is_said_as_such_not_as_a_unit_to_declare(tmp_path, capsys):
    """The real pair given gyro file first: its 'accelerometer' looks like g. The advice was to
    declare --accel-unit g, which a raw-count pair refuses; now the files or the sidecar are named."""
    argv = ["calibrate", str(XSENS / "xsens_gyro.mat"), "--gyro-file", str(XSENS / "xsens_acc.mat")]
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "x.json"), "--no-audit"]) == 2
    err = capsys.readouterr().err
    assert "look like g, not m/s2" in err and "--accel-unit" not in err
    assert "the accelerometer and gyro files may be swapped" in err
    assert err.count("\n") == 1 and not (tmp_path / "x.json").exists()


def test_diagnose_f0_counts_rest_as_the_service_does_not_a_flights_manoeuvres(tmp_path, capsys):
    """A fault-free flight of the unit the passport was made of: F0 found 225 'static' samples out
    of the shell, because the chain's detector (thresholds from the session's own noise) took
    manoeuvres for rest; replay of the same flight tested 1901 and found none. F0 now uses the
    service's detector (thresholds raised to the passport's noise): none leaves the shell."""
    for argv in (
        ["simulate", "--out", tmp_path / "mp.csv", "--seed", "1"],
        ["calibrate", tmp_path / "mp.csv", "--out", tmp_path / "mp.json", "--no-audit"],
        [
            "simulate",
            "--out",
            tmp_path / "fl.csv",
            "--profile",
            "flight",
            "--duration-s",
            "300",
            "--seed",
            "1",
        ],
    ):
        assert main([str(a) for a in argv]) == 0
    capsys.readouterr()
    main(["diagnose", str(tmp_path / "fl.csv"), "--passport", str(tmp_path / "mp.json"), "--json"])
    f0 = json.loads(capsys.readouterr().out)["f0"]["accel"]
    assert f0["run"] and f0["tested"] > 1000 and f0["failed"] == 0


def test_the_verdict_is_headed_with_the_session_files_name(unit_files, capsys):
    """Issue 34: the faulty session's verdict was headed ``clean:``, the passport's unit id (the
    passport was calibrated from clean.csv): the header names the file diagnosed, then the unit."""
    capsys.readouterr()
    main(["diagnose", str(unit_files / "faulty.csv"), "--passport", str(unit_files / "pp.json")])
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("faulty.csv: 18 positions, against the passport of clean, g = ")


def test_diagnose_through_the_api_is_the_commands_diagnosis(unit_files, capsys):
    """``ins_health.diagnose`` gives what ``diagnose --json`` prints, as a value; nothing printed."""
    import ins_health

    argv = (str(unit_files / "faulty.csv"), "--passport", str(unit_files / "pp.json"))
    out = _diagnose_json(capsys, *argv, status=1)
    result = ins_health.diagnose(unit_files / "faulty.csv", unit_files / "pp.json", latitude=45)
    assert capsys.readouterr() == ("", "")
    assert result.exit_status == 1 and result.verdict == "fault"
    assert json.loads(json.dumps(result.to_dict())) == out
    assert out["session"] == "faulty.csv" and out["unit_id"] == "clean"


def test_every_step_of_calibrate_past_the_bound_is_named_on_stderr(
    unit_files, tmp_path, capsys, monkeypatch
):
    """Issue 34: calibrate and audit of the Xsens session said nothing for 15–23 s. A step still
    running after PROGRESS_AFTER_S is named with its time; with the bound at 0 every step is."""
    import service.cli

    monkeypatch.setattr(service.cli, "PROGRESS_AFTER_S", 0.0)
    capsys.readouterr()
    argv = [str(unit_files / "clean.csv"), "--out", str(tmp_path / "pp.json"), "--replicas", "5"]
    assert main(["calibrate", *argv, "--latitude", "45"]) == 0
    steps = [
        line.split(": ", 1)[1].rsplit(" (", 1)[0]
        for line in capsys.readouterr().err.splitlines()
        if line.startswith("ins-health calibrate: ") and line.endswith(" s)")
    ]
    assert steps == [
        "reading clean.csv",
        "static detection, positions and the fit",
        "the audit (5 replicas)",
        "the fit with the audited noise",
        "the passport's estimates",
        "the passport against its own session",
    ]
