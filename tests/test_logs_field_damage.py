"""Damaged logs as the field produces them (a fuzzing pass found each): a clear error or a counted rejection.

Every damaged input is built here from the project's own log writers and a few hand-made bytes.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from pymavlink import DFReader
from pyulog import ULog

from estimators.session import ImuSession
from protocols import ulog as ulog_module
from protocols.logs import (
    LogReader,
    NoImuDataError,
    read_log_sessions,
    write_dataflash_bin,
    write_dataflash_text,
    write_tlog,
)
from protocols.ulog import MAX_FLAT_FIELDS, NearestPairer, UlogError, write_ulog
from service.cli import EXIT_UNTESTED, main
from service.commands import replay as replay_command

N = 40
FMT_OF_FMT = "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n"


def _session(n: int = N, rate_hz: float = 200.0) -> dict[int, ImuSession]:
    rng = np.random.default_rng(7)
    t = 10.0 + np.arange(n) / rate_hz
    acc = rng.normal([0.3, -0.2, -9.8], 0.05, (n, 3))
    temp_c = 30.0 + 0.01 * np.arange(n, dtype=np.float64)
    return {0: ImuSession(t, acc, rng.normal(0.0, 0.01, (n, 3)), temp_c)}


def _fmt(type_id: int, length: int, name: bytes, fmt: bytes, columns: bytes) -> bytes:
    """A binary ``FMT`` message."""
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name, fmt, columns)


def _imu_offsets(data: bytes) -> list[int]:
    """Where the ``IMU`` messages (type 129, as the writer numbers it) of a binary log start."""
    first = data.index(b"\xa3\x95\x81", 2 * 89)  # after the two FMT messages
    size = (len(data) - first) // N
    return [first + k * size for k in range(N)]


def _text_lines(tmp_path, name: str = "flight.log") -> tuple[object, list[str]]:
    path = tmp_path / name
    write_dataflash_text(path, _session())
    return path, path.read_text().splitlines()


def _replay(capsys, *argv) -> tuple[int, str, str]:
    """Exit status, stdout without the coverage line that ends ``--json`` output, stderr."""
    status = main(["replay", *map(str, argv)])
    out = capsys.readouterr()
    lines = out.out.splitlines(keepends=True)
    if lines and '"type": "ins.health.coverage"' in lines[-1]:
        lines.pop()
    return status, "".join(lines), out.err


# ------------------------------------------------------------------ C1, C2: unusable FMT definitions


@pytest.mark.parametrize(
    "fmt_line",
    [
        "FMT, 129, 52, IMU, QBfffffff, TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,T,Extra\n",
        "FMT, 129, 3, IMU, , TimeUS\n",
    ],
    ids=["more-columns-than-format", "empty-format"],
)
def test_text_fmt_with_more_columns_than_format_is_a_counted_corrupt_message(tmp_path, fmt_line):
    path, lines = _text_lines(tmp_path)
    path.write_text("\n".join([lines[0], fmt_line.rstrip(), *lines[2:]]) + "\n")
    with pytest.raises(NoImuDataError, match=r"IMU 40; left out: corrupt_messages 1$"):
        read_log_sessions(path)


def test_binary_fmt_with_more_columns_than_format_is_counted_and_its_bytes_skipped(tmp_path):
    path = tmp_path / "flight.bin"
    write_dataflash_bin(path, _session())
    data = path.read_bytes()
    bad = _fmt(129, 38, b"IMU", b"QBfffffff", b"TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,T,Extra")
    path.write_bytes(data[:89] + bad + data[2 * 89 :])
    reader = LogReader(path)
    with pytest.raises(NoImuDataError, match="corrupt_messages 1, skipped_bytes"):
        list(reader)
    # Past the refused FMT's header, its body and the messages of the type it failed to define
    # start no message: every one of their bytes is skipped.
    assert reader.stats.skipped_bytes == len(data) - 89 - 3


def test_an_fmt_redefining_fmt_is_a_counted_corrupt_message(tmp_path):
    path = tmp_path / "flight.bin"
    write_dataflash_bin(path, _session())
    data = path.read_bytes()
    path.write_bytes(data[:89] + _fmt(128, 5, b"FMT", b"BB", b"Type,Length") + data[89:])
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N and stats.dropped == {"corrupt_messages": 1}


# ------------------------------------------------------------------ C3, C4, U3, U4: field values


@pytest.mark.parametrize("instance", ["inf", "300"])
def test_an_instance_field_that_is_no_uint8_is_a_counted_corrupt_message(tmp_path, instance):
    """``I`` declared a float (``f``), as a damaged FMT may: neither inf nor 300 is an instance."""
    path, lines = _text_lines(tmp_path)
    lines[1] = lines[1].replace("QBfffffff", "Qffffffff")
    row = lines[5].split(", ")
    row[2] = instance  # IMU, TimeUS, I, ...
    lines[5] = ", ".join(row)
    path.write_text("\n".join(lines) + "\n")
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N - 1 and stats.dropped == {"corrupt_messages": 1}


@pytest.mark.parametrize("sample_us", [str(2**64), "-5"])
def test_acc_sample_time_outside_uint64_is_a_counted_corrupt_message(tmp_path, sample_us):
    path = tmp_path / "raw.log"
    rows = [FMT_OF_FMT]
    rows.append("FMT, 130, 35, ACC, QBQfff, TimeUS,I,SampleUS,AccX,AccY,AccZ\n")
    rows.append("FMT, 131, 35, GYR, QBQfff, TimeUS,I,SampleUS,GyrX,GyrY,GyrZ\n")
    for k in range(N):
        t_us = str(1000 * (k + 1)) if k != 5 else sample_us
        rows.append(f"ACC, {1000 * (k + 1)}, 0, {t_us}, 0.1, 0.2, -9.8\n")
        rows.append(f"GYR, {1000 * (k + 1)}, 0, {1000 * (k + 1)}, 0.01, 0.0, 0.0\n")
    path.write_text("".join(rows))
    back, stats = read_log_sessions(path)
    assert back[3].n_samples == N - 1 and stats.dropped == {"corrupt_messages": 1}


def test_a_text_field_declared_a_string_is_a_counted_corrupt_message(tmp_path):
    """AccX declared ``N`` (char[16]): pymavlink gives a string; one that is no number is counted."""
    path, lines = _text_lines(tmp_path)
    lines[1] = lines[1].replace("QBfffffff", "QBfffNfff")
    row = lines[5].split(", ")
    row[6] = "x"  # IMU, TimeUS, I, GyrX, GyrY, GyrZ, AccX
    lines[5] = ", ".join(row)
    path.write_text("\n".join(lines) + "\n")
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N - 1 and stats.dropped == {"corrupt_messages": 1}


def test_a_non_finite_vibe_clip_counter_is_a_counted_corrupt_message(tmp_path):
    path, lines = _text_lines(tmp_path)
    vibe = ["FMT, 140, 16, VIBE, QBf, TimeUS,IMU,Clip", "VIBE, 1, 0, 2", "VIBE, 2, 0, inf"]
    path.write_text("\n".join([*lines, *vibe, "VIBE, 3, 0, 5"]) + "\n")
    _, stats = read_log_sessions(path)
    assert stats.clipped == {0: 3} and stats.dropped == {"corrupt_messages": 1}


# ------------------------------------------------------------------ U5: what a damaged log holds


def test_no_imu_data_lists_readable_names_only_and_a_bounded_number(tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "garbled.log"
    named = [f"M{k}, 1\n".encode() for k in range(60)]
    garbled = [rng.integers(0, 256, 40, dtype=np.uint8).tobytes() + b", 1\n" for _ in range(30)]
    path.write_bytes(FMT_OF_FMT.encode() + b"".join(named + garbled))
    with pytest.raises(NoImuDataError) as err:
        read_log_sessions(path)
    text = str(err.value)
    assert len(text.splitlines()) == 1 and "\\x" not in text
    assert "M43 1 and 21 more types" in text and "messages with unreadable names" in text


# ------------------------------------------------------------------ S1, S2, S3: bytes not read


def test_binary_bytes_skipped_to_the_next_message_are_counted(tmp_path):
    path = tmp_path / "flight.bin"
    write_dataflash_bin(path, _session())
    data = path.read_bytes()
    at = _imu_offsets(data)[10]
    path.write_bytes(data[:at] + bytes(4096) + data[at:])
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N and stats.skipped_bytes == 4096
    assert stats.left_out() == "skipped_bytes 4096"


def test_tlog_packets_with_a_bad_crc_are_counted(tmp_path):
    path = tmp_path / "flight.tlog"
    write_tlog(path, _session())
    data = bytearray(path.read_bytes())
    record = len(data) // N  # 8-byte stamp and a RAW_IMU packet
    data[20 * record + 8 + 12] ^= 0x20  # a payload byte of the 21st packet
    path.write_bytes(bytes(data))
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N - 1 and stats.dropped == {"corrupt_messages": 1}
    assert stats.skipped_bytes == record - 8


def _cut_text(path) -> int:
    data = path.read_bytes()
    start = data.index(b"\nIMU", len(data) // 2) + 1
    path.write_bytes(data[: start + 12])
    return start


def _cut_binary(path) -> int:
    start = _imu_offsets(path.read_bytes())[N // 2]
    path.write_bytes(path.read_bytes()[: start + 12])
    return start


@pytest.mark.parametrize(
    "suffix, writer, cut",
    [
        ("bin", write_dataflash_bin, _cut_binary),
        ("log", write_dataflash_text, _cut_text),
        ("tlog", write_tlog, None),
        ("ulg", write_ulog, None),
    ],
)
def test_a_file_cut_mid_message_says_where(tmp_path, capsys, suffix, writer, cut):
    path = tmp_path / f"flight.{suffix}"
    writer(path, _session())
    if cut is None:  # a tlog or ULog record: the last one is cut 5 bytes short
        data = path.read_bytes()
        path.write_bytes(data[:-5])
        _, stats = read_log_sessions(path)
        assert stats.cut_at_byte is not None and len(data) - 60 < stats.cut_at_byte < len(data) - 5
    else:
        start = cut(path)
        _, stats = read_log_sessions(path)
        assert stats.cut_at_byte == start
    status, _, err = _replay(capsys, path, "--json")
    assert (
        status == EXIT_UNTESTED
        and f"is cut mid-message at byte {stats.cut_at_byte}: read up to" in err
    )


# ------------------------------------------------------------------ C5, M1, S4, U1, U2: ULog


def _insert_before_subscriptions(path, *messages: bytes) -> None:
    """Add definition messages (``uint16 size, type, payload``) just before the first ``A`` message."""
    data = path.read_bytes()
    pos = 16
    while data[pos + 2] != ord("A"):
        pos += 3 + struct.unpack_from("<H", data, pos)[0]
    path.write_bytes(data[:pos] + b"".join(messages) + data[pos:])


def _ulog_message(mtype: bytes, payload: bytes) -> bytes:
    return struct.pack("<H", len(payload)) + mtype + payload


def test_a_ulog_topic_format_that_nests_itself_is_a_clear_error(tmp_path):
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session())
    _insert_before_subscriptions(path, _ulog_message(b"F", b"sensor_selection:sensor_selection x;"))
    with pytest.raises(
        UlogError,
        match=r"topic sensor_selection: .* nests itself: sensor_selection > sensor_selection$",
    ):
        read_log_sessions(path)


def test_a_ulog_format_flattening_past_any_message_is_refused_at_once(tmp_path, capsys):
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session())
    nested = [b"n1:float[1000] a;", b"n2:n1[1000] b;", b"n3:n2[1000] c;", b"sensor_selection:n3[1000] d;"]  # fmt: skip
    _insert_before_subscriptions(path, *(_ulog_message(b"F", f) for f in nested))
    status, out, err = _replay(capsys, path, "--json")
    assert status == 2 and out == "" and len(err.splitlines()) == 1
    assert f"topic sensor_selection: format 'sensor_selection' flattens to more than {MAX_FLAT_FIELDS}" in err  # fmt: skip


def test_definitions_followed_by_erased_flash_are_refused_within_the_read_budget(
    tmp_path, capsys, monkeypatch
):
    # The definitions, then erased flash: pyulog steps a byte at a time and re-reads 64 KiB each.
    monkeypatch.setattr(ulog_module, "DEFINITIONS_READ_BUDGET_BYTES", 1 << 20)
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session())
    data = path.read_bytes()
    pos = 16
    while data[pos + 2] != ord("A"):
        pos += 3 + struct.unpack_from("<H", data, pos)[0]
    path.write_bytes(data[:pos] + b"\xff" * (64 << 10))
    status, out, err = _replay(capsys, path, "--json")
    assert status == 2 and out == ""
    assert "its definitions are corrupt beyond repair: pyulog read 1048576 bytes" in err
    # The whole file reads well within the same budget.
    write_ulog(path, _session())
    assert _replay(capsys, path, "--json")[0] == EXIT_UNTESTED


def test_pyulog_findings_stay_off_stdout_and_are_counted(tmp_path, capsys):
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session())
    _insert_before_subscriptions(
        path, _ulog_message(b"I", b"\xff")
    )  # a key longer than the message
    status, out, err = _replay(capsys, path, "--json")
    assert status == EXIT_UNTESTED and out == "" and "left out corrupt_messages 1;" in err


def test_a_ulog_topic_without_a_field_it_is_read_from_is_left_out_with_the_reason(tmp_path):
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session())
    path.write_bytes(path.read_bytes().replace(b"float[3] gyro_rad;", b"float[3] gyro_xyz;"))
    with pytest.raises(
        NoImuDataError,
        match=r"left out: sensor_combined\.0 its format has no numeric field gyro_rad\[3\]",
    ):
        read_log_sessions(path)


def test_pairing_with_no_accelerometer_sample_ready_gives_empty_rows():
    dtype = np.dtype([("timestamp_sample", "<u8"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("clip_counter", "u1", (3,))])  # fmt: skip
    pairer = NearestPairer("sensor_accel+sensor_gyro", 1)
    gyro, accel = np.zeros(3, dtype), np.zeros(3, dtype)
    gyro["timestamp_sample"] = [1000, 2000, 3000]
    accel["timestamp_sample"] = [
        9000,
        10000,
        11000,
    ]  # all later than the last gyro sample: they wait
    pairer.add(False, gyro)
    pairer.add(True, accel)
    rows = pairer.paired()
    assert rows is not None and rows.t_s.size == 0 and rows.clipped.shape == (0,)


def _without_last_gyro_messages(path, name: str, n_last: int) -> None:
    """Rewrite a ULog without the last ``n_last`` data messages of topic ``name`` (all instances)."""
    data = path.read_bytes()
    pos, ids, kept, found = 16, {}, [data[:16]], []
    while pos < len(data):
        size, mtype = struct.unpack_from("<HB", data, pos)
        msg = data[pos : pos + 3 + size]
        if mtype == ord("A"):
            ids[struct.unpack_from("<H", msg, 4)[0]] = msg[6:].decode()
        if mtype == ord("D") and ids.get(struct.unpack_from("<H", msg, 3)[0]) == name:
            found.append(len(kept))
        kept.append(msg)
        pos += 3 + size
    for k in found[-n_last:]:
        kept[k] = b""
    path.write_bytes(b"".join(kept))


def test_accelerometer_samples_after_the_last_gyro_sample_are_counted_not_lost(tmp_path, capsys):
    """A log whose gyro stream stops before the accelerometer's: the accelerometer samples left
    waiting for a gyro sample at the end are said (they were dropped without a word). DataFlash
    ACC/GYR and a ULog sensor_accel/sensor_gyro pair; pyulog confirms what the edited ULog holds."""
    rows = [FMT_OF_FMT]
    rows.append("FMT, 130, 35, ACC, QBQfff, TimeUS,I,SampleUS,AccX,AccY,AccZ\n")
    rows.append("FMT, 131, 35, GYR, QBQfff, TimeUS,I,SampleUS,GyrX,GyrY,GyrZ\n")
    for k in range(N):
        rows.append(f"ACC, {1000 * (k + 1)}, 0, {1000 * (k + 1)}, 0.1, 0.2, -9.8\n")
        if k < N - 7:
            rows.append(f"GYR, {1000 * (k + 1)}, 0, {1000 * (k + 1)}, 0.01, 0.0, 0.0\n")
    path = tmp_path / "raw.log"
    path.write_text("".join(rows))
    back, stats = read_log_sessions(path)
    assert back[3].n_samples == N - 7
    assert stats.skipped == {"ACC.0": "7 samples without a GYR sample near in time"}

    n = 600
    session = _session(n=n, rate_hz=200.0)[0]
    ulg = tmp_path / "flight.ulg"
    write_ulog(ulg, {1: session})
    _without_last_gyro_messages(ulg, "sensor_gyro", 30)
    by_topic = {(d.name, d.multi_id): len(d.data["timestamp"]) for d in ULog(str(ulg)).data_list}
    assert by_topic[("sensor_accel", 0)] == n and by_topic[("sensor_gyro", 0)] == n - 30
    back, stats = read_log_sessions(ulg)
    assert back[1].n_samples == n - 30
    assert stats.skipped == {
        "sensor_accel.0": "30 samples without a sensor_gyro sample near in time"
    }
    status, _, err = _replay(capsys, ulg)
    assert status == EXIT_UNTESTED
    assert (
        "not replayed: sensor_accel.0 30 samples without a sensor_gyro sample near in time" in err
    )


def _ulog_with_dropouts(path, dropouts_ms: dict[float, int]) -> None:
    """A ULog of 30 s of IMU 0 at 250 Hz in which the logger lost, at each time (s), that many ms:
    the samples of that stretch are missing and a dropout message stands in their place, as PX4 writes it."""
    n = 7500
    session = _session(n=n, rate_hz=250.0)[0]
    lost = np.zeros(n, bool)
    for t0, ms in dropouts_ms.items():
        lost |= (session.t_s >= t0) & (session.t_s < t0 + ms * 1e-3)
    keep = ~lost
    write_ulog(
        path,
        {0: ImuSession(session.t_s[keep], session.accel_mps2[keep], session.gyro_rps[keep], None)},
    )
    data, out, pos = path.read_bytes(), [], 16
    out.append(data[:16])
    pending = sorted(dropouts_ms.items())
    while pos < len(data):
        size, mtype = struct.unpack_from("<HB", data, pos)
        if (
            mtype == ord("D")
            and pending
            and struct.unpack_from("<Q", data, pos + 5)[0] >= pending[0][0] * 1e6
        ):
            out.append(_ulog_message(b"O", struct.pack("<H", pending.pop(0)[1])))
        out.append(data[pos : pos + 3 + size])
        pos += 3 + size
    path.write_bytes(b"".join(out))


def test_ulog_dropouts_are_said_as_the_loggers_with_their_duration(tmp_path, capsys):
    """PX4's logger writes a dropout message where its buffer overflowed: the replay says how often and
    how long, so the gaps in the samples are not taken for the sensor's (pyulog reads the same dropouts)."""
    path = tmp_path / "dropouts.ulg"
    _ulog_with_dropouts(path, {20.0: 600, 25.0: 150})
    assert [d.duration for d in ULog(str(path)).dropouts] == [600, 150]
    _, stats = read_log_sessions(path)
    assert (stats.logger_lost, stats.logger_lost_ms) == (2, 750)
    status, _, err = _replay(capsys, path)
    assert status == EXIT_UNTESTED
    assert "dropouts.ulg: the logger lost data 2 times, 750 ms in all (ULog dropouts)" in err
    write_ulog(path, _session())
    assert read_log_sessions(path)[1].logger() == ""


