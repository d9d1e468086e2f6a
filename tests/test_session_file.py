"""Session files: CSV round trip, the Xsens raw-count pair, and one-line errors for bad files."""

import os

import numpy as np
import pytest
from real_data import XSENS, needs
from scipy.optimize import least_squares

from estimators.session import ImuSession, SessionError, validate_session
from estimators.sim import CycleTemperature, Grade, multi_position_spec, simulate
from protocols.session_file import (
    SessionFileError,
    load_session,
    load_xsens_sidecar,
    read_csv_session,
    read_session,
    read_xsens_pair,
    write_csv_session,
)


def _write(tmp_path, text, name="s.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


# --- CSV ---------------------------------------------------------------------


def test_csv_round_trip_is_exact(tmp_path):
    res = simulate(
        multi_position_spec(
            grade=Grade.MEMS, static_s=3.0, n_positions=9, temperature=CycleTemperature()
        ),
        2,
    )
    p = write_csv_session(
        tmp_path / "a.csv",
        res.session,
        metadata={"gravity_mps2": res.truth.gravity_mps2, "seed": 2},
    )
    loaded = load_session(p)
    s = loaded.session
    for name in ("t_s", "accel_mps2", "gyro_rps", "temp_c"):
        np.testing.assert_array_equal(getattr(s, name), getattr(res.session, name))
    assert loaded.gravity_mps2 == res.truth.gravity_mps2
    assert loaded.metadata["seed"] == "2"
    assert os.listdir(tmp_path) == ["a.csv"]  # replaced atomically: no temporary left


def test_single_triad_file_round_trips_with_the_other_triad_absent(tmp_path):
    t = np.arange(5) * 0.01
    gyro = np.arange(15.0).reshape(5, 3) * 1e-3
    p = write_csv_session(tmp_path / "g.csv", ImuSession(t, None, gyro))
    assert p.read_text().splitlines()[1] == "t,gx,gy,gz"
    s = read_session(p)
    assert s.accel_mps2 is None and s.temp_c is None
    np.testing.assert_array_equal(s.gyro_rps, gyro)


def test_columns_in_any_order_with_comments_blank_lines_and_spaces(tmp_path):
    p = _write(
        tmp_path,
        "# a comment\n\n  temp , gz,gy,gx,az,ay,ax,t\n# inside\n20.5, 3e-3, 2e-3, 1e-3, 9.8, 0.2, 0.1, 0.0\n\n21,6e-3,5e-3,4e-3,9.7,0.5,0.4,0.01\n",
    )
    s = read_session(p)
    np.testing.assert_array_equal(s.t_s, [0.0, 0.01])
    np.testing.assert_array_equal(s.accel_mps2[1], [0.4, 0.5, 9.7])
    np.testing.assert_array_equal(s.gyro_rps[0], [1e-3, 2e-3, 3e-3])
    np.testing.assert_array_equal(s.temp_c, [20.5, 21.0])


def test_nan_and_inf_are_passed_to_validation_which_counts_them(tmp_path):
    p = _write(
        tmp_path,
        "t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0.01,nan,0,9.8,0,0,0\n0.02,0,0,9.8,inf,0,0\n0.03,0,0,9.8,0,0,-Inf\n0.04,0,0,9.8,0,0,0\n",
    )
    s = read_session(p)
    assert s.n_samples == 5  # the reader drops nothing
    out, rej = validate_session(s)
    assert rej.counts == {"non_finite": 3} and out.n_samples == 2


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", r"empty file \(no header row"),
        ("# only a comment\n\n", "empty file"),
        ("t,ax,ay,az,gx,gy,gz\n", r"no data rows after the header \(line 1\)"),
        ("t,ax,ay,gx,gy,gz\n0,0,0,0,0,0\n", r"line 1: missing column 'az'"),
        ("ax,ay,az\n0,0,9.8\n", r"line 1: missing column 't'"),
        (
            "t;ax;ay;az\n0;0;0;9,8\n",
            r"line 1: the header is separated by ';'; a session file is comma-separated",
        ),
        ("t\tax\tay\taz\n0\t0\t0\t9.8\n", r"line 1: the header is separated by tabs"),
        ("t,temp\n0,20\n", "missing columns ax,ay,az and gx,gy,gz"),
        ("t,ax,ay,az,tmp\n0,0,0,9.8,20\n", r"unknown column 'tmp'"),
        ("t,ax,ay,az,ax\n0,0,0,9.8,1\n", r"duplicate column 'ax'"),
        (
            "#c\nt,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0.01,0,0,9.8,abc,0,0\n",
            r"line 4, column 'gx': not a number: 'abc'",
        ),
        (
            "t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0.01,0,0,9.8,,0,0\n",
            r"line 3, column 'gx': not a number: ''",
        ),
        (
            "t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0.01,0,0,9.8,0,0\n",
            r"line 3: expected 7 fields \(t,ax,ay,az,gx,gy,gz\), got 6",
        ),
        ("t,ax,ay,az\n0,0,0,9.8\n0.01,0,0,9.8,1\n", r"line 3: expected 4 fields"),
        ("0.01 33000 33100 36000\n", "looks like one file of a raw-count pair"),
    ],
)
def test_bad_csv_files_give_a_one_line_error_naming_line_and_column(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(SessionFileError, match=match) as info:
        read_csv_session(p)
    msg = str(info.value)
    assert "\n" not in msg and str(p) in msg
    assert isinstance(info.value, ValueError) and isinstance(info.value, SessionError)


def test_binary_and_missing_files_are_clear_errors(tmp_path):
    p = tmp_path / "b.csv"
    p.write_bytes(b"\xff\xfe\x00\x01binary")
    with pytest.raises(SessionFileError, match="not a text file"):
        read_session(p)
    with pytest.raises(FileNotFoundError, match="no such session file"):
        read_session(tmp_path / "missing.csv")


def test_bad_gravity_comment_is_an_error(tmp_path):
    p = _write(tmp_path, "# gravity_mps2 = heavy\nt,ax,ay,az\n0,0,0,9.8\n")
    with pytest.raises(SessionFileError, match="gravity_mps2 is not a number"):
        load_session(p)


# --- Xsens raw-count pair ---------------------------------------------------------


def _pair(tmp_path, acc_rows, gyr_rows):
    d = tmp_path / "pair"
    d.mkdir()
    (d / "unit_acc.txt.dat").write_text("".join(" ".join(map(str, r)) + "\n" for r in acc_rows))
    (d / "unit_gyro.dat").write_text("".join(" ".join(map(str, r)) + "\n" for r in gyr_rows))
    return d, d / "unit_acc.txt.dat", d / "unit_gyro.dat"


def test_raw_counts_become_si_with_the_sidecar(tmp_path):
    nominal = load_xsens_sidecar()
    acc_rows = [(0.01, 32768, 32768 + 4060, 32768), (0.02, 32769, 32768, 32768 - 4060)]
    gyr_rows = [(0.01, 32768 + 6258, 32768, 32768), (0.02, 32768, 32768, 32768)]
    d, a, g = _pair(tmp_path, acc_rows, gyr_rows)
    loaded = read_xsens_pair(a, g)
    s = loaded.session
    np.testing.assert_allclose(s.accel_mps2[0], [0.0, 9.81744, 0.0], rtol=1e-4)
    np.testing.assert_allclose(s.accel_mps2[1, 2], -9.81744, rtol=1e-4)
    np.testing.assert_allclose(s.gyro_rps[0], [1.0, 0.0, 0.0], rtol=1e-12)
    assert loaded.gravity_mps2 == nominal.gravity_mps2 == 9.81744
    # A directory finds its pair; a sidecar in it overrides the default.
    np.testing.assert_array_equal(read_session(d).accel_mps2, s.accel_mps2)
    (d / "unit.toml").write_text(
        'format = "ins-health/xsens-nominal"\nversion = 1\n'
        "[accel]\noffset_counts = 32768\nscale_si_per_count = 1e-3\n[gyro]\noffset_counts = 0\nscale_si_per_count = 1.0\n"
    )
    other = load_session(d)
    np.testing.assert_allclose(other.session.accel_mps2[0], [0.0, 4.06, 0.0])
    np.testing.assert_allclose(other.session.gyro_rps[1], [32768.0] * 3)
    assert other.gravity_mps2 is None


@pytest.mark.parametrize(
    ("gyr_rows", "match"),
    [
        ([(0.01, 1, 2, 3)], "has 2 samples but .* has 1: not a pair"),
        ([(0.01, 1, 2, 3), (0.03, 1, 2, 3)], r"time stamps differ at sample 2 \(0.02 vs 0.03\)"),
        ([(0.01, 1, 2, 3), (0.02, 1, "x", 3)], r"line 2, column 'y': not a number: 'x'"),
        ([(0.01, 1, 2, 3), (0.02, 1, 2)], r"line 2: expected 4 fields \(time_s,x,y,z\), got 3"),
    ],
)
def test_bad_raw_count_pairs_are_clear_errors(tmp_path, gyr_rows, match):
    _, a, g = _pair(tmp_path, [(0.01, 1, 2, 3), (0.02, 1, 2, 3)], gyr_rows)
    with pytest.raises(SessionFileError, match=match):
        read_xsens_pair(a, g)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('format = "ins-health/xsens-nominal"\nversion = 2\n', "unknown sidecar version 2"),
        ('format = "other"\nversion = 1\n', "format must be 'ins-health/xsens-nominal'"),
        (
            'format = "ins-health/xsens-nominal"\nversion = 1\n[accel]\noffset_counts = 0\n',
            r"needs a \[accel\] table",
        ),
        (
            'format = "ins-health/xsens-nominal"\nversion = 1\n[accel]\noffset_counts = 0\nscale_si_per_count = 0\n'
            "[gyro]\noffset_counts = 0\nscale_si_per_count = 1\n",
            "must not be zero",
        ),
        ("version = [", "not valid TOML"),
    ],
)
def test_bad_sidecars_are_typed_errors(tmp_path, text, match):
    p = _write(tmp_path, text, "s.toml")
    with pytest.raises(SessionFileError, match=match):
        load_xsens_sidecar(p)


