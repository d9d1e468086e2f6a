"""The rotation-invariant cross-IMU check in flight (estimators.cross_imu_norm, issue 32).

Two simulated IMUs on one vehicle (the project's flight profile, 100 Hz, MEMS grade): IMU 1 sits
7.8 cm from IMU 0 and is mounted turned (body z onto its y axis, 30° of yaw), with errors and noise of
its own. A 0.5 % scale fault of IMU 1's thrust-carrying axis is found within 5 s; fault-free flights,
with IMU 1 turned 10° more, raise nothing, where the autopilots' vector comparison would; the streaming
path gives the batch path's blocks; the threshold meets its false-alarm rate.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from real_data import REAL_TLOG, needs
from scipy.spatial.transform import Rotation
from scipy.stats import binom
from service_support import run_fleet

import ins_health
from estimators.conventions import Triad
from estimators.cross_imu_norm import (
    CrossImuNorm,
    NormBlock,
    NormChannel,
    NormCheckConfig,
    NormTrace,
    cross_imu_norm_batch,
    cross_imu_norm_sessions,
    cusum_arl,
    cusum_threshold,
)
from estimators.nominal_passport import SensorClass
from estimators.session import ImuSession
from estimators.sim import (
    PAIR_LEVER_ARM_M,
    PAIR_MOUNT_ZX_DEG,
    Fault,
    FaultKind,
    pair_flight_specs,
    simulate,
)
from estimators.stream_validity import ValidityLimits, compare_imus
from protocols.checkpoint_codec import decode_state, encode_state
from protocols.events import Predicate, decode_event, encode_event, event_version
from protocols.frames import SampleBatch, split_session
from protocols.logs import read_log_sessions
from service.pipeline import FleetProcessor
from service.pipeline.norm_check import VehicleNorm

LEVER_ARM_M = np.array(PAIR_LEVER_ARM_M)
MOUNT = Rotation.from_euler("zx", PAIR_MOUNT_ZX_DEG, degrees=True).as_matrix()
FLY_S = 100.0
REST_S = 10.0


def thrust_axis(mat_sb: np.ndarray) -> int:
    """IMU 1's axis that body z (the thrust) falls on."""
    return int(np.argmax(np.abs(mat_sb[:, 2])))


def flight_pair(
    seed: int, *, faults: tuple[Fault, ...] = (), mat_sb: np.ndarray = MOUNT
) -> tuple[ImuSession, ImuSession]:
    spec0, spec1 = pair_flight_specs(fly_s=FLY_S, rest_s=REST_S, mat_sb=mat_sb, faults=faults)
    return simulate(spec0, seed).session, simulate(spec1, seed).session


def batch(s0: ImuSession, s1: ImuSession) -> NormTrace:
    return cross_imu_norm_sessions(s0, s1)


def test_siegmund_run_length_matches_a_simulated_cusum() -> None:
    """The threshold's footing: a CUSUM on N(0, 1) with k = 1, h = 2.5 runs as long as Siegmund's
    ARL says (2,000 runs: the mean's standard error is ~2 %; the approximation is good to ~5 %)."""
    rng = np.random.default_rng(1)
    k, h, runs = 1.0, 2.5, 2000
    g = np.zeros(runs)
    length = np.zeros(runs)
    alive = np.ones(runs, bool)
    steps = 0
    while alive.any():
        steps += 1
        g[alive] = np.maximum(0.0, g[alive] + rng.standard_normal(alive.sum()) - k)
        done = alive & (g > h)
        length[done] = steps
        alive &= ~done
    se = length.std() / math.sqrt(runs)
    assert abs(length.mean() - cusum_arl(0.0, k, h)) < 3.0 * se + 0.05 * cusum_arl(0.0, k, h)
    assert cusum_arl(0.0, k, cusum_threshold(1.0e6, k)) == pytest.approx(1.0e6)


