"""Stream validity (PX4-style timeout, stale axis, error density) and cross-IMU consistency."""

from __future__ import annotations

import numpy as np
import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2, Triad
from estimators.stream_validity import (
    CLOCK_FRAMES,
    CrossImuMonitor,
    StreamValidity,
    ValidityLimits,
    best_clock_offset,
    compare_imus,
    run_lengths,
    typical_step_s,
    typical_steps_s,
)
from protocols.checkpoint_codec import decode_state, encode_state

RATE_HZ = 1000.0
ACCEL_NOISE_MPS2 = 0.02
GYRO_NOISE_RPS = 1e-3


def static_samples(rng: np.random.Generator, n: int, *, t0_s: float = 0.0):
    t = t0_s + np.arange(n) / RATE_HZ
    accel = np.array([0.0, 0.0, STANDARD_GRAVITY_MPS2]) + ACCEL_NOISE_MPS2 * rng.standard_normal(
        (n, 3)
    )
    gyro = GYRO_NOISE_RPS * rng.standard_normal((n, 3))
    return t, accel, gyro


def test_run_lengths_by_hand():
    values = np.array([[1.0], [1.0], [2.0], [2.0], [2.0], [3.0]])
    runs = run_lengths(values, np.array([1.0]), np.array([4]))
    np.testing.assert_array_equal(runs[:, 0], [5, 6, 1, 2, 3, 1])


def test_run_lengths_are_those_counted_sample_by_sample():
    # Coarse values repeat (runs of every length, across the cuts), NaN breaks every run.
    rng = np.random.default_rng(71)
    values = np.round(rng.normal(0.0, 0.6, (3000, 6)))
    values[rng.random(3000) < 0.01, 2] = np.nan
    prev_value, prev_run = np.full(6, np.nan), np.zeros(6, dtype=np.int64)
    expected = np.empty(values.shape, dtype=np.int64)
    last, run = prev_value.copy(), prev_run.copy()
    for i, row in enumerate(values):
        for k, x in enumerate(row):
            run[k] = run[k] + 1 if x == last[k] else 1
            last[k] = x
        expected[i] = run
    i = 0
    for size in [0, 1, *rng.integers(1, 400, size=30).tolist(), values.shape[0]]:
        piece = values[i : i + size]
        runs = run_lengths(piece, prev_value, prev_run)
        assert runs.shape == piece.shape and runs.dtype == np.int64
        np.testing.assert_array_equal(runs, expected[i : i + size])
        if piece.shape[0]:
            prev_value, prev_run = piece[-1], runs[-1]
        i += piece.shape[0]
    assert i == values.shape[0]


def test_noisy_stream_is_never_stale_and_stuck_gyro_is_named():
    rng = np.random.default_rng(1)
    limits = ValidityLimits()
    sv = StreamValidity(limits=limits)
    for k in range(20):
        _, a, g = static_samples(rng, 500)
        rep = sv.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(500, bool), arrival_s=k * 0.5)
        assert rep.stale == () and rep.changes == () and not rep.error_dense
    # The gyro z axis sticks at its last value (the ICM42688 "stuck gyro").
    t, a, g = static_samples(rng, 500, t0_s=10.0)
    g[:, 2] = 0.0123
    rep = sv.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(500, bool), arrival_s=10.0, t_s=t)
    assert [(c.triad, c.axis, c.stale) for c in rep.changes] == [(Triad.GYRO, "z", True)]
    # The run reaches 100 identical values at the 100th stuck sample.
    assert rep.changes[0].t_s == pytest.approx(t[99])
    assert rep.changes[0].run_samples == 100 and rep.changes[0].value == pytest.approx(0.0123)
    # Still stuck: reported as stale, but not as newly stale again.
    _, a, g = static_samples(rng, 100)
    g[:, 2] = 0.0123
    rep = sv.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(100, bool), arrival_s=10.1)
    assert (
        rep.changes == ()
        and [s.axis for s in rep.stale] == ["z"]
        and rep.stale[0].run_samples == 600
    )


