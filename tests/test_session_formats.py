"""Files as real users' tools write them (issue 30, item 6): an Arduino logger's metadata lines and
raw counts without a time column, a space-separated table with a ``#`` header and extra columns,
and a EuRoC file re-saved by a spreadsheet (E-notation stamps, junk rows at the end).

Each file is written here from a simulated session the way its tool writes it; the oracle is the
same session read from our own CSV format: the samples agree to the precision the file holds, and
what the reader did beyond reading is said with its count.
"""

from __future__ import annotations

import numpy as np
import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2
from estimators.sim import Grade, multi_position_spec, simulate
from protocols.session_file import SessionFileError, SessionUnits, load_session
from service.cli import main
from tests.real_data import MPU6050_SESSION, needs

ACCEL_COUNTS_PER_G = 16384.0
GYRO_COUNTS_PER_DPS = 131.0
MPU_SCALES = ["--accel-scale", "1/16384", "--accel-unit", "g", "--gyro-scale", "1/131"]
MPU_SCALES += ["--gyro-unit", "deg/s"]


@pytest.fixture(scope="module")
def simulated():
    return simulate(multi_position_spec(grade=Grade.MEMS, static_s=3.0, n_positions=12), 7)


def _counts(session):
    a = np.round(session.accel_mps2 / STANDARD_GRAVITY_MPS2 * ACCEL_COUNTS_PER_G).astype(int)
    w = np.round(np.degrees(session.gyro_rps) * GYRO_COUNTS_PER_DPS).astype(int)
    return a, w


def _arduino_file(tmp_path, session, rate_hz):
    """The MPU-6050 logger's layout (``../shared/data/field/mpu6050-multiposition``)."""
    a, w = _counts(session)
    lines = [f"Fs,{rate_hz:g}", "Logging Type,0", "Initialization time,36.5", "Waiting time,3"]
    lines.append("ax,ay,az,gx,gy,gz")
    lines += [",".join(map(str, [*ai, *wi])) for ai, wi in zip(a, w, strict=True)]
    path = tmp_path / "arduino.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_metadata_lines_a_rate_and_stated_scales_read_an_arduino_loggers_raw_counts(
    tmp_path, simulated
):
    """The metadata lines are read and said, Fs gives sample k the time k/Fs, and the counts times
    the stated scales are the samples to half a count."""
    s = simulated.session
    rate_hz = 1.0 / float(np.median(np.diff(s.t_s)))
    path = _arduino_file(tmp_path, s, rate_hz)
    units = SessionUnits("g", "deg/s", None, "1/16384", "1/131")
    loaded = load_session(path, units=units)
    half_count_mps2 = 0.5 * STANDARD_GRAVITY_MPS2 / ACCEL_COUNTS_PER_G
    half_count_rps = 0.5 * np.radians(1.0 / GYRO_COUNTS_PER_DPS)
    assert np.max(np.abs(loaded.session.accel_mps2 - s.accel_mps2)) <= half_count_mps2 * 1.0001
    assert np.max(np.abs(loaded.session.gyro_rps - s.gyro_rps)) <= half_count_rps * 1.0001
    np.testing.assert_allclose(loaded.session.t_s, np.arange(s.t_s.size) / rate_hz)
    assert loaded.metadata["Fs"] == f"{rate_hz:g}" and loaded.metadata["Waiting time"] == "3"
    said = "\n".join(loaded.notes)
    assert "4 metadata line(s) before the header read: Fs=" in said
    assert f"no time column: time from Fs={rate_hz:g} Hz" in said


def test_the_arduino_file_resaved_by_a_spreadsheet_keeps_its_metadata_lines(tmp_path, simulated):
    """A spreadsheet saves every row as wide as the widest, its metadata lines too (``Fs,100,,,,``):
    still metadata, read as before, not a header ("unknown column 'fs'")."""
    s = simulated.session
    rate_hz = 1.0 / float(np.median(np.diff(s.t_s)))
    path = _arduino_file(tmp_path, s, rate_hz)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([line + ",,,," for line in lines[:4]] + lines[4:]) + "\n")
    loaded = load_session(path, units=SessionUnits("g", "deg/s", None, "1/16384", "1/131"))
    np.testing.assert_allclose(loaded.session.t_s, np.arange(s.t_s.size) / rate_hz)
    assert loaded.metadata["Fs"] == f"{rate_hz:g}" and loaded.metadata["Waiting time"] == "3"
    assert "4 metadata line(s) before the header read: Fs=" in "\n".join(loaded.notes)