def test_streaming_path_reproduces_the_batch_path() -> None:
    """The per-sample path is the batch path's oracle: frames of 37 samples, the two IMUs' clocks 3 ms
    apart (IMU 1 interpolated), a fault in the middle: the same blocks, lever arm and alarm."""
    s0, s1 = flight_pair(
        2, faults=(Fault(FaultKind.STEP, Triad.ACCEL, 3 + thrust_axis(MOUNT), 60.0, 0.005),)
    )
    t1 = s1.t_s + 0.003
    trace = cross_imu_norm_batch(s0.t_s, s0.accel_mps2, s0.gyro_rps, t1, s1.accel_mps2, s1.gyro_rps)
    stream = CrossImuNorm()
    blocks = []
    for k in range(0, s0.t_s.size, 37):
        sl = slice(k, k + 37)
        blocks += stream.add(1, t1[sl], s1.accel_mps2[sl], s1.gyro_rps[sl])
        blocks += stream.add(0, s0.t_s[sl], s0.accel_mps2[sl], s0.gyro_rps[sl])
    assert len(blocks) == len(trace.blocks) > 100
    for a, b in zip(blocks, trace.blocks, strict=True):
        assert a.t_s == b.t_s and a.samples == b.samples
        for ca, cb in ((a.accel, b.accel), (a.gyro, b.gyro)):
            # Block sums of ~100 terms up to |f|²/m ≈ 10 differ in their last bits with the order
            # of summation; the innovations (1e-4…1e-2) are their small differences: 1e-10 apart.
            np.testing.assert_allclose(
                [ca.innovation_si, ca.innovation_sd_si],
                [cb.innovation_si, cb.innovation_sd_si],
                rtol=1e-8,
                atol=1e-10,
            )
            # The CUSUMs (in standard deviations) add and cancel: summation order shows at 1e-10.
            np.testing.assert_allclose(
                [ca.cusum_pos, ca.cusum_neg], [cb.cusum_pos, cb.cusum_neg], atol=1e-8
            )
        np.testing.assert_allclose(a.lever_arm_m, b.lever_arm_m, rtol=1e-8, atol=1e-12)
    assert [x.t_s for b in blocks for x in b.alarms] == [x.t_s for x in trace.alarms]
    assert stream.counts.paired == trace.paired


def test_scale_fault_of_the_thrust_axis_is_found_within_5_s() -> None:
    """IMU 1's thrust-axis scale +0.5 % (0.049 m/s² of |f| in hover) from a random time mid-flight:
    found by the accelerometer norm within 5 s. For a detection probability of 0.95, 17 or more of 20
    flights (P(X <= 16 | p = 0.95) = 0.016); benchmarks/bench_inflight.py runs 100."""
    rng = np.random.default_rng(32)
    axis = thrust_axis(MOUNT)
    detected = 0
    for seed in range(20):
        onset = REST_S + float(rng.uniform(40.0, 80.0))
        s0, s1 = flight_pair(
            seed, faults=(Fault(FaultKind.STEP, Triad.ACCEL, 3 + axis, onset, 0.01),)
        )
        alarms = [a for a in batch(s0, s1).alarms if a.channel is NormChannel.ACCEL]
        assert all(a.t_s > onset for a in alarms)
        detected += bool(alarms) and alarms[0].t_s - onset <= 5.0
    assert binom.cdf(16, 20, 0.95) < 0.02
    assert detected >= 17


def test_scale_fault_of_the_yaw_gyro_is_found_by_the_gyro_norm() -> None:
    """IMU 1's gyro scale +1 % on the axis body z falls on (the flight's turns are mostly yaw) from
    60 s: found by the gyro channel within 5 s in at least 8 of 10 flights (P(X <= 7 | p = 0.95) =
    0.012). A gyro zero signal shows only along the rotation, so the norm says little of it in hover."""
    axis = thrust_axis(MOUNT)
    detected = 0
    for seed in range(10):
        s0, s1 = flight_pair(
            seed, faults=(Fault(FaultKind.STEP, Triad.GYRO, 3 + axis, 60.0, 0.01),)
        )
        alarms = [a for a in batch(s0, s1).alarms if a.channel is NormChannel.GYRO]
        assert all(a.t_s > 60.0 for a in alarms)
        detected += bool(alarms) and alarms[0].t_s - 60.0 <= 5.0
    assert binom.cdf(7, 10, 0.95) < 0.02
    assert detected >= 8


def test_fault_free_flights_with_a_turned_imu_raise_nothing() -> None:
    """12 fault-free flights (24 min) with IMU 1 turned another 10°: at 1e-4 false alarms per flight
    hour 4e-5 are expected, so any alarm fails. The autopilots' vector comparison flags that pair."""
    turned = Rotation.from_euler("x", 10.0, degrees=True).as_matrix() @ MOUNT
    for seed in range(100, 112):
        s0, s1 = flight_pair(seed, mat_sb=turned)
        trace = batch(s0, s1)
        assert trace.alarms == ()
        # Tested from the end of the warm-up to the last whole block.
        assert trace.tested_s >= FLY_S + 2.0 * REST_S - NormCheckConfig().warmup_blocks - 1.0
    # Even told the mounting (IMU 1 rotated back by the nominal MOUNT), a 10° error is 1.7 m/s² at rest.
    back = s1.accel_mps2[:100] @ MOUNT
    verdict = compare_imus((0, 1), np.array([s0.accel_mps2[:100].mean(0), back.mean(0)]),
                           np.array([s0.gyro_rps[:100].mean(0), (s1.gyro_rps[:100] @ MOUNT).mean(0)]),
                           limits=ValidityLimits())  # fmt: skip
    assert verdict.disagreeing == (0, 1)