def test_run_spanning_batches_and_bad_samples_do_not_break_it():
    rng = np.random.default_rng(2)
    limits = ValidityLimits(stale_run_samples=100)
    sv = StreamValidity(limits=limits)
    reports = []
    for k in range(4):
        _, a, g = static_samples(rng, 40)
        a[:, 0] = 1.5
        bad = np.zeros(40, bool)
        bad[5] = True
        a[5, 0] = np.nan  # a rejected sample neither extends nor resets the run
        reports.append(sv.update(accel_mps2=a, gyro_rps=g, bad=bad, arrival_s=float(k)))
    assert [len(r.changes) for r in reports] == [0, 0, 1, 0]
    # 39 good samples per batch: the 100th identical value is the 22nd good one of the third batch.
    assert reports[2].changes[0].run_samples == 100 and reports[2].stale[0].run_samples == 3 * 39


def test_error_density_window_and_rejected_frames():
    limits = ValidityLimits(error_window_samples=100, error_density_max=0.1)
    sv = StreamValidity(limits=limits)
    rng = np.random.default_rng(3)
    _, a, g = static_samples(rng, 200)
    bad = np.zeros(200, bool)
    bad[::20] = True  # 5 %: below the limit
    rep = sv.update(accel_mps2=a, gyro_rps=g, bad=bad, arrival_s=0.0)
    assert rep.error_density == pytest.approx(0.05) and not rep.error_dense
    rep = sv.record_rejected(15)  # a rejected frame of 15 samples: 15 + 4 errors among the last 100
    assert rep.error_dense and rep.error_density == pytest.approx(0.19)
    _, a, g = static_samples(rng, 200)
    rep = sv.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(200, bool), arrival_s=1.0)
    assert rep.error_density == 0.0 and rep.peak_error_density == pytest.approx(0.19)


def test_every_change_inside_one_batch_is_reported_in_time_order():
    """Stuck, free, stuck again within one batch: the same changes as sample by sample."""
    rng = np.random.default_rng(7)
    t, a, g = static_samples(rng, 600)
    a[:150, 0] = 0.5
    a[200:350, 0] = 0.7
    g[300:420, 2] = 0.001
    whole = StreamValidity().update(
        accel_mps2=a, gyro_rps=g, bad=np.zeros(600, bool), arrival_s=0.0, t_s=t
    )
    one = StreamValidity()
    singles = [
        c
        for k in range(600)
        for c in one.update(
            accel_mps2=a[k : k + 1],
            gyro_rps=g[k : k + 1],
            bad=np.zeros(1, bool),
            arrival_s=0.0,
            t_s=t[k : k + 1],
        ).changes
    ]
    assert whole.changes == tuple(singles)
    assert [(c.axis, c.stale, c.t_s) for c in whole.changes] == [
        ("x", True, t[99]),
        ("x", False, t[150]),
        ("x", True, t[299]),
        ("x", False, t[350]),
        ("z", True, t[399]),
        ("z", False, t[420]),
    ]
    assert whole.changes[1].run_samples == 150 and whole.changes[3].value == 0.7


def test_timeout_uses_the_arrival_clock():
    sv = StreamValidity(limits=ValidityLimits(timeout_s=0.5))
    assert not sv.timed_out(100.0)  # nothing arrived yet: not a timeout but "no data"
    sv.update(
        accel_mps2=np.zeros((1, 3)),
        gyro_rps=np.zeros((1, 3)),
        bad=np.zeros(1, bool),
        arrival_s=10.0,
    )
    assert not sv.timed_out(10.5) and sv.timed_out(10.51)


def test_state_round_trip_keeps_the_run():
    rng = np.random.default_rng(4)
    sv = StreamValidity()
    _, a, g = static_samples(rng, 60)
    g[:, 0] = 0.5
    sv.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(60, bool), arrival_s=0.0)
    restored = StreamValidity.from_state(sv.state_dict())
    _, a, g = static_samples(rng, 60)
    g[:, 0] = 0.5
    rep = restored.update(accel_mps2=a, gyro_rps=g, bad=np.zeros(60, bool), arrival_s=1.0)
    assert [(c.triad, c.axis, c.stale) for c in rep.changes] == [(Triad.GYRO, "x", True)]
    assert rep.stale[0].run_samples == 120


