"""The demo: a simulated vehicle, a Zenoh router and the service, all in this process.

What ``ins-health demo`` does (everything on 127.0.0.1, nothing downloaded):

1. **Passport.** The simulated MEMS unit is *calibrated from its own
   fault-free handling session*: a separate 18-position session of the same
   unit is simulated and run through the offline chain
   (:func:`estimators.chain.run_chain`: static positions, refined M1 estimate
   of the nine parameters) and the passport is built by the default tolerance
   rule (:func:`estimators.passport.passport_from_estimates`, MEMS floors), as
   ``ins-health calibrate`` does. The simulator's truth is used only to print
   how close that calibration came.
2. **Router and service.** An in-process Zenoh router on a free port of
   127.0.0.1, the service (:class:`service.daemon.Service`) as a client of it,
   and a ground-station session that receives and acknowledges the events.
3. **The vehicle** publishes its IMU at 200 Hz (frames of 20 samples): ground
   handling through 12 static positions, a short flight, a rest after landing
   during which a fault is injected into one sensor (a +3 % scale-factor step
   of the z accelerometer), then a post-flight handling of 12 positions. F0
   catches the fault on the first static samples after it; the diagnosis over
   the post-fault positions names the sensor and the cause. The simulated time
   (≈ 117 s) is played at :data:`DEFAULT_SPEED`× real time (the sample rate
   stays 200 Hz in data time) so the demo ends by itself in well under a minute.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from estimators.chain import ChainConfig, run_chain
from estimators.conventions import Grade, Triad, reference_magnitude
from estimators.passport import Passport, passport_from_estimates, per_sample_noise_std
from estimators.session import ImuSession
from estimators.sim import (
    Fault,
    FaultKind,
    Fly,
    Hold,
    MotionProfile,
    SessionSpec,
    Turn,
    grade_error_model,
    simulate,
)
from estimators.sim import Grade as SimGrade
from estimators.sim.motion import eighteen_position_attitudes
from protocols.events import Predicate
from protocols.zenoh_adapter import (
    EventReceiver,
    FramePublisher,
    open_router,
    open_session,
    subscribe_status,
)
from protocols.zenoh_router import free_local_port
from protocols.zenoh_settings import Mode, ZenohSettings
from service.config import config_from_dict
from service.daemon import Service
from service.log_setup import logging_to
from service.passport_store import PassportStore

DEMO_VEHICLE = "demo-uav"
DEMO_RATE_HZ = 200.0
DEMO_FRAME_SAMPLES = 20
DEFAULT_SPEED = 5.0
DEMO_LATITUDE_DEG = 45.0
DEMO_FAULT_INDEX = 5
DEMO_FAULT_MAGNITUDE = 0.03
"""The demo's fault: a +3 % step of the z accelerometer's scale-factor error (parameter ``ez``)."""


def calibrate_passport(
    session: ImuSession, *, unit_id: str, grade: Grade, gravity_mps2: float, created: str
) -> Passport:
    """A passport from a fault-free multi-position session: the offline chain (:func:`estimators.chain.run_chain`,
    refined M1 estimate) and the default tolerance rule, as ``ins-health calibrate`` does.

    Every triad whose positions determine its nine parameters is included; a MEMS gyro
    against the Earth rate is not (its noise is many times Ω, M1), so such a unit's
    passport covers its accelerometers only.
    """
    result = run_chain(session, ChainConfig(gravity_mps2=gravity_mps2))
    estimates = {t: r.estimate for t, r in result.triads.items() if r.estimate.params is not None}
    return passport_from_estimates(
        estimates,
        unit_id=unit_id,
        sensor_model="simulated MEMS IMU",
        sensor_ids={},
        created=created,
        noise_std={
            t: per_sample_noise_std(result.positions, t, reference_magnitude(t, gravity_mps2))
            for t in estimates
        },
        sample_rate_hz=session.rate_hz,
        grade=grade,
    )


@dataclass(frozen=True)
class DemoScenario:
    """The streamed session and where its phases start (data time, s)."""

    session: ImuSession
    spec: SessionSpec
    flight_start_s: float
    landing_s: float
    fault_s: float
    handling2_start_s: float
    truth_accel: np.ndarray


def handling_segments(attitudes: np.ndarray, *, hold_s: float, turn_s: float) -> list:
    segments: list = []
    for m in attitudes:
        segments += [Turn(m, turn_s), Hold(hold_s)]
    return segments


def demo_scenario(
    *,
    seed: int = 7,
    n_positions: int = 12,
    hold_s: float = 2.5,
    turn_s: float = 1.5,
    fault_index: int = DEMO_FAULT_INDEX,
    fault_magnitude: float = DEMO_FAULT_MAGNITUDE,
) -> DemoScenario:
    """Handling (``n_positions``) → level rest → flight → landing, fault → handling again (module docstring).

    The fault is a step of accelerometer parameter ``fault_index`` (order ``[b, e, d]``) by
    ``fault_magnitude`` one second after landing; magnitude 0 gives the fault-free session.
    """
    att = eighteen_position_attitudes()
    level = att[0]
    first = [Hold(3.0), *handling_segments(att[1:n_positions], hold_s=hold_s, turn_s=turn_s)]
    to_level = [Turn(level, turn_s), Hold(3.0)]
    flight = [Fly(12.0), Hold(5.0)]
    second = [
        *handling_segments(att[1:n_positions], hold_s=hold_s, turn_s=turn_s),
        Turn(level, turn_s),
        Hold(3.0),
    ]
    segments = first + to_level + flight + second
    durations = np.cumsum([0.0] + [s.duration_s for s in segments])
    i_fly = len(first) + len(to_level)
    flight_start, landing = durations[i_fly], durations[i_fly + 1]
    fault_s = landing + 1.0
    spec = SessionSpec(
        MotionProfile(level, tuple(segments)),
        grade_error_model(SimGrade.MEMS),
        rate_hz=DEMO_RATE_HZ,
        latitude_deg=DEMO_LATITUDE_DEG,
        faults=(Fault(FaultKind.STEP, Triad.ACCEL, fault_index, fault_s, fault_magnitude),)
        if fault_magnitude
        else (),
    )
    res = simulate(spec, seed=seed)
    return DemoScenario(
        res.session,
        spec,
        float(flight_start),
        float(landing),
        float(fault_s),
        float(durations[i_fly + 2]),
        res.truth.accel_params.copy(),
    )


def demo_passport(*, seed: int = 11) -> tuple[Passport, float]:
    """The demo unit's passport from its own fault-free 18-position session; also the local g used."""
    spec = SessionSpec(
        MotionProfile(
            eighteen_position_attitudes()[0],
            tuple(
                [
                    Hold(4.0),
                    *handling_segments(eighteen_position_attitudes()[1:], hold_s=4.0, turn_s=1.5),
                ]
            ),
        ),
        grade_error_model(SimGrade.MEMS),
        rate_hz=DEMO_RATE_HZ,
        latitude_deg=DEMO_LATITUDE_DEG,
    )
    res = simulate(spec, seed=seed)
    g = res.spec.assumed_gravity_mps2
    passport = calibrate_passport(
        res.session,
        unit_id=f"{DEMO_VEHICLE}-imu0",
        grade=Grade.MEMS,
        gravity_mps2=g,
        created=dt.date(2024, 1, 1).isoformat(),
    )
    return passport, g


