"""The thrust-axis check of one IMU against its vehicle's GNSS (:mod:`estimators.thrust_gnss`) as
events: IMU frames and GNSS epochs in, ``thrust_axis`` events out.

An alarm episode raises one event, at its first alarmed epoch: the accelerometer's axis the check
sees (the one the specific force falls on, as the coverage says: z for a unit mounted level, y for
one turned 90° about x; none named when two share it), cause ``disagreement``, the estimate the window's ``D_L`` (m/s²), the tolerance its
threshold ``h·σ_L`` and the sigma ``σ_L``. The episode ends when no epoch has alarmed for
:data:`EPISODE_GAP_S`; a later alarm is a new episode and a new event. The evaluations are kept
(time, statistic ``z``) for the replay report's plot of the statistic against its threshold.
:class:`ThrustAxisReplay` runs it in ``replay`` on the log's own GNSS velocity.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimators.conventions import AXES, Triad
from estimators.coverage import CheckCoverage, ImuCoverage
from estimators.thrust_gnss import (
    Evaluations,
    ThrustAxisConfig,
    ThrustAxisMonitor,
    thrust_axis_coverage,
)
from protocols.events import Event, Predicate, StreamCause, make_event
from protocols.frames import SampleBatch

if TYPE_CHECKING:
    from protocols.gnss_logs import GnssTrack
from service.pipeline.options import SEVERITY

THRUST_CONFIG = ThrustAxisConfig()
"""The check's settings in the daemon and in replay (estimators.thrust_gnss's defaults)."""

EPISODE_GAP_S = 10.0
"""Alarms this far apart are separate episodes (separate events), s."""


@dataclass(frozen=True)
class ThrustStatistic:
    """One IMU's thrust-axis statistic through the flight: epoch times (s of the log's clock), ``z``
    (NaN where not judged) and the threshold."""

    t_s: np.ndarray
    z: np.ndarray
    threshold: float


class ThrustAxisCheck:
    """One IMU's check against a GNSS track; feed frames in time order (:meth:`imu`, :meth:`gnss`)."""

    def __init__(
        self, vehicle: str, imu: int, gnss_rate_hz: float, config: ThrustAxisConfig = THRUST_CONFIG
    ):
        self.vehicle = vehicle
        self.imu_index = imu
        self.monitor = ThrustAxisMonitor(config, gnss_rate_hz=gnss_rate_hz)
        self.t_s: list[np.ndarray] = []
        self.z: list[np.ndarray] = []
        self._last_alarm_t_s = -np.inf

    def imu(self, batch: SampleBatch) -> list[Event]:
        return self._events(self.monitor.update_imu(batch.t_s, batch.accel_mps2, batch.gyro_rps))

    def gnss(self, t_s: np.ndarray, vel_enu_mps: np.ndarray) -> list[Event]:
        return self._events(self.monitor.update_gnss(t_s, vel_enu_mps))

    def _events(self, ev: Evaluations) -> list[Event]:
        if ev.t_s.size:
            self.t_s.append(ev.t_s)
            self.z.append(ev.z)
        out = []
        noise = self.monitor.noise
        for k in np.flatnonzero(ev.alarm):
            t = float(ev.t_s[k])
            new = t - self._last_alarm_t_s > EPISODE_GAP_S
            self._last_alarm_t_s = t
            if not new or noise is None:
                continue
            seen = [AXES[i] for i in np.flatnonzero(self.monitor.summary().observable)]
            window = int(np.argmax(np.abs(ev.d_mps2[k]) / noise.sigma_mps2))
            sigma = float(noise.sigma_mps2[window])
            length = self.monitor.config.windows_s[window]
            out.append(
                make_event(
                    vehicle=self.vehicle,
                    imu=self.imu_index,
                    t_s=t,
                    predicate=Predicate.THRUST_AXIS,
                    cause=StreamCause.DISAGREEMENT,
                    severity=SEVERITY[Predicate.THRUST_AXIS],
                    triad=Triad.ACCEL,
                    axis=seen[0] if len(seen) == 1 else None,
                    estimate=float(ev.d_mps2[k, window]),
                    nominal=0.0,
                    tolerance=self.monitor.threshold * sigma,
                    sigma=sigma,
                    unit="m/s^2",
                    text=(
                        f"{self.vehicle} IMU{self.imu_index} accelerometer {', '.join(seen)}: "
                        f"|f| in flight off "
                        f"GNSS by {ev.d_mps2[k, window]:+.3f} m/s^2 over {length:g} s "
                        f"({ev.z[k]:.1f} sigma, threshold {self.monitor.threshold:.1f}) [thrust_axis]"
                    ),
                )
            )
        return out

    def statistic(self) -> tuple[np.ndarray, np.ndarray]:
        """(epoch times, ``z``) of every epoch judged so far (``z`` NaN where not tested)."""
        if not self.t_s:
            return np.empty(0), np.empty(0)
        return np.concatenate(self.t_s), np.concatenate(self.z)

    def coverage(self) -> CheckCoverage:
        return thrust_axis_coverage(self.monitor.summary())


