"""IMU frame schema: lossless round trip, and every kind of bad input rejected with its reason."""

import dataclasses

import msgpack
import numpy as np
import pytest

from estimators.session import ImuSession
from protocols._schema import Reason
from protocols.frames import (
    FRAME_TYPE,
    MAX_SAMPLES,
    FrameError,
    SampleBatch,
    SampleDtype,
    concat_batches,
    decode_frame,
    encode_frame,
    split_session,
)


def _batch(n=50, *, seed=0, temp=True, seq=7, vehicle="uav-01.a", imu=2):
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.arange(n) * 0.005
    acc = rng.normal([0.0, 0.0, 9.81], 0.02, size=(n, 3))
    gyr = rng.normal(0.0, 1e-3, size=(n, 3))
    return SampleBatch(
        vehicle, imu, seq, t, acc, gyr, 25.0 + rng.normal(0, 0.1, n) if temp else None
    )


def _raw(batch, **override):
    obj = msgpack.unpackb(encode_frame(batch), raw=False)
    obj.update(override)
    return msgpack.packb({k: v for k, v in obj.items() if v is not _DROP}, use_bin_type=True)


_DROP = object()


@pytest.mark.parametrize("temp", [True, False])
def test_float64_round_trip_is_bit_exact(temp):
    b = _batch(temp=temp)
    out = decode_frame(encode_frame(b))
    assert out == b
    assert out.accel_mps2.dtype == np.float64 and not out.accel_mps2.flags.writeable
    assert (out.temp_c is None) == (not temp)


def test_float32_round_trip_within_float32_resolution_and_time_stays_exact():
    b = _batch(n=200)
    data = encode_frame(b, dtype=SampleDtype.F32)
    out = decode_frame(data)
    np.testing.assert_array_equal(out.t_s, b.t_s)  # time is always float64
    # float32 keeps 24 bits: relative rounding error <= 2^-24 per value.
    np.testing.assert_allclose(out.accel_mps2, b.accel_mps2, rtol=2.0**-24, atol=0)
    np.testing.assert_allclose(out.gyro_rps, b.gyro_rps, rtol=2.0**-24, atol=0)
    # Size: 8 (t) + 4*(3+3+1) bytes per sample instead of 8*8, plus a fixed header.
    assert len(data) < len(encode_frame(b)) and len(encode_frame(b)) - len(data) == 200 * 4 * 7


def test_wire_layout_is_the_documented_one():
    b = _batch(n=3)
    obj = msgpack.unpackb(encode_frame(b), raw=False)
    assert obj["type"] == FRAME_TYPE and obj["v"] == 1 and obj["n"] == 3 and obj["dtype"] == "<f8"
    acc = np.frombuffer(obj["accel_mps2"], "<f8").reshape(3, 3)
    np.testing.assert_array_equal(acc, b.accel_mps2)  # row-major (sample, axis)
    np.testing.assert_array_equal(np.frombuffer(obj["t_s"], "<f8"), b.t_s)


def test_batch_is_read_only_and_does_not_alias_the_callers_array():
    acc = np.tile([0.0, 0.0, 9.81], (4, 1))
    b = SampleBatch("v", 0, 0, np.arange(4.0), acc, np.zeros((4, 3)))
    acc[0, 0] = 99.0
    assert b.accel_mps2[0, 0] == 0.0
    with pytest.raises(ValueError):
        b.accel_mps2[0, 0] = 1.0


def test_concat_batches_joins_into_a_session():
    a, b = _batch(n=5, seq=1), _batch(n=5, seq=2)
    b = SampleBatch(b.vehicle, b.imu, 2, b.t_s + 1.0, b.accel_mps2, b.gyro_rps, None)
    s = concat_batches([a, b])
    assert s.n_samples == 10 and s.temp_c is None
    with pytest.raises(ValueError, match="several IMUs"):
        concat_batches([a, SampleBatch("other", 0, 0, a.t_s, a.accel_mps2, a.gyro_rps)])


