"""A unit without a usable passport runs on its class's nominal passport ([service] default_grade): the
fleet in process, and the daemon over Zenoh (estimators.nominal_passport, service.pipeline.fleet)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from service_support import run_fleet, wait_subscribed, wait_until
from test_service_faults import (
    ServiceProcess,
    ground_and_vehicle,
    publish_blocking,
    put_store,
)

from estimators.conventions import STANDARD_GRAVITY_MPS2, Triad
from estimators.nominal_passport import SensorClass, nominal_passport
from protocols.events import ImuState, Predicate
from protocols.frames import SampleBatch
from protocols.zenoh_adapter import EventReceiver, frame_key
from service.passport_store import PassportStore, PassportStoreError
from service.pipeline import FleetProcessor, PipelineOptions

G = STANDARD_GRAVITY_MPS2
RATE_HZ = 200.0


def resting(vehicle: str, z_g: float, *, seconds: float = 10.0, seed: int = 1, imu: int = 0):
    """Frames of 100 samples of a unit at rest, z up, whose z accelerometer reads ``z_g`` g, with the
    consumer-MEMS class noise at 200 Hz (4 mg and 0.05 °/s per sample)."""
    cls = nominal_passport(SensorClass.CONSUMER_MEMS, gravity_mps2=G)
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE_HZ)
    noise = {
        t: tp.noise_std[0] * tp.reference * math.sqrt(RATE_HZ / tp.sample_rate_hz)
        for t, tp in cls.triads.items()
    }
    accel = rng.normal(0.0, noise[Triad.ACCEL], (n, 3))
    accel[:, 2] += z_g * G
    gyro = rng.normal(0.0, noise[Triad.GYRO], (n, 3))
    t = 1.0 + np.arange(n) / RATE_HZ
    return [
        SampleBatch(vehicle, imu, k, t[s : s + 100], accel[s : s + 100], gyro[s : s + 100])
        for k, s in enumerate(range(0, n, 100))
    ]


def options() -> PipelineOptions:
    return PipelineOptions(gravity_mps2=G)


def missing(vehicle: str, imu: int):
    return None


def test_a_unit_without_a_passport_gets_f0_from_its_class_and_says_so():
    """1.2 g at rest (s = 0.22 against λ0 0.219 at 200 Hz, 2.4 mg of noise in s): F0's event; the healthy
    twin none. Without a class ("none") the same unit has no passport: no F0, but the gross test."""
    fleet = FleetProcessor(passports=missing, options=options(), nominal=SensorClass.CONSUMER_MEMS)
    events = run_fleet(fleet, resting("uav-bad", 1.2) + resting("uav-ok", 1.0, seed=2))
    # F0 per sample, and the gross test on its windows (5 s of them) too.
    assert [(e.vehicle, e.predicate) for e in events] == [
        ("uav-bad", Predicate.F0),
        ("uav-bad", Predicate.GROSS),
    ]
    for vehicle in ("uav-bad", "uav-ok"):
        st = fleet.status(vehicle, service="t", now_unix_s=0.0).imus[0]
        assert st.state is not ImuState.NO_PASSPORT
        assert st.detail.startswith("passport: nominal consumer_mems; F0 accel: λ0 0.219")
    # Without a class ("none") F0 has no passport to run against; the gross test, which needs none,
    # still finds the unit off g and says whose tolerances it took.
    off = FleetProcessor(passports=missing, options=options(), nominal=None)
    assert [e.predicate for e in run_fleet(off, resting("uav-bad", 1.2))] == [Predicate.GROSS]
    st = off.status("uav-bad", service="t", now_unix_s=0.0).imus[0]
    assert st.state is ImuState.FAULT and "nominal consumer_mems (no passport)" in st.detail
    assert "F0 accel" not in st.detail


def test_a_refused_entry_falls_back_to_the_nominal_passport_and_stays_reported(tmp_path):
    """An altered entry is refused (checksum) and counted as refused; the unit still gets F0 from its
    class, and its status names the refusal beside the nominal passport."""
    store = PassportStore(tmp_path)
    path = store.put("uav-x", 0, nominal_passport(SensorClass.TACTICAL, gravity_mps2=G))
    path.write_text(path.read_text().replace('"nominal-tactical"', '"altered"'))
    with pytest.raises(PassportStoreError):
        store.get("uav-x", 0)
    told = []
    fleet = FleetProcessor(
        passports=store.get,
        options=options(),
        nominal=SensorClass.CONSUMER_MEMS,
        on_passport_error=lambda v, i, why: told.append(why),
    )
    events = run_fleet(fleet, resting("uav-x", 1.2))
    assert [e.predicate for e in events] == [Predicate.F0, Predicate.GROSS]
    assert len(told) == 1 and store.rejected_counts() == {"checksum_mismatch": 1}
    detail = fleet.status("uav-x", service="t", now_unix_s=0.0).imus[0].detail
    assert detail.startswith(f"passport: nominal consumer_mems; {told[0]}")


def test_a_checkpoint_made_on_a_nominal_passport_resumes_on_the_same_class_only():
    """The failing F0 is carried by the checkpoint of a nominal unit (identity nominal-consumer_mems), so
    the restarted fleet does not raise it again; against another class's passport it is discarded
    (moved aside by the daemon) and the unit starts fresh."""
    fleet = FleetProcessor(passports=missing, options=options(), nominal=SensorClass.CONSUMER_MEMS)
    frames = resting("uav-c", 1.2)
    assert [e.predicate for e in run_fleet(fleet, frames[:10], finish=False)] == [
        Predicate.F0,
        Predicate.GROSS,
    ]
    state = fleet.pipelines[("uav-c", 0)].state_dict()
    assert state["passport"] == "nominal-consumer_mems 2026-01-01"
    for cls, restored in ((SensorClass.CONSUMER_MEMS, True), (SensorClass.TACTICAL, False)):
        again = FleetProcessor(passports=missing, options=options(), nominal=cls)
        errors = []
        again.set_restore(lambda v, i: state, lambda v, i, why: errors.append(why))
        events = run_fleet(again, frames[10:], finish=False)
        counters = again.vehicle_counters["uav-c"]
        if restored:
            assert counters["checkpoints.restored"] == 1 and events == [] and errors == []
        else:
            assert counters["checkpoints.discarded"] == 1 and len(errors) == 1
            assert "nominal-consumer_mems 2026-01-01" in errors[0]


def test_at_the_vehicle_limit_a_nominal_vehicle_makes_room_for_one_with_its_own_passport():
    """The store's semantics stay: only a passport of its own counts, so a flood of unknown vehicle ids
    (each on a nominal passport) cannot lock a fleet's real vehicles out."""
    own = nominal_passport(SensorClass.INDUSTRIAL_MEMS, gravity_mps2=G, unit_id="real-unit")
    fleet = FleetProcessor(
        passports=lambda v, i: own if v == "uav-real" else None,
        options=options(),
        nominal=SensorClass.CONSUMER_MEMS,
        max_vehicles=1,
    )
    run_fleet(fleet, resting("uav-made-up", 1.0)[:2], finish=False)
    run_fleet(fleet, resting("uav-other", 1.0)[:2], finish=False)
    assert fleet.service_counters["frames.rejected.over_vehicle_limit"] == 2
    run_fleet(fleet, resting("uav-real", 1.0)[:2], finish=False)
    assert fleet.vehicles() == ["uav-real"]
    assert fleet.service_counters["vehicles.evicted_without_passport"] == 1


