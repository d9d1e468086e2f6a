"""The numpy DataFlash reader against pymavlink's per-message decoding, its oracle.

:mod:`protocols.dataflash_numpy` must give :class:`protocols.logs.LogReader` the same batches (IMU,
order, samples, values bit for bit) and the same counts (``LogStats``: what is held, left out,
skipped, where a file is cut) as ``DataFlashStream`` with pymavlink's ``DFMessage``, on every real
log and on logs damaged every way a field log is: cut anywhere, bits flipped, junk and stray start
bytes inserted, formats redefined or wrong mid-log.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from log_oracle import assert_same_as_pymavlink, current_and_legacy
from real_data import SHARED, needs

from protocols.byte_chain import chain, walk
from protocols.logs import write_dataflash_bin

REAL_BINS = sorted(SHARED.glob("data/logs/*.BIN")) + sorted(SHARED.glob("data/field/*.bin"))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, bytes]:
    """Three IMUs, in current ArduPilot's ``IMU`` with instance and in the legacy IMU/IMU2/IMU3 names."""
    return current_and_legacy(tmp_path_factory.mktemp("df"), write_dataflash_bin, "bin", 700)


@pytest.mark.parametrize("path", REAL_BINS, ids=lambda p: p.name)
@needs(SHARED / "data" / "logs")
def test_every_real_binary_log_reads_as_pymavlink_reads_it(path, monkeypatch):
    assert_same_as_pymavlink(path, monkeypatch)


@pytest.mark.parametrize("batch", [1, 100, 1000])
@pytest.mark.parametrize("legacy", [False, True])
def test_clean_logs_of_three_imus_in_every_batch_size(tmp_path, clean, monkeypatch, legacy, batch):
    path = tmp_path / "flight.bin"
    path.write_bytes(clean[f"legacy{legacy}"])
    assert_same_as_pymavlink(path, monkeypatch, batch_samples=batch)


def _damaged(data: bytes, how: str, rng: np.random.Generator) -> bytes:
    """``data`` damaged one way (a seeded draw of where and what)."""
    b = bytearray(data)
    if how == "cut":
        return bytes(b[: int(rng.integers(1, len(b)))])
    if how == "bit_flips":
        for at in rng.integers(0, len(b), 20):
            b[at] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    at = int(rng.integers(200, len(b)))
    inserted = {
        "junk": rng.integers(0, 256, int(rng.integers(1, 300))).astype(np.uint8).tobytes(),
        "stray_a3": b"\xa3",
        "stray_header": b"\xa3\x95",
        "stray_typed_header": b"\xa3\x95\x81",
        "zeros": bytes(int(rng.integers(1, 4096))),
    }[how]
    return bytes(b[:at]) + inserted + bytes(b[at:])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    "how",
    ["cut", "bit_flips", "junk", "stray_a3", "stray_header", "stray_typed_header", "zeros"],
)
def test_damaged_logs_read_as_pymavlink_reads_them(tmp_path, clean, monkeypatch, how, seed):
    rng = np.random.default_rng(seed)
    path = tmp_path / "flight.bin"
    for data in clean.values():
        path.write_bytes(_damaged(data, how, rng))
        assert_same_as_pymavlink(path, monkeypatch, batch_samples=64)


def _fmt(type_id: int, length: int, name: bytes, fmt: bytes, columns: bytes) -> bytes:
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name, fmt, columns)


@pytest.mark.parametrize(
    "middle",
    [
        # a second log after the first (its FMTs again, then its samples: the clock restarts)
        "second_log",
        # IMU redefined with a length its format does not have: its messages are corrupt
        "wrong_length",
        # IMU redefined with its instance a float: those messages go the per-message way
        "float_instance",
        # an FMT cut by junk: refused, its bytes skipped
        "broken_fmt",
    ],
)
def test_formats_defined_mid_log(tmp_path, clean, monkeypatch, middle):
    data = clean["legacyFalse"]
    half = 89 * 2 + 40 * 900  # after the FMTs, at a message boundary (40-byte IMU messages)
    cols = b"TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,T"
    extra = {
        "second_log": data,
        "wrong_length": _fmt(129, 44, b"IMU", b"QBfffffff", cols) + data[2 * 89 :],
        "float_instance": _fmt(129, 43, b"IMU", b"Qffffffff", cols)
        + b"".join(
            b"\xa3\x95\x81" + struct.pack("<Qffffffff", 9_000_000 + k, k % 3, *range(7))
            for k in range(300)
        ),
        "broken_fmt": _fmt(129, 40, b"IMU", b"QBfffffff", cols)[:40] + data[half:],
    }[middle]
    path = tmp_path / "flight.bin"
    path.write_bytes(data[:half] + extra + data[half:])
    assert_same_as_pymavlink(path, monkeypatch, batch_samples=50)


def test_the_chain_is_the_walk_also_beside_a_long_false_chain():
    """A walk's messages found as a set (a few rounds) or, past :data:`ROUNDS`, walked: the same.
    The false chain runs beside the real one to the end, as a payload copying headers would."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 400))
        succ = np.where(rng.random(n) < 0.1, -1, np.arange(n) + rng.integers(1, 4, n)).astype(
            np.int64
        )
        succ[succ >= n] = -1
        first = int(rng.integers(0, n))
        np.testing.assert_array_equal(chain(first, succ), walk(first, succ))
    parallel = np.arange(2, 202, dtype=np.int64)
    parallel[-2:] = -1
    np.testing.assert_array_equal(chain(0, parallel), np.arange(0, 200, 2))
    np.testing.assert_array_equal(chain(-1, parallel), [])