def test_dataflash_refused_writes_are_said_from_the_growth_of_dsf_dp(tmp_path, capsys):
    """ArduPilot's DSF.Dp counts the writes its logger refused; the log's are the counter's growth from
    its first DSF, a lower value being a counter cleared since (3 → 3 → 10 → 2 → 5: 7 + 2 + 3)."""
    path, lines = _text_lines(tmp_path)
    lines.append("FMT, 246, 34, DSF, QIBHIIII, TimeUS,Dp,IErr,Blk,Bytes,FMn,FMx,FAv")
    for k, dp in enumerate([3, 3, 10, 2, 5]):
        lines.append(f"DSF, {10_000_000 + k * 1_000_000}, {dp}, 0, {k}, {4096 * k}, 100, 200, 150")
    path.write_text("\n".join(lines) + "\n")
    oracle = DFReader.DFReader_text(str(path))
    dp = []
    while (m := oracle.recv_match(type="DSF")) is not None:
        dp.append(m.Dp)
    assert dp == [3, 3, 10, 2, 5]
    _, stats = read_log_sessions(path)
    assert stats.logger_lost == 12 and stats.logger_lost_ms is None
    status, _, err = _replay(capsys, path)
    assert status == EXIT_UNTESTED and "flight.log: the logger refused 12 writes (DSF.Dp)" in err