def test_limits_are_validated():
    with pytest.raises(ValueError, match="timeout_s"):
        ValidityLimits(timeout_s=0.0)
    with pytest.raises(ValueError, match="stale_run_samples"):
        ValidityLimits(stale_run_samples=1)
    with pytest.raises(ValueError, match="error_density_max"):
        ValidityLimits(error_density_max=1.5)


def test_compare_three_imus_names_the_outlier_only():
    limits = ValidityLimits()
    a = np.array([[0, 0, 9.81], [0.05, 0, 9.80], [0.9, 0, 9.81]])
    g = np.zeros((3, 3))
    v = compare_imus((0, 1, 2), a, g, limits=limits)
    assert v.disagreeing == (2,)
    assert v.accel_dev_mps2[2] == pytest.approx(0.85)
    # Gyro disagreement of 6 °/s on IMU 0.
    g[0, 1] = np.radians(6.0)
    v = compare_imus((0, 1, 2), np.zeros((3, 3)), g, limits=limits)
    assert v.disagreeing == (0,)


def test_compare_two_imus_flags_the_pair():
    v = compare_imus(
        (0, 1), np.array([[0, 0, 9.8], [0, 0.8, 9.8]]), np.zeros((2, 3)), limits=ValidityLimits()
    )
    assert v.disagreeing == (0, 1)
    v = compare_imus(
        (0, 1), np.array([[0, 0, 9.8], [0, 0.6, 9.8]]), np.zeros((2, 3)), limits=ValidityLimits()
    )
    assert v.disagreeing == ()


def test_cross_imu_monitor_persistence_and_recovery():
    """Three IMUs in 0.5 s bins; IMU 1 has a 1 m/s² offset for 3 s, then recovers (after as many
    agreeing bins as disagreeing ones raised it)."""
    rng = np.random.default_rng(5)
    limits = ValidityLimits(cross_imu_persist_windows=4)
    mon = CrossImuMonitor(limits=limits)
    reports = []
    for step in range(28):  # 28 batches of 0.25 s at 1 kHz
        t0 = step * 0.25
        for imu in (0, 1, 2):
            t, a, g = static_samples(rng, 250, t0_s=t0)
            if imu == 1 and 1.0 <= t0 < 4.0:
                a[:, 0] += 1.0
            reports.extend(mon.add(imu, t, a, g))
    bad = [r for r in reports if not r.consistent]
    good = [r for r in reports if r.consistent]
    assert [r.imu for r in bad] == [1] and bad[0].others == (0, 2)
    assert bad[0].accel_dev_mps2 == pytest.approx(1.0, abs=5 * ACCEL_NOISE_MPS2)
    # Flagged after the 4th consecutive disagreeing bin (bins at 1.0, 1.5, 2.0, 2.5 s).
    assert bad[0].bin_start_s == pytest.approx(2.5)
    # Recovered after the 4th agreeing bin (bins at 4.0, 4.5, 5.0, 5.5 s).
    assert [r.imu for r in good] == [1] and good[0].bin_start_s == pytest.approx(5.5)
    assert mon.flagged == frozenset()


def _offset_stream(seed: int):
    """Three IMUs in 0.25 s batches at 1 kHz; IMU 1 off by 1 m/s² from 1 to 4 s (flagged at 2.5 s, recovers at 5.5 s)."""
    rng = np.random.default_rng(seed)
    for step in range(28):
        for imu in (0, 1, 2):
            t, a, g = static_samples(rng, 250, t0_s=step * 0.25)
            if imu == 1 and 1.0 <= step * 0.25 < 4.0:
                a[:, 0] += 1.0
            yield imu, t, a, g


