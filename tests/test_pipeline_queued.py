"""FleetProcessor.process_queued: queued frames taken together give what frame-by-frame processing gives."""

from __future__ import annotations

import dataclasses

import numpy as np
from service_support import batches_of, demo_fleet, disagreeing_pair

from protocols.events import Event, Predicate
from protocols.frames import SampleBatch
from service.demo import DEMO_VEHICLE, demo_scenario
from service.pipeline import FleetProcessor, ImuPipeline
from service.pipeline.imu_pipeline import join_batches

V = DEMO_VEHICLE


def one_by_one(frames: list[SampleBatch]) -> tuple[list[Event], FleetProcessor]:
    f = demo_fleet()
    events = []
    for b in frames:
        events += f.process(b, arrival_s=float(b.t_s[-1]))
    return events, f


def queued(frames: list[SampleBatch], seed: int) -> tuple[list[Event], FleetProcessor]:
    """The frames in groups of 1…40, as a service that falls behind takes them off its queue."""
    f = demo_fleet()
    rng = np.random.default_rng(seed)
    events, k = [], 0
    while k < len(frames):
        group = frames[k : k + int(rng.integers(1, 41))]
        events += f.process_queued(group, arrival_s=float(group[-1].t_s[-1]))
        k += len(group)
    return events, f


def frames_taken(monkeypatch) -> list[int]:
    """The frames each call of the chain takes from now on (``ImuPipeline.process``'s ``frames``)."""
    taken: list[int] = []
    process = ImuPipeline.process

    def spy(self, batch, *, arrival_s, frames=1):
        taken.append(frames)
        return process(self, batch, arrival_s=arrival_s, frames=frames)

    monkeypatch.setattr(ImuPipeline, "process", spy)
    return taken


def counters(f: FleetProcessor) -> dict:
    return {key: dict(p.counters) for key, p in f.pipelines.items()}


def test_the_faulty_demo_unit_gives_the_same_events_and_counters_in_queued_groups(monkeypatch):
    """F0, positions and the diagnosis of the demo's fault, in frames of 20: same events, same counters."""
    frames = list(batches_of(demo_scenario().session, vehicle=V, imu=0, batch_samples=20))
    alone, f_alone = one_by_one(frames)
    joined = frames_taken(monkeypatch)
    together, f_together = queued(frames, seed=1)
    # Most frames went through the chain joined with others.
    assert sum(n for n in joined if n > 1) > 0.9 * len(frames)
    assert {e.predicate for e in alone} == {Predicate.F0, Predicate.F6}
    assert sorted(together, key=lambda e: e.event_id) == sorted(alone, key=lambda e: e.event_id)
    assert counters(f_together) == counters(f_alone)
    a, b = f_alone.pipelines[(V, 0)], f_together.pipelines[(V, 0)]
    assert (b.n_positions, b.last_seq, b.last_t_s) == (a.n_positions, a.last_seq, a.last_t_s)


def test_irregular_frames_of_two_imus_are_taken_alone_and_counted_as_frame_by_frame():
    """Lost, repeated, late, non-finite and time-jumping frames among two interleaved IMUs."""
    sc = demo_scenario(fault_magnitude=0.0)
    imu0 = list(batches_of(sc.session, vehicle=V, imu=0, batch_samples=20))[:900]
    imu1 = [dataclasses.replace(b, imu=1) for b in imu0]
    accel = imu0[300].accel_mps2.copy()
    accel[5, 1] = np.nan
    nan = dataclasses.replace(imu0[300], accel_mps2=accel)
    jumped = [dataclasses.replace(b, t_s=b.t_s + 3.0) for b in imu0[501:]]
    irregular = [*imu0[:200], *imu0[201:300], nan, *imu0[301:400], imu0[399], imu0[390]]
    irregular += [*imu0[400:501], *jumped]
    frames = [b for pair in zip(irregular, imu1, strict=False) for b in pair]
    alone, f_alone = one_by_one(frames)
    c = counters(f_alone)[(V, 0)]
    assert c["frames.missing"] == 1 and c["frames.duplicate"] == 1 and c["time_jumps"] >= 1
    assert c["frames.out_of_order"] == 1 and c["samples.rejected.out_of_order_or_non_finite"] == 1
    # Several cuttings into groups: each irregular frame lands inside a group in some of them.
    for seed in range(2, 8):
        together, f_together = queued(frames, seed=seed)
        assert sorted(together, key=lambda e: e.event_id) == sorted(alone, key=lambda e: e.event_id)
        assert counters(f_together) == counters(f_alone), seed


def test_a_cross_imu_disagreement_is_the_same_whichever_frames_were_queued_together():
    """Two interleaved IMUs, IMU1's z accelerometer off by 0.1 g after landing: in queued groups each IMU's
    frames go through its chain together, but the cross-IMU check takes them in the order they came,
    so it compares the same bins and raises the same disagreement (same ids) as frame by frame."""
    frames = disagreeing_pair(V)
    alone, _ = one_by_one(frames)
    assert sorted(e.imu for e in alone if e.predicate is Predicate.CROSS_IMU) == [0, 1]
    together, _ = queued(frames, seed=3)
    assert sorted(e.event_id for e in together) == sorted(e.event_id for e in alone)


