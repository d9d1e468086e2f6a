"""Inputs that cannot poison the pipeline: implausible sample rates and checkpoints that cannot be resumed."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from service_support import batches_of, demo_fleet

from estimators.stream_validity import ValidityLimits, plausible_rate_hz, typical_step_s
from service.checkpoint import CheckpointStore, encode_state
from service.demo import demo_scenario

V = "uav-p"


@functools.cache
def scenario():
    return demo_scenario()


def frames(n: int):
    return list(batches_of(scenario().session, vehicle=V, imu=0, batch_samples=100))[:n]


def test_plausible_rate_is_the_median_spacing_inside_the_limits():
    limits = ValidityLimits(min_rate_hz=1.0, max_rate_hz=1000.0)
    t = np.arange(20) * 0.01
    t[5:] += 3.0  # one gap: the median ignores it
    assert plausible_rate_hz(t, limits) == pytest.approx(100.0)
    # The start of the real tlog: 0.24 s steps, five slower ones: the median keeps 4.1 Hz (the
    # interquartile mean gave 2.8 Hz, and the rate watch re-sized the detector two minutes later).
    steps = [0.239, 0.242, 0.238, 0.242, 1.498, 0.5, 0.5, 0.499, 0.501, 0.501, 0.499, 0.24, 0.242]
    assert plausible_rate_hz(np.cumsum([0.0, *steps, 0.238, 0.241]), limits) == pytest.approx(
        1 / 0.242, rel=0.01
    )
    assert plausible_rate_hz(np.arange(20) * 1e-9, limits) is None
    assert plausible_rate_hz(np.arange(20) * 10.0, limits) is None
    assert plausible_rate_hz(np.array([1.0]), limits) is None
    # A block of the rate watch: 400 Hz stamped in whole ms, steps of 2 and 3 ms whose median flips
    # between 333 and 500 Hz: the interquartile mean stays near 2.5 ms.
    ms = np.floor((np.arange(129) / 400.0 + 0.0012) * 1e3) / 1e3
    assert sorted(set(np.round(np.diff(ms) * 1e3).astype(int))) == [2, 3]
    assert 1.0 / typical_step_s(np.diff(ms)) == pytest.approx(400.0, rel=0.02)
    with pytest.raises(ValueError, match="min_rate_hz must be below"):
        ValidityLimits(min_rate_hz=10.0, max_rate_hz=5.0)
    with pytest.raises(ValueError, match="max_rate_hz must be finite"):
        ValidityLimits(max_rate_hz=float("inf"))


def test_sub_microsecond_stamps_are_refused_counted_and_cost_no_memory():
    """A new IMU whose first samples are 1 ns apart: refused with a counted reason, its state stays
    small, and the same IMU's later plausible stream is taken up at its own rate."""
    f = demo_fleet()
    good = frames(40)
    hostile = [
        dataclasses.replace(b, t_s=1e-9 * np.arange(b.n_samples) + 1e-7 * k)
        for k, b in enumerate(good[:20])
    ]
    for b in hostile:
        f.process(b, arrival_s=0.0)
    pipe = f.pipelines[(V, 0)]
    assert pipe.detection is None
    assert pipe.counters["samples.rejected.implausible_rate"] == sum(b.n_samples for b in hostile)
    assert len(encode_state(pipe.state_dict())) < 4096
    later = [dataclasses.replace(b, seq=b.seq + 100, t_s=b.t_s + 10.0) for b in good[20:]]
    for b in later:
        f.process(b, arrival_s=0.0)
    assert pipe.detection is not None
    assert pipe.detection.rate_hz == pytest.approx(1.0 / np.median(np.diff(good[0].t_s)))


@pytest.mark.parametrize(
    "poison",
    [
        {"rate_hz": 1e300},
        {"rate_hz": float("inf")},
        {"accumulator": "not a state"},
        {"validity": [1, 2, 3]},
        {"counters": {"x": "y"}},
    ],
    ids=["huge_rate", "infinite_rate", "bad_accumulator", "bad_validity", "bad_counters"],
)
def test_a_checkpoint_that_cannot_be_resumed_costs_only_its_unit(tmp_path, poison):
    """Its unit starts fresh and the caller is told why (so it can move the row aside); the state is
    otherwise a real one, so only the poisoned field can be the cause."""
    source = demo_fleet()
    for b in frames(30):
        source.process(b, arrival_s=0.0)
    state = {**source.pipelines[(V, 0)].state_dict(), **poison}
    told = []
    f = demo_fleet()
    f.set_restore(
        lambda v, i: state if v == V else None, lambda v, i, why: told.append((v, i, why))
    )
    pipe = f.admit(V, 0)
    assert pipe is not None and pipe.n_samples == 0 and pipe.detection is None
    assert f.vehicle_counters[V]["checkpoints.discarded"] == 1
    assert [(v, i) for v, i, _ in told] == [(V, 0)]
    healthy = f.admit("uav-ok", 0)
    assert healthy is not None and "checkpoints.discarded" not in f.vehicle_counters["uav-ok"]


def test_quarantine_moves_the_row_aside_with_its_reason(tmp_path):
    path = tmp_path / "c.sqlite"
    with CheckpointStore(path) as store:
        store.save("a/0", {"n": 1})
        store.save("b/0", {"n": 2})
        store.quarantine("a/0", "rate 1e300 Hz")
    with CheckpointStore(path) as store:
        assert store.keys() == ["b/0"] and store.load("a/0") is None
        assert store.quarantined() == [("a/0", "rate 1e300 Hz")]