@pytest.mark.parametrize("cut", [5, 16, 31, 37, 44, 52, 60])
def test_cross_imu_monitor_resumes_from_its_checkpoint_exactly(cut):
    """Cut anywhere (mid-bin, mid-streak, while flagged), the state through checkpoint bytes and a new
    monitor: the same reports as one monitor over the whole stream, none raised again."""
    limits = ValidityLimits(cross_imu_persist_windows=4)
    items = list(_offset_stream(9))
    whole = CrossImuMonitor(limits=limits)
    want = [r for item in items for r in whole.add(*item)]
    assert [(r.imu, r.consistent) for r in want] == [(1, False), (1, True)]
    first = CrossImuMonitor(limits=limits)
    got = [r for item in items[:cut] for r in first.add(*item)]
    saved = encode_state(first.state_dict())
    second = CrossImuMonitor.from_state(decode_state(saved), limits=limits)
    assert second.flagged == first.flagged
    got += [r for item in items[cut:] for r in second.add(*item)]
    assert got == want


def test_cross_imu_state_of_another_version_or_malformed_is_a_value_error():
    state = CrossImuMonitor().state_dict()
    with pytest.raises(ValueError, match="version 99"):
        CrossImuMonitor.from_state({**state, "version": 99})
    with pytest.raises(ValueError, match="malformed"):
        CrossImuMonitor.from_state({**state, "open": [[0, 1, 2, [1.0, 2.0], [0.0] * 3]]})
    with pytest.raises(ValueError, match="malformed"):
        CrossImuMonitor.from_state({k: v for k, v in state.items() if k != "flagged"})


def test_cross_imu_monitor_does_not_wait_for_a_dead_imu():
    rng = np.random.default_rng(6)
    mon = CrossImuMonitor(limits=ValidityLimits(cross_imu_persist_windows=1))
    reports = []
    for step in range(16):
        t0 = step * 0.25
        for imu in (0, 1, 2):
            if imu == 2 and t0 >= 1.0:
                continue  # IMU 2 stops sending
            t, a, g = static_samples(rng, 250, t0_s=t0)
            if imu == 1 and t0 >= 2.0:
                a[:, 2] += 2.0
            reports.extend(mon.add(imu, t, a, g))
    assert {r.imu for r in reports if not r.consistent} == {0, 1}


def test_cross_imu_monitor_compares_every_bin_when_each_imu_sends_long_frames():
    """Two IMUs at 4 Hz in 25 s frames, one after the other (a replayed log): IMU 1 is off by 1 m/s² from 60 to 70 s."""
    rng = np.random.default_rng(8)
    mon = CrossImuMonitor(limits=ValidityLimits(cross_imu_persist_windows=4))
    reports = []
    for frame in range(6):
        for imu in (0, 1):
            t = frame * 25.0 + np.arange(100) * 0.25
            a = np.tile([0.0, 0.0, -9.81], (100, 1)) + ACCEL_NOISE_MPS2 * rng.standard_normal(
                (100, 3)
            )
            g = 1e-3 * rng.standard_normal((100, 3))
            if imu == 1:
                a[(t >= 60.0) & (t < 70.0), 0] += 1.0
            reports.extend(mon.add(imu, t, a, g))
    bad = [r for r in reports if not r.consistent]
    good = [r for r in reports if r.consistent]
    # Both IMUs disagree with the only other one: both flagged after the 4th bin (60.0, 60.5, 61.0, 61.5 s),
    # both recover after the 4th agreeing one (70.0 … 71.5 s).
    assert sorted(r.imu for r in bad) == [0, 1] and {r.bin_start_s for r in bad} == {61.5}
    assert sorted(r.imu for r in good) == [0, 1] and {r.bin_start_s for r in good} == {71.5}


UNIX_S, BOOT_S = 1.7e9, 100.0
"""Where two clocks of one vehicle start: one IMU stamps Unix time, the other time since boot."""