class _Screen:
    """Event lines and one progress line on a terminal (or plain lines into a file), thread-safe."""

    def __init__(self, out: TextIO):
        self.out = out
        self.tty = out.isatty()
        self._lock = threading.Lock()
        self._progress = ""

    def line(self, text: str) -> None:
        with self._lock:
            if self.tty and self._progress:
                self.out.write("\r\033[K")
            self.out.write(text + "\n")
            if self.tty and self._progress:
                self.out.write(self._progress)
            self.out.flush()

    def progress(self, text: str, *, milestone: bool = False) -> None:
        """Update the progress line (a terminal redraws it; a file gets it at milestones only)."""
        with self._lock:
            self._progress = text
            if self.tty or milestone:
                self.out.write(("\r\033[K" + text) if self.tty else text + "\n")
                self.out.flush()

    def end_progress(self) -> None:
        with self._lock:
            if self._progress:
                self.out.write(("\r\033[K" if self.tty else "") + self._progress + "\n")
                self.out.flush()
            self._progress = ""


def _phase(sc: DemoScenario, t_s: float) -> str:
    if t_s < sc.flight_start_s:
        return "ground handling"
    if t_s < sc.landing_s:
        return "flight"
    if t_s < sc.handling2_start_s:
        return "landed" + (", fault injected" if t_s >= sc.fault_s else "")
    return "post-flight handling"


