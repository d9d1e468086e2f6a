"""Other tools' IMU CSV files (EuRoC/ASL, Kalibr, ROS ``rostopic echo -p``) read as they are.

Each file is written here the way its tool writes it (header text, nanosecond time stamps, column
order, a ROS message's other fields), from a simulated session with known errors; the oracle is
the same session read from our own CSV format: the samples must agree to the precision the file
holds, and calibration must find the same positions and parameters.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimators.sim import Grade, multi_position_spec, simulate
from protocols.session_file import (
    SessionFileError,
    SessionUnits,
    TimeUnit,
    load_session,
    write_csv_session,
)
from service.cli import main

EPOCH_NS = 1_403_715_273_262_142_976
"""A EuRoC-like start time (2014): time stamps of 19 digits, as the tools write them."""
EUROC = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
KALIBR = "timestamp,omega_x,omega_y,omega_z,alpha_x,alpha_y,alpha_z"
ROS = (
    "%time,field.header.seq,field.header.stamp,field.header.frame_id,field.orientation.x,"
    "field.orientation.y,field.orientation.z,field.orientation.w,"
    + ",".join(f"field.orientation_covariance{k}" for k in range(9))
    + ",field.angular_velocity.x,field.angular_velocity.y,field.angular_velocity.z,"
    + ",".join(f"field.angular_velocity_covariance{k}" for k in range(9))
    + ",field.linear_acceleration.x,field.linear_acceleration.y,field.linear_acceleration.z,"
    + ",".join(f"field.linear_acceleration_covariance{k}" for k in range(9))
)


def _session():
    spec = multi_position_spec(grade=Grade.MEMS, static_s=3.0, n_positions=18)
    return simulate(spec, 11)


def _rows(session, kind):
    t_ns = EPOCH_NS + np.round(session.t_s * 1e9).astype(np.int64)
    for k, (t, a, w) in enumerate(zip(t_ns, session.accel_mps2, session.gyro_rps, strict=True)):
        g, f = ",".join(repr(float(v)) for v in w), ",".join(repr(float(v)) for v in a)
        if kind == "ros":
            zeros = ",".join(["0.0"] * 9)
            yield f"{t + 150_000},{k},{t},imu_link,0.0,0.0,0.0,1.0,{zeros},{g},{zeros},{f},{zeros}"
        else:
            yield f"{t},{g},{f}"


def _write(tmp_path, session, kind):
    header = {"euroc": EUROC, "kalibr": KALIBR, "ros": ROS}[kind]
    path = tmp_path / f"{kind}.csv"
    path.write_text("\n".join([header, *_rows(session, kind)]) + "\n")
    return path


@pytest.fixture(scope="module")
def simulated():
    return _session()


@pytest.mark.parametrize(
    "kind, name",
    [
        ("euroc", "EuRoC/ASL imu0/data.csv"),
        ("kalibr", "Kalibr imu0.csv"),
        ("ros", "ROS sensor_msgs/Imu (rostopic echo -p)"),
    ],
)
def test_each_format_reads_the_samples_of_our_own_file(tmp_path, simulated, kind, name):
    """The same samples as the native file: values exactly (repr round-trips a float), time to the
    float64 spacing of seconds since 1970 (0.24 µs at 2014), in ns, rad/s and m/s², said as such."""
    native = load_session(write_csv_session(tmp_path / "native.csv", simulated.session))
    theirs = load_session(_write(tmp_path, simulated.session, kind))
    s, ref = theirs.session, native.session
    np.testing.assert_array_equal(s.accel_mps2, ref.accel_mps2)
    np.testing.assert_array_equal(s.gyro_rps, ref.gyro_rps)
    assert s.temp_c is None
    offset_s = EPOCH_NS * 1e-9
    assert np.max(np.abs((s.t_s - offset_s) - ref.t_s)) < 1e-6
    assert theirs.metadata["format"] == name
    assert (str(theirs.units.time), str(theirs.units.accel), str(theirs.units.gyro)) == (
        "ns",
        "m/s2",
        "rad/s",
    )


def test_calibrating_a_euroc_file_gives_the_native_files_passport(tmp_path, simulated, capsys):
    """The oracle is the native file's calibration: same positions, same parameters (the time stamps
    differ by the offset and its rounding only), and the format is said on stderr."""
    native = write_csv_session(tmp_path / "native.csv", simulated.session)
    euroc = _write(tmp_path, simulated.session, "euroc")
    g = str(simulated.truth.gravity_mps2)
    assert main(["calibrate", str(native), "--gravity", g, "--out", str(tmp_path / "n.json")]) == 0
    native_said = capsys.readouterr()
    assert main(["calibrate", str(euroc), "--gravity", g, "--out", str(tmp_path / "e.json")]) == 0
    captured = capsys.readouterr()
    assert f"{euroc} read as EuRoC/ASL imu0/data.csv (time ns" in captured.err
    assert (
        "calibrate: 18 positions" in native_said.err and "calibrate: 18 positions" in captured.err
    )
    n, e = (json.loads((tmp_path / f).read_text()) for f in ("n.json", "e.json"))
    np.testing.assert_allclose(
        e["triads"]["accel"]["nominal"], n["triads"]["accel"]["nominal"], rtol=1e-9, atol=1e-12
    )


def test_a_declared_unit_still_overrides_the_formats(tmp_path, simulated):
    """A Kalibr file someone wrote in µs (a converter's mistake): --time-unit us reads it so."""
    path = tmp_path / "us.csv"
    t_us = np.round(simulated.session.t_s * 1e6).astype(np.int64)
    rows = [
        f"{t},{','.join(map(repr, w))},{','.join(map(repr, a))}"
        for t, w, a in zip(
            t_us,
            simulated.session.gyro_rps.tolist(),
            simulated.session.accel_mps2.tolist(),
            strict=True,
        )
    ]
    path.write_text("\n".join([KALIBR, *rows]) + "\n")
    loaded = load_session(path, units=SessionUnits(time=TimeUnit.US))
    assert np.max(np.abs(loaded.session.t_s - simulated.session.t_s)) < 1e-6


@pytest.mark.parametrize(
    "text, match",
    [
        (
            KALIBR.replace(",omega_z", "") + "\n1,0,0,0,0,9.8\n",
            r"missing column 'gz'.*read as Kalibr imu0.csv, whose columns are timestamp, omega_x",
        ),
        (EUROC + "\n1,0,0,0,0,0\n", r"line 2: expected 7 fields, got 6"),
        (ROS + "\n" + ",".join(["1"] * 50) + "\n", r"line 2: expected 41 fields, got 50"),
        (KALIBR + "\n1,0,0,0,0,0,x\n", r"line 2, column 'az': not a number: 'x'"),
        (
            "timestamp,omega_x,omega_y,omega_z,alpha_x,alpha_y,alpha_z,extra\n1,0,0,0,0,0,9.8,0\n",
            r"unknown column 'timestamp'",
        ),
    ],
)
def test_a_damaged_file_of_another_format_is_one_line_naming_it(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(SessionFileError, match=match):
        load_session(path)


@pytest.mark.parametrize("kind", ["native", "euroc", "kalibr"])
def test_a_file_saved_with_a_byte_order_mark_reads_as_without_it(tmp_path, simulated, kind):
    """Windows editors and spreadsheets save UTF-8 with a byte-order mark: its header was read as
    '\\ufefftimestamp' (or the first comment as a header) and refused as an unknown column."""
    if kind == "native":
        plain = write_csv_session(tmp_path / "plain.csv", simulated.session)
    else:
        plain = _write(tmp_path, simulated.session, kind)
    marked = tmp_path / "marked.csv"
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    a, b = load_session(plain), load_session(marked)
    np.testing.assert_array_equal(a.session.t_s, b.session.t_s)
    np.testing.assert_array_equal(a.session.accel_mps2, b.session.accel_mps2)
    assert a.metadata == b.metadata