def test_a_declared_time_unit_does_not_scale_the_time_a_rate_gives(tmp_path, simulated):
    """The time made from Fs is in seconds (the rate is in Hz): a --time-unit given for every file
    of a batch is said not to apply, not applied (it made the 100 Hz file a 100 kHz one)."""
    s = simulated.session
    rate_hz = 1.0 / float(np.median(np.diff(s.t_s)))
    path = _arduino_file(tmp_path, s, rate_hz)
    loaded = load_session(path, units=SessionUnits("g", "deg/s", "ms", "1/16384", "1/131"))
    np.testing.assert_allclose(loaded.session.t_s, np.arange(s.t_s.size) / rate_hz)
    assert loaded.units.time == "s"
    assert "the declared time unit ms is not used" in "\n".join(loaded.notes)


def test_raw_counts_without_a_scale_are_refused_naming_what_is_missing(tmp_path, simulated):
    path = _arduino_file(tmp_path, simulated.session, 100.0)
    with pytest.raises(SessionFileError, match=r"raw counts.*missing: --accel-scale.*--gyro-scale"):
        load_session(path)
    with pytest.raises(
        SessionFileError, match=r"gyro values are whole numbers.*missing: --gyro-scale"
    ):
        load_session(path, units=SessionUnits(accel="g", accel_scale="1/16384"))


def test_a_sidecar_states_the_scales_the_file_does_not(tmp_path, simulated):
    path = _arduino_file(tmp_path, simulated.session, 100.0)
    sidecar = tmp_path / "mpu.toml"
    sidecar.write_text(
        'accel_unit = "g"\naccel_scale = "1/16384"\ngyro_unit = "deg/s"\ngyro_scale = "1/131"\n'
    )
    by_options = load_session(path, units=SessionUnits("g", "deg/s", None, 1 / 16384, 1 / 131))
    by_sidecar = load_session(path, sidecar=sidecar)
    np.testing.assert_array_equal(by_sidecar.session.accel_mps2, by_options.session.accel_mps2)
    np.testing.assert_array_equal(by_sidecar.session.gyro_rps, by_options.session.gyro_rps)
    sidecar.write_text("accel_scal = 1\n")
    with pytest.raises(SessionFileError, match="unknown sidecar key"):
        load_session(path, sidecar=sidecar)


def test_a_file_without_time_column_nor_rate_is_refused_naming_both(tmp_path):
    path = tmp_path / "no_time.csv"
    path.write_text("ax,ay,az\n0,0,9.8\n")
    with pytest.raises(SessionFileError, match=r"missing column 't'.*no rate line \(fs"):
        load_session(path)


def test_a_rate_line_the_time_column_contradicts_is_said(tmp_path, simulated):
    """A file with both: the time column is the time; a stated rate it contradicts (a logger's
    header left at its default) is said, not silently passed over."""
    s = simulated.session
    rate_hz = 1.0 / float(np.median(np.diff(s.t_s)))
    rows = [
        ",".join(repr(float(v)) for v in (t, *a, *w))
        for t, a, w in zip(s.t_s, s.accel_mps2, s.gyro_rps, strict=True)
    ]
    path = tmp_path / "both.csv"
    path.write_text("\n".join([f"Fs,{rate_hz / 2:g}", "t,ax,ay,az,gx,gy,gz", *rows]) + "\n")
    loaded = load_session(path)
    np.testing.assert_array_equal(loaded.session.t_s, s.t_s)
    said = "\n".join(loaded.notes)
    assert (
        f"Fs={rate_hz / 2:g} Hz stated, but the time column's median step is a rate of {rate_hz:.4g} Hz"
        in said
    )
    path.write_text("\n".join([f"Fs,{rate_hz:g}", "t,ax,ay,az,gx,gy,gz", *rows]) + "\n")
    assert "time column" not in "\n".join(load_session(path).notes)