class ThrustAxisReplay:
    """The thrust-axis check of each IMU of ``vehicle`` against the log's own GNSS velocity
    (:mod:`protocols.gnss_logs`, :mod:`service.pipeline.thrust_axis`), fed frame by frame as the
    reader gives them; its events go to ``on_event`` as they come and join the replay's in time
    order. A log without GNSS, or whose GNSS cannot be read, is said in the coverage (the check
    does not apply) and in a note; an IMU stream the check refuses (its clock went back) stops
    that IMU's check, said in a note."""

    def __init__(self, log: Path, vehicle: str, on_event: Callable[[Event], None] | None):
        self.log = log
        self.vehicle = vehicle
        self.on_event = on_event
        self.events: list[Event] = []
        self.notes: list[str] = []
        self.checks: dict[int, ThrustAxisCheck] = {}
        self.fed: dict[int, int] = {}
        self.stopped: dict[int, str] = {}
        self.why_not = "no IMU sample read"
        self.track: GnssTrack | None = None
        self._opened = False

    def _open(self) -> None:
        """Read the GNSS once the IMU reader has taken the file (its errors are the ones said)."""
        from protocols.gnss_logs import GnssLogError, read_gnss_track

        self._opened = True
        self.why_not = "no GNSS velocity in the log"
        try:
            track = read_gnss_track(self.log)
        except GnssLogError as exc:
            self.why_not = str(exc)
            self.notes.append(f"thrust axis not tested: {exc}")
            return
        if track is None:
            return
        left = ", ".join(f"{k} {n}" for k, n in track.rejected.items()) or "none"
        if track.t_s.size < 2:
            # The log holds GNSS records: say what kept them out, not "no GNSS" as if absent.
            self.why_not = (
                f"{track.t_s.size} GNSS epoch(s) with a 3D fix and a valid velocity of "
                f"{track.source}, 2 needed; left out {left}{_unused(track)}"
            )
            return
        self.notes.append(
            f"GNSS: {track.t_s.size} epochs of {track.source} at {track.rate_hz:.3g} Hz; "
            f"left out {left}{_unused(track)}"
        )
        self.track = track

    def batch(self, batch: SampleBatch) -> None:
        if not self._opened:
            self._open()
        track = self.track
        if track is None or batch.vehicle != self.vehicle or batch.imu in self.stopped:
            return
        check = self.checks.get(batch.imu)
        if check is None:
            check = self.checks[batch.imu] = ThrustAxisCheck(
                batch.vehicle, batch.imu, track.rate_hz
            )
            self.fed[batch.imu] = 0
        j = self.fed[batch.imu]
        k = int(np.searchsorted(track.t_s, batch.t_s[-1], "right"))
        try:
            found = check.gnss(track.t_s[j:k], track.vel_enu_mps[j:k]) + check.imu(batch)
        except ValueError as exc:
            self.stopped[batch.imu] = str(exc)
            self.notes.append(f"IMU{batch.imu}: thrust axis stopped at {batch.t_s[0]:.6g} s: {exc}")
            return
        self.fed[batch.imu] = k
        for event in found:
            self.events.append(event)
            if self.on_event is not None:
                self.on_event(event)

    def merged(self, events: list[Event]) -> list[Event]:
        """The replay's events with the thrust-axis ones, in time order."""
        if not self.events:
            return events
        return sorted(events + self.events, key=lambda e: e.t_s)

    def covered(self, coverage: ImuCoverage) -> ImuCoverage:
        """``coverage`` with this IMU's thrust-axis line."""
        check = self.checks.get(coverage.imu)
        if check is None:
            line = thrust_axis_coverage(None, reason=self.why_not)
        else:
            stop = self.stopped.get(coverage.imu)
            line = check.coverage()
            if stop:
                line = dataclasses.replace(line, reason=f"stopped: {stop}")
        return ImuCoverage(coverage.imu, (*coverage.checks, line))

    def statistics(self) -> dict[int, ThrustStatistic]:
        out = {}
        for imu, check in sorted(self.checks.items()):
            t, z = check.statistic()
            out[imu] = ThrustStatistic(t, z, check.monitor.threshold)
        return out


def _unused(track: GnssTrack) -> str:
    """The log's other GNSS topics or instances, not taken (protocols.gnss_logs: the most epochs)."""
    said = ""
    if track.unused:
        listed = ", ".join(f"{source} {n} epochs" for source, n in track.unused.items())
        said = f"; not used: {listed} (the one with the most epochs is taken)"
    if track.unreadable:
        listed = ", ".join(f"{source} ({why})" for source, why in track.unreadable.items())
        said += f"; unreadable: {listed}"
    return said