def test_lever_arm_is_found_with_its_covariance() -> None:
    """The lever arm of 7.8 cm is estimated in flight: within 5 stated standard deviations per axis,
    each below 3 mm (the fit's model error — the check's ω̇ is a central difference of sampled rates —
    is within the covariance's reach at this size)."""
    s0, s1 = flight_pair(7)
    trace = batch(s0, s1)
    sd = np.sqrt(np.diag(trace.lever_arm_cov_m2))
    assert np.all(sd < 3e-3)
    assert np.all(np.abs(trace.lever_arm_m - LEVER_ARM_M) < 5.0 * sd)


def interleaved_frames(s0: ImuSession, s1: ImuSession, n: int = 50) -> list[SampleBatch]:
    """Both IMUs' frames of ``n`` samples in arrival order, as a vehicle streams them."""
    f0 = list(split_session(s0, vehicle="uav", imu=0, batch_samples=n))
    f1 = list(split_session(s1, vehicle="uav", imu=1, batch_samples=n))
    return [b for pair in zip(f0, f1, strict=True) for b in pair]


def test_the_fleet_raises_a_cross_imu_norm_event_and_states_its_coverage() -> None:
    """Through the daemon's per-frame path (FleetProcessor, consumer-MEMS nominal passports): the
    0.5 % fault is one event of predicate cross_imu_norm on IMU 1 within 5 s; its fault-free twin
    raises none of them, and the coverage of both IMUs says how long the norms were tested and
    their MDF. The event is a schema-2 event and reads back."""
    onset = REST_S + 50.0
    fault = Fault(FaultKind.STEP, Triad.ACCEL, 3 + thrust_axis(MOUNT), onset, 0.005)
    covered = {}
    for faults in ((), (fault,)):
        fleet = FleetProcessor(passports=lambda v, i: None, nominal=SensorClass.CONSUMER_MEMS)
        events = run_fleet(fleet, interleaved_frames(*flight_pair(4, faults=faults)))
        norm = [e for e in events if e.predicate is Predicate.CROSS_IMU_NORM]
        if not faults:
            assert norm == []
            covered = {i: fleet.norm_coverage("uav", i) for i in (0, 1)}
            continue
        assert [(e.imu, e.triad) for e in norm] == [(1, Triad.ACCEL)]
        assert onset < norm[0].t_s <= onset + 5.0 and norm[0].estimate > 0.0
        assert decode_event(encode_event(norm[0])) == norm[0] and event_version(norm[0]) == 2
    # A zero signal moves |f| by its component along the specific force: each IMU's thrust axis
    # (IMU 0's z, IMU 1's y) is tested, the two across it are not observable (0.02 m/s², 3 times
    # the norm's MDF, on them was not found in two simulated flights; the thrust-axis convention).
    for imu, thrust in ((0, 2), (1, thrust_axis(MOUNT))):
        accel, gyro = covered[imu]
        assert accel.ran and gyro.ran and accel.samples >= FLY_S - 1.0
        assert 0.0 < accel.mdf_bias_si[thrust] < 0.049
        # A gyro zero signal shows in the norm only while the rotation about its axis keeps one
        # sign: no axis is claimed (module docstring of estimators.coverage's norm_coverage).
        assert gyro.mdf_bias_si == (math.inf,) * 3
        assert "a zero signal on x, y, z not observable" in gyro.line(" rad/s")
        assert [math.isfinite(m) for m in accel.mdf_bias_si] == [k == thrust for k in range(3)]
        blind = ", ".join("xyz"[k] for k in range(3) if k != thrust)
        assert "cross_imu_norm: in flight tested on" in accel.line(" m/s²")
        assert f"{blind} not observable" in accel.line(" m/s²")


def test_a_pair_too_short_to_test_says_so() -> None:
    """Five seconds of two IMUs: the norm check has not finished its warm-up, and says it did not
    run and why (silence is not health)."""
    s0, s1 = flight_pair(5)
    short = [b for b in interleaved_frames(s0, s1) if b.t_s[-1] < 5.0]
    fleet = FleetProcessor(passports=lambda v, i: None)
    run_fleet(fleet, short)
    accel, _ = fleet.norm_coverage("uav", 1)
    assert not accel.ran and accel.missing and "the test starts after 20 s" in accel.reason