def test_a_space_separated_table_with_a_hash_header_reads_its_columns_and_says_the_others(
    tmp_path, simulated
):
    """TUM-style: ``t`` names the translational acceleration, ``w`` the rate; the magnetometer and
    quaternion columns are not read, and said."""
    s = simulated.session
    path = tmp_path / "imu.txt"
    rows = [
        " ".join(repr(float(v)) for v in (t, *a, *w, 0.2, -0.1, 0.4, 1.0, 0.0, 0.0, 0.0))
        for t, a, w in zip(s.t_s, s.accel_mps2, s.gyro_rps, strict=True)
    ]
    header = "# time tx ty tz wx wy wz mx my mz qw qx qy qz"
    path.write_text("\n".join([header, *rows]) + "\n")
    loaded = load_session(path)
    np.testing.assert_array_equal(loaded.session.accel_mps2, s.accel_mps2)
    np.testing.assert_array_equal(loaded.session.gyro_rps, s.gyro_rps)
    np.testing.assert_array_equal(loaded.session.t_s, s.t_s)
    assert "7 column(s) not read: mx my mz qw qx qy qz" in loaded.notes
    assert loaded.metadata["format"].startswith("whitespace-separated table")


@pytest.mark.parametrize(
    "rate_line", ["# rate_hz 100", "# rate_hz = 100", "Fs 100"], ids=["comment", "key=", "line"]
)
def test_a_space_separated_table_without_time_takes_its_time_from_a_rate_line(
    tmp_path, simulated, rate_line
):
    """As a comma-separated file: with no time column, a rate line (a ``#`` comment or a leading
    ``key value`` line) gives sample k the time k/rate, and says so."""
    s = simulated.session
    path = tmp_path / "imu.txt"
    rows = [
        " ".join(repr(float(v)) for v in (*a, *w))
        for a, w in zip(s.accel_mps2, s.gyro_rps, strict=True)
    ]
    path.write_text("\n".join([rate_line, "# ax ay az gx gy gz", *rows]) + "\n")
    loaded = load_session(path)
    np.testing.assert_array_equal(loaded.session.accel_mps2, s.accel_mps2)
    np.testing.assert_array_equal(loaded.session.gyro_rps, s.gyro_rps)
    np.testing.assert_allclose(loaded.session.t_s, np.arange(s.t_s.size) / 100.0)
    key = rate_line.lstrip("# ").split()[0]
    assert f"no time column: time from {key}=100 Hz (sample k at k/100 s)" in loaded.notes
    path.write_text("\n".join(["# ax ay az gx gy gz", *rows]) + "\n")
    with pytest.raises(SessionFileError, match=r"without a time column, a rate line above it"):
        load_session(path)


def test_a_hash_header_followed_by_a_units_line_is_still_the_header(tmp_path, simulated):
    """Loggers write a line of units under the names (``# [s] [m/s^2] ...``): the names are the
    header, the comment between them and the first row no reason to refuse the file."""
    s = simulated.session
    path = tmp_path / "imu.txt"
    rows = [
        " ".join(repr(float(v)) for v in (t, *a, *w))
        for t, a, w in zip(s.t_s, s.accel_mps2, s.gyro_rps, strict=True)
    ]
    header = ["# time tx ty tz wx wy wz", "# [s] [m/s^2] [m/s^2] [m/s^2] [rad/s] [rad/s] [rad/s]"]
    path.write_text("\n".join([*header, *rows]) + "\n")
    loaded = load_session(path)
    np.testing.assert_array_equal(loaded.session.accel_mps2, s.accel_mps2)
    np.testing.assert_array_equal(loaded.session.t_s, s.t_s)


def test_a_wide_table_without_named_columns_is_not_taken_for_half_a_raw_count_pair(tmp_path):
    """A raw-count pair's files hold four fields a line (time x y z); a line of fourteen is a
    table whose '#' line is missing or not understood, and the message says only that."""
    path = tmp_path / "imu.txt"
    path.write_text("# time[s] ax[m/s^2] ay az gx gy gz mx my mz qw qx qy qz\n" + "0 " * 13 + "0\n")
    with pytest.raises(SessionFileError) as refused:
        load_session(path)
    assert "raw-count pair" not in str(refused.value)
    assert "a space-separated table needs a '#' line naming its columns" in str(refused.value)


