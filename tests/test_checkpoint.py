"""Checkpoints of per-unit estimator state: exact round trip, atomic replacement, versioned."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from protocols.checkpoint_codec import decode_state, encode_state
from service.checkpoint import CheckpointError, CheckpointStore


def test_state_round_trip_keeps_dtype_shape_and_values():
    rng = np.random.default_rng(0)
    state = {
        "positions": [
            {"mean": rng.standard_normal(3), "cov": rng.standard_normal((3, 3)), "n": 1000}
        ],
        "flags": np.array([True, False]),
        "counts": np.arange(6, dtype=np.int64).reshape(2, 3),
        "f32": np.float32(1.5),
        "name": "imu0",
        "none": None,
        "pair": (1, 2.5),
    }
    back = decode_state(encode_state(state))
    np.testing.assert_array_equal(back["positions"][0]["mean"], state["positions"][0]["mean"])
    assert back["positions"][0]["cov"].shape == (3, 3) and back["counts"].dtype == np.int64
    assert (
        back["flags"].dtype == bool
        and back["f32"] == 1.5
        and back["none"] is None
        and back["pair"] == [1, 2.5]
    )
    assert back["counts"].flags.writeable  # a restored estimator may update its arrays in place


def test_store_replaces_atomically_and_survives_reopen(tmp_path):
    path = tmp_path / "c.sqlite"
    with CheckpointStore(path) as store:
        store.save("v1/0", {"n": 1})
        store.save_many({"v1/0": {"n": 2}, "v1/1": {"n": 7}}, now_unix_s=123.0)
    with CheckpointStore(path) as store:
        assert store.keys() == ["v1/0", "v1/1"]
        cp = store.load("v1/0")
        assert cp.state == {"n": 2} and cp.saved_unix_s == 123.0
        assert store.load("v9/0") is None
        store.delete("v1/1")
        assert store.keys() == ["v1/0"]


def test_unknown_version_and_garbage_are_typed_errors(tmp_path):
    path = tmp_path / "c.sqlite"
    with CheckpointStore(path) as store:
        store.save("a", {"n": 1})
        store.save("b", {"n": 1})
    db = sqlite3.connect(path)
    db.execute("UPDATE checkpoints SET version = 42 WHERE key = 'a'")
    db.execute("UPDATE checkpoints SET payload = x'c1c1c1' WHERE key = 'b'")
    db.commit()
    db.close()
    with CheckpointStore(path) as store:
        with pytest.raises(CheckpointError, match="schema version 42"):
            store.load("a")
        with pytest.raises(CheckpointError, match="cannot be decoded"):
            store.load("b")


def test_object_arrays_are_refused():
    with pytest.raises(TypeError, match="object arrays"):
        encode_state({"x": np.array([object()])})


def test_cross_imu_states_are_saved_with_the_units_and_moved_aside_when_unusable(tmp_path):
    path = tmp_path / "c.sqlite"
    with CheckpointStore(path) as store:
        store.save_encoded(
            {"v1/0": encode_state({"n": 1}), "v1/1": encode_state({"n": 2})},
            cross={"v1": encode_state({"flagged": [1]})},
            now_unix_s=5.0,
        )
        assert store.load_cross("v1").state == {"flagged": [1]} and store.load_cross("v2") is None
        assert store.keys() == ["v1/0", "v1/1"]
    with sqlite3.connect(path) as db:
        db.execute("UPDATE cross_imu SET payload = x'c1' WHERE vehicle = 'v1'")
    with CheckpointStore(path) as store:
        with pytest.raises(CheckpointError, match="cannot be decoded"):
            store.load_cross("v1")
        store.quarantine_cross("v1", "undecodable")
        assert store.load_cross("v1") is None
        assert store.quarantined() == [("v1/cross_imu", "undecodable")]
        assert store.load("v1/0").state == {"n": 1}


def test_a_file_written_before_the_cross_imu_table_still_loads(tmp_path):
    """The checkpoint file of an earlier version (no ``cross_imu`` table): its units load, its vehicles
    have no cross-IMU state, and the next save adds it."""
    path = tmp_path / "c.sqlite"
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE checkpoints (key TEXT PRIMARY KEY, version INTEGER NOT NULL, "
        "saved_unix_s REAL NOT NULL, payload BLOB NOT NULL);"
    )
    db.execute("INSERT INTO checkpoints VALUES ('v1/0', 1, 3.0, ?)", (encode_state({"n": 4}),))
    db.commit()
    db.close()
    with CheckpointStore(path) as store:
        assert store.load("v1/0").state == {"n": 4} and store.load_cross("v1") is None
        store.save_encoded({"v1/1": encode_state({"n": 1})}, cross={"v1": encode_state({"x": 1})})
        assert store.load_cross("v1").state == {"x": 1}


def test_keys_can_be_limited_to_the_checkpoints_saved_since_a_time(tmp_path):
    with CheckpointStore(tmp_path / "c.sqlite") as store:
        store.save("old/0", {"n": 1}, now_unix_s=1_000.0)
        store.save("new/0", {"n": 1}, now_unix_s=2_000.0)
        assert store.keys() == ["new/0", "old/0"]
        assert store.keys(saved_since_unix_s=1_500.0) == ["new/0"]
