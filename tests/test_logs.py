"""Log readers on the real logs (pinned counts and values) and round trips of the log writers."""

import os
import struct
import tracemalloc

import numpy as np
import pytest
from pymavlink import DFReader, mavutil
from real_data import LOGS, REAL_BIN, REAL_TLOG, needs

from estimators.conventions import STANDARD_GRAVITY_MPS2
from estimators.session import ImuSession
from protocols.frames import concat_batches
from protocols.logs import (
    DATAFLASH_IMU_NAMES,
    LogFormat,
    LogReader,
    NoImuDataError,
    detect_format,
    read_log_sessions,
    write_dataflash_bin,
    write_dataflash_text,
    write_tlog,
)
from protocols.mavlink_adapter import ImuMessage
from protocols.ulog import SYNC_BYTES, write_ulog
from service.pipeline.imu_pipeline import split_batch

REAL_COPTER31 = LOGS / "ardupilot-copter31-no-imu.log"

# ------------------------------------------------------------------ real logs


@needs(REAL_BIN)
def test_real_dataflash_log_two_imus_with_temperature():
    sessions, stats = read_log_sessions(REAL_BIN)
    assert stats.messages == {"IMU": 45, "IMU2": 45} and stats.dropped == {}
    assert sorted(sessions) == [0, 1]
    imu0, imu1 = sessions[0], sessions[1]
    assert imu0.n_samples == imu1.n_samples == 45
    # Logged every 20 ms (median) over 0.975 s, from 81.794643 s after boot.
    assert imu0.t_s[0] == pytest.approx(81.794643, abs=1e-9)
    assert imu0.rate_hz == pytest.approx(49.94, abs=0.01)
    assert imu0.t_s[-1] - imu0.t_s[0] == pytest.approx(0.974846, abs=1e-6)
    np.testing.assert_allclose(imu0.accel_mps2[0], [0.41619188, 0.46917608, -9.78099442], rtol=1e-7)
    np.testing.assert_allclose(imu0.gyro_rps[0], [-0.11657085, 0.00964673, -0.00366144], rtol=1e-6)
    np.testing.assert_allclose(imu1.accel_mps2[0], [0.387851, 0.52207196, -9.67627525], rtol=1e-6)
    assert imu0.temp_c[0] == pytest.approx(44.4232826) and imu1.temp_c[0] == pytest.approx(
        39.9229507
    )
    # Specific force magnitude near g (the vehicle is not quite still in this second).
    assert np.linalg.norm(imu0.accel_mps2, axis=1).mean() == pytest.approx(9.93140, abs=1e-5)


@pytest.fixture(scope="module")
def real_tlog():
    reader = LogReader(REAL_TLOG, vehicle="vtol", batch_samples=100)
    return reader, list(reader), reader.stats


@needs(REAL_TLOG)
def test_real_tlog_counts_and_an_out_of_order_record(real_tlog):
    _, batches, stats = real_tlog
    sessions = {imu: concat_batches([b for b in batches if b.imu == imu]) for imu in (0, 1)}
    assert stats.messages == {"RAW_IMU": 795, "SCALED_IMU2": 796}
    # One record of each stream arrives a second late in the log: left out and counted.
    assert stats.dropped == {"time_not_increasing": 2}
    assert {k: s.n_samples for k, s in sessions.items()} == {0: 794, 1: 795}
    assert sessions[0].rate_hz == pytest.approx(4.17, abs=0.01)
    assert sessions[0].t_s[0] == pytest.approx(608.582234)
    # RAW_IMU (ArduPilot: mG, mrad/s): xacc 33, zacc -999, zgyro -231.
    np.testing.assert_allclose(
        sessions[0].accel_mps2[0], np.array([33, -10, -999]) * STANDARD_GRAVITY_MPS2 / 1000
    )
    np.testing.assert_allclose(sessions[0].gyro_rps[0], [-0.009, 0.003, -0.231])
    assert (
        sessions[0].temp_c is None and sessions[1].temp_c is None
    )  # temperature field 0: not provided