@pytest.mark.network
def test_the_daemon_gives_a_unit_without_a_passport_its_class_and_raises_f0_over_zenoh(tmp_path):
    """``ins-health run`` with an empty store and the documented default grade, on a real router: the
    unit reading 1.2 g at rest raises F0 over Zenoh, its healthy twin nothing; both statuses say
    ``passport: nominal consumer_mems``, and the start-up line says what units without one run on."""
    bad, ok = resting("uav-bad", 1.2), resting("uav-ok", 1.0, seed=2)
    root = put_store(tmp_path, [])
    with ground_and_vehicle(tmp_path, root) as (config, ground, vehicle, status):
        got = []
        with EventReceiver(ground, got.append):
            daemon = ServiceProcess(config)
            try:
                wait_subscribed(vehicle, frame_key("uav-ok", 0))
                publish_blocking(vehicle, ok)
                publish_blocking(vehicle, bad)
                wait_until(
                    lambda: (
                        {e.predicate for e in got if e.vehicle == "uav-bad"}
                        == {Predicate.F0, Predicate.GROSS}
                    ),
                    timeout_s=60,
                    what=lambda: f"the F0 and gross events of uav-bad (got {got})",
                )
                wait_until(
                    lambda: all(
                        status.counter(v, "imu0.samples.accepted") == 2000
                        for v in ("uav-ok", "uav-bad")
                    ),
                    timeout_s=30,
                    what=lambda: f"every sample accepted ({status.get('uav-ok')})",
                )
                details = {v: status.get(v).imus[0].detail for v in ("uav-ok", "uav-bad")}
            finally:
                code = daemon.terminate()
    assert code == 0, daemon.lines
    assert sorted((e.vehicle, e.imu, e.predicate.value) for e in got) == [
        ("uav-bad", 0, "F0"),
        ("uav-bad", 0, "gross"),
    ]
    assert all(d.startswith("passport: nominal consumer_mems; ") for d in details.values()), details
    assert any(
        "0 refused; 0 unit(s) run on nominal passports" in line
        and "default_grade consumer_mems: any unit without a usable passport runs on the nominal "
        "consumer_mems passport"
        in line
        for line in daemon.lines
    ), daemon.lines