@needs(REAL_TLOG)
def test_a_real_telemetry_log_at_4_hz_is_said_too_slow_for_the_check_not_passed(tmp_path) -> None:
    """ArduPlane SITL's VTOL telemetry log (RAW_IMU and SCALED_IMU2 snapshots at 4.2 Hz, 208 s): fed
    from its first samples (as a live link gives them, one sample a frame), one manoeuvre's snapshots
    put a block's gyro norm difference 7 σ off and raised a false cross_imu_norm alarm at 786.5 s.
    Below :data:`~estimators.cross_imu_norm.MIN_RATE_HZ` the check does not apply, and the coverage
    and the report say so with the rate, in replay and in one-sample frames alike. The other logs with
    two IMUs hold 1 s or less of them (tests/real_data.py's REAL_BIN: 45 samples each)."""
    sessions, _ = read_log_sessions(REAL_TLOG)
    report = tmp_path / "report"
    result = ins_health.replay(REAL_TLOG, report=report)
    assert [e for e in result.events if e.predicate is Predicate.CROSS_IMU_NORM] == []
    assert json.loads((report / "report.json").read_text())["cross_imu_norm"] is None
    one_sample = [
        b
        for imu in (0, 1)
        for b in split_session(sessions[imu], vehicle="uav", imu=imu, batch_samples=1)
    ]
    fleet = FleetProcessor(passports=lambda v, i: None)
    events = run_fleet(fleet, sorted(one_sample, key=lambda b: float(b.t_s[0])))
    assert [e for e in events if e.predicate is Predicate.CROSS_IMU_NORM] == []
    for imu in (0, 1):
        for c in fleet.norm_coverage("uav", imu):
            assert not c.ran and not c.applies and re.search(r"samples at 4\.\d+ Hz", c.reason), c


def test_a_checkpointed_check_goes_on_where_it_was() -> None:
    """The check's state through the checkpoint codec mid-flight (samples waiting to be paired, an
    open block, both CUSUMs): the resumed check gives the blocks and the alarm of one that never
    stopped; a state of another version is refused with the reason."""
    s0, s1 = flight_pair(
        3, faults=(Fault(FaultKind.STEP, Triad.ACCEL, 3 + thrust_axis(MOUNT), 70.0, 0.005),)
    )
    frames = [(slot, s, k) for k in range(0, s0.t_s.size, 50) for slot, s in ((1, s1), (0, s0))]

    def feed(check: CrossImuNorm, part) -> list:
        out = []
        for slot, s, k in part:
            sl = slice(k, k + 50)
            out += check.add(slot, s.t_s[sl], s.accel_mps2[sl], s.gyro_rps[sl])
        return out

    whole = feed(CrossImuNorm(), frames)
    cut = len(frames) // 2 + 1
    first = CrossImuNorm()
    before = feed(first, frames[:cut])
    resumed = CrossImuNorm.from_state(decode_state(encode_state(first.state_dict())))
    after = feed(resumed, frames[cut:])

    def key(b: NormBlock) -> tuple:
        return (b.t_s, b.samples, b.accel, b.gyro, tuple(b.lever_arm_m), b.alarms)

    assert [key(b) for b in before + after] == [key(b) for b in whole]
    assert any(b.alarms for b in after)
    with pytest.raises(ValueError, match="version 0 is not 1"):
        CrossImuNorm.from_state({**first.state_dict(), "version": 0})


def test_the_axes_shares_of_the_specific_force_go_through_the_checkpoint() -> None:
    """The vehicle's norm check keeps each IMU's share of the specific force (its coverage's
    observable axes) in its checkpoint; one written before the shares were kept starts them afresh,
    a malformed one is refused with the reason."""
    norm = VehicleNorm("uav", (0, 1), 100.0, gravity_mps2=9.8)
    t = np.arange(50) * 0.01
    norm.add(SampleBatch("uav", 1, 0, t, np.tile([0.0, 9.8, 0.0], (50, 1)), np.zeros((50, 3))), {})
    saved = decode_state(encode_state(norm.state_dict()))
    back = VehicleNorm.from_state("uav", saved, gravity_mps2=9.8)
    assert (back.accel_share_sums, back.accel_share_n) == ([[0.0] * 3, [0.0, 50.0, 0.0]], [0, 50])
    older = {k: v for k, v in saved.items() if not k.startswith("accel_share")}
    assert VehicleNorm.from_state("uav", older, gravity_mps2=9.8).accel_share_n == [0, 0]
    with pytest.raises(ValueError, match="malformed"):
        VehicleNorm.from_state("uav", {**saved, "accel_share_n": [1]}, gravity_mps2=9.8)
