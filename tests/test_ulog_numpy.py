"""ULog data messages found in runs (:mod:`protocols.ulog_numpy`) against the stream's own loop, one
message a step: the same batches and counts on every real ULog and on damaged ones."""

from __future__ import annotations

import random

import numpy as np
import pytest
from log_oracle import assert_same_reading, three_imus
from real_data import FIELD, LOGS, needs

from protocols import ulog
from protocols.logs import LogReader
from protocols.ulog import write_ulog

REAL_ULOGS = sorted(LOGS.glob("*.ulg")) + sorted(FIELD.glob("*.ulg"))


def _one_at_a_time(buf, pos, stop, max_size):
    """No run: the stream reads every message with its own loop (the oracle)."""
    empty = np.zeros(0, dtype=np.int64)
    return empty, empty.astype(np.uint8), empty


def _read(path, monkeypatch, runs: bool):
    if not runs:
        monkeypatch.setattr(ulog, "message_run", _one_at_a_time)
    reader = LogReader(path, batch_samples=64)
    out = [(b.imu, b.seq, b.run, b.t_s, b.accel_mps2, b.gyro_rps, b.temp_c) for b in reader]
    monkeypatch.undo()
    return out, reader.stats


def _assert_same_as_the_loop(path, monkeypatch):
    assert_same_reading(_read(path, monkeypatch, True), _read(path, monkeypatch, False))


@pytest.mark.parametrize("path", REAL_ULOGS, ids=lambda p: p.name)
@needs(LOGS)
def test_every_real_ulog_reads_as_the_loop_reads_it(path, monkeypatch):
    _assert_same_as_the_loop(path, monkeypatch)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("how", ["clean", "cut", "junk", "bit_flips", "huge_size"])
def test_damaged_ulogs_read_as_the_loop_reads_them(tmp_path, monkeypatch, how, seed):
    """Three IMUs (sensor_combined and two sensor_accel/sensor_gyro pairs), damaged one way."""
    rng = random.Random(seed)
    path = tmp_path / "flight.ulg"
    write_ulog(path, three_imus(1500, seed=seed))
    data = bytearray(path.read_bytes())
    at = rng.randrange(600, len(data))
    if how == "cut":
        data = data[:at]
    elif how == "junk":
        data[at:at] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))
    elif how == "bit_flips":
        for _ in range(10):
            data[rng.randrange(600, len(data))] ^= 1 << rng.randrange(8)
    elif how == "huge_size":  # a header whose size is past any message (corrupt: to the next sync)
        data[at : at + 3] = b"\xff\xff\x44"
    path.write_bytes(bytes(data))
    _assert_same_as_the_loop(path, monkeypatch)


@pytest.mark.parametrize(
    "short",
    [b"\x01\x00D\x07", b"\x01\x00A\x00", b"\x02\x00A\x00\x00"],
    ids=["data_of_one_byte", "subscription_of_one_byte", "subscription_of_two_bytes"],
)
@pytest.mark.parametrize("where", ["at_the_end", "mid_log"])
def test_a_message_too_short_for_its_fields_is_corrupt(tmp_path, monkeypatch, short, where):
    """A data message holds a uint16 msg_id, a subscription a uint8 and a uint16: one shorter was
    read past its end, and at the file's end that raised (IndexError, struct.error) instead of a
    counted corrupt message. Mid-log it is skipped by its size, the samples all read."""
    clean = tmp_path / "clean.ulg"
    write_ulog(clean, three_imus(300, seed=0))
    data = clean.read_bytes()
    path = tmp_path / "flight.ulg"
    # mid-log: a dropout message (5 ms) after it
    path.write_bytes(data + short + (b"\x02\x00O\x05\x00" if where == "mid_log" else b""))
    want, _ = _read(clean, monkeypatch, True)
    for runs in (True, False):
        got, stats = _read(path, monkeypatch, runs)
        assert stats.dropped.get("corrupt_messages") == 1
        assert_same_reading((got, None), (want, None))
