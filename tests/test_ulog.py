"""PX4 ULog: the writer against pyulog, the streaming reader against the writer and pyulog, the real log."""

import numpy as np
import pytest
from pyulog import ULog
from real_data import LOGS, needs

from estimators.session import ImuSession
from protocols.logs import LogFormat, LogReader, NoImuDataError, detect_format, read_log_sessions
from protocols.ulog import DEVICE_ID_BASE, FLUSH_MESSAGES, SYNC_BYTES, UlogImuStream, write_ulog

REAL_ULOG = LOGS / "px4-events.ulg"


def _sessions(n=1200, rate_hz=200.0, imus=(0, 1, 2), seed=5):
    rng = np.random.default_rng(seed)
    out = {}
    for imu in imus:
        t = 3.0 + np.arange(n) / rate_hz + imu * 1e-4
        acc = rng.normal([0.2, -0.1, -9.8], 0.05, (n, 3))
        gyr = rng.normal(0.0, 0.01, (n, 3))
        out[imu] = ImuSession(t, acc, gyr, 35.0 + imu + np.arange(n) / n)
    return out


def test_pyulog_reads_what_the_writer_writes(tmp_path):
    sessions = _sessions(n=300, imus=(0, 1))
    path = tmp_path / "w.ulg"
    write_ulog(path, sessions)
    log = ULog(str(path))
    assert not log.file_corruption and log.msg_info_dict["sys_name"] == "ins-health"
    combined = log.get_dataset("sensor_combined").data
    np.testing.assert_array_equal(combined["timestamp"], np.round(sessions[0].t_s * 1e6))
    np.testing.assert_allclose(
        combined["accelerometer_m_s2[2]"], sessions[0].accel_mps2[:, 2], rtol=2.0**-24
    )
    gyro1 = log.get_dataset("sensor_gyro", 0).data
    np.testing.assert_allclose(gyro1["x"], sessions[1].gyro_rps[:, 0], rtol=2.0**-24)
    assert set(gyro1["device_id"]) == {DEVICE_ID_BASE + 1}


def test_instances_temperature_and_clipping(tmp_path):
    sessions = _sessions()
    clipped = {0: np.zeros(1200, bool), 2: np.zeros(1200, bool)}
    clipped[0][[10, 11, 500]] = True
    clipped[2][700:710] = True
    path = tmp_path / "flight.ulg"
    write_ulog(path, sessions, clipped=clipped)
    assert detect_format(path) is LogFormat.ULOG
    back, stats = read_log_sessions(path)
    assert sorted(back) == [0, 1, 2] and stats.dropped == {}
    assert stats.sources == {
        0: "sensor_combined",
        1: "sensor_accel+sensor_gyro",
        2: "sensor_accel+sensor_gyro",
    }
    assert stats.clipped == {0: 3, 1: 0, 2: 10}
    for imu, s in sessions.items():
        np.testing.assert_allclose(back[imu].t_s, s.t_s, atol=0.5e-6, rtol=0)
        np.testing.assert_allclose(back[imu].accel_mps2, s.accel_mps2, rtol=2.0**-24)
        np.testing.assert_allclose(back[imu].gyro_rps, s.gyro_rps, rtol=2.0**-24)
    # IMUs 1, 2: their own temperature on every sample.
    np.testing.assert_allclose(back[1].temp_c, sessions[1].temp_c, rtol=2.0**-24)
    # IMU 0: the selected accelerometer's 1 Hz temperature, held from each reading to the next.
    held = sessions[0].temp_c[np.searchsorted(np.floor(sessions[0].t_s), np.floor(sessions[0].t_s))]
    np.testing.assert_allclose(back[0].temp_c, held, rtol=2.0**-24)
    # The slow temperature instance is not an IMU of its own: it is left out, and says why.
    assert stats.skipped == {} or all("Hz" in v for v in stats.skipped.values())


