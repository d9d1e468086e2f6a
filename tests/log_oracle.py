"""The numpy DataFlash readers' oracle: the same log read by :class:`protocols.logs.LogReader` with
numpy decoding and with pymavlink's per-message decoding (``NUMPY_DECODING`` off) must give the
same batches (IMU, order, run, values bit for bit) and the same ``LogStats``."""

from __future__ import annotations

import numpy as np

from estimators.session import ImuSession
from protocols import logs
from protocols.logs import LogReader, NoImuDataError


def read_log(path, numpy_decoding: bool, monkeypatch, **options):
    """The batches of ``path`` (or the NoImuDataError's message) and the reader's stats."""
    monkeypatch.setattr(logs, "NUMPY_DECODING", numpy_decoding)
    reader = LogReader(path, **options)
    try:
        out = [(b.imu, b.seq, b.run, b.t_s, b.accel_mps2, b.gyro_rps, b.temp_c) for b in reader]
    except NoImuDataError as e:
        out = str(e)
    return out, reader.stats


def assert_same_as_pymavlink(path, monkeypatch, **options) -> None:
    fast, fast_stats = read_log(path, True, monkeypatch, **options)
    oracle, oracle_stats = read_log(path, False, monkeypatch, **options)
    assert_same_reading((fast, fast_stats), (oracle, oracle_stats))


def assert_same_reading(fast, oracle) -> None:
    """Two readings (batches or the NoImuDataError's message, and stats) are the same to the bit."""
    (fast, fast_stats), (oracle, oracle_stats) = fast, oracle
    assert fast_stats == oracle_stats
    if isinstance(oracle, str):
        assert fast == oracle
        return
    assert len(fast) == len(oracle)
    for got, want in zip(fast, oracle, strict=True):
        assert got[:3] == want[:3]
        for g, w in zip(got[3:], want[3:], strict=True):
            assert (g is None) == (w is None)
            if w is not None:
                np.testing.assert_array_equal(g, w)
                np.testing.assert_array_equal(np.signbit(g), np.signbit(w))


def three_imus(
    n: int, seed: int, *, gyro_sd: float = 0.01, temp: bool = True
) -> dict[int, ImuSession]:
    """Three IMUs at 400 Hz, their clocks 0.1 ms apart, at rest with noise."""
    rng = np.random.default_rng(seed)
    out = {}
    for imu in (0, 1, 2):
        t = 5.0 + imu * 1e-4 + np.arange(n) / 400.0
        acc = rng.normal([0.1, -0.2, -9.8], 0.05, (n, 3))
        gyr = rng.normal(0.0, gyro_sd, (n, 3))
        out[imu] = ImuSession(t, acc, gyr, 25.0 + 0.01 * np.arange(n) if temp else None)
    return out


def current_and_legacy(folder, write, suffix: str, n: int, **noise) -> dict[str, bytes]:
    """:func:`three_imus` written by ``write`` in current ArduPilot's ``IMU`` with instance
    (``legacyFalse``) and in the legacy IMU/IMU2/IMU3 names (``legacyTrue``): the logs' bytes."""
    out = {}
    for legacy in (False, True):
        path = folder / f"legacy{legacy}.{suffix}"
        write(path, three_imus(n, seed=int(legacy), **noise), legacy_names=legacy)
        out[f"legacy{legacy}"] = path.read_bytes()
    return out
