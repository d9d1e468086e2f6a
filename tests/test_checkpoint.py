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
