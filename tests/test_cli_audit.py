"""``ins-health audit``: the JSON it prints, its options and its answers to unusable input."""

import json

import numpy as np
import pytest

from estimators.audit import CANDIDATE_NAMES
from estimators.audit.hidden import GRAVITY_MPS2, baseline_model, hide, session_of
from estimators.conventions import Triad
from protocols.session_file import write_csv_session
from service.cli import main


@pytest.fixture(scope="module")
def drift_csv(tmp_path_factory):
    """A trial session with an obvious accelerometer drift on y (12 detection standard errors)."""
    seed = 5200
    h = hide(seed, "bias_drift", Triad.ACCEL, "y", 12.0)
    path = tmp_path_factory.mktemp("audit") / "drift.csv"
    write_csv_session(path, session_of(h.model, seed)[0])
    return path


def test_json_has_the_issue_keys_and_names_the_hidden_drift(drift_csv, capsys):
    assert (
        main(
            [
                "audit",
                str(drift_csv),
                "--gravity",
                str(GRAVITY_MPS2),
                "--json",
                "--replicas",
                "5",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert {"baseline", "candidates", "named_causes", "extended", "gain"} <= set(out)
    assert out["replicas"] == 5
    for block in ("baseline", "extended"):
        assert out[block]["headline"] == "chi2_per_dof" and np.isfinite(out[block]["ratio"])
        assert all(
            {"statistic", "triad", "axis", "measured", "ratio", "tail_prob"} <= set(s)
            for s in out[block]["statistics"]
        )
    assert all(
        {"effect", "triad", "axis", "score", "selected"} <= set(c) for c in out["candidates"]
    )
    assert {c["effect"] for c in out["candidates"]} == set(CANDIDATE_NAMES)
    assert [(c["effect"], c["triad"], c["axis"]) for c in out["named_causes"]] == [
        ("bias_drift", "accel", "y")
    ]
    assert out["named_causes"][0]["evidence"]
    assert [e["effect"] for e in out["extended"]["effects_added"]] == ["bias_drift"]
    assert {
        "heldout_chi2_baseline",
        "heldout_chi2_extended",
        "f0_false_alarm_rate_baseline",
        "f0_false_alarm_rate_extended",
    } <= set(out["gain"])


def test_the_seed_makes_the_replicas_reproducible(drift_csv, capsys):
    runs = []
    for _ in range(2):
        assert (
            main(
                [
                    "audit",
                    str(drift_csv),
                    "--gravity",
                    str(GRAVITY_MPS2),
                    "--json",
                    "--replicas",
                    "5",
                    "--seed",
                    "9",
                ]
            )
            == 0
        )
        runs.append(json.loads(capsys.readouterr().out)["baseline"]["statistics"])
    assert runs[0] == runs[1]


def test_text_output_names_the_cause_in_one_line(drift_csv, capsys):
    assert main(["audit", str(drift_csv), "--gravity", str(GRAVITY_MPS2), "--replicas", "5"]) == 0
    out = capsys.readouterr().out
    assert "5 replicas" in out and "CAUSE bias_drift accel y" in out


def test_too_few_replicas_is_a_usage_error(drift_csv, capsys):
    assert main(["audit", str(drift_csv), "--replicas", "2"]) == 2
    assert "--replicas must be at least 5, got 2" in capsys.readouterr().err


def test_a_missing_or_empty_file_is_a_one_line_error(tmp_path, capsys):
    assert main(["audit", str(tmp_path / "nope.csv")]) == 2
    assert "nope.csv" in capsys.readouterr().err
    (tmp_path / "empty.csv").write_text("t,ax,ay,az,gx,gy,gz\n")
    assert main(["audit", str(tmp_path / "empty.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ins-health audit:") and err.count("\n") == 1


def test_an_effect_free_session_names_nothing(tmp_path, capsys):
    write_csv_session(
        tmp_path / "clean.csv", session_of(baseline_model(np.random.default_rng(7001)), 7001)[0]
    )
    assert (
        main(
            [
                "audit",
                str(tmp_path / "clean.csv"),
                "--gravity",
                str(GRAVITY_MPS2),
                "--json",
                "--replicas",
                "5",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["named_causes"] == [] and out["extended"]["effects_added"] == []
    assert out["extended"]["ratio"] == out["baseline"]["ratio"]
