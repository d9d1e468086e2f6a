"""The unit options on the method commands that read sessions (``passport tilt|triad|temperature``,
``rocking --log``, ``publish``): a session in other units is read the same once declared, and a
wrong declaration is refused with one line naming the unit the values look like (issue 11)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2
from protocols.session_file import read_session, write_csv_session
from service.cli import main


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def _rewrite(src: Path, dst: Path, *, accel_per_si: float = 1.0, gyro_per_si: float = 1.0) -> Path:
    """``src`` with its columns scaled into other units (the file's own comment lines dropped)."""
    s = read_session(src)
    scaled = type(s)(
        t_s=s.t_s,
        accel_mps2=None if s.accel_mps2 is None else s.accel_mps2 * accel_per_si,
        gyro_rps=None if s.gyro_rps is None else s.gyro_rps * gyro_per_si,
        temp_c=s.temp_c,
    )
    write_csv_session(dst, scaled)
    return dst


def _sessions(paths: list[Path]) -> list[str]:
    return [arg for p in paths for arg in ("--session", str(p))]


@pytest.fixture(scope="module")
def triad_runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    folder = tmp_path_factory.mktemp("triad")
    assert (
        main(["passport", "triad", "--simulate", "--runs", "2", "--save-sessions", str(folder)])
        == 0
    )
    return sorted(folder.glob("run*.csv"))


def test_passport_triad_reads_a_session_in_g_once_declared(triad_runs, tmp_path, capsys):
    capsys.readouterr()
    args = ["--latitude", "45", "--json"]
    si = ["passport", "triad", *_sessions(triad_runs), *args]
    status, out_si, _ = _cli(capsys, *si)
    assert status == 0
    in_g = [
        _rewrite(p, tmp_path / p.name, accel_per_si=1.0 / STANDARD_GRAVITY_MPS2) for p in triad_runs
    ]
    g_args = _sessions(in_g)
    status, _, err = _cli(capsys, "passport", "triad", *g_args, *args)
    assert status == 2
    assert err.count("\n") == 1
    assert "units: the accelerometer values look like g, not m/s2" in err, err
    status, out_g, _ = _cli(capsys, "passport", "triad", *g_args, "--accel-unit", "g", *args)
    assert status == 0
    a, b = json.loads(out_si)["passport_value"], json.loads(out_g)["passport_value"]
    np.testing.assert_allclose(list(b.values()), list(a.values()), rtol=1e-6, atol=1e-12)


@pytest.fixture(scope="module")
def rocking_record(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rocking") / "rocking.csv"
    assert main(["rocking", "--simulate", "--save-csv", str(path)]) == 0
    return path


def test_rocking_reads_gyros_in_deg_s_once_declared(rocking_record, tmp_path, capsys):
    capsys.readouterr()
    status, out_si, _ = _cli(capsys, "rocking", "--log", str(rocking_record), "--json")
    assert status == 0
    in_dps = _rewrite(rocking_record, tmp_path / "dps.csv", gyro_per_si=float(np.degrees(1.0)))
    status, _, err = _cli(capsys, "rocking", "--log", str(in_dps), "--json")
    assert status == 2 and err.count("\n") == 1
    assert "units: the gyro values look like deg/s, not rad/s" in err, err
    status, out_dps, _ = _cli(
        capsys, "rocking", "--log", str(in_dps), "--gyro-unit", "deg/s", "--json"
    )
    assert status == 0
    a, b = json.loads(out_si)["dK"], json.loads(out_dps)["dK"]
    np.testing.assert_allclose(b, a, rtol=1e-6)


def test_passport_temperature_and_publish_refuse_a_session_in_g(triad_runs, tmp_path, capsys):
    in_g = _rewrite(triad_runs[0], tmp_path / "g.csv", accel_per_si=1.0 / STANDARD_GRAVITY_MPS2)
    capsys.readouterr()
    for argv in (
        ["passport", "temperature", "--session", str(in_g)],
        # Refused before any router is contacted: none runs here.
        ["publish", str(in_g), "--vehicle", "v1", "--router", "tcp/127.0.0.1:9"],
    ):
        status, _, err = _cli(capsys, *argv)
        assert status == 2 and err.count("\n") == 1, (argv, err)
        assert "units: the accelerometer values look like g, not m/s2" in err, (argv, err)