def _two_clocks(seed: int, *, base1_s, steps: int = 200, fault_from_s: float = 5.0):
    """Two IMUs in 0.1 s frames at 1 kHz, taken in turn, IMU 0 on a Unix clock and IMU 1 at
    ``base1_s(step)``; IMU 1 off by 0.1 g on x from ``fault_from_s`` of its own time."""
    rng = np.random.default_rng(seed)
    for step in range(steps):
        for imu in (0, 1):
            t, a, g = static_samples(rng, 100, t0_s=step * 0.1)
            if imu == 1:
                a[t >= fault_from_s, 0] += 0.1 * STANDARD_GRAVITY_MPS2
            yield imu, t + (UNIX_S if imu == 0 else base1_s(step)), a, g


def test_cross_imu_aligns_two_clocks_with_a_steady_offset():
    """Unix time against time since boot: the offset bounded by CLOCK_FRAMES frames of each IMU, then
    compared bin for bin; a 0.1 g disagreement is reported (both IMUs: with two, neither is the
    reference)."""
    mon = CrossImuMonitor(limits=ValidityLimits(cross_imu_persist_windows=4))
    reports, why = [], []
    for imu, t, a, g in _two_clocks(3, base1_s=lambda step: BOOT_S):
        reports += mon.add(imu, t, a, g)
        why.append(mon.not_compared(1))
    assert why[1].startswith("IMU1 stamps time on another clock than IMU0")
    assert "measuring the offset (0 of 8 frames)" in why[1]
    # Its 8 frames and the reference's 8 after its first: aligned at its 9th.
    aligned = why.index(None, 2)
    assert aligned == 2 * CLOCK_FRAMES + 1 and set(why[aligned:]) == {None}
    # The bounds are one 0.1 s frame apart: the middle is right within half of it.
    assert mon.clock_offsets_s[1] == pytest.approx(BOOT_S - UNIX_S, abs=0.05 + 1e-6)
    assert sorted((r.imu, r.consistent) for r in reports) == [(0, False), (1, False)]
    # The bin means of 500 samples: their noise (0.02 / sqrt(500) m/s²) is far below 0.05.
    assert [r.accel_dev_mps2 for r in reports] == pytest.approx(
        [0.1 * STANDARD_GRAVITY_MPS2] * 2, abs=0.05
    )


def test_cross_imu_on_clocks_whose_offset_does_not_hold_still_is_not_running_and_says_why():
    """IMU 1's clock jumps by tens of seconds from frame to frame: no offset is taken, the 0.1 g
    disagreement cannot be seen, and the monitor says why rather than nothing."""
    jumps = np.random.default_rng(4).uniform(-30.0, 30.0, size=200)
    mon = CrossImuMonitor(limits=ValidityLimits(cross_imu_persist_windows=4))
    reports = []
    for imu, t, a, g in _two_clocks(3, base1_s=lambda step: BOOT_S + jumps[step]):
        reports += mon.add(imu, t, a, g)
    assert reports == [] and mon.clock_offsets_s == {}
    why = mon.not_compared(1)
    assert why is not None and "offset not steady" in why and "over 8 frames" in why


def test_cross_imu_offset_survives_a_checkpoint():
    limits = ValidityLimits(cross_imu_persist_windows=4)
    items = list(_two_clocks(5, base1_s=lambda step: BOOT_S))
    whole = CrossImuMonitor(limits=limits)
    want = [r for item in items for r in whole.add(*item)]
    first = CrossImuMonitor(limits=limits)
    got = [r for item in items[:17] for r in first.add(*item)]
    second = CrossImuMonitor.from_state(
        decode_state(encode_state(first.state_dict())), limits=limits
    )
    got += [r for item in items[30:] for r in second.add(*item)]
    assert got == want and len(want) == 2


