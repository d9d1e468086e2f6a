"""The thrust-axis check live (issue 32): GNSS frames (``ins/<vehicle>/gnss``, version 1) beside the
IMU frames, into the fleet's per-IMU checks; the daemon takes them from Zenoh and a thrust-axis
fault in flight arrives as an event at a ground station.

The flight: the project's flight profile (10 s rest, 170 s of ``Fly``, 10 s rest), consumer MEMS
at 100 Hz, a receiver at 10 Hz (0.05 m/s, 0.15 s latency); z + 0.1 m/s² from 140 s.
"""

from __future__ import annotations

import asyncio
import functools
import threading

import numpy as np
import pytest
import zenoh
from service_support import (
    batches_of,
    served_vehicle,
    wait_subscribed,
    wait_until,
)

from estimators.nominal_passport import SensorClass
from estimators.session import ImuSession
from estimators.sim import Fly, flight_spec, simulate
from estimators.sim.gnss import gnss_velocity
from protocols.events import Predicate
from protocols.frames import FrameError
from protocols.gnss_frames import GnssFrame, decode_gnss_frame, encode_gnss_frame
from protocols.zenoh_adapter import (
    EventReceiver,
    FramePublisher,
    GnssPublisher,
    frame_key,
    gnss_key,
    gnss_selector,
    subscribe_service_status,
    subscribe_status,
)
from service.intake import Intake
from service.pipeline import FleetProcessor
from service.pipeline.thrust_axis import ThrustAxisCheck

ONSET_S = 140.0


@functools.cache
def flight():
    res = simulate(flight_spec(fly=Fly(170.0), rest_s=10.0), 4)
    s = res.session
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(4)
    )
    accel = s.accel_mps2.copy()
    accel[s.t_s >= ONSET_S, 2] += 0.1
    return ImuSession(s.t_s, accel, s.gyro_rps), gt, gv


@functools.cache
def fault_free_flight():
    res = simulate(flight_spec(fly=Fly(170.0), rest_s=10.0), 4)
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(4)
    )
    return res.session, gt, gv


def _interleaved(vehicle: str, of=flight):
    """IMU frames of 100 samples, each followed by the GNSS epochs up to its last sample."""
    session, gt, gv = of()
    j, seq = 0, 0
    for batch in batches_of(session, vehicle=vehicle, imu=0, batch_samples=100):
        yield batch
        k = int(np.searchsorted(gt, batch.t_s[-1], "right"))
        if k > j:
            yield GnssFrame(vehicle, seq, 10.0, gt[j:k], gv[j:k])
            j, seq = k, seq + 1


def test_a_gnss_frame_round_trips_and_a_bad_one_is_refused_with_its_reason():
    frame = GnssFrame("uav-1", 7, 10.0, [1.0, 1.1], [[0.0, 1.0, -0.5], [0.1, 1.0, -0.4]])
    back = decode_gnss_frame(encode_gnss_frame(frame))
    assert (back.vehicle, back.seq, back.rate_hz) == ("uav-1", 7, 10.0)
    np.testing.assert_array_equal(back.vel_enu_mps, frame.vel_enu_mps)
    backwards = GnssFrame("uav-1", 8, 10.0, [1.2, 1.1], [[0.0] * 3, [0.0] * 3])
    with pytest.raises(FrameError, match="strictly increase") as err:
        decode_gnss_frame(encode_gnss_frame(backwards))
    assert err.value.reason.value == "time_not_increasing"
    nan = GnssFrame("uav-1", 9, 10.0, [1.3], [[np.nan, 0.0, 0.0]])
    with pytest.raises(FrameError, match="NaN"):
        decode_gnss_frame(encode_gnss_frame(nan))
    assert gnss_key("uav-1") == "ins/uav-1/gnss"
    assert gnss_selector("ins/uav-7/imu/*") == "ins/uav-7/gnss"
    assert gnss_selector("ins/*/imu/*") == "ins/*/gnss"