BAD = {
    "malformed msgpack": (b"\xc1\x00\xff", Reason.MALFORMED),
    "truncated": (lambda: encode_frame(_batch())[:-10], Reason.MALFORMED),
    "not a map": (msgpack.packb([1, 2, 3]), Reason.NOT_A_MAP),
    "unknown type": (lambda: _raw(_batch(), type="ins.imu.other"), Reason.UNKNOWN_TYPE),
    "unknown version": (lambda: _raw(_batch(), v=3), Reason.UNKNOWN_VERSION),
    "version as str": (lambda: _raw(_batch(), v="1"), Reason.UNKNOWN_VERSION),
    "missing seq": (lambda: _raw(_batch(), seq=_DROP), Reason.MISSING_FIELD),
    "imu as float": (lambda: _raw(_batch(), imu=1.0), Reason.WRONG_TYPE),
    "imu as bool": (lambda: _raw(_batch(), imu=True), Reason.WRONG_TYPE),
    "imu out of range": (lambda: _raw(_batch(), imu=256), Reason.BAD_VALUE),
    "vehicle with wildcard": (lambda: _raw(_batch(), vehicle="a/*"), Reason.BAD_VALUE),
    "negative seq": (lambda: _raw(_batch(), seq=-1), Reason.BAD_VALUE),
    "n zero": (lambda: _raw(_batch(), n=0), Reason.BAD_VALUE),
    "n too large": (lambda: _raw(_batch(), n=MAX_SAMPLES + 1), Reason.BAD_VALUE),
    "n disagrees with arrays": (lambda: _raw(_batch(n=50), n=49), Reason.WRONG_LENGTH),
    "accel as list": (lambda: _raw(_batch(), accel_mps2=[1.0, 2.0]), Reason.WRONG_TYPE),
    "gyro short by one byte": (
        lambda: _raw(_batch(), gyro_rps=encode_and_get(_batch(), "gyro_rps")[:-1]),
        Reason.WRONG_LENGTH,
    ),
    "unknown dtype": (lambda: _raw(_batch(), dtype=">f2"), Reason.BAD_VALUE),
    "temp of wrong length": (lambda: _raw(_batch(), temp_c=b"\x00" * 8), Reason.WRONG_LENGTH),
    "time going back": (
        lambda: encode_frame(_with(_batch(), t_s=lambda t: t[::-1])),
        Reason.TIME_NOT_INCREASING,
    ),
    "duplicate time": (
        lambda: encode_frame(_with(_batch(), t_s=lambda t: np.repeat(t[:25], 2))),
        Reason.TIME_NOT_INCREASING,
    ),
    "NaN accel": (
        lambda: encode_frame(_with(_batch(), accel_mps2=lambda a: _put(a, (3, 1), np.nan))),
        Reason.NON_FINITE,
    ),
    "Inf gyro": (
        lambda: encode_frame(_with(_batch(), gyro_rps=lambda a: _put(a, (0, 2), -np.inf))),
        Reason.NON_FINITE,
    ),
    "NaN time": (
        lambda: encode_frame(_with(_batch(), t_s=lambda a: _put(a, (4,), np.nan))),
        Reason.NON_FINITE,
    ),
    "Inf temp f32": (
        lambda: encode_frame(
            _with(_batch(), temp_c=lambda a: _put(a, (1,), np.inf)), dtype=SampleDtype.F32
        ),
        Reason.NON_FINITE,
    ),
    "not bytes": ("a string", Reason.WRONG_TYPE),
}


def encode_and_get(batch, name):
    return msgpack.unpackb(encode_frame(batch), raw=False)[name]


def _put(a, idx, value):
    a = np.array(a)
    a[idx] = value
    return a


def _with(batch, **changes):
    kw = {k: getattr(batch, k) for k in ("t_s", "accel_mps2", "gyro_rps", "temp_c")}
    for k, f in changes.items():
        kw[k] = f(kw[k])
    return SampleBatch(batch.vehicle, batch.imu, batch.seq, **kw)


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_frames_are_rejected_with_their_reason(case):
    data, reason = BAD[case]
    data = data() if callable(data) else data
    with pytest.raises(FrameError) as info:
        decode_frame(data)
    assert info.value.reason is reason, str(info.value)
    assert str(info.value).startswith(reason.value + ":")