def test_a_slow_instance_is_left_out_and_the_reason_kept(tmp_path):
    fast = _sessions(n=400, imus=(0,))
    slow = _sessions(n=20, rate_hz=2.0, imus=(1,))
    path = tmp_path / "slow.ulg"
    write_ulog(path, {**fast, **slow})
    back, stats = read_log_sessions(path)
    assert sorted(back) == [0]
    assert stats.skipped == {"sensor_accel.0": "logged at 2 Hz, below 20 Hz"}


def test_a_ulog_without_imu_topics_says_what_it_holds(tmp_path):
    path = tmp_path / "status.ulg"
    write_ulog(path, _sessions(n=1000, imus=(0,)), topics=["vehicle_status"])
    with pytest.raises(NoImuDataError, match=r"no IMU data \(topics sensor_combined") as info:
        read_log_sessions(path)
    assert "the log holds vehicle_status.0 5" in str(info.value)


def test_corrupt_bytes_are_skipped_to_the_next_sync_and_counted(tmp_path):
    sessions = _sessions(n=3000, imus=(0,))
    path = tmp_path / "bad.ulg"
    write_ulog(path, sessions)
    data = bytearray(path.read_bytes())
    syncs = [k for k in range(len(data)) if data.startswith(SYNC_BYTES, k)]
    cut = syncs[1] + len(SYNC_BYTES)  # the header of the message after the second sync
    data[cut : cut + 3] = b"\x00\x00\x00"  # a message of size 0: corrupt
    path.write_bytes(bytes(data))
    back, stats = read_log_sessions(path)
    assert stats.dropped["corrupt_messages"] >= 1
    # The thousand messages up to the next sync are lost (a few of them temperature readings), the rest is read.
    assert 3000 - 1000 <= back[0].n_samples <= 3000 - 990
    np.testing.assert_allclose(back[0].accel_mps2[-1], sessions[0].accel_mps2[-1], rtol=2.0**-24)


def test_long_logs_decode_in_flushes_with_the_same_result(tmp_path):
    n = FLUSH_MESSAGES + 1000  # more than one flush of the stream
    sessions = _sessions(n=n, imus=(0, 1))
    path = tmp_path / "long.ulg"
    write_ulog(path, sessions)
    reader = LogReader(path, batch_samples=500)
    batches = list(reader)
    assert reader.stats.samples == {0: n, 1: n} and reader.fraction_read == 1.0
    assert [b.seq for b in batches if b.imu == 1] == list(range(len(batches) // 2 + 1))[
        : n // 500 + 1
    ]


@needs(REAL_ULOG)
def test_real_px4_log_matches_pyulog():
    """PX4 SITL flight (SOURCE.md): sensor_combined at 250 Hz; the per-instance topics are logged at 1–2 Hz."""
    stream = UlogImuStream(REAL_ULOG)
    assert stream.contents.system == "PX4 PX4_SITL"
    back, stats = read_log_sessions(REAL_ULOG)
    assert sorted(back) == [0] and stats.samples == {0: 7783} and stats.dropped == {}
    assert stats.skipped == {
        "sensor_accel.0": "logged at 1 Hz, below 20 Hz",
        "vehicle_imu.0": "logged at 2 Hz, below 20 Hz",
    }
    s = back[0]
    # Time stamps are µs of the simulator's UNIX-like clock (1.7e9 s): float64 resolves 0.24 µs there.
    assert 1.0 / np.median(np.diff(s.t_s)) == pytest.approx(250.0, abs=0.01)
    assert s.t_s[-1] - s.t_s[0] == pytest.approx(31.128, abs=1e-3)
    assert s.temp_c is None  # SITL logs 0 °C: no sensor temperature
    assert stats.clipped == {0: 0}
    assert stats.held["sensor_combined.0"] == 7783 and stats.held["vehicle_imu.0"] == 62
    ref = ULog(str(REAL_ULOG), ["sensor_combined"]).get_dataset("sensor_combined").data
    np.testing.assert_array_equal(s.t_s, ref["timestamp"] * 1e-6)
    for k in range(3):
        np.testing.assert_array_equal(s.accel_mps2[:, k], ref[f"accelerometer_m_s2[{k}]"])
        np.testing.assert_array_equal(s.gyro_rps[:, k], ref[f"gyro_rad[{k}]"])