def test_the_fleet_checks_each_imu_against_its_vehicles_gnss():
    """Frames and GNSS frames through the fleet as the daemon hands them (IMU frames queued and
    joined: the joined path fed nothing to the check before), on the nominal passport the daemon
    gives a unit without one: one thrust_axis event
    on the accelerometer's z within 10 s of the onset; the IMU's status coverage has the line."""
    fleet = FleetProcessor(passports=lambda v, i: None, nominal=SensorClass.CONSUMER_MEMS)
    items = list(_interleaved("uav-1"))
    events = []
    for start in range(0, len(items), 20):
        piece = items[start : start + 20]
        for item in piece:
            if isinstance(item, GnssFrame):
                events += fleet.gnss(item)
        # Queued frames, joined where the chain allows, as the daemon's intake takes them.
        imu = [item for item in piece if not isinstance(item, GnssFrame)]
        for raised in fleet.queued_steps(imu, arrival_s=float(imu[-1].t_s[-1])):
            events += raised
    thrust = [e for e in events if e.predicate is Predicate.THRUST_AXIS]
    assert len(thrust) == 1 and thrust[0].axis == "z"
    assert ONSET_S <= thrust[0].t_s <= ONSET_S + 10.0
    status = fleet.status("uav-1", service="test", now_unix_s=0.0)
    lines = [c for c in status.imus[0].coverage if c.check.value == "thrust_axis"]
    assert len(lines) == 1 and lines[0].ran
    assert status.counters["service.gnss.frames"] > 0


class _GnssFrames:
    """A GNSS source of the frames given (the calls of ``GnssSource`` the intake uses)."""

    dropped = 0

    def __init__(self, frames: list[GnssFrame]):
        self._frames = frames

    async def get(self) -> GnssFrame:
        if not self._frames:
            raise EOFError
        return self._frames.pop(0)


def _through_intake(items: list) -> tuple[FleetProcessor, list, list[str]]:
    """IMU and GNSS frames in their order through the daemon's intake, the GNSS ones over the wire
    (encoded and decoded, as the Zenoh source gives them): the fleet, events, log lines."""
    fleet = FleetProcessor(passports=lambda v, i: None, nominal=SensorClass.CONSUMER_MEMS)
    events: list = []
    said: list[str] = []
    intake = Intake(fleet, store=events.extend, clock=lambda: 0.0, say=said.append)

    async def feed() -> None:
        for item in items:
            if isinstance(item, GnssFrame):
                wire = decode_gnss_frame(encode_gnss_frame(item))
                await intake.gnss_frames(_GnssFrames([wire]))  # type: ignore[arg-type]
            else:
                intake.process([item])

    asyncio.run(feed())
    return fleet, events, said


def test_a_damaged_gnss_velocity_is_left_out_and_counted_and_the_check_goes_on():
    """One epoch of 1e20 m/s in a fault-free flight, 60 s after the learning (a damaged float on the
    wire: no civil receiver reports above 515 m/s): the check's velocity integral carried it and its
    differences were lost to rounding, an alarm on a sound unit. The intake leaves the epoch out,
    counts it as gnss.rejected.speed_over_515_mps, says it once, and the check goes on as if the
    epoch had never come: the same statistic as the flight without it, no event."""
    session, gt, gv = fault_free_flight()
    k = int(np.searchsorted(gt, 140.0))
    damaged = gv.copy()
    damaged[k, 0] = 1e20
    fleet, events, said = _through_intake(
        list(_interleaved("uav-1", lambda: (session, gt, damaged)))
    )
    assert [e for e in events if e.predicate is Predicate.THRUST_AXIS] == []
    status = fleet.status("uav-1", service="test", now_unix_s=0.0)
    assert status.counters["service.gnss.rejected.speed_over_515_mps"] == 1
    assert [line for line in said if "speed_over_515_mps" in line] != []
    without = (session, np.delete(gt, k), np.delete(gv, k, axis=0))
    clean, _, _ = _through_intake(list(_interleaved("uav-1", lambda: without)))
    t, z = fleet.pipelines[("uav-1", 0)].thrust.statistic()
    t_clean, z_clean = clean.pipelines[("uav-1", 0)].thrust.statistic()
    np.testing.assert_array_equal(t, t_clean)
    np.testing.assert_array_equal(z, z_clean)
    assert np.isfinite(z[t > gt[k]]).any()