@needs(REAL_TLOG)
def test_reading_is_deterministic_and_batches_stay_interleaved(real_tlog):
    reader, first, _ = real_tlog
    assert list(reader) == first
    assert [(b.imu, b.seq) for b in first[:4]] == [(0, 0), (1, 0), (0, 1), (1, 1)]
    assert {b.vehicle for b in first} == {"vtol"} and all(b.n_samples == 100 for b in first[:14])


@needs(REAL_BIN)
@needs(REAL_TLOG)
def test_detect_format_by_content():
    assert detect_format(REAL_BIN) is LogFormat.DATAFLASH_BIN
    assert detect_format(REAL_TLOG) is LogFormat.TLOG


# ------------------------------------------------------------------ writers: round trips


def _sessions(n=400, rate_hz=200.0, seed=3, temp=True, imus=(0, 1, 2)):
    rng = np.random.default_rng(seed)
    out = {}
    for imu in imus:
        t = 10.0 + np.arange(n) / rate_hz + imu * 1e-3  # IMUs sampled 1 ms apart
        acc = rng.normal([0.3, -0.2, -9.8], 0.05, (n, 3))
        gyr = rng.normal(0.0, 0.01, (n, 3))
        out[imu] = ImuSession(t, acc, gyr, 30.0 + imu + 0.01 * np.arange(n) if temp else None)
    return out


@pytest.mark.parametrize("legacy", [False, True], ids=["instance-field", "IMU-IMU2-IMU3"])
def test_dataflash_bin_round_trip_through_pymavlink(tmp_path, legacy):
    sessions = _sessions()
    path = tmp_path / "flight.bin"
    assert write_dataflash_bin(path, sessions, legacy_names=legacy) == 1200
    # pymavlink's own reader accepts the file ...
    reader = DFReader.DFReader_binary(str(path))
    names = {"IMU", "IMU2", "IMU3"} if legacy else {"IMU"}
    assert set(reader.name_to_id) == names | {"FMT"}
    reader.close()
    # ... and ours gives the sessions back, at float32 precision and 1 µs time resolution.
    back, stats = read_log_sessions(path)
    assert stats.dropped == {} and sorted(back) == [0, 1, 2]
    for imu, s in sessions.items():
        np.testing.assert_allclose(back[imu].t_s, s.t_s, atol=0.5e-6, rtol=0)
        np.testing.assert_allclose(back[imu].accel_mps2, s.accel_mps2, rtol=2.0**-24, atol=0)
        np.testing.assert_allclose(back[imu].gyro_rps, s.gyro_rps, rtol=2.0**-24, atol=0)
        np.testing.assert_allclose(back[imu].temp_c, s.temp_c, rtol=2.0**-24, atol=0)


@pytest.mark.parametrize("legacy", [False, True], ids=["instance-field", "IMU-IMU2-IMU3"])
def test_dataflash_text_round_trip_is_exact(tmp_path, legacy):
    sessions = _sessions(n=150, temp=False)
    path = tmp_path / "flight.log"
    write_dataflash_text(path, sessions, legacy_names=legacy)
    assert detect_format(path) is LogFormat.DATAFLASH_TEXT
    back, _ = read_log_sessions(path)
    for imu, s in sessions.items():
        np.testing.assert_allclose(
            back[imu].t_s, s.t_s, atol=0.5e-6, rtol=0
        )  # TimeUS is an integer µs
        np.testing.assert_array_equal(back[imu].accel_mps2, s.accel_mps2)
        np.testing.assert_array_equal(back[imu].gyro_rps, s.gyro_rps)
        assert back[imu].temp_c is None


