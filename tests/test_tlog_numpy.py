"""The numpy tlog reader against pymavlink's parsing, its oracle.

:mod:`protocols.tlog_numpy` must give :class:`protocols.logs.LogReader` the same batches and
``LogStats`` as pymavlink's ``mavlogfile`` on the real tlog (MAVLink 1) and on simulated MAVLink 2
logs of every IMU message, clean and damaged (cut anywhere, bits flipped, junk and stray start
bytes inserted, a signed packet): where it cannot read on, pymavlink reads the rest.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from log_oracle import assert_same_as_pymavlink, three_imus
from real_data import REAL_TLOG, needs
from test_dataflash_numpy import _damaged

from protocols.logs import write_tlog
from protocols.mavlink_adapter import ImuMessage, imu_message, mavlink2
from protocols.tlog_numpy import _CRC_TABLE

MESSAGES = {
    "raw_scaled": {0: ImuMessage.RAW_IMU, 1: ImuMessage.SCALED_IMU2, 2: ImuMessage.SCALED_IMU3},
    "highres": {k: ImuMessage.HIGHRES_IMU for k in (0, 1, 2)},
}


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("tlog")
    out = {}
    for name, messages in MESSAGES.items():
        for temp in (True, False):
            path = folder / f"{name}{temp}.tlog"
            write_tlog(path, three_imus(500, seed=len(out), temp=temp), messages=messages)
            out[f"{name}{temp}"] = path.read_bytes()
    return out


@needs(REAL_TLOG)
def test_the_real_mavlink1_tlog_reads_as_pymavlink_reads_it(monkeypatch):
    assert_same_as_pymavlink(REAL_TLOG, monkeypatch)
    assert_same_as_pymavlink(REAL_TLOG, monkeypatch, batch_samples=7)


@pytest.mark.parametrize("batch", [1, 100, 1000])
def test_clean_tlogs_of_every_imu_message(tmp_path, clean, monkeypatch, batch):
    path = tmp_path / "flight.tlog"
    for data in clean.values():
        path.write_bytes(data)
        assert_same_as_pymavlink(path, monkeypatch, batch_samples=batch)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("how", ["cut", "bit_flips", "junk", "zeros", "stray_fd", "stray_fe"])
def test_damaged_tlogs_read_as_pymavlink_reads_them(tmp_path, clean, monkeypatch, how, seed):
    rng = np.random.default_rng(seed)
    path = tmp_path / "flight.tlog"
    for data in clean.values():
        if how in ("stray_fd", "stray_fe"):
            at = int(rng.integers(100, len(data)))
            data = data[:at] + (b"\xfd" if how == "stray_fd" else b"\xfe") + data[at:]
        else:
            data = _damaged(data, how, rng)
        path.write_bytes(data)
        assert_same_as_pymavlink(path, monkeypatch, batch_samples=64)


def _record(msg, mav, t_us: int) -> bytes:
    return struct.pack(">Q", t_us) + msg.pack(mav)


def test_a_signed_packet_and_highres_without_updated_triads(tmp_path, monkeypatch):
    """A signed packet mid-log (the fast path stops; pymavlink reads on) and HIGHRES_IMU messages
    whose ``fields_updated`` leaves out a triad field (counted as pymavlink's path counts them)."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    records = []
    for k in range(600):
        msg = imu_message(
            ImuMessage.HIGHRES_IMU, t_s=1.0 + k / 200, accel_mps2=[0, 0, -9.8], gyro_rps=[0, 0, 0]
        )
        if k % 7 == 3:
            msg.fields_updated &= ~mavlink2.HIGHRES_IMU_UPDATED_YGYRO
        records.append(_record(msg, mav, 1_700_000_000_000_000 + k * 5000))
    signer = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    signer.signing.secret_key = bytes(32)
    signer.signing.sign_outgoing = True
    signed = imu_message(ImuMessage.RAW_IMU, t_s=2.0, accel_mps2=[0, 0, -9.8], gyro_rps=[0, 0, 0])
    records.insert(400, _record(signed, signer, 1_700_000_002_000_000))
    path = tmp_path / "flight.tlog"
    path.write_bytes(b"".join(records))
    assert_same_as_pymavlink(path, monkeypatch, batch_samples=50)


def test_the_crc_table_steps_as_pymavlink_does():
    rng = np.random.default_rng(1)
    for _ in range(20):
        data = rng.integers(0, 256, int(rng.integers(1, 80))).astype(np.uint8).tobytes()
        crc = 0xFFFF
        for b in data:
            crc = (crc >> 8) ^ int(_CRC_TABLE[(crc ^ b) & 0xFF])
        assert crc == mavlink2.x25crc(data).crc