def test_oversized_frame_rejected_before_unpacking():
    data = encode_frame(_batch(n=5000))  # 5000 * 64 bytes = 320 kB
    assert decode_frame(data).n_samples == 5000
    with pytest.raises(
        FrameError, match=r"too_large: \d+ bytes exceeds the limit of 100000"
    ) as info:
        decode_frame(data, max_bytes=100_000)
    assert info.value.reason is Reason.TOO_LARGE


def test_unknown_version_error_gives_a_hint():
    with pytest.raises(
        FrameError, match=r"version 3 is not supported \(this build reads \[1, 2\]\); upgrade"
    ):
        decode_frame(_raw(_batch(), v=3))


def test_a_run_id_travels_in_version_2_and_a_frame_without_one_stays_version_1():
    """Version 2 adds the publisher's run id; a frame without one is written as version 1, which
    a daemon of the earlier build reads, and a version-1 frame carrying a stray ``run`` key is
    read as version 1 says (no run id)."""
    b = _batch()
    with_run = dataclasses.replace(b, run=2**63 + 5)
    obj = msgpack.unpackb(encode_frame(with_run), raw=False)
    assert obj["v"] == 2 and obj["run"] == 2**63 + 5
    assert decode_frame(encode_frame(with_run)) == with_run != b
    assert msgpack.unpackb(encode_frame(b), raw=False)["v"] == 1
    assert decode_frame(_raw(b, run=9)).run is None
    with pytest.raises(FrameError) as info:
        decode_frame(_raw(with_run, run="a"))
    assert info.value.reason is Reason.WRONG_TYPE
    assert [
        f.run for f in split_session(b.to_session(), vehicle="v", imu=0, batch_samples=20, run=4)
    ] == [4] * 3


def test_random_corruption_never_escapes_as_another_exception():
    # Bit flips and truncations of a valid frame: each either decodes to a
    # valid batch or raises FrameError; nothing else ever escapes.
    rng = np.random.default_rng(1)
    good = encode_frame(_batch(n=8))
    outcomes = {"ok": 0, "rejected": 0}
    for _ in range(3000):
        data = bytearray(good)
        if rng.random() < 0.5:
            for pos in rng.integers(0, len(data), size=rng.integers(1, 4)):
                data[pos] ^= 1 << int(rng.integers(0, 8))
        else:
            data = data[: rng.integers(0, len(data))]
        try:
            b = decode_frame(bytes(data))
        except FrameError:
            outcomes["rejected"] += 1
        else:
            assert np.isfinite(b.accel_mps2).all() and b.n_samples == 8
            outcomes["ok"] += 1
    assert outcomes["rejected"] > 1000 and outcomes["ok"] > 0


def test_construction_checks_shapes_and_ids():
    t = np.arange(3.0)
    with pytest.raises(FrameError, match=r"accel_mps2 must have shape \(3, 3\), got \(3, 2\)"):
        SampleBatch("v", 0, 0, t, np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(FrameError, match="vehicle id"):
        SampleBatch("bad/id", 0, 0, t, np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(FrameError, match="seq must be"):
        SampleBatch("v", 0, 1.5, t, np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(FrameError, match="numeric array"):
        SampleBatch("v", 0, 0, t, None, np.zeros((3, 3)))


def test_split_session_is_the_inverse_of_concat_batches():
    rng = np.random.default_rng(5)
    n = 250
    session = ImuSession(
        np.arange(n) * 0.01, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), 20 + rng.random(n)
    )
    batches = list(split_session(session, vehicle="uav-1", imu=2, batch_samples=100, first_seq=7))
    assert [(b.seq, b.n_samples, b.imu) for b in batches] == [(7, 100, 2), (8, 100, 2), (9, 50, 2)]
    back = concat_batches(batches)
    for name in ("t_s", "accel_mps2", "gyro_rps", "temp_c"):
        np.testing.assert_array_equal(getattr(back, name), getattr(session, name))
    with pytest.raises(ValueError, match="accelerometer and gyro"):
        split_session(
            ImuSession(session.t_s, None, session.gyro_rps), vehicle="v", imu=0, batch_samples=1
        )