def test_tlog_round_trip_quantized_as_the_messages_are(tmp_path):
    sessions = _sessions(n=200)
    path = tmp_path / "flight.tlog"
    assert write_tlog(path, sessions) == 600
    back, stats = read_log_sessions(path)
    assert stats.messages == {"RAW_IMU": 200, "SCALED_IMU2": 200, "SCALED_IMU3": 200}
    half_mg, half_mrad = STANDARD_GRAVITY_MPS2 * 0.5e-3, 0.5e-3
    for imu, s in sessions.items():
        time_quantum = 1e-6 if imu == 0 else 1e-3  # RAW_IMU: time_usec; SCALED_IMU*: time_boot_ms
        np.testing.assert_allclose(back[imu].t_s, s.t_s, atol=time_quantum / 2 + 1e-9, rtol=0)
        np.testing.assert_allclose(
            back[imu].accel_mps2, s.accel_mps2, atol=half_mg * (1 + 1e-9), rtol=0
        )
        np.testing.assert_allclose(
            back[imu].gyro_rps, s.gyro_rps, atol=half_mrad * (1 + 1e-9), rtol=0
        )
        np.testing.assert_allclose(back[imu].temp_c, s.temp_c, atol=0.005 + 1e-9)
    # Every record is an 8-byte big-endian µs wall stamp + one MAVLink 2 packet.
    data = path.read_bytes()
    assert (
        int.from_bytes(data[:8], "big") == round((1.7e9 + sessions[0].t_s[0]) * 1e6)
        and data[8] == 0xFD
    )


def test_reading_a_tlog_leaves_pymavlink_global_state_alone(tmp_path):
    before = (os.environ.get("MAVLINK20"), mavutil.mavlink, mavutil.current_dialect)
    path = tmp_path / "flight.tlog"
    write_tlog(path, _sessions(n=5))
    assert sum(s.n_samples for s in read_log_sessions(path)[0].values()) == 15
    assert (os.environ.get("MAVLINK20"), mavutil.mavlink, mavutil.current_dialect) == before


def test_tlog_highres_round_trip_at_float32(tmp_path):
    sessions = _sessions(n=100, imus=(0, 1))
    path = tmp_path / "px4.tlog"
    write_tlog(path, sessions, messages={0: ImuMessage.HIGHRES_IMU, 1: ImuMessage.HIGHRES_IMU})
    back, stats = read_log_sessions(path)
    assert stats.messages == {"HIGHRES_IMU": 200}
    for imu, s in sessions.items():
        np.testing.assert_allclose(back[imu].accel_mps2, s.accel_mps2, rtol=2.0**-24, atol=0)
        np.testing.assert_allclose(back[imu].temp_c, s.temp_c, rtol=2.0**-24, atol=0)


# ------------------------------------------------------------------ bad input


def test_non_finite_and_repeated_samples_are_dropped_and_counted(tmp_path):
    s = _sessions(n=20, imus=(0,))[0]
    acc = s.accel_mps2.copy()
    acc[5, 1] = np.nan
    t = s.t_s.copy()
    t[9] = t[8]
    path = tmp_path / "bad.log"
    write_dataflash_text(path, {0: ImuSession(t, acc, s.gyro_rps, s.temp_c)})
    back, stats = read_log_sessions(path)
    assert stats.dropped == {"non_finite": 1, "time_not_increasing": 1} and back[0].n_samples == 18


def test_unreadable_files_are_clear_errors(tmp_path):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"this is not a log at all, just some text")
    with pytest.raises(
        ValueError, match=r"not a MAVLink \.tlog, a DataFlash \.bin/\.log or a PX4 ULog"
    ):
        LogReader(junk)
    with pytest.raises(ValueError, match="no such log file"):
        LogReader(tmp_path / "missing.tlog")
    with pytest.raises(ValueError, match="batch_samples"):
        LogReader(junk, batch_samples=0)
    with pytest.raises(ValueError, match="SCALED_IMU2 carries IMU 1 only, not IMU 0"):
        write_tlog(
            tmp_path / "x.tlog", _sessions(n=2, imus=(0,)), messages={0: ImuMessage.SCALED_IMU2}
        )