def test_queued_steps_give_process_queued_s_events_imu_by_imu_then_the_cross_check():
    """Two interleaved IMUs of the faulty demo in groups of 1…40: the steps, joined, are process_queued's events."""
    sc = demo_scenario()
    frames = [
        b
        for pair in zip(
            batches_of(sc.session, vehicle=V, imu=0, batch_samples=20),
            batches_of(sc.session, vehicle=V, imu=1, batch_samples=20),
            strict=True,
        )
        for b in pair
    ]
    together, _ = queued(frames, seed=3)
    f = demo_fleet()
    rng = np.random.default_rng(3)
    stepped, k, steps_per_group = [], 0, []
    while k < len(frames):
        group = frames[k : k + int(rng.integers(1, 41))]
        steps = list(f.queued_steps(group, arrival_s=float(group[-1].t_s[-1])))
        # One step per IMU of the group, then the cross-IMU check's.
        steps_per_group.append(len(steps) == len({b.imu for b in group}) + 1)
        stepped += [e for step in steps for e in step]
        k += len(group)
    assert all(steps_per_group)
    assert [e.event_id for e in stepped] == [e.event_id for e in together]
    assert {e.predicate for e in stepped} >= {Predicate.F0}


def test_the_imu_with_the_fewest_queued_samples_goes_through_first():
    """Three frames of IMU0 queued before one of IMU1, both running: IMU1's step comes first, so its events
    do not wait for the work of IMU0's larger share of the group."""
    imu0 = list(batches_of(demo_scenario().session, vehicle=V, imu=0, batch_samples=20))[:4]
    imu1 = [dataclasses.replace(b, imu=1) for b in imu0[:2]]
    f = demo_fleet()
    for b in (imu0[0], imu1[0]):
        f.process(b, arrival_s=float(b.t_s[-1]))
    steps = f.queued_steps([*imu0[1:], imu1[1]], arrival_s=float(imu0[-1].t_s[-1]))
    next(steps)
    assert {key: p.n_samples for key, p in f.pipelines.items()} == {(V, 0): 20, (V, 1): 40}
    assert len(list(steps)) == 2
    assert {key: p.n_samples for key, p in f.pipelines.items()} == {(V, 0): 80, (V, 1): 40}


def test_imus_without_a_pipeline_are_admitted_in_the_order_their_frames_came():
    """At the admission limit the IMU whose frame came first takes the last place, as frame by frame,
    even when a later IMU has fewer queued samples."""
    imu0 = list(batches_of(demo_scenario().session, vehicle=V, imu=0, batch_samples=20))[:3]
    f = demo_fleet(max_imus_per_vehicle=1)
    f.process_queued([*imu0, dataclasses.replace(imu0[0], imu=1)], arrival_s=0.0)
    assert sorted(f.pipelines) == [(V, 0)]
    assert f.status(V, service="t", now_unix_s=0.0).counters["frames.rejected.over_imu_limit"] == 1


def test_frames_joined_as_a_log_reader_joins_them_give_what_they_give_one_by_one(monkeypatch):
    """A lost frame, a non-finite sample and a time jump at a frame's start: consecutive frames
    joined (1…8, as :class:`~protocols.logs.LogReader` joins them, ``frames`` saying how many)
    and queued give the events and counters of the frames one by one. A joined batch holding the
    jump or the bad sample is taken frame by frame (its frames would not join), so the jump is
    counted where it was and the bad sample's frame goes through the checks alone."""
    sc = demo_scenario(fault_magnitude=0.0)
    imu0 = list(batches_of(sc.session, vehicle=V, imu=0, batch_samples=20))[:900]
    accel = imu0[300].accel_mps2.copy()
    accel[5, 1] = np.nan
    nan = dataclasses.replace(imu0[300], accel_mps2=accel)
    jumped = [dataclasses.replace(b, t_s=b.t_s + 3.0) for b in imu0[501:]]
    frames = [*imu0[:200], *imu0[201:300], nan, *imu0[301:501], *jumped]
    alone, f_alone = one_by_one(frames)
    c = counters(f_alone)[(V, 0)]
    assert c["frames.missing"] == 1 and c["time_jumps"] == 2  # the lost frame, the jump
    assert c["samples.rejected.out_of_order_or_non_finite"] == 1
    taken = frames_taken(monkeypatch)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        runs, k = [], 0
        while k < len(frames):
            run = [frames[k]]
            while len(run) < rng.integers(1, 9) and k + len(run) < len(frames):
                nxt = frames[k + len(run)]
                if nxt.seq != run[-1].seq + 1:
                    break
                run.append(nxt)
            runs.append(run)
            k += len(run)
        f = demo_fleet()
        together = []
        for g in range(0, len(runs), 3):
            group = runs[g : g + 3]
            together += f.process_queued(
                [join_batches(run) for run in group],
                arrival_s=float(group[-1][-1].t_s[-1]),
                frames=[len(run) for run in group],
            )
        assert sorted(together, key=lambda e: e.event_id) == sorted(alone, key=lambda e: e.event_id)
        assert counters(f) == counters(f_alone), seed
    assert max(taken) > 8  # joined batches went through joined
