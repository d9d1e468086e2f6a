"""Property-based tests of every decoder of untrusted bytes and of the config loader (issue 15).

For any input each gives a value or its typed error, never another exception; and the invariants the
code claims hold for any input (checkpoint round trips, per-sample and batch paths for any cut).
Example counts are modest so the suite stays fast.
"""

from __future__ import annotations

import functools
import json
import math
import tempfile
from pathlib import Path

import msgpack
import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from test_positions import CFG, _assert_identical, _batched, _messy, _per_sample

from estimators.passport import PassportError
from estimators.positions import PositionAccumulator
from estimators.session import SessionError
from estimators.stream_validity import CrossImuMonitor, ValidityLimits
from protocols.events import EventError, decode_event, decode_status
from protocols.frames import FrameError, SampleBatch, decode_frame, encode_frame
from protocols.logs import LogFormat, LogReader
from protocols.mavlink_adapter import ImuSample, decode_imu_message
from protocols.passport_codec import PassportCodecError, decode_passport
from protocols.session_file import read_csv_session
from protocols.zenoh_adapter import parse_frame_key
from service.checkpoint import CheckpointError, CheckpointStore, decode_state, encode_state
from service.config import ConfigError, config_from_dict

FEW = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# msgpack-shaped values: what a hostile peer can put in a well-formed payload.
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=64)
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=12), inner, max_size=6)
    ),
    max_leaves=30,
)


def _frame_bytes() -> bytes:
    n = 4
    batch = SampleBatch(
        "uav-1",
        0,
        7,
        np.arange(n) * 0.01,
        np.ones((n, 3)),
        np.zeros((n, 3)),
        np.full(n, 25.0),
    )
    return encode_frame(batch)


def _mutations(valid: bytes):
    """Raw bytes, random maps, and a valid message with one field replaced or one byte flipped."""
    fields = msgpack.unpackb(valid, raw=False)
    replaced = st.tuples(st.sampled_from(sorted(fields)), values).map(
        lambda kv: msgpack.packb({**fields, kv[0]: kv[1]}, use_bin_type=True)
    )
    flipped = st.tuples(st.integers(0, len(valid) - 1), st.integers(0, 255)).map(
        lambda p: valid[: p[0]] + bytes([p[1]]) + valid[p[0] + 1 :]
    )
    maps = st.dictionaries(st.text(max_size=12), values, max_size=8).map(
        lambda d: msgpack.packb(d, use_bin_type=True)
    )
    return st.binary(max_size=256) | maps | replaced | flipped


@FEW
@given(_mutations(_frame_bytes()))
def test_frame_decoder_gives_a_batch_or_a_frame_error(data):
    try:
        batch = decode_frame(data)
    except FrameError:
        return
    assert batch.t_s.shape[0] == batch.accel_mps2.shape[0] == batch.gyro_rps.shape[0]


@FEW
@given(st.text(max_size=40) | st.from_regex(r"ins/[a-z0-9-]{1,8}/imu/\w{1,4}", fullmatch=True))
def test_frame_key_parser_gives_ascii_indices_or_a_frame_error(key):
    try:
        vehicle, imu = parse_frame_key(key)
    except FrameError:
        return
    assert key == f"ins/{vehicle}/imu/{imu}" and 0 <= imu <= 255


def _event_bytes() -> bytes:
    from protocols.events import (
        EventCause,
        Predicate,
        Severity,
        StreamCause,
        encode_event,
        make_event,
    )

    cause: EventCause = StreamCause.RECOVERED
    event = make_event(
        vehicle="uav-1",
        imu=0,
        t_s=1.0,
        predicate=Predicate.TIMEOUT,
        cause=cause,
        severity=Severity.INFO,
        unit="s",
    )
    return encode_event(event)


@FEW
@given(st.data())
def test_event_and_status_decoders_give_a_value_or_an_event_error(data):
    payload = data.draw(_mutations(_event_bytes()))
    for decode in (decode_event, decode_status):
        try:
            decode(payload)
        except EventError:
            pass


@functools.cache
def _passport_bytes() -> bytes:
    from protocols.passport_codec import encode_passport
    from service.demo import demo_passport

    return encode_passport(demo_passport()[0])


@FEW
@given(st.data())
def test_passport_decoder_gives_a_passport_or_its_typed_error(data):
    try:
        decode_passport(data.draw(_mutations(_passport_bytes())))
    except (PassportCodecError, PassportError):
        pass