@dataclass(frozen=True)
class DemoResult:
    """What the demo saw: the events in arrival order and whether the fault was found and named."""

    events: tuple
    detected: bool
    named: bool


async def run_demo(
    *, out: TextIO = sys.stdout, speed: float = DEFAULT_SPEED, seed: int = 7
) -> DemoResult:
    """The demo (module docstring); prints as it goes and returns what it saw."""
    screen = _Screen(out)
    screen.line(
        "ins-health demo: a Zenoh router, a simulated vehicle and the service, all on 127.0.0.1"
    )
    passport, g = demo_passport()
    sc = demo_scenario(seed=seed)
    tp = passport.triads[Triad.ACCEL]
    screen.line(
        "passport: calibrated from the unit's own fault-free 18-position handling session (offline chain, refined M1 "
        f"estimate, MEMS default tolerances); z accelerometer scale error {tp.nominal[5]:+.5f} (simulator truth "
        f"{sc.truth_accel[5]:+.5f}), tolerance {tp.tolerance[5]:.4f}; the gyros are not resolved against the Earth rate (MEMS)"
    )
    port = free_local_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    n_frames = int(np.ceil(sc.session.n_samples / DEMO_FRAME_SAMPLES))
    screen.line(
        f"router: {endpoint} (in-process); vehicle {DEMO_VEHICLE}: IMU0 at {DEMO_RATE_HZ:.0f} Hz in frames of {DEMO_FRAME_SAMPLES}, "
        f"{sc.session.t_s[-1]:.0f} s of simulated time played at {speed:g}x real time"
    )
    screen.line(
        f"script: ground handling (12 positions), flight at {sc.flight_start_s:.1f} s, landing at {sc.landing_s:.1f} s, "
        f"fault at {sc.fault_s:.1f} s (z accelerometer scale factor +{DEMO_FAULT_MAGNITUDE:.0%}), post-flight handling from "
        f"{sc.handling2_start_s:.1f} s\n"
    )
    events: list = []
    latest: dict = {}
    with (
        tempfile.TemporaryDirectory(prefix="ins-health-demo-") as tmp,
        open_router(endpoint),
        # The service's warnings (a passport refused, a send retried) on the demo's screen.
        logging_to(out, level="warning"),
    ):
        PassportStore(Path(tmp) / "passports").put(DEMO_VEHICLE, 0, passport)
        config = config_from_dict(
            {
                "service": {
                    "name": "demo",
                    "data_dir": str(Path(tmp) / "data"),
                    "passport_dir": str(Path(tmp) / "passports"),
                    "status_period_s": 0.25,
                },
                "site": {"gravity_mps2": g},
                "zenoh": {"connect": [endpoint]},
                "validity": {"timeout_s": 5.0},
            }
        )
        service = Service(config)
        stop, ready = asyncio.Event(), asyncio.Event()
        running = asyncio.create_task(service.run(stop, ready=ready))
        await ready.wait()

        def on_event(event) -> None:
            events.append(event)
            screen.line(f"[{event.t_s:7.2f} s] {event.severity.name:<8s} {event.text}")

        with (
            open_session(_client_settings(port)) as ground,
            open_session(_client_settings(port)) as vehicle,
        ):
            receiver = EventReceiver(ground, on_event)
            status_sub = subscribe_status(ground, lambda s: latest.__setitem__("status", s))
            with FramePublisher(vehicle, DEMO_VEHICLE, 0, batch_samples=DEMO_FRAME_SAMPLES) as pub:
                await _wait_matched(pub)
                wall0 = time.monotonic()
                s = sc.session
                accel, gyro = s.accel_mps2, s.gyro_rps
                if accel is None or gyro is None:
                    raise ValueError("the demo session must hold both triads")
                for k in range(n_frames):
                    sl = slice(
                        k * DEMO_FRAME_SAMPLES, min(s.n_samples, (k + 1) * DEMO_FRAME_SAMPLES)
                    )
                    t_end = float(s.t_s[sl][-1])
                    delay = (t_end - float(s.t_s[0])) / speed - (time.monotonic() - wall0)
                    if delay > 0:
                        await asyncio.sleep(delay)
                    pub.add(s.t_s[sl], accel[sl], gyro[sl])
                    if k % 10 == 0:
                        screen.progress(
                            _progress_text(sc, t_end, latest.get("status")), milestone=k % 500 == 0
                        )
            # The last frames are in; give the service a moment to diagnose and deliver.
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline and not any(
                e.predicate is Predicate.F6 for e in events
            ):
                await asyncio.sleep(0.1)
            screen.progress(_progress_text(sc, float(sc.session.t_s[-1]), latest.get("status")))
            screen.end_progress()
            status_sub.undeclare()
            receiver.close()
        stop.set()
        await running
    return _summary(screen, sc, events)