def _log_with_times(tmp_path, t_us: list[int]):
    """A text DataFlash log of one IMU whose samples carry these TimeUS (µs), in this order."""
    path = tmp_path / "times.log"
    write_dataflash_text(path, _session(n=len(t_us)))
    lines = path.read_text().splitlines()
    imu = [k for k, line in enumerate(lines) if line.startswith("IMU,")]
    for k, t in zip(imu, t_us, strict=True):
        row = lines[k].split(", ")
        row[1] = str(t)
        lines[k] = ", ".join(row)
    path.write_text("\n".join(lines) + "\n")
    return path


_STEP = 5000  # µs: 200 Hz


@pytest.mark.parametrize(
    ("times", "kept", "dropped", "restarts"),
    [
        # a real 5 s gap in the log: both sides kept
        ([_STEP * k for k in range(40)] + [5_000_000 + _STEP * k for k in range(40)], 80, {}, 0),
        # the last sample 10 s ahead: nothing after it to say it went wrong, kept
        ([_STEP * k for k in range(40)] + [10_000_000], 41, {}, 0),
        # one stamp 2^32 µs ahead, then the clock goes on
        (
            [_STEP * k for k in range(20)] + [2**32] + [_STEP * k for k in range(21, 40)],
            39,
            {"time_glitch": 1},
            0,
        ),
        # five late samples (older than the last, increasing), then the clock goes on
        (
            [_STEP * k for k in range(40)]
            + [_STEP * k for k in range(5)]
            + [_STEP * k for k in range(40, 60)],
            60,
            {"time_not_increasing": 5},
            0,
        ),
        # the clock started again: 30 samples from 0 after 40
        ([_STEP * k for k in range(40)] + [_STEP * k for k in range(30)], 70, {}, 1),
        # fewer late samples than a restart at the end of the log
        (
            [_STEP * k for k in range(40)] + [_STEP * k for k in range(10)],
            40,
            {"time_not_increasing": 10},
            0,
        ),
        # duplicates
        ([_STEP * (k // 2) for k in range(40)], 20, {"time_not_increasing": 20}, 0),
    ],
    ids=["gap", "last-ahead", "glitch", "late-run", "restart", "late-run-at-end", "duplicates"],
)
@pytest.mark.parametrize("batch", [1, 7, 100])
def test_time_order_glitches_late_samples_and_restarts(
    tmp_path, times, kept, dropped, restarts, batch
):
    """What the reader keeps of an IMU's samples whose time stamps are out of order, in each case
    counted: kept + dropped = all, and the kept ones increase but across a restart."""
    path = _log_with_times(tmp_path, times)
    reader = LogReader(path, vehicle="v", batch_samples=batch)
    t = np.concatenate([b.t_s for b in reader])
    stats = reader.stats
    assert (t.size, stats.dropped, stats.clock_restarts) == (kept, dropped, restarts)
    assert t.size + sum(stats.dropped.values()) == len(times)
    assert int((np.diff(t) <= 0).sum()) == restarts


def test_text_imu_lines_cut_short_are_counted_corrupt(tmp_path):
    """Every other IMU line of a text log missing its last field was skipped without a count
    ('left out none'); a binary message that does not decode is counted, and now so is such a line."""
    path, lines = _text_lines(tmp_path)
    imu = [k for k, line in enumerate(lines) if line.startswith("IMU,")]
    for k in imu[::2]:
        lines[k] = lines[k].rsplit(", ", 1)[0]
    path.write_text("\n".join(lines) + "\n")
    back, stats = read_log_sessions(path)
    assert back[0].n_samples == N - len(imu[::2])
    assert stats.dropped == {"corrupt_messages": len(imu[::2])}


def test_ulog_data_whose_subscription_is_lost_is_counted(tmp_path):
    """The subscription ('A') of sensor_combined lost: its data messages name a topic nobody knows.
    They were passed over without a count; now the log says how many there were."""
    path = tmp_path / "flight.ulg"
    write_ulog(path, _session(n=200))
    data, out, pos = path.read_bytes(), [], 16
    out.append(data[:16])
    while pos < len(data):
        size, mtype = struct.unpack_from("<HB", data, pos)
        msg = data[pos : pos + 3 + size]
        if not (mtype == ord("A") and msg.endswith(b"sensor_combined")):
            out.append(msg)
        pos += 3 + size
    path.write_bytes(b"".join(out))
    with pytest.raises(NoImuDataError, match=r"left out: data_without_subscription 200"):
        read_log_sessions(path)


# ------------------------------------------------------------------ C6, H2: --pace recorded


@pytest.mark.parametrize("jump_us", [10**10, 10**17], ids=["1e4-s", "1e11-s-past-what-sleep-takes"])
def test_paced_replay_does_not_wait_through_a_time_jump(tmp_path, capsys, monkeypatch, jump_us):
    """200 samples at 500 Hz with a jump in log time after sample 150: ~0.4 s of waits, the jump not waited for."""
    path = tmp_path / "jump.bin"
    session = _session(n=200, rate_hz=500.0)
    write_dataflash_bin(path, session)
    data = bytearray(path.read_bytes())
    first = data.index(b"\xa3\x95\x81", 2 * 89)
    size = (len(data) - first) // 200
    for k in range(150, 200):
        at = first + k * size + 3
        (t_us,) = struct.unpack_from("<Q", data, at)
        struct.pack_into("<Q", data, at, t_us + jump_us)
    path.write_bytes(bytes(data))
    sleeps: list[float] = []
    monkeypatch.setattr(replay_command.time, "sleep", sleeps.append)
    status, _, err = _replay(capsys, path, "--json", "--pace", "recorded")
    assert status == EXIT_UNTESTED and "samples IMU0 200" in err
    assert "--pace recorded: 1 steps of log time over 60 s not waited for" in err
    assert sum(sleeps) < 1.0


def test_tlog_highres_messages_without_their_accel_and_gyro_flagged_updated_are_counted_out(
    tmp_path,
):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from protocols.mavlink_adapter import ImuMessage, imu_message

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    records = []
    for k in range(300):
        msg = imu_message(
            ImuMessage.HIGHRES_IMU,
            t_s=10.0 + k / 200,
            accel_mps2=(0.0, 0.0, -9.8),
            gyro_rps=(0, 0, 0),
        )
        if k % 30 == 7:
            msg.fields_updated = 0b111000  # the accelerometer fields not updated (held or zeroed)
        records.append(struct.pack(">Q", int(1.7e15) + 5000 * k) + msg.pack(mav))
    path = tmp_path / "flight.tlog"
    path.write_bytes(b"".join(records))
    reader = LogReader(path)
    assert sum(b.n_samples for b in reader) == 290
    assert reader.stats.dropped == {"fields_not_updated": 10}