# ----------------------------------------------------------------------------- checkpoints

arrays = st.builds(
    lambda shape, dtype, seed: np.random.default_rng(seed).standard_normal(shape).astype(dtype),
    st.lists(st.integers(0, 4), max_size=3).map(tuple),
    st.sampled_from(["<f8", "<f4", "<i8", "|b1", "<u2"]),
    st.integers(0, 2**32 - 1),
)
states = st.dictionaries(
    st.text(max_size=10),
    st.recursive(
        scalars.filter(lambda v: not isinstance(v, bytes)) | arrays,
        lambda inner: (
            st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
        ),
        max_leaves=20,
    ),
    max_size=6,
)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


@FEW
@given(states)
def test_checkpoint_round_trip_is_identical(state):
    assert _same(decode_state(encode_state(state)), state)


# A vehicle's IMUs as the fleet feeds them: frames in any order and of any size, each IMU
# at 100 Hz on its own clock, some off by 1 m/s² (disagreeing for a while).
cross_frames = st.lists(
    st.tuples(st.integers(0, 2), st.integers(1, 120), st.booleans()), min_size=1, max_size=30
)


def _cross_items(frames, seed: int):
    rng = np.random.default_rng(seed)
    sent = {0: 0, 1: 0, 2: 0}
    for imu, n, off in frames:
        t = (sent[imu] + np.arange(n)) * 0.01
        sent[imu] += n
        accel = np.array([0.0, 0.0, 9.81]) + 0.02 * rng.standard_normal((n, 3))
        accel[:, 0] += 1.0 if off else 0.0
        yield imu, t, accel, 1e-3 * rng.standard_normal((n, 3))


@FEW
@given(cross_frames, st.integers(0, 30), st.integers(0, 2**32 - 1))
def test_cross_imu_checkpoint_round_trip_is_identical_and_resumes_exactly(frames, cut, seed):
    """A vehicle's cross-IMU state, cut anywhere: the checkpoint bytes give back the same state, and
    the resumed monitor reports what one monitor over the whole stream does."""
    limits = ValidityLimits(cross_imu_persist_windows=2)
    items = list(_cross_items(frames, seed))
    whole = CrossImuMonitor(limits=limits)
    want = [r for item in items for r in whole.add(*item)]
    first = CrossImuMonitor(limits=limits)
    got = [r for item in items[:cut] for r in first.add(*item)]
    state = first.state_dict()
    back = decode_state(encode_state(state))
    assert _same(back, state)
    resumed = CrossImuMonitor.from_state(back, limits=limits)
    assert _same(resumed.state_dict(), state)
    got += [r for item in items[cut:] for r in resumed.add(*item)]
    assert got == want