def _client_settings(port: int) -> ZenohSettings:
    """A client session of the demo's router (no multicast scouting)."""
    return ZenohSettings(mode=Mode.CLIENT, connect=(f"tcp/127.0.0.1:{port}",))


async def _wait_matched(pub: FramePublisher, timeout_s: float = 10.0) -> None:
    """Wait until the service's frame subscription is known to the vehicle's session."""
    deadline = time.monotonic() + timeout_s
    while not pub.matched:
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"the service did not subscribe to the frames of {pub.vehicle} IMU{pub.imu} within {timeout_s} s"
            )
        await asyncio.sleep(0.05)


def _progress_text(sc: DemoScenario, t_s: float, status) -> str:
    text = f"progress: t = {t_s:6.1f} / {sc.session.t_s[-1]:.1f} s  {_phase(sc, t_s):<26s}"
    if status is not None and status.imus:
        imu = status.imus[0]
        text += f" samples {imu.samples:6d}  positions {imu.positions:2d}  IMU0 {imu.state.value}"
    return text


def _summary(screen: _Screen, sc: DemoScenario, events: list) -> DemoResult:
    f0 = next((e for e in events if e.predicate is Predicate.F0), None)
    named = next((e for e in events if e.predicate is Predicate.F6 and e.axis == "z"), None)
    truth = sc.truth_accel[DEMO_FAULT_INDEX] + DEMO_FAULT_MAGNITUDE
    screen.line("")
    if f0 is not None:
        screen.line(
            f"detected: F0 at {f0.t_s:.2f} s, {f0.t_s - sc.fault_s:.2f} s after the fault started (the unit was resting after landing)"
        )
    if named is not None:
        screen.line(
            f"named: accelerometer z, scale factor error {named.estimate:.4f} ± {named.sigma:.4f} (simulator truth {truth:.4f}), "
            f"at {named.t_s:.1f} s, once the post-flight handling had given the diagnosis its 9 positions"
        )
    if f0 is None or named is None:
        screen.line(
            "the fault was NOT "
            + ("detected" if f0 is None else "named")
            + " — this is a failure of the demo"
        )
    return DemoResult(tuple(events), f0 is not None, named is not None)