def test_a_euroc_file_resaved_by_a_spreadsheet_drops_and_counts_its_junk_rows(
    tmp_path, simulated, capsys
):
    """E-notation stamps at 15 significant digits (10 µs at 2014's epoch in ns) and six junk rows
    at the end: the rows read, the junk dropped and counted, the command says both."""
    s = simulated.session
    t_ns = 1_403_715_273_262_142_976 + np.round(s.t_s * 1e9)
    head = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    head += "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
    rows = [
        f"{t:.14E}," + ",".join(repr(float(v)) for v in (*w, *a))
        for t, w, a in zip(t_ns, s.gyro_rps, s.accel_mps2, strict=True)
    ]
    junk = [",,,,,,", ",,,,,,", "mean,,,,,,", ",,,,,,", ";;;", ",,,,,,"]
    path = tmp_path / "data.csv"
    path.write_text("\n".join([head, *rows, *junk]) + "\n")
    loaded = load_session(path)
    assert loaded.session.t_s.size == s.t_s.size
    assert np.max(np.abs(np.diff(loaded.session.t_s) - np.diff(s.t_s))) < 2e-5
    said = "\n".join(loaded.notes)
    assert f"6 row(s) that are no data dropped (lines {len(rows) + 2}-" in said
    assert "time stamps in E-notation" in said and ": 0 repeat" in said
    assert main(["calibrate", str(path), "--out", str(tmp_path / "p.json")]) in (0, 3)
    assert "6 row(s) that are no data dropped" in capsys.readouterr().err


def test_rows_with_no_number_are_dropped_and_counted_wherever_they_are(tmp_path, simulated):
    """A row with no number holds no sample (a spreadsheet's empty row, a label between blocks):
    dropped and counted in the middle as at the end, the samples around it read unchanged. A row
    with numbers and text is a damaged sample: which column slipped is unknown, so it is refused
    naming its line and column."""
    s = simulated.session
    head = "t,ax,ay,az,gx,gy,gz"
    rows = [
        ",".join(repr(float(v)) for v in (t, *a, *w))
        for t, a, w in zip(s.t_s, s.accel_mps2, s.gyro_rps, strict=True)
    ]
    path = tmp_path / "middle.csv"
    path.write_text("\n".join([head, *rows[:5], ",,,,,,", "block 2,,,,,,", *rows[5:], ",,,,,,"]))
    loaded = load_session(path)
    np.testing.assert_array_equal(loaded.session.t_s, s.t_s)
    np.testing.assert_array_equal(loaded.session.accel_mps2, s.accel_mps2)
    n = len(rows) + 4
    assert f"3 row(s) that are no data dropped (lines 7-8, {n}, first ',,,,,,')" in loaded.notes
    damaged = tmp_path / "damaged.csv"
    damaged.write_text("\n".join([head, *rows[:5], "0.05,,x,,,,", *rows[5:10]]) + "\n")
    with pytest.raises(SessionFileError, match=r"line 7, column 'ax': not a number"):
        load_session(damaged)


@needs(MPU6050_SESSION)
def test_the_shared_mpu6050_session_reads_with_its_stated_scales(capsys):
    """SOURCE.md: 10,245 rows at Fs 100, counts at 16,384 per g and 131 per °/s."""
    with pytest.raises(SessionFileError, match="missing: --accel-scale"):
        load_session(MPU6050_SESSION)
    loaded = load_session(
        MPU6050_SESSION, units=SessionUnits("g", "deg/s", None, 1 / 16384, 1 / 131)
    )
    assert loaded.session.t_s.size == 10_245
    np.testing.assert_allclose(np.diff(loaded.session.t_s), 0.01)
    # At rest |a| is g up to the zero signals: the author's own fit (params_acc.csv) has 1,840
    # counts (0.11 g) on z.
    norm = np.linalg.norm(loaded.session.accel_mps2[:3000], axis=1)
    assert abs(np.median(norm) - STANDARD_GRAVITY_MPS2) < 0.15 * STANDARD_GRAVITY_MPS2