@FEW
@given(st.binary(max_size=256) | states.map(encode_state).map(lambda b: b[: len(b) // 2]))
def test_checkpoint_decoder_gives_a_state_or_a_checkpoint_error(payload):
    try:
        assert isinstance(decode_state(payload), dict)
    except CheckpointError:
        pass


@settings(max_examples=20, deadline=None)
@given(st.binary(max_size=128))
def test_checkpoint_store_load_gives_a_checkpoint_or_a_checkpoint_error(payload):
    with tempfile.TemporaryDirectory() as tmp, CheckpointStore(Path(tmp) / "c.sqlite") as store:
        store.save_encoded({"v/0": payload})
        try:
            store.load("v/0")
        except CheckpointError:
            pass


# ----------------------------------------------------------------------------- files

csv_lines = st.lists(
    st.one_of(
        st.just("t,ax,ay,az,gx,gy,gz"),
        st.just("t,ax,ay,az,gx,gy,gz,temp"),
        st.lists(
            st.floats(allow_nan=True, allow_infinity=True).map(repr) | st.text(max_size=5),
            min_size=6,
            max_size=9,
        ).map(",".join),
        st.text(max_size=30).map(lambda s: "# " + s),
        st.text(max_size=30),
    ),
    max_size=30,
)


@FEW
@given(csv_lines)
def test_session_file_reader_gives_a_session_or_a_session_error(lines):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.csv"
        path.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
        try:
            read_csv_session(path)
        except (SessionError, UnicodeError):
            pass


@settings(max_examples=25, deadline=None)
@given(st.sampled_from(list(LogFormat)), st.binary(max_size=512))
def test_log_readers_give_batches_or_a_value_error(fmt, data):
    """Every log reader's errors are ValueError subclasses (NoImuDataError, UlogError, …)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log"
        path.write_bytes(data)
        try:
            for batch in LogReader(path, log_format=fmt, batch_samples=16):
                assert batch.n_samples >= 1
        except ValueError:
            pass


# ----------------------------------------------------------------------------- MAVLink input

_MAV = mavlink2.MAVLink(None)
int16 = st.integers(-(2**15), 2**15 - 1)
imu_messages = st.one_of(
    st.builds(
        mavlink2.MAVLink_raw_imu_message,
        st.integers(0, 2**64 - 1),
        *[int16] * 9,
        st.integers(0, 255),
        int16,
    ),
    st.builds(mavlink2.MAVLink_scaled_imu2_message, st.integers(0, 2**32 - 1), *[int16] * 9, int16),
    st.builds(
        mavlink2.MAVLink_highres_imu_message,
        st.integers(0, 2**64 - 1),
        *[st.floats(width=32)] * 13,
        st.integers(0, 2**16 - 1),
        st.integers(0, 255),
    ),
)


@FEW
@given(imu_messages, st.binary(max_size=64))
def test_mavlink_input_gives_samples_or_nothing(msg, garbage):
    """Any field values give a sample (or None for a message not read); garbage bytes on the wire
    are refused by the parser's own typed error or give no message."""
    sample = decode_imu_message(msg)
    assert sample is None or isinstance(sample, ImuSample)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    try:
        for m in parser.parse_buffer(garbage + msg.pack(_MAV)) or []:
            decoded = decode_imu_message(m)
            assert decoded is None or isinstance(decoded, ImuSample)
    except mavlink2.MAVError:
        pass


# ----------------------------------------------------------------------------- config

config_tables = st.dictionaries(
    st.sampled_from(["service", "site", "zenoh", "mavlink", "pipeline", "validity", "other"]),
    st.dictionaries(
        st.sampled_from(
            [
                "name",
                "status_period_s",
                "vehicles",
                "gravity_mps2",
                "mode",
                "connect",
                "connect_timeout_s",
                "enabled",
                "autopilot_system",
                "baud",
                "raw_scale",
                "imu_index",
                "messages",
                "queue_capacity",
                "timeout_s",
                "max_rate_hz",
                "frames_key",
                "signing_key_hex",
                "signing_key_file",
                "data_dir",
                "bogus",
            ]
        ),
        values,
        max_size=5,
    ),
    max_size=4,
)


@FEW
@given(config_tables)
# A key with a line break once made a two-line error (found by this test).
@example({"mavlink": {"raw_scale": {"\n": None}, "imu_index": {"a\rb": -1}}})
def test_config_loader_gives_a_config_or_config_errors_one_per_line(raw):
    with tempfile.TemporaryDirectory() as tmp:
        try:
            config_from_dict(raw, base_dir=Path(tmp))
        except ConfigError as exc:
            assert exc.lines and all(line and "\n" not in line for line in exc.lines)


# ----------------------------------------------------------------------------- invariants


@functools.cache
def _reference():
    session = _messy(np.random.default_rng(7))
    ref = PositionAccumulator(rate_hz=100.0, config=CFG)
    positions, decisions = _per_sample(ref, session)
    return session, positions, decisions, json.dumps(ref.state_dict())


@settings(max_examples=10, deadline=None)
@given(st.lists(st.integers(1, 4000), min_size=1, max_size=40))
def test_batch_path_equals_per_sample_path_for_any_cut(sizes):
    session, expected, expected_decisions, ref_state = _reference()
    n = session.t_s.size
    cuts = np.unique(np.clip(np.concatenate([[0], np.cumsum(sizes), [n]]), 0, n))
    acc = PositionAccumulator(rate_hz=100.0, config=CFG)
    got, decisions = _batched(acc, session, cuts)
    assert np.array_equal(decisions.static, expected_decisions.static)
    assert np.array_equal(decisions.brk, expected_decisions.brk)
    assert len(got) == len(expected)
    for p, q in zip(got, expected, strict=True):
        _assert_identical(p, q)
    assert json.dumps(acc.state_dict()) == ref_state