def test_the_event_names_the_axis_the_thrust_falls_on():
    """A unit mounted turned 90° about x (body z, the thrust, on its y axis) with the same fault on
    its y: the event names y, the axis the coverage says was tested, not z, which saw nothing."""
    session, gt, gv = flight()
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    turned = ImuSession(session.t_s, session.accel_mps2 @ turn.T, session.gyro_rps @ turn.T)
    check = ThrustAxisCheck("uav-1", 1, 10.0)
    events = check.gnss(gt, gv)
    for batch in batches_of(turned, vehicle="uav-1", imu=1, batch_samples=100):
        events += check.imu(batch)
    assert [(e.axis, e.imu) for e in events] == [("y", 1)]
    assert "accelerometer y:" in events[0].text
    assert (
        check.coverage().line(" m/s²").startswith("accel thrust_axis: in flight: y accelerometer")
    )


@pytest.mark.network
def test_the_daemon_takes_gnss_frames_from_zenoh_and_the_fault_arrives(tmp_path):
    """The flight published in 10 s pieces, each piece's GNSS frames first, and each piece waited
    for on the status (frames of two topics have no order between them: a burst of the whole
    flight lets the IMU frames through before any GNSS one, as a live vehicle never does)."""
    v = "uav-1"
    items = list(_interleaved(v))
    with served_vehicle(tmp_path, tmp_path / "passports", validity={"timeout_s": 60.0}) as (
        vehicle,
        ground,
    ):
        got, statuses, instance = [], [], []
        lock = threading.Lock()

        def keep(into: list):
            return lambda s: (lock.acquire(), into.append(s), lock.release())

        def counter(of: list, name: str) -> int:
            with lock:
                return of[-1].counters.get(name, 0) if of else 0

        with EventReceiver(ground, lambda e: got.append(e)):
            subscribe_status(ground, keep(statuses))
            subscribe_service_status(ground, keep(instance))
            wait_subscribed(vehicle, frame_key(v, 0))
            wait_subscribed(vehicle, gnss_key(v))
            gnss = GnssPublisher(vehicle, v, rate_hz=10.0)
            samples = gnss_frames = 0
            with FramePublisher(
                vehicle, v, 0, congestion_control=zenoh.CongestionControl.BLOCK
            ) as frames:
                for start in range(0, len(items), 20):
                    piece = items[start : start + 20]
                    for item in piece:
                        if isinstance(item, GnssFrame):
                            gnss.publish(item.t_s, item.vel_enu_mps)
                            gnss_frames += 1
                    wait_until(
                        lambda: counter(instance, "service.gnss.frames") >= gnss_frames,
                        timeout_s=10,
                        what="the GNSS frames counted",
                    )
                    for item in piece:
                        if not isinstance(item, GnssFrame):
                            frames.publish(item)
                            samples += item.n_samples
                    wait_until(
                        lambda: counter(statuses, "imu0.samples.accepted") >= samples,
                        timeout_s=10,
                        what="the IMU frames counted",
                    )
            gnss.close()
            wait_until(
                lambda: any(e.predicate is Predicate.THRUST_AXIS for e in got),
                timeout_s=30,
                what="the thrust_axis event",
            )
        (e,) = [e for e in got if e.predicate is Predicate.THRUST_AXIS]
        assert e.vehicle == v and e.axis == "z" and ONSET_S <= e.t_s <= ONSET_S + 10.0