@pytest.mark.parametrize(
    "name,writer",
    [("cut.bin", write_dataflash_bin), ("cut.tlog", write_tlog), ("cut.log", write_dataflash_text)],
)
def test_truncated_logs_give_what_they_hold(tmp_path, name, writer):
    sessions = _sessions(n=100, imus=(0, 1))
    path = tmp_path / name
    writer(path, sessions)
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:
        fh.truncate(size * 2 // 3 + 5)  # mid-record
    back, _stats = read_log_sessions(path)
    kept = sum(s.n_samples for s in back.values())
    assert 120 <= kept < 200  # about two thirds survive, the cut record does not
    for imu, s in back.items():
        np.testing.assert_allclose(s.accel_mps2, sessions[imu].accel_mps2[: s.n_samples], atol=5e-3)


def test_old_dataflash_text_with_time_in_ms_and_no_temperature(tmp_path):
    path = tmp_path / "old.log"
    path.write_text(
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n"
        "FMT, 129, 31, IMU2, Iffffff, TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ\n"
        "IMU2, 1000, 0.01, 0.02, 0.03, 0.1, 0.2, -9.8\n"
        "IMU2, 1020, 0.01, 0.02, 0.03, 0.1, 0.2, -9.7\n"
    )
    back, stats = read_log_sessions(path)
    assert list(back) == [1] and stats.messages == {"IMU2": 2}
    np.testing.assert_array_equal(back[1].t_s, [1.0, 1.02])
    np.testing.assert_array_equal(back[1].accel_mps2[:, 2], [-9.8, -9.7])
    assert back[1].temp_c is None


# ------------------------------------------------------------------ text DataFlash as firmware writes it


def _firmware_text_log(sessions, *, header, crlf, time_field, instance_field):
    """A text DataFlash log the way ArduCopter writes one (header lines, CRLF, TimeMS), built line by line."""
    lines = ["9", "", "ArduCopter V3.1 (5c6503e2)", "Free RAM: 1044", "APM 2"] if header else []
    lines.append("FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns")
    lines.append("FMT, 129, 23, PARM, Nf, Name,Value")
    ms = time_field == "TimeMS"
    tfmt = "I" if ms else "Q"
    cols = "GyrX,GyrY,GyrZ,AccX,AccY,AccZ"
    if instance_field:
        lines.append(f"FMT, 130, 40, IMU, {tfmt}Bffffff, {time_field},I,{cols}")
    else:
        for k in sorted(sessions):
            lines.append(
                f"FMT, {130 + k}, 40, {DATAFLASH_IMU_NAMES[k]}, {tfmt}ffffff, {time_field},{cols}"
            )
    lines.append("PARM, INS_GYRO_FILTER, 20")
    rows = sorted((float(t), imu, k) for imu, s in sessions.items() for k, t in enumerate(s.t_s))
    for t, imu, k in rows:
        s = sessions[imu]
        stamp = round(t * 1e3) if ms else round(t * 1e6)
        name = "IMU" if instance_field else DATAFLASH_IMU_NAMES[imu]
        values = [
            stamp,
            *([imu] if instance_field else []),
            *map(float, [*s.gyro_rps[k], *s.accel_mps2[k]]),
        ]
        lines.append(", ".join([name, *map(repr, values)]))
    return ("\r\n" if crlf else "\n").join(lines) + ("\r\n" if crlf else "\n")


@pytest.mark.parametrize(
    "header, crlf, time_field, imus, instance_field",
    [
        (True, True, "TimeMS", (0,), False),
        (True, False, "TimeUS", (0, 1), False),
        (False, True, "TimeUS", (0, 1, 2), False),
        (True, True, "TimeUS", (0, 1, 2), True),
        (False, False, "TimeMS", (0, 1), True),
    ],
    ids=["hdr-crlf-ms-1", "hdr-lf-us-2", "crlf-us-3", "hdr-crlf-us-3-I", "lf-ms-2-I"],
)
def test_text_dataflash_as_firmware_writes_it(
    tmp_path, header, crlf, time_field, imus, instance_field
):
    sessions = _sessions(n=60, rate_hz=50.0, temp=False, imus=imus)
    # TimeMS logs hold whole milliseconds: put the samples on them.
    sessions = {
        i: ImuSession(np.round(s.t_s, 3), s.accel_mps2, s.gyro_rps, None)
        for i, s in sessions.items()
    }
    path = tmp_path / "flight.txt"  # the extension says nothing: the content decides
    path.write_bytes(
        _firmware_text_log(
            sessions, header=header, crlf=crlf, time_field=time_field, instance_field=instance_field
        ).encode()
    )
    assert detect_format(path) is LogFormat.DATAFLASH_TEXT
    back, stats = read_log_sessions(path)
    assert sorted(back) == list(imus) and stats.dropped == {}
    assert stats.held["PARM"] == 1 and stats.held["FMT"] >= 3
    for imu, s in sessions.items():
        np.testing.assert_allclose(back[imu].t_s, s.t_s, atol=1e-9, rtol=0)
        np.testing.assert_array_equal(back[imu].accel_mps2, s.accel_mps2)
        np.testing.assert_array_equal(back[imu].gyro_rps, s.gyro_rps)


@needs(REAL_COPTER31)
def test_real_copter31_text_log_says_no_imu_data_and_what_it_holds():
    assert detect_format(REAL_COPTER31) is LogFormat.DATAFLASH_TEXT
    with pytest.raises(NoImuDataError, match="no IMU data") as info:
        read_log_sessions(REAL_COPTER31)
    text = str(info.value)
    for held in (
        "ATT 1100",
        "CTUN 1100",
        "MOT 1100",
        "GPS 551",
        "PARM 298",
        "MODE 151",
        "CURR 110",
    ):
        assert held in text
    assert (
        "IMU " not in text.split("the log holds")[1]
    )  # its FMT defines IMU, but no IMU row is there


@needs(REAL_BIN)
def test_real_bin_clip_counters_and_what_it_holds():
    _, stats = read_log_sessions(REAL_BIN)
    assert stats.sources == {0: "IMU", 1: "IMU2"}
    assert stats.held["VIBE"] == 23 and stats.held["PARM"] == 809 and stats.held["IMU"] == 45
    # The file ends inside its 24th AHR2 message: 23 are held (pymavlink's index counted 24).
    assert stats.held["AHR2"] == 23 and len(stats.held) == 47
    assert stats.clipped == {0: 0, 1: 0, 2: 0}  # VIBE Clip0..2 did not move in this second


def test_acc_and_gyr_messages_are_paired_by_sample_time(tmp_path):
    """ArduPilot's per-sample ACC and GYR (instance I, SampleUS): each accelerometer sample takes the
    nearest gyro sample; the gyro here runs at twice the rate, 0.2 ms early."""
    rng = np.random.default_rng(4)
    lines = [
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
        "FMT, 130, 40, ACC, QBQfff, TimeUS,I,SampleUS,AccX,AccY,AccZ",
        "FMT, 131, 40, GYR, QBQfff, TimeUS,I,SampleUS,GyrX,GyrY,GyrZ",
    ]
    n = 700  # more than one block of gathered messages
    acc = {i: rng.normal([0, 0, -9.8], 0.1, (n, 3)) for i in (0, 1)}
    gyr = {i: rng.normal(0, 0.01, (2 * n, 3)) for i in (0, 1)}
    t_acc = 5_000_000 + 2_000 * np.arange(n)  # 500 Hz, µs
    t_gyr = 4_999_800 + 1_000 * np.arange(2 * n)  # 1 kHz, 0.2 ms early
    rows = [(t, "ACC", i, k) for i in (0, 1) for k, t in enumerate(t_acc)]
    rows += [(t, "GYR", i, k) for i in (0, 1) for k, t in enumerate(t_gyr)]
    for t, name, i, k in sorted(rows):
        v = (acc if name == "ACC" else gyr)[i][k]
        lines.append(f"{name}, {t + 100}, {i}, {t}, " + ", ".join(repr(float(x)) for x in v))
    path = tmp_path / "raw.log"
    path.write_text("\r\n".join(lines) + "\r\n")
    back, stats = read_log_sessions(path)
    assert sorted(back) == [3, 4] and stats.sources == {3: "ACC+GYR", 4: "ACC+GYR"}
    assert stats.samples == {3: n, 4: n} and stats.skipped == {}
    for i in (0, 1):
        s = back[3 + i]
        np.testing.assert_array_equal(s.t_s, t_acc * 1e-6)
        np.testing.assert_array_equal(s.accel_mps2, acc[i])
        # Accelerometer sample k at 2k ms: the nearest gyro sample is 2k (0.2 ms earlier; 2k + 1 is 0.8 ms later).
        np.testing.assert_array_equal(s.gyro_rps, gyr[i][::2])


_LEGACY_RAW_FMT = {
    name: (
        type_id,
        31,
        "QQfff",
        f"TimeUS,SampleUS,{name[:3].title()}X,{name[:3].title()}Y,{name[:3].title()}Z",
    )
    for type_id, name in zip(
        range(176, 182), ("ACC1", "ACC2", "ACC3", "GYR1", "GYR2", "GYR3"), strict=True
    )
}
"""ArduPilot before 4.1: ``ACC1``…``GYR3`` (type, length, format, columns), as its real logs define them."""


def _fmt_record(name, type_id, length, fmt, columns):
    return b"\xa3\x95\x80" + struct.pack(
        "<BB4s16s64s", type_id, length, name.encode(), fmt.encode(), columns.encode()
    )


@needs(REAL_BIN)
def test_real_bin_defines_the_legacy_per_sample_messages_as_the_test_below_writes_them():
    """The real log's FMT records of ACC1…GYR3 (ArduPilot before 4.1), byte for byte."""
    data = REAL_BIN.read_bytes()
    for name, definition in _LEGACY_RAW_FMT.items():
        assert data.count(_fmt_record(name, *definition)) == 1, name


def test_legacy_acc1_gyr1_messages_are_paired_as_acc_and_gyr_are(tmp_path):
    """ACC1/GYR1 and ACC2/GYR2 (one name per instance, no ``I`` field) become IMUs 3 and 4, as ACC and
    GYR instances 0 and 1 do; pymavlink's DFReader reads the same values from the same file."""
    rng = np.random.default_rng(7)
    n = 700  # more than one block of gathered messages
    t_us = 8_000_000 + 1_000 * np.arange(
        n
    )  # 1 kHz, the gyro sampled 0.1 ms after the accelerometer
    acc = {i: rng.normal([0, 0, -9.8], 0.1, (n, 3)).astype(np.float32) for i in (1, 2)}
    gyr = {i: rng.normal(0, 0.01, (n, 3)).astype(np.float32) for i in (1, 2)}
    out = bytearray(_fmt_record("FMT", 128, 89, "BBnNZ", "Type,Length,Name,Format,Columns"))
    for name in ("ACC1", "ACC2", "GYR1", "GYR2"):
        out += _fmt_record(name, *_LEGACY_RAW_FMT[name])
    for k in range(n):
        for name in ("ACC1", "GYR1", "ACC2", "GYR2"):
            i, v = int(name[3]), (acc if name[0] == "A" else gyr)[int(name[3])][k]
            t = int(t_us[k]) + (100 if name[0] == "G" else 0)
            out += (
                b"\xa3\x95"
                + bytes([_LEGACY_RAW_FMT[name][0]])
                + struct.pack("<QQfff", t + 50, t, *v)
            )
    path = tmp_path / "legacy_raw.bin"
    path.write_bytes(bytes(out))

    back, stats = read_log_sessions(path)
    assert stats.sources == {3: "ACC1+GYR1", 4: "ACC2+GYR2"}
    assert stats.samples == {3: n, 4: n} and stats.skipped == {} and stats.dropped == {}
    oracle = DFReader.DFReader_binary(str(path))
    expected: dict[str, list[list[float]]] = {}
    while (m := oracle.recv_msg()) is not None:
        if m.get_type() != "FMT":
            axes = "Acc" if m.get_type()[0] == "A" else "Gyr"
            row = [m.SampleUS * 1e-6, *(getattr(m, axes + c) for c in "XYZ")]
            expected.setdefault(m.get_type(), []).append(row)
    for i in (1, 2):
        s, a, g = back[2 + i], np.array(expected[f"ACC{i}"]), np.array(expected[f"GYR{i}"])
        np.testing.assert_array_equal(s.t_s, a[:, 0])
        np.testing.assert_array_equal(s.accel_mps2, a[:, 1:])
        np.testing.assert_array_equal(s.gyro_rps, g[:, 1:])
        np.testing.assert_array_equal(s.accel_mps2, acc[i])


# ------------------------------------------------------------------ long DataFlash logs, corrupt messages

_FILLER_FMT = (200, 11, "XKF1", "Q", "TimeUS")
"""A message type the IMU reader skips: its ``FMT`` (type, length, name, format, columns)."""


def _log_with_filler(path, n_filler):
    """An IMU log of 1000 samples, then ``n_filler`` messages of another type, in ``path``'s format."""
    session = _sessions(n=1000, rate_hz=1000.0, temp=False, imus=(0,))
    type_id, length, name, fmt, columns = _FILLER_FMT
    if path.suffix == ".bin":
        write_dataflash_bin(path, session)
        head = struct.pack(
            "<BB4s16s64s", type_id, length, *(v.encode() for v in (name, fmt, columns))
        )
        fmt_msg = b"\xa3\x95\x80" + head
        filler = b"\xa3\x95" + bytes([type_id]) + struct.pack("<Q", 123456)
    else:
        write_dataflash_text(path, session)
        fmt_msg = f"FMT, {type_id}, {length}, {name}, {fmt}, {columns}\n".encode()
        filler = f"{name}, 123456\n".encode()
    with open(path, "ab") as fh:
        fh.write(fmt_msg + filler * n_filler)


@pytest.mark.parametrize("suffix", ["bin", "log"])
def test_dataflash_reader_memory_does_not_grow_with_the_log(tmp_path, suffix):
    """The DataFlash readers stream: the Python memory they peak at over a log four times longer is
    the same. (pymavlink's DFReader, which indexes every message when it opens a log, grew by 2.2 MB
    (binary) and 2.5 MB (text) for 60,000 more messages: the old reader failed this.) Both logs are
    longer than the numpy text reader's largest block (2.6 and 10 MB): its peak is a block's."""
    peaks, read = {}, {}
    for n in (200_000, 800_000):
        path = tmp_path / f"filler{n}.{suffix}"
        _log_with_filler(path, n)
        tracemalloc.start()
        try:
            reader = LogReader(path)
            samples = sum(b.n_samples for b in reader)
            peaks[n] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        read[n] = (samples, reader.stats.held["XKF1"])
    assert peaks[800_000] - peaks[200_000] < 256 * 1024, peaks
    assert read == {200_000: (1000, 200_000), 800_000: (1000, 800_000)}


def test_corrupt_dataflash_messages_are_skipped_and_counted(tmp_path):
    session = _sessions(n=20, imus=(0,))
    text = tmp_path / "bad.log"
    write_dataflash_text(text, session)
    lines = text.read_text().splitlines()
    lines[5] = lines[5].replace(", ", ", x", 3)  # a field of the 4th IMU row is not a number
    text.write_text("\n".join(lines) + "\n")
    back, stats = read_log_sessions(text)
    assert back[0].n_samples == 19 and stats.dropped == {"corrupt_messages": 1}
    # Garbage between two binary messages: skipped to the next message header, nothing lost.
    binary = tmp_path / "bad.bin"
    write_dataflash_bin(binary, session)
    data = binary.read_bytes()
    cut = data.index(b"\xa3\x95\x81", 200)  # the start of an IMU message
    binary.write_bytes(data[:cut] + b"\x00\xa3\x07garbage" + data[cut:])
    back, stats = read_log_sessions(binary)
    assert back[0].n_samples == 20 and stats.dropped == {}
    np.testing.assert_allclose(back[0].accel_mps2, session[0].accel_mps2, rtol=2.0**-23)


def test_an_endless_text_line_costs_a_bounded_read_and_is_counted(tmp_path):
    """8 MB without a line break between two IMU rows: counted as one corrupt message, read in
    pieces (the peak stays far below the line's size), and every IMU row around it is kept."""
    session = _sessions(n=20, imus=(0,))
    text = tmp_path / "long-line.log"
    write_dataflash_text(text, session)
    lines = text.read_text().splitlines()
    first_imu = next(k for k, line in enumerate(lines) if line.startswith("IMU,"))
    lines.insert(first_imu + 10, "x" * (8 << 20))
    text.write_text("\n".join(lines) + "\n")
    tracemalloc.start()
    try:
        back, stats = read_log_sessions(text)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert back[0].n_samples == 20 and stats.dropped == {"corrupt_messages": 1}
    assert peak < 2 << 20, peak


def _second_boot(data, writer):
    """A log's data after its definitions, as the second boot of logs joined end to end: a
    DataFlash log's two FMT messages (89 bytes each, or two lines), a ULog's header up to its
    first sync message (a tlog has none)."""
    if writer is write_dataflash_bin:
        return data[2 * 89 :]
    if writer is write_dataflash_text:
        return data.split(b"\n", 2)[2]
    return data[data.index(b"\x08\x00S" + SYNC_BYTES) :] if writer is write_ulog else data


def _rebooted(tmp_path, writer, sizes, imus):
    """A log of two boots of ``sizes`` samples of ``imus`` (the clock starts again at the second)."""
    parts = []
    for k, n in enumerate(sizes):
        path = tmp_path / f"boot{k}"
        writer(path, _sessions(n=n, seed=k, imus=imus))
        parts.append(path.read_bytes() if k == 0 else _second_boot(path.read_bytes(), writer))
    log = tmp_path / "joined"
    log.write_bytes(b"".join(parts))
    return log


def _joined(log):
    """The batches read one by one, and those read with ``join_frames`` 7 with the frames of each."""
    one_by_one = list(LogReader(log, batch_samples=100))
    reader = LogReader(log, batch_samples=100, join_frames=7)
    joined = list(reader)
    return one_by_one, joined, [reader.frames_of(b) for b in joined]


_WRITERS = pytest.mark.parametrize(
    "writer",
    [write_dataflash_bin, write_dataflash_text, write_tlog, write_ulog],
    ids=["bin", "log", "tlog", "ulg"],
)


@_WRITERS
def test_joined_batches_are_the_batches_one_by_one(tmp_path, writer):
    """Two IMUs, then the autopilot rebooted (its clock starts again): with ``join_frames`` the
    reader gives each IMU's full batches that come in a row joined, numbered as the last; split
    again they are the batches read one by one, in their order, each IMU's last and the one
    before the reboot shorter and alone. A ULog's topics come in runs of messages, so batches
    come in a row; the IMUs of the other formats take turns batch by batch (no batch of one
    passes another IMU's)."""
    log = _rebooted(tmp_path, writer, (2345, 1234), (0, 1))
    one_by_one, joined, frames = _joined(log)
    assert max(frames) == (7 if writer is write_ulog else 1)
    split = [part for b, f in zip(joined, frames, strict=True) for part in split_batch(b, f)]
    assert split == one_by_one
    assert {b.run for b in one_by_one} == {0, 1}


@_WRITERS
def test_a_lone_imus_batches_come_joined_in_every_format(tmp_path, writer):
    """One IMU, rebooted: its full batches come ``join_frames`` at a time whatever blocks the
    format's reader decodes (a DataFlash log's or tlog's a few kB to 256 kB of messages at a
    time, 1 to 32 batches), those before the reboot and the last fewer, then each run's short
    batch alone; split again they are the batches read one by one."""
    sizes = (12345, 3050)
    log = _rebooted(tmp_path, writer, sizes, (0,))
    one_by_one, joined, frames = _joined(log)
    expected = []
    for n in sizes:
        full = n // 100
        expected += [7] * (full // 7) + [full % 7] * (full % 7 > 0) + [1] * (n % 100 > 0)
    assert frames == expected
    split = [part for b, f in zip(joined, frames, strict=True) for part in split_batch(b, f)]
    assert split == one_by_one