def test_cross_imu_skewed_by_0_7_s_while_moving_does_not_flap():
    """Two IMUs on one clock, IMU 1's stamps 0.7 s late, the vehicle swaying (0.5 m/s² at 0.25 Hz on
    x): the skew alone moves the bin means apart by up to 0.52 m/s², under the 0.75 limit. IMU 1
    off by 0.1 g from 10 to 50 s: the difference swings between 0.46 and 1.5 m/s², under the limit
    for at most 3 bins of each 8 s cycle. One report of the disagreement and one of its end."""
    rng = np.random.default_rng(11)
    mon = CrossImuMonitor(limits=ValidityLimits(cross_imu_persist_windows=4))
    reports = []
    for step in range(240):
        for imu in (0, 1):
            t, a, g = static_samples(rng, 250, t0_s=step * 0.25)
            true_t = t - (0.7 if imu == 1 else 0.0)
            a[:, 0] += 0.5 * np.sin(2 * np.pi * 0.25 * true_t)
            if imu == 1:
                a[(true_t >= 10.0) & (true_t < 50.0), 0] += 0.1 * STANDARD_GRAVITY_MPS2
            reports += mon.add(imu, t, a, g)
    per_imu = {imu: [r.consistent for r in reports if r.imu == imu] for imu in (0, 1)}
    assert per_imu == {0: [False, True], 1: [False, True]}


def test_best_clock_offset_is_the_lag_of_the_rotation_both_imus_saw():
    """A turn rate record (sum of sines, 200 Hz) seen by two IMUs whose clocks differ by 12.3456 s,
    each with its own bias and noise: the offset found within one sample step (5 ms) of it; at rest
    (noise only) no offset is told."""
    rng = np.random.default_rng(12)
    t = np.arange(0.0, 8.0, 0.005)
    turn = np.column_stack(
        [np.sin(2 * np.pi * f * t + p) for f, p in ((0.7, 0.0), (1.3, 1.0), (0.4, 2.0))]
    )
    offset = 12.3456

    def seen(rate, bias):
        return rate + bias + 1e-3 * rng.standard_normal(rate.shape)

    ref = (t, seen(turn, 0.01))
    measured = (t[:-200] + offset, seen(turn[:-200], -0.02))
    found = best_clock_offset(measured, ref, lowest_s=offset - 0.3, highest_s=offset + 0.3)
    assert found == pytest.approx(offset, abs=0.005)
    rest = (t + offset, seen(np.zeros_like(turn), 0.0))
    assert (
        best_clock_offset(
            rest, (t, seen(np.zeros_like(turn), 0.0)), lowest_s=offset - 0.3, highest_s=offset + 0.3
        )
        is None
    )


def test_cross_imu_state_of_version_1_is_resumed_without_clocks():
    """A checkpoint written before the clock offsets (version 1) resumes: the same bins and streaks,
    the reference taken afresh."""
    limits = ValidityLimits(cross_imu_persist_windows=4)
    items = list(_offset_stream(9))
    whole = CrossImuMonitor(limits=limits)
    want = [r for item in items for r in whole.add(*item)]
    first = CrossImuMonitor(limits=limits)
    got = [r for item in items[:16] for r in first.add(*item)]
    v2 = first.state_dict()
    v1 = {
        k: v
        for k, v in v2.items()
        if k in ("open", "span", "closed", "streak", "flagged", "last_compared")
    }
    second = CrossImuMonitor.from_state({**v1, "version": 1}, limits=limits)
    got += [r for item in items[16:] for r in second.add(*item)]
    assert got == want


def test_typical_steps_of_blocks_are_each_block_s_typical_step_bit_for_bit():
    """The rate watch takes the blocks a batch completes at once: each row's typical step is the
    one typical_step_s gives that block alone, to the bit (it is compared with the tolerance and
    sizes the detector), for steps of 1 kHz with jitter, of whole milliseconds, and with gaps."""
    rng = np.random.default_rng(4)
    blocks = np.vstack(
        [
            1e-3 + rng.normal(0.0, 1e-5, (300, 128)),
            rng.choice([2e-3, 3e-3], (300, 128)),
            rng.exponential(2.5e-3, (300, 128)),
        ]
    )
    assert typical_steps_s(blocks).tolist() == [typical_step_s(b) for b in blocks]
    assert typical_steps_s(np.empty((0, 128))).shape == (0,)