def test_a_directory_without_a_single_pair_is_an_error(tmp_path):
    (tmp_path / "a_acc.mat").write_text("0 1 2 3\n")
    with pytest.raises(SessionFileError, match="expected one accelerometer file"):
        read_session(tmp_path)


@needs(XSENS)
def test_the_measured_xsens_session_reads_with_nominal_scales_within_a_few_percent():
    loaded = load_session(XSENS)
    s = loaded.session
    assert s.n_samples == 51175 and loaded.gravity_mps2 == 9.81744
    assert np.all(np.diff(s.t_s) > 0) and 99.0 < s.rate_hz < 101.0
    # Half-second windows with a quiet gyro are static; a sphere fit of their
    # accelerometer means (free centre = the zero signals) has radius g when the
    # nominal scale is right. The calibration finds the rest; a few % is the claim.
    w = 50
    n = s.n_samples // w
    acc = s.accel_mps2[: n * w].reshape(n, w, 3)
    quiet = np.linalg.norm(s.gyro_rps[: n * w].reshape(n, w, 3).std(axis=1), axis=1) < 0.01
    means = acc[quiet].mean(axis=1)
    assert quiet.sum() > 300
    fit = least_squares(lambda p: np.linalg.norm(means - p[:3], axis=1) - p[3], [0, 0, 0, 9.8])
    assert abs(fit.x[3] / loaded.gravity_mps2 - 1) < 0.03
    # Static gyro output is small against the ±300 °/s range (its zero signals).
    assert np.abs(s.gyro_rps[:3000].mean(axis=0)).max() < 0.1


def test_the_header_sniffers_lines_are_splitlines_ones_read_a_chunk_at_a_time():
    # The sniffers read a session's first lines without splitting its thousands of others: the
    # lines they see are str.splitlines()'s, whichever line ending straddles a chunk's end.
    from protocols.session_file import _head_lines

    rng = np.random.default_rng(5)
    pieces = ["1.5,2,3", "# ax", " ", "\r", "\n", "\r\n", "\x0c", "\u2028", "x" * 3000]
    for _ in range(60):
        text = "".join(rng.choice(pieces, size=rng.integers(0, 1000)))
        assert list(_head_lines(text)) == text.splitlines()
