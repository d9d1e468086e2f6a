"""The daemon: sources → :class:`~service.pipeline.FleetProcessor` → durable outbox → sinks, in asyncio.

Tasks of :meth:`Service.run`
----------------------------
* **frames** (Zenoh) and **mavlink-frames** — IMU frames from Zenoh (:class:`protocols.zenoh_adapter.FrameSource`:
  a bounded queue per (vehicle, IMU) between Zenoh's thread and the loop, taken in turn; a unit's
  frames beyond ``queue_capacity``, or beyond its fair share of ``instance_queue_capacity``, are
  dropped, counted per unit and logged) and, when configured, from MAVLink
  (:class:`protocols.mavlink_adapter.MavlinkSource`: the samples that arrive within
  :data:`service.intake.COALESCE_WINDOW_S` of the first, one batch per IMU; the link is read and
  parsed in a child process, :mod:`protocols.mavlink_process`, unless ``[mavlink] reader =
  "thread"``). Each
  frame goes through its (vehicle, IMU) pipeline (:class:`service.intake.Intake`); the events it raises are written to the
  outbox in one transaction *before* any sink sees them. While the outbox cannot take them (disk
  full or read-only, file locked by another process, data directory gone) they are held in memory
  and delivered from there while frames are still taken (detection goes on), and no checkpoint is
  written ahead of an event not yet with every sink (:mod:`service.outbox_writer`); the status
  topic says ``outbox.unavailable``.
* **delivery**, one per sink (:mod:`service.sinks`, :mod:`service.delivery`) — a lane per vehicle
  with pending events: its events in order to the transport, acks what the transport accepted; a
  vehicle whose event is refused is retried after ``delivery_retry_s`` while the others go on. Zenoh: the event stream on
  ``ins/<vehicle>/health/events``, acknowledged end to end by the receiving
  application (:class:`protocols.zenoh_adapter.EventPublisher`, ``[zenoh]
  event_ack``); each attempt puts the event again, so a plain subscriber that
  is there while no acknowledging receiver is may see an id more than once
  (ids are stable: deduplicate by id). MAVLink: STATUSTEXT alerts through a rate limiter
  (:class:`service.alert_policy.AlertPolicy`): a repeat is suppressed (it counts as delivered to
  that sink; the full stream stays on Zenoh), distinct alerts are paced.
* **status** — every ``status_period_s``: the timeout checks, then the instance's own
  :class:`~protocols.events.ServiceStatus` on ``ins/_service/<name>/status`` (from the start,
  before any vehicle) and one :class:`~protocols.events.Status` per vehicle on
  ``ins/<vehicle>/health/status`` with every counter (rejections by reason, drops per IMU, outbox
  backlog, …); the frames dropped are logged naming vehicle and IMU. With the Zenoh session the
  instance declares its liveliness token (:class:`protocols.zenoh_adapter.StatusPublisher`), which
  Zenoh withdraws when the daemon is killed, stopped or cut off (``ins-health watch`` says
  ``lost``).
* **checkpoints** — every ``checkpoint_period_s`` the state of every pipeline
  (positions, recursive estimates) and of each vehicle's cross-IMU comparison
  (the disagreements it raised) to SQLite, a vehicle's taken at one moment. A checkpoint the
  store cannot write (disk full, file locked by another process) ends neither the task nor the
  daemon: the state stays in memory and is saved by the next attempt, retried with back-off
  (:class:`service.checkpoint.SaveFailures`); the status topic says ``checkpoints.unavailable``.
* **storage** — the held events written once the outbox takes them again (back-off), the data
  directory checked (removed or replaced: a storage fault, its stores' writes refused); storage
  away past ``storage_timeout_s`` stops the daemon with :data:`EXIT_STORAGE`.
* **heartbeat** — MAVLink HEARTBEAT every ``heartbeat_period_s``.
* **gnss** (Zenoh) and **mavlink-gnss** — a receiver's velocity into the thrust-axis checks of
  its vehicle's IMUs: GNSS frames on ``ins/<vehicle>/gnss`` (:class:`protocols.zenoh_adapter.GnssSource`)
  and the MAVLink link's ``GPS_RAW_INT`` (:class:`protocols.mavlink_gnss.MavlinkGnssSource`).
* **mavlink-open** — only while the MAVLink device cannot be opened (a serial adapter not plugged
  in yet, an autopilot's TCP port not up yet): an attempt every :data:`CONNECT_PAUSE_S`, logged once
  per kind of failure and counted as ``service.mavlink.open_failures``; the rest of the service runs
  meanwhile, and the link's sink, source, heartbeat and delivery start when it opens.
* **zenoh-connect** — only while the router is out of reach: the first attempt at opening the
  Zenoh session (at most :data:`CONNECT_ATTEMPT_S`) is made before the service says it runs; if
  it fails the service runs without Zenoh (MAVLink is served, events wait in the outbox) and this
  task tries again every :data:`CONNECT_PAUSE_S`, then starts the Zenoh side. It says so in the
  log, and past ``connect_timeout_s`` (when set) the daemon exits non-zero. The status task logs
  when the session's connections are lost and come back (Zenoh reconnects by itself).
* **watchdog** — under systemd with ``WatchdogSec=``: ``WATCHDOG=1`` while the frame path moves
  (:class:`service.notify.FramePathWatch`); ``READY=1`` once running, ``STOPPING=1`` at SIGTERM.

Every task runs under a :class:`~service.supervisor.Supervisor`: an exception is logged with its
traceback, counted (``service.task.<name>.failures``) and the task restarted with back-off; a task
failing again and again without progress makes the daemon exit with status 70 for systemd to
restart it. Each task's last progress is on the status topic
(``service.task.<name>.last_progress_unix_ms``).

SIGTERM (``stop`` set) drains: the sources stop, the frames already received
are processed, the checkpoints are written, and delivery continues for up to
:data:`DRAIN_TIMEOUT_S` before the outbox is closed; whatever is still pending is
re-sent by the next start; events held in memory that could not be stored, or a data directory
removed or replaced (its pending events are in a file the next start will not see), make the exit
status :data:`EXIT_STORAGE`. ``kill -9`` loses only the frames in flight and the
state since the last checkpoint; no event that reached the outbox is lost, and
events are never stored twice (their ids derive from the data, see
:mod:`protocols.events`).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from typing import Any

from estimators.passport import Passport
from protocols.checkpoint_codec import encode_state
from protocols.events import (
    Event,
    ServiceStatus,
)
from protocols.log_rate import LogRate
from protocols.mavlink_adapter import READER_RETRY_S, MavlinkLink, MavlinkSource
from protocols.mavlink_gnss import MavlinkGnssSource
from protocols.mavlink_process import MavlinkProcessLink
from protocols.zenoh_adapter import (
    FrameSource,
    GnssSource,
    Session,
    StatusPublisher,
    connected_nodes,
    gnss_selector,
    open_session_within,
)
from protocols.zenoh_settings import ZenohSettings
from service.alert_policy import AlertPolicy
from service.checkpoint import (
    CheckpointError,
    CheckpointStore,
    CheckpointUnavailable,
    SaveFailures,
    checkpoint_unit,
    open_checkpoints,
)
from service.config import MavlinkReader, ServiceConfig
from service.delivery import SinkDelivery
from service.intake import COALESCE_MAX, COALESCE_WINDOW_S, Intake
from service.log_setup import logger
from service.notify import FramePathWatch, Notifier
from service.outbox import DataDirLock, Outbox, OutboxUnavailable
from service.outbox_writer import RETRY_MAX_S, RETRY_MIN_S, OutboxWriter
from service.passport_store import PassportStore
from service.pipeline import FleetProcessor
from service.pipeline.options import pipeline_options
from service.sinks import TRANSPORT_ERRORS, EventSink, MavlinkAlertSink, ZenohEventSink
from service.supervisor import Supervisor

EXIT_STORAGE = 74
"""Exit status when storage stayed away past ``storage_timeout_s``, or the daemon stopped with events
it could not store (EX_IOERR of sysexits.h): the service manager restarts it and the operator sees it."""

DRAIN_TIMEOUT_S = 5.0
"""How long SIGTERM keeps delivering before the service exits (the rest is re-sent at the next start)."""

CONNECT_ATTEMPT_S = 3.0
"""How long one attempt at opening the Zenoh session may take: the first is made before the
service says it runs, the others in the background; SIGTERM waits for at most one."""
CONNECT_PAUSE_S = 2.0
"""The pause between two attempts at opening the Zenoh session."""
INPUT_TASKS = ("frames", "mavlink-frames")
"""The tasks of the frame path (their progress feeds the systemd watchdog)."""
HANDOFF_WAIT_S = 0.005
"""Longest the rest of a group of frames waits for the events of one IMU to reach the transports.

The deliveries send from worker threads (a Zenoh put, a write to the MAVLink reader), which wait
for the interpreter while the loop goes on with the group's other IMUs: under 50 k MAVLink
messages/s the Zenoh delivery took p90 1.4 ms to reach its thread and 1.4 ms more to put
(``bench_mavlink_e2e.py``, 40 trials)."""
STORAGE_CHECK_S = 1.0
"""How often the data directory is checked (removed or replaced under the daemon)."""
EVENT_CHECKPOINT_DELAY_S = 0.003
"""How long the checkpoint of the vehicles whose events were just stored waits for their delivery to start."""

log = logger("daemon")


REVIVE_MAX_AGE_S = 7 * 86_400.0
"""Checkpoints saved longer ago than this are not admitted at start (a unit heard again resumes from its own)."""


class _Wake:
    """An asyncio event per sink, set whenever new events reach the outbox; :attr:`handed` is clear
    while a delivery that was idle when they came has not yet handed them to its transport."""

    def __init__(self, names: Iterable[str]):
        self.events = {name: asyncio.Event() for name in names}
        self.handed = asyncio.Event()
        self.handed.set()
        self._idle: set[str] = set()
        self._unsent: set[str] = set()

    def set(self) -> None:
        for e in self.events.values():
            e.set()
        # A delivery busy with earlier events (waiting for their acknowledgement) takes the new
        # ones after: the intake does not wait for it.
        self._unsent |= self._idle
        self._idle.clear()
        if self._unsent:
            self.handed.clear()

    def idle(self, sink: str) -> None:
        """``sink``'s delivery has handed everything over and waits for new events."""
        self._idle.add(sink)
        self.sent(sink)

    def sent(self, sink: str) -> None:
        """``sink``'s transport holds the events its delivery took."""
        self._unsent.discard(sink)
        if not self._unsent:
            self.handed.set()

    def give_up(self) -> None:
        """Stop waiting for the deliveries not yet heard from (a transport that blocks): they are
        waited for again once idle, not at every event stored meanwhile."""
        self._unsent.clear()
        self.handed.set()


@dataclass
class _Run:
    """What :meth:`Service.run` opens before any frame is taken, for its whole duration."""

    lock: DataDirLock
    outbox: Outbox
    checkpoints: CheckpointStore
    wake: _Wake
    writer: OutboxWriter
    deliveries: dict[str, SinkDelivery]


class Service:
    """The ins-health daemon (module docstring).

    Parameters
    ----------
    config : the service configuration.
    clock : the monotonic clock that stamps arrivals (timeouts) and paces alerts.
    notifier : the service manager's notification socket (default: from the environment, a
        no-op when ``NOTIFY_SOCKET`` is not set).
    supervisor : runs the tasks (default: :class:`~service.supervisor.Supervisor`'s back-off).
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        notifier: Notifier | None = None,
        supervisor: Supervisor | None = None,
    ):
        self.config = config
        self._clock = clock
        self.notifier = Notifier() if notifier is None else notifier
        self.supervisor = Supervisor() if supervisor is None else supervisor
        self.frame_watch = FramePathWatch()
        self._session: Session | None = None
        self._router_connected = False
        self._reader_failures = 0
        self.store = PassportStore(config.service.passport_dir)
        self._passports: dict[tuple[str, int], Passport] = {}
        self._pipeline_errors_logged: set[tuple[str, int, str]] = set()
        self.fleet = FleetProcessor(
            passports=self._passport,
            options=pipeline_options(config),
            vehicles=config.service.vehicles,
            max_vehicles=config.pipeline.max_vehicles,
            max_imus_per_vehicle=config.pipeline.max_imus_per_vehicle,
            on_passport_error=self._passport_error,
            on_pipeline_error=self._pipeline_error,
            on_evicted=self._evicted,
            nominal=config.service.nominal_class,
        )
        self.intake = Intake(
            self.fleet,
            store=self._store,
            handed_over=self._handed_over,
            clock=clock,
            say=log.warning,
        )
        self._run: _Run | None = None
        self.source: FrameSource | None = None
        self.sinks: list[EventSink] = []
        self._status_pub: StatusPublisher | None = None
        self.mavlink_sink: MavlinkAlertSink | None = None
        self.mavlink_source: MavlinkSource | None = None
        self._said_running = False
        self._reported: set[str] = set()
        self.events_stored = 0
        # Set when events are stored: their vehicles' state is saved at once, not a period later.
        self._checkpoint_soon = asyncio.Event()
        self._checkpoint_vehicles: set[str] = set()
        self._saves = SaveFailures(clock=clock)
        self._drops_log = LogRate()
        self._given_up_log = LogRate()
        self._data_dir_lost_s: float | None = None
        self._unstored = 0
        self._refused_log = LogRate()
        self._cross_off: set[tuple[str, int]] = set()

    @property
    def outbox(self) -> Outbox | None:
        """The outbox, once :meth:`run` has opened it."""
        return None if self._run is None else self._run.outbox

    @property
    def checkpoints(self) -> CheckpointStore | None:
        """The checkpoint store, once :meth:`run` has opened it."""
        return None if self._run is None else self._run.checkpoints

    def _running(self) -> _Run:
        if self._run is None:
            raise RuntimeError("the service is not running (Service.run opens the outbox)")
        return self._run

    # ------------------------------------------------------------------ passports and checkpoints

    def _passport(self, vehicle: str, imu: int) -> Passport:
        key = (vehicle, imu)
        if key not in self._passports:
            self._passports[key] = self.store.get(vehicle, imu)
        return self._passports[key]

    def _without_passport(self) -> str:
        """What a unit without a usable passport runs ([service] default_grade)."""
        cls = self.fleet.nominal
        return "the stream checks only" if cls is None else f"on the nominal {cls.value} passport"

    def _passport_error(self, vehicle: str, imu: int, message: str) -> None:
        log.warning("%s; %s IMU%d runs %s", message, vehicle, imu, self._without_passport())

    def _evicted(self, evicted: str, admitted: str) -> None:
        log.warning(
            "vehicle limit reached: %s, without a passport and idle longest, makes room for %s, "
            "which has one (counted as service.vehicles.evicted_without_passport)",
            evicted,
            admitted,
        )

    def _pipeline_error(self, vehicle: str, imu: int, message: str) -> None:
        # Logged once per IMU and kind of error (the counter has them all): a hostile stream must
        # not fill the journal.
        key = (vehicle, imu, message.split(":", 1)[0])
        if key not in self._pipeline_errors_logged:
            self._pipeline_errors_logged.add(key)
            log.error(
                "%s IMU%d: the pipeline failed on a frame (%s); the IMU starts afresh, counted as "
                "imu%d.pipeline.errors (further errors of this kind are counted, not logged)",
                vehicle, imu, message, imu,
            )  # fmt: skip

    def _restore(self, vehicle: str, imu: int) -> dict[str, Any] | None:
        try:
            cp = self._running().checkpoints.load(f"{vehicle}/{imu}")
        except CheckpointError as exc:
            self._discard_checkpoint(vehicle, imu, str(exc))
            return None
        return None if cp is None else cp.state

    def _restore_cross(self, vehicle: str) -> dict[str, Any] | None:
        try:
            cp = self._running().checkpoints.load_cross(vehicle)
        except CheckpointError as exc:
            self._discard_cross(vehicle, str(exc))
            return None
        return None if cp is None else cp.state

    def _discard_cross(self, vehicle: str, why: str) -> None:
        self._running().checkpoints.quarantine_cross(vehicle, why)
        log.warning(
            "cross-IMU checkpoint of %s unusable (%s); moved aside to the quarantined table, "
            "the comparison starts fresh",
            vehicle, why,
        )  # fmt: skip

    def _discard_checkpoint(self, vehicle: str, imu: int, why: str) -> None:
        self._running().checkpoints.quarantine(f"{vehicle}/{imu}", why)
        log.warning(
            "checkpoint of %s IMU%d unusable (%s); moved aside to the quarantined table, the unit starts fresh",
            vehicle, imu, why,
        )  # fmt: skip

    def _startup_scan(self) -> None:
        """Load every passport in the store and report the unusable ones (the other units start normally).

        IMU 0 of every configured vehicle is expected to have one; other units are checked
        when their first frame arrives.
        """
        scan = self.store.scan([(v, 0) for v in self.config.service.vehicles])
        self._passports.update(scan.passports)
        loaded = ", ".join(f"{v} IMU{i}" for v, i in sorted(scan.passports)) or "none"
        nominal = self.fleet.nominal
        log.info(
            "passports in %s: %d loaded (%s), %d refused; %d unit(s) run on nominal passports "
            "(those refused; [service] default_grade %s: any unit without a usable passport runs %s)",
            self.store.root, len(scan.passports), loaded, len(scan.errors),
            0 if nominal is None else len(scan.errors),
            "none" if nominal is None else nominal.value, self._without_passport(),
        )  # fmt: skip
        for err in scan.errors.values():
            log.warning("refused %s; the unit runs %s", err, self._without_passport())
        for path, why in scan.strays:
            log.warning("passport store: %s is not read: %s", path, why)

    def _log_summary(self) -> None:
        """What this instance serves: one line per input and output."""
        cfg = self.config
        vehicles = ", ".join(cfg.service.vehicles) or "every vehicle its key expression delivers"
        log.info(
            "%s starting: data in %s; vehicles: %s",
            cfg.service.name, cfg.service.data_dir, vehicles,
        )  # fmt: skip
        if cfg.zenoh.enabled:
            z = cfg.zenoh.session
            log.info(
                "zenoh %s, connect %s, listen %s, connect timeout %s; frames %s; events acknowledged by %s (%d needed)",
                z.mode.value, list(z.connect), list(z.listen),
                "none (wait for the router)" if z.connect_timeout_s is None else f"{z.connect_timeout_s:g} s",
                cfg.zenoh.frames_key, cfg.zenoh.event_ack.value, cfg.zenoh.min_acks,
            )  # fmt: skip
        else:
            log.info("zenoh disabled")
        if cfg.mavlink.enabled:
            m = cfg.mavlink.link
            log.info(
                "mavlink %s: vehicle %s, autopilot system %s, read in a %s, signing %s",
                m.device, m.vehicle, "the first heard" if m.autopilot_system is None else m.autopilot_system,
                cfg.mavlink.reader.value,
                "off" if m.signing_key is None else ("on, unsigned accepted" if m.accept_unsigned else "on"),
            )  # fmt: skip
        else:
            log.info("mavlink disabled")

    # ------------------------------------------------------------------ events

    def _store(self, events: list[Event]) -> None:
        """Events into the outbox, or held in memory and delivered from there (:mod:`service.outbox_writer`)."""
        # Every frame taken (processed or rejected) ends here: the progress of the frame path.
        self.supervisor.beat()
        self._running().writer.write(events)

    async def _handed_over(self) -> None:
        """Until the events just stored are in the transports' hands (at most :data:`HANDOFF_WAIT_S`)."""
        wake = self._running().wake
        if wake.handed.is_set():
            await asyncio.sleep(0)
            return
        try:
            await asyncio.wait_for(wake.handed.wait(), HANDOFF_WAIT_S)
        except TimeoutError:
            wake.give_up()

    def _stored(self, new: int, vehicles: set[str]) -> None:
        self.events_stored += new
        self._running().wake.set()
        self._checkpoint_vehicles |= vehicles
        self._checkpoint_soon.set()

    def _held(self) -> None:
        """Events held in memory: the deliveries take them from there."""
        self._running().wake.set()

    async def _heartbeat(self, sink: MavlinkAlertSink, stop: asyncio.Event) -> None:
        while not stop.is_set():
            try:
                await sink.heartbeat()
                self.supervisor.beat()
            except TRANSPORT_ERRORS as exc:
                self._transport_error(sink.name, exc)
            await _wait_any(stop, None, timeout_s=self.config.mavlink.heartbeat_period_s)

    def _transport_error(self, name: str, exc: BaseException) -> None:
        """A send that failed: counted, and reported once per kind of failure (the send is retried)."""
        kind = f"{name}: {type(exc).__name__}: {exc}"
        self.fleet.count_service(f"delivery.{name}.errors")
        if kind not in self._reported:
            self._reported.add(kind)
            log.warning("sending on %s (retrying; counted as delivery.%s.errors)", kind, name)

    async def _publish_status(self, publisher: StatusPublisher) -> None:
        extra = (
            {f"service.{k}": v for k, v in self.source.counters.as_dict("frames").items()}
            if self.source
            else {}
        )
        if self.mavlink_sink is not None and self.mavlink_source is not None:
            link = self.mavlink_sink.link.counters
            extra["service.mavlink.messages"] = link.messages
            # Snapshots: the reader thread may add a key meanwhile.
            samples, rejected = dict(link.imu_samples), dict(link.rejected)
            extra.update({f"service.mavlink.samples.{k}": n for k, n in samples.items()})
            extra.update({f"service.mavlink.rejected.{k}": n for k, n in rejected.items()})
            extra["service.mavlink.rejected.other_system"] = link.ignored_system
            extra["service.mavlink.alerts_sent"] = link.alerts_sent
            extra["service.mavlink.alerts_suppressed"] = self.mavlink_sink.policy.suppressed
            extra["service.mavlink.alerts_deferred"] = self.mavlink_sink.policy.deferred
            extra["service.mavlink.heartbeats_sent"] = link.heartbeats_sent
            extra["service.mavlink.gnss_messages"] = link.gnss_messages
            extra["service.mavlink.dropped_overload"] = self.mavlink_source.dropped_overload
            extra["service.mavlink.dropped_kernel"] = link.dropped_kernel
            extra["service.mavlink.signing_stale"] = link.signing_stale
            extra["service.mavlink.reader_failures"] = self.mavlink_source.failures
            if isinstance(self.mavlink_sink.link, MavlinkProcessLink):
                extra["service.mavlink.reader_restarts"] = self.mavlink_sink.link.restarts
        extra.update(
            {f"service.passports.rejected.{k}": n for k, n in self.store.rejected_counts().items()}
        )
        if (zsink := self._zenoh_sink()) is not None:
            extra["service.zenoh.acks_refused"] = zsink.refused[0]
        run = self._running()
        extra.update(self.supervisor.counters())
        extra.update({f"service.{k}": n for k, n in run.writer.counters().items()})
        extra.update({f"service.{k}": n for k, n in self._saves.counters().items()})
        with contextlib.suppress(OutboxUnavailable):
            counts = run.outbox.counts()
            extra["service.outbox.stored"] = counts.stored
            extra.update(
                {f"service.outbox.pending.{s}": n for s, n in counts.pending_by_sink.items()}
            )
        extra.update(self._delivery_counters())
        now = time.time()
        name = self.config.service.name
        vehicles = self.fleet.vehicles()
        publisher.publish_service(
            ServiceStatus(
                service=name,
                t_s=now,
                vehicles=tuple(vehicles),
                counters={
                    **{f"service.{k}": n for k, n in self.fleet.service_counters.items()},
                    **{k: n for k, n in extra.items() if k.startswith("service.")},
                },
            )
        )
        units = self._unit_frames()
        waiting = {s: d.pending_vehicles() for s, d in run.deliveries.items()}
        for vehicle in vehicles:
            own = {f"outbox.pending.{s}": by.get(vehicle, 0) for s, by in waiting.items()}
            publisher.publish(
                self.fleet.status(
                    vehicle,
                    service=name,
                    now_unix_s=now,
                    extra=extra | units.get(vehicle, {}) | own,
                )
            )
            # One vehicle at a time: frames waiting behind a large fleet's status are not held up.
            await asyncio.sleep(0)

    def _delivery_counters(self) -> dict[str, int]:
        """The storage state and what the sinks gave up, for the status topic; a sink's new
        give-ups logged (:class:`~protocols.log_rate.LogRate`)."""
        run = self._running()
        away_s = self._storage_away_s()
        out = {
            "service.storage.fault": int(away_s is not None),
            "service.storage.unavailable_s": 0 if away_s is None else int(away_s),
            **{f"service.outbox.given_up.{s}": n for s, n in run.outbox.given_up.items()},
            **{
                f"service.delivery.{s}.acks_unrecorded": d.unrecorded
                for s, d in run.deliveries.items()
            },
        }
        if new := self._given_up_log.due(dict(run.outbox.given_up)):
            log.warning(
                "outbox: %s; a sink's backlog beyond outbox_max_pending = %d gives up its oldest "
                "events (the other sinks still deliver them), counted as outbox.given_up.<sink>",
                ", ".join(f"{n} given up for {s}" for s, n in sorted(new.items())),
                self.config.service.outbox_max_pending,
            )  # fmt: skip
        return out

    def _unit_frames(self) -> dict[str, dict[str, int]]:
        """Each vehicle's frames from Zenoh per IMU: ``imu<n>.frames.received`` (dropped ones
        included), ``imu<n>.frames.dropped_overload`` and ``imu<n>.frames.queued`` (waiting now):
        what ``ins-health publish`` compares with what it sent."""
        source = self.source
        if source is None:
            return {}
        received, dropped = source.unit_counts()
        out: dict[str, dict[str, int]] = {}
        for (vehicle, imu), n in received.items():
            out.setdefault(vehicle, {}).update(
                {
                    f"imu{imu}.frames.received": n,
                    f"imu{imu}.frames.dropped_overload": dropped.get((vehicle, imu), 0),
                    f"imu{imu}.frames.queued": source.queued_of(vehicle, imu),
                }
            )
        return out

    def _log_drops(self) -> None:
        """Frames dropped because a queue was full, said per vehicle and IMU: a new unit at once,
        more at most once per period (:class:`~protocols.log_rate.LogRate`)."""
        if self.source is None:
            return
        dropped = {f"{v} IMU{i}": n for (v, i), n in self.source.unit_counts()[1].items()}
        if new := self._drops_log.due(dropped):
            p = self.config.pipeline
            log.warning(
                "frames dropped, their queue full (queue_capacity %d per IMU, instance_queue_capacity "
                "%d): %s; the newest are dropped, counted on the status topic as "
                "imu<n>.frames.dropped_overload",
                p.queue_capacity, p.instance_queue_capacity,
                ", ".join(f"{n} of {unit}" for unit, n in sorted(new.items())),
            )  # fmt: skip

    def _zenoh_sink(self) -> ZenohEventSink | None:
        return next((s for s in self.sinks if isinstance(s, ZenohEventSink)), None)

    def _log_cross_imu(self) -> None:
        """An IMU the cross-IMU check stops comparing (another clock, its offset not steady or still
        measured, a lag) said once with why, and when it compares it again."""
        for vehicle, imu in sorted(self.fleet.pipelines):
            why = self.fleet.cross_not_running(vehicle, imu)
            if why is not None and (vehicle, imu) not in self._cross_off:
                self._cross_off.add((vehicle, imu))
                log.warning("%s IMU%d: cross-IMU check not running: %s", vehicle, imu, why)
            elif why is None and (vehicle, imu) in self._cross_off:
                self._cross_off.discard((vehicle, imu))
                log.info("%s IMU%d: cross-IMU check running again", vehicle, imu)

    def _log_refused_acks(self) -> None:
        """Acknowledgements from receivers ``[zenoh] ack_from`` does not name, said as they grow (at
        most once per period, :class:`~protocols.log_rate.LogRate`) with the last one's receiver."""
        sink = self._zenoh_sink()
        if sink is None:
            return
        n, last = sink.refused
        if new := self._refused_log.due({"acks": n} if n else {}):
            log.warning(
                "%d acknowledgement(s) refused, their receiver not in [zenoh] ack_from %s (the last "
                "from %s); counted as service.zenoh.acks_refused",
                new["acks"], list(self.config.zenoh.ack_from), last,
            )  # fmt: skip

    async def _status(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            async with self.intake.group_lock:
                self._store(self.fleet.tick(self._clock()))
            self._track_router()
            self._check_mavlink_reader()
            self.intake.log_refusals()
            self._log_drops()
            self._log_refused_acks()
            self._log_cross_imu()
            if self._status_pub is not None:
                await self._publish_status(self._status_pub)
            await _wait_any(stop, None, timeout_s=self.config.service.status_period_s)

    async def checkpoint(self, vehicles: Collection[str] | None = None) -> None:
        """Write the state of every vehicle that changed since the last checkpoint (one transaction);
        ``vehicles``: of these vehicles only.

        A vehicle's changed units and its cross-IMU state are taken at one moment
        (:meth:`FleetProcessor.checkpoint_states`; its other units' saved states are still
        theirs); the loop yields between vehicles only. A write the store refuses
        (:class:`CheckpointUnavailable`) is counted and logged (:class:`SaveFailures`), and its
        units are written by the next checkpoint, with their state then, even if they do not
        change meanwhile.
        """
        if self._running().writer.undelivered:
            # State ahead of events neither stored nor delivered everywhere would, after kill -9,
            # resume past events that exist nowhere.
            self.fleet.count_service("checkpoints.deferred")
            return
        payloads: dict[str, bytes] = {}
        cross: dict[str, bytes] = {}
        keys = self.fleet.changed_keys(vehicles)
        changed: dict[str, set[int]] = {}
        for v, i in keys:
            changed.setdefault(v, set()).add(i)
        for vehicle, imus in sorted(changed.items()):
            # A vehicle of many units, one of them streaming, cost every unit's encoding (1.5 ms each).
            async with self.intake.group_lock:
                if self._running().writer.undelivered:
                    # A group run while the loop yielded had its events held: a state taken now
                    # would be ahead of them. Nothing is written; the next checkpoint takes them all.
                    self.fleet.mark_unsaved(keys)
                    self.fleet.count_service("checkpoints.deferred")
                    return
                units, cross_state = self.fleet.checkpoint_states(vehicle, imus)
            payloads.update((k, encode_state(s)) for k, s in units.items())
            if cross_state is not None:
                cross[vehicle] = encode_state(cross_state)
            # One vehicle at a time, so frames keep flowing while a large fleet is saved.
            await asyncio.sleep(0)
        if not payloads:
            return
        try:
            self._running().checkpoints.save_encoded(payloads, cross=cross)
        except CheckpointUnavailable as exc:
            # Only saved work: the state is in memory, the daemon goes on without it meanwhile.
            self.fleet.mark_unsaved(keys)
            self._saves.failed(exc, len(payloads))
            return
        self._saves.saved(len(payloads))

    async def _storage(self, stop: asyncio.Event) -> None:
        """Storage faults degrade, never silence: the held events written as soon as the outbox takes
        them (retried with back-off, :data:`~service.outbox_writer.RETRY_MIN_S` doubling to
        :data:`~service.outbox_writer.RETRY_MAX_S`), the data directory checked every
        :data:`STORAGE_CHECK_S` (:meth:`DataDirLock.problem`: removed or replaced, its stores' writes
        are refused until its own lock file is back at its path, they would be lost at the next
        start), and past
        ``storage_timeout_s`` of the outbox, the checkpoints or the data directory away the daemon
        stops (the watchdog is no longer fed) and exits with :data:`EXIT_STORAGE`."""
        run = self._running()
        limit_s = self.config.service.storage_timeout_s
        delay_s = RETRY_MIN_S
        while not stop.is_set():
            problem = run.lock.problem()
            if self._data_dir_lost_s is not None and problem is None:
                # The same lock file (device and inode) at its path: the folder held, moved back or
                # uncovered by an unmount; its outbox is the one the next start sees.
                lasted_s, self._data_dir_lost_s = self._clock() - self._data_dir_lost_s, None
                run.outbox.refuse_writes(None)
                log.warning(
                    "the data directory %s is back after %.1f s (the lock file held); its outbox "
                    "takes writes again", run.lock.data_dir, lasted_s,
                )  # fmt: skip
            if self._data_dir_lost_s is None and problem is not None:
                self._data_dir_lost_s = self._clock()
                run.outbox.refuse_writes(problem)
                self.fleet.count_service("storage.data_dir_lost")
                log.error(
                    "%s: a storage fault; new events are held in memory and delivered from there, "
                    "and the daemon exits after storage_timeout_s = %g s unless stopped before "
                    "(counted as service.storage.data_dir_lost)",
                    problem, limit_s,
                )  # fmt: skip
            flushed = run.writer.flush()
            if (away_s := self._storage_away_s()) is not None and away_s >= limit_s:
                self.supervisor.fail(
                    f"storage unavailable for {away_s:.1f} s (storage_timeout_s = {limit_s:g} s); "
                    "the watchdog is no longer fed",
                    code=EXIT_STORAGE,
                )
                return
            self.supervisor.beat()
            delay_s = RETRY_MIN_S if flushed else min(2.0 * delay_s, RETRY_MAX_S)
            await _wait_any(stop, None, timeout_s=STORAGE_CHECK_S if flushed else delay_s)

    def _storage_away_s(self) -> float | None:
        """How long the longest storage fault going on has lasted, s (None: none is)."""
        run = self._running()
        lost = None if self._data_dir_lost_s is None else self._clock() - self._data_dir_lost_s
        away = [run.writer.unavailable_s(), self._saves.unavailable_s(), lost]
        return max((t for t in away if t is not None), default=None)

    async def _checkpoints(self, stop: asyncio.Event) -> None:
        """A checkpoint every ``checkpoint_period_s``, and of the vehicles whose events were stored
        as soon as they were.

        A unit whose event is in the outbox but whose state is not saved would, after a
        kill -9 and with a live source that does not send its frames again, raise the
        same finding again under a new id (its disagreement, its fault); saving right
        after the event leaves that to the few milliseconds between the two writes.
        The checkpoint waits :data:`EVENT_CHECKPOINT_DELAY_S` for the deliveries to hand
        the events over. Only those vehicles: saving every changed unit after each event cost a streaming
        fleet of 48 IMUs about 70 ms of the loop per event, and the events of a fleet's
        faults in one second made seconds of latency. Events stored while a checkpoint is
        written are covered by the next one.

        While the store refuses writes, the next checkpoint (of every changed unit, those of the
        failed attempt included) comes after the back-off of :class:`SaveFailures` instead of the
        period, and the events' vehicles wait for it.
        """
        period_s = self.config.service.checkpoint_period_s
        saves = self._saves
        due_s = self._clock() + period_s
        while not stop.is_set():
            await _wait_any(stop, self._checkpoint_soon, timeout_s=max(0.0, due_s - self._clock()))
            self._checkpoint_soon.clear()
            vehicles, self._checkpoint_vehicles = self._checkpoint_vehicles, set()
            if self._clock() >= due_s:
                await self.checkpoint()
                due_s = self._clock() + (saves.retry_s if saves.unavailable else period_s)
            elif vehicles and not saves.unavailable:
                # The events' deliveries go first: encoding a unit's state holds the interpreter
                # for about 1.5 ms, and a delivery thread that has not yet put its event waited
                # for all of it (up to 9 ms of a fault-to-event latency of 12).
                await asyncio.sleep(EVENT_CHECKPOINT_DELAY_S)
                await self.checkpoint(vehicles)
                if saves.unavailable:
                    due_s = min(due_s, self._clock() + saves.retry_s)
            self.supervisor.beat()

    # ------------------------------------------------------------------ run

    async def run(self, stop: asyncio.Event, *, ready: asyncio.Event | None = None) -> int:
        """Run until ``stop`` is set, then drain (module docstring); the exit status.

        ``ready`` is set (and ``READY=1`` sent) once frames are accepted from every input that is
        up: a router that does not answer the first attempt is connected to in the background.
        Returns 0 after the drain, :data:`~service.supervisor.EXIT_TASK_FAILED` when a task
        kept failing or the router stayed out of reach beyond ``connect_timeout_s``, and
        :data:`EXIT_STORAGE` when storage stayed away beyond ``storage_timeout_s`` or events held
        in memory could not be stored before the exit.
        """
        cfg = self.config
        with contextlib.ExitStack() as resources:
            names = self.sink_names()
            # Closed in reverse order on the way out, whatever happened in between.
            lock = DataDirLock(cfg.service.data_dir)
            resources.callback(lock.close)
            outbox = resources.enter_context(
                Outbox(
                    cfg.outbox_path,
                    sinks=names,
                    max_bytes=cfg.service.outbox_max_bytes,
                    max_pending=cfg.service.outbox_max_pending,
                )
            )
            if outbox.over_limit_bytes:
                log.warning(
                    "outbox: %s is %.3f MB above outbox_max_mb with events not yet delivered; it is "
                    "held at its present size until a restart after their delivery compacts it",
                    cfg.outbox_path, outbox.over_limit_bytes / 1e6,
                )  # fmt: skip
            if elsewhere := outbox.pending_elsewhere():
                log.warning(
                    "outbox: events pending for sinks not configured now, kept until they are back "
                    "(re-enable them, or move the outbox aside to drop them): %s",
                    ", ".join(f"{n} for {sink}" for sink, n in elsewhere.items()),
                )
            checkpoints, replaced = open_checkpoints(cfg.checkpoint_path)
            if replaced is not None:
                self.fleet.count_service("checkpoints.store_replaced")
                log.error("checkpoints: %s; every unit starts fresh", replaced)
            run = self._run = _Run(
                lock,
                outbox,
                resources.enter_context(checkpoints),
                _Wake(names),
                OutboxWriter(
                    outbox,
                    on_stored=self._stored,
                    on_held=self._held,
                    clock=self._clock,
                    max_held=cfg.service.max_held_events,
                ),
                {},
            )
            resources.callback(self.notifier.close)
            # Before the outbox and the checkpoints close, whatever ended the run.
            resources.callback(self.supervisor.cancel_all)
            self.fleet.set_restore(
                self._restore,
                self._discard_checkpoint,
                load_cross=self._restore_cross,
                on_cross_error=self._discard_cross,
            )
            self._log_summary()
            self._startup_scan()
            # Units seen before the restart come back with their positions before their first frame
            # (so one that stays silent times out); not those gone for longer than REVIVE_MAX_AGE_S,
            # which would fill the vehicle limit with retired vehicles. Those resume on a frame.
            recent = run.checkpoints.keys(saved_since_unix_s=time.time() - REVIVE_MAX_AGE_S)
            for key in recent:
                try:
                    vehicle, imu = checkpoint_unit(key)
                except CheckpointError as exc:
                    run.checkpoints.quarantine(key, str(exc))
                    log.warning("checkpoint %r moved aside to the quarantined table: %s", key, exc)
                    continue
                self.fleet.admit(vehicle, imu)
            if cfg.mavlink.enabled and (link := await self._try_mavlink(stop)) is not None:
                self._mavlink_up(link, resources)
            connector = _Connector(cfg.zenoh.session) if cfg.zenoh.enabled else None
            session = None if connector is None else await connector.attempt()
            run.wake.set()  # deliver what a previous run left in the outbox
            drain = asyncio.Event()
            sup = self.supervisor
            if session is not None:
                self._zenoh_up(session, resources, drain)
            if self.mavlink_sink is not None:
                self._mavlink_tasks(drain, stop)
            elif cfg.mavlink.enabled:
                sup.start("mavlink-open", lambda: self._mavlink_open(resources, drain, stop))
            sup.start("status", lambda: self._status(stop))
            sup.start("checkpoints", lambda: self._checkpoints(stop))
            sup.start("storage", lambda: self._storage(stop))
            if connector is not None and session is None:
                sup.start(
                    "zenoh-connect",
                    lambda: self._connect(connector, resources, drain, stop),
                )
            if (watchdog_s := self.notifier.watchdog_s) is not None:
                sup.start("watchdog", lambda: self._watchdog(stop, period_s=watchdog_s / 2))
            if ready is not None:
                ready.set()
            self.notifier.send("READY=1", f"STATUS={self._say_inputs()}")
            await _wait_any(stop, sup.fatal, timeout_s=None)
            stop.set()
            self.notifier.send("STOPPING=1")
            await self._drain(drain)
        if sup.fatal.is_set():
            return sup.exit_code
        return EXIT_STORAGE if self._unstored or self._data_dir_lost_s is not None else 0

    def _say_inputs(self) -> str:
        """Log ``NAME running`` once an input is connected, ``NAME waiting for …`` before; the line said.

        "running" came once the tasks had started, with no router reached and no link open, where
        INSTALL.md says it means frames are taken. An input still down beside one that is up is
        said by its own retries (a warning at the first failed attempt)."""
        cfg = self.config
        waiting = []
        if cfg.zenoh.enabled and self.source is None:
            waiting.append(
                f"the Zenoh router at {', '.join(cfg.zenoh.session.connect) or '(none)'}"
            )
        if cfg.mavlink.enabled and self.mavlink_source is None:
            waiting.append(f"the MAVLink link {cfg.mavlink.link.device}")
        up = self.source is not None or self.mavlink_source is not None
        line = (
            f"{cfg.service.name} running"
            if up
            else f"{cfg.service.name} waiting for {' and '.join(waiting) or 'an input (none is enabled)'}"
        )
        if not (up and self._said_running):
            log.info("%s", line)
        self._said_running = up
        return line

    def _zenoh_up(
        self, session: Session, resources: contextlib.ExitStack, drain: asyncio.Event
    ) -> None:
        """The Zenoh side on an open session: event sink, status, frame source, and their tasks."""
        cfg = self.config
        self._session = resources.enter_context(session)
        zsink = ZenohEventSink(
            session,
            ack=cfg.zenoh.event_ack,
            ack_timeout_s=cfg.zenoh.ack_timeout_s,
            min_acks=cfg.zenoh.min_acks,
            max_lanes=cfg.pipeline.max_vehicles,
            ack_from=cfg.zenoh.ack_from,
        )
        resources.callback(zsink.close)
        self.sinks.insert(0, zsink)
        self._status_pub = resources.enter_context(StatusPublisher(session, cfg.service.name))
        source = self.source = FrameSource(
            session,
            (cfg.zenoh.frames_key,),
            capacity=cfg.pipeline.queue_capacity,
            total=cfg.pipeline.instance_queue_capacity,
            on_reject=self.intake.reject,
            refused_vehicles=self.intake.mavlink_fed,
        )
        resources.callback(source.close)
        gnss = GnssSource(
            session, (gnss_selector(cfg.zenoh.frames_key),), on_reject=self.intake.gnss_reject
        )
        resources.callback(gnss.close)
        self._start_delivery(zsink, drain)
        self.supervisor.start("frames", lambda: self.intake.zenoh_frames(source))
        self.supervisor.start("gnss", lambda: self.intake.gnss_frames(gnss))

    async def _try_mavlink(self, stop: asyncio.Event) -> MavlinkLink | MavlinkProcessLink | None:
        """The MAVLink link opened, or None when its device cannot be opened now (logged once per kind
        of failure, counted as ``service.mavlink.open_failures``): a serial adapter not plugged in
        yet, an autopilot's TCP port not up yet. That stopped the whole daemon at start, with a
        traceback, Zenoh input included. None too when ``stop`` is set first.

        The open runs in a daemon thread of its own, not the loop's executor: it may block a minute
        (the reader process's start, pymavlink's TCP retries), and ``asyncio.run`` waits for the
        executor's threads at exit without a bound, past the stop bound. A link that opens after
        the wait was given up is closed."""
        loop = asyncio.get_running_loop()
        done: asyncio.Future[MavlinkLink | MavlinkProcessLink] = loop.create_future()

        def settle(
            link: MavlinkLink | MavlinkProcessLink | None, exc: BaseException | None
        ) -> None:
            if done.cancelled():
                if link is not None:
                    link.close()
            elif exc is not None:
                done.set_exception(exc)
            else:
                done.set_result(link)  # type: ignore[arg-type]

        def open_link() -> None:
            link, exc = None, None
            try:
                link = self._open_mavlink()
            except BaseException as e:  # handed to the loop, which tells them apart
                exc = e
            try:
                loop.call_soon_threadsafe(settle, link, exc)
            except RuntimeError:  # the loop is closed: the service is gone
                if link is not None:
                    link.close()

        threading.Thread(target=open_link, name="mavlink-open", daemon=True).start()
        stopped = asyncio.create_task(stop.wait())
        try:
            waits: list[asyncio.Future[Any]] = [done, stopped]
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopped.cancel()
            if not done.done():
                done.cancel()
        if done.cancelled():
            return None
        try:
            return done.result()
        except OSError as exc:  # ReaderProcessFailed, a serial port absent, a TCP peer refusing
            self.fleet.count_service("mavlink.open_failures")
            kind = f"{type(exc).__name__}: {exc}"
            if kind not in self._reported:
                self._reported.add(kind)
                log.error(
                    "mavlink %s: cannot open it (%s); trying again every %.0f s, the rest of the "
                    "service runs meanwhile (counted as service.mavlink.open_failures)",
                    self.config.mavlink.link.device, kind, CONNECT_PAUSE_S,
                )  # fmt: skip
            return None

    def _mavlink_up(
        self, link: MavlinkLink | MavlinkProcessLink, resources: contextlib.ExitStack
    ) -> None:
        """The MAVLink side on an open link: the alert sink and the IMU source."""
        cfg = self.config
        resources.callback(link.close)
        _warn_short_rcvbuf(link)
        policy = AlertPolicy(
            min_interval_s=cfg.mavlink.alert_min_interval_s,
            max_per_s=cfg.mavlink.alert_max_per_s,
        )
        self.mavlink_sink = MavlinkAlertSink(link, policy=policy, clock=self._clock)
        self.sinks.append(self.mavlink_sink)
        self.mavlink_source = MavlinkSource(
            link,
            capacity=cfg.pipeline.queue_capacity * COALESCE_MAX,
            gather_s=COALESCE_WINDOW_S,
        )
        resources.callback(self.mavlink_source.close)

    def _mavlink_tasks(self, drain: asyncio.Event, stop: asyncio.Event) -> None:
        sink, source = self.mavlink_sink, self.mavlink_source
        assert sink is not None and source is not None
        self._start_delivery(sink, drain)
        self.supervisor.start("heartbeat", lambda: self._heartbeat(sink, stop))
        self.supervisor.start("mavlink-frames", lambda: self.intake.mavlink_frames(source))
        gnss = MavlinkGnssSource(source)
        self.supervisor.start(
            "mavlink-gnss",
            lambda: self.intake.gnss_frames(gnss, dropped_as="mavlink.gnss_dropped"),
        )

    async def _mavlink_open(
        self, resources: contextlib.ExitStack, drain: asyncio.Event, stop: asyncio.Event
    ) -> None:
        """Attempts to open the MAVLink link every :data:`CONNECT_PAUSE_S` until one succeeds or ``stop`` is set."""
        while not stop.is_set():
            await _wait_any(stop, None, timeout_s=CONNECT_PAUSE_S)
            if stop.is_set():
                return
            link = await self._try_mavlink(stop)
            self.supervisor.beat()
            if link is not None:
                if stop.is_set():
                    link.close()
                    return
                self._mavlink_up(link, resources)
                self._mavlink_tasks(drain, stop)
                log.info("mavlink %s: open", self.config.mavlink.link.device)
                self.notifier.send(f"STATUS={self._say_inputs()}")
                return

    def _start_delivery(self, sink: EventSink, drain: asyncio.Event) -> None:
        run = self._running()
        loop = asyncio.get_running_loop()
        name = sink.name

        def sent() -> None:
            # From the transport's worker thread too.
            loop.call_soon_threadsafe(run.wake.sent, name)

        delivery = run.deliveries[name] = SinkDelivery(
            sink,
            run.outbox,
            run.writer,
            retry_s=self.config.service.delivery_retry_s,
            idle=lambda: run.wake.idle(name),
            sent=sent,
            count=self.fleet.count_service,
            transport_error=lambda exc: self._transport_error(name, exc),
            beat=self.supervisor.beat,
        )
        wake = run.wake.events[name]
        self.supervisor.start(f"deliver-{name}", lambda: delivery.run(wake, drain))

    async def _connect(
        self,
        connector: _Connector,
        resources: contextlib.ExitStack,
        drain: asyncio.Event,
        stop: asyncio.Event,
    ) -> None:
        """Attempts to open the Zenoh session until one succeeds, ``stop`` is set or ``connect_timeout_s`` passes."""
        while not stop.is_set():
            if connector.expired():
                self.supervisor.fail(
                    f"zenoh: no router at {list(connector.settings.connect)} within connect_timeout_s = "
                    f"{connector.settings.connect_timeout_s:g} s"
                )
                return
            session = await connector.attempt()
            self.supervisor.beat()
            if session is not None:
                if stop.is_set():
                    session.close()
                    return
                self._zenoh_up(session, resources, drain)
                self.notifier.send(f"STATUS={self._say_inputs()}")
                return
            await _wait_any(stop, None, timeout_s=CONNECT_PAUSE_S)

    async def _watchdog(self, stop: asyncio.Event, *, period_s: float) -> None:
        """``WATCHDOG=1`` every ``period_s`` (half the watchdog timeout) while the frame path is healthy
        (:class:`~service.notify.FramePathWatch`)."""
        watch = self.frame_watch
        stalled = False
        while not stop.is_set():
            waiting = self._frames_waiting()
            if watch.healthy(taken=self.supervisor.beats(*INPUT_TASKS), waiting=waiting):
                self.notifier.send("WATCHDOG=1")
                self.supervisor.beat()
                if stalled:
                    stalled = False
                    log.info("the frame path moves again; the watchdog is fed")
            elif not stalled:
                stalled = True
                log.error(
                    "the frame path is stalled: %d frames wait and none was taken for %.1f s; the "
                    "watchdog is no longer fed (the service manager restarts the daemon)",
                    waiting, period_s,
                )  # fmt: skip
            await _wait_any(stop, None, timeout_s=period_s)

    def _frames_waiting(self) -> int:
        zenoh_waiting = 0 if self.source is None else self.source.queued
        return zenoh_waiting + (0 if self.mavlink_source is None else self.mavlink_source.queued)

    def _track_router(self) -> None:
        """Log when the session's Zenoh connections come and go (Zenoh reconnects by itself)."""
        if self._session is None:
            return
        nodes = connected_nodes(self._session)
        if bool(nodes) == self._router_connected:
            return
        self._router_connected = bool(nodes)
        if nodes:
            log.info("zenoh: connected (%s)", ", ".join(nodes))
        else:
            log.warning(
                "zenoh: connection lost; Zenoh reconnects by itself, events wait in the outbox"
            )

    def _open_mavlink(self) -> MavlinkLink | MavlinkProcessLink:
        m = self.config.mavlink
        if m.reader is MavlinkReader.PROCESS:
            return MavlinkProcessLink(m.link, gather_s=COALESCE_WINDOW_S)
        return MavlinkLink(m.link)

    def _check_mavlink_reader(self) -> None:
        """Log the MAVLink reader thread's failures (it reads again after a pause)."""
        source = self.mavlink_source
        if source is None or source.failures == self._reader_failures:
            return
        self._reader_failures = source.failures
        log.error(
            "the MAVLink reader failed (%d failure(s) so far, counted as service.mavlink.reader_failures); "
            "it reads again after %.0f s",
            source.failures, READER_RETRY_S, exc_info=source.last_failure,
        )  # fmt: skip

    def sink_names(self) -> list[str]:
        """The sinks every event must reach (the outbox keeps a delivery state for each)."""
        names = [ZenohEventSink.name] if self.config.zenoh.enabled else []
        return names + ([MavlinkAlertSink.name] if self.config.mavlink.enabled else [])

    async def _drain(self, drain: asyncio.Event) -> None:
        sup = self.supervisor
        sup.stop_restarts()
        tasks = sup.tasks
        # A connection attempt ends within its bound; what it opened is then closed with the rest.
        # (gather: a task that failed or was cancelled must not stop the drain.)
        await asyncio.gather(
            *[t for n, t in tasks.items() if n == "zenoh-connect"], return_exceptions=True
        )
        if self.source is not None:
            self.source.close()
        if self.mavlink_source is not None:
            await asyncio.to_thread(self.mavlink_source.close)
        # The sources are closed: the input tasks finish what is queued, then end. Should the
        # outbox still be unavailable after DRAIN_TIMEOUT_S, they stop waiting for it.
        await asyncio.gather(
            *[t for n, t in tasks.items() if n in INPUT_TASKS], return_exceptions=True
        )
        try:
            await self.checkpoint()
        except Exception:
            log.exception("the last checkpoint failed; the next start resumes from the one before")
        if self._saves.unavailable:
            log.error(
                "the last checkpoint could not be saved (the store is unavailable); the next start "
                "resumes from the last one saved"
            )
        drain.set()
        run = self._running()
        run.wake.set()
        deliveries = [t for name, t in tasks.items() if name.startswith("deliver-")]
        _done, pending = (
            await asyncio.wait(deliveries, timeout=DRAIN_TIMEOUT_S)
            if deliveries
            else (set(), set())
        )
        for t in list(pending) + [t for t in tasks.values() if t not in deliveries]:
            t.cancel()
        await asyncio.gather(*tasks.values(), return_exceptions=True)
        run.writer.flush()
        self._unstored = run.writer.stop()
        left = 0
        with contextlib.suppress(OutboxUnavailable):
            left = sum(run.outbox.counts().pending_by_sink.values())
        if left and self._data_dir_lost_s is not None:
            log.error(
                "%d event deliveries still pending, in the outbox of a data directory the next start "
                "will not see: lost; exiting non-zero", left,
            )  # fmt: skip
        elif left:
            log.warning("%d event deliveries still pending; they are sent at the next start", left)


class _Connector:
    """Bounded attempts at opening the Zenoh session, each in a worker thread (the loop stays free)."""

    def __init__(self, settings: ZenohSettings):
        self.settings = settings
        self._first_s: float | None = None
        self._reported = False

    def expired(self) -> bool:
        limit = self.settings.connect_timeout_s
        return (
            limit is not None
            and self._first_s is not None
            and time.monotonic() - self._first_s >= limit
        )

    async def attempt(self) -> Session | None:
        """One attempt of at most :data:`CONNECT_ATTEMPT_S`; the session, or ``None`` (logged once)."""
        if self._first_s is None:
            self._first_s = time.monotonic()
        limit = self.settings.connect_timeout_s
        timeout_s = CONNECT_ATTEMPT_S if limit is None else min(CONNECT_ATTEMPT_S, limit)
        try:
            session = await asyncio.to_thread(open_session_within, self.settings, timeout_s)
        except ConnectionError as exc:
            if not self._reported:
                self._reported = True
                log.warning(
                    "zenoh: cannot reach %s (%s); retrying in the background every %.0f s, "
                    "the other inputs are served meanwhile",
                    list(self.settings.connect), exc, CONNECT_ATTEMPT_S + CONNECT_PAUSE_S,
                )  # fmt: skip
            return None
        if self._reported:
            log.info(
                "zenoh: session open after %.1f s of attempts", time.monotonic() - self._first_s
            )
        return session


def _warn_short_rcvbuf(link: MavlinkLink | MavlinkProcessLink) -> None:
    """Say when the kernel granted a UDP link less receive buffer than ``udp_rcvbuf_bytes`` asked:
    a stock kernel caps the default 4 MiB at 208 KiB, about 500 datagrams of one message, and a
    backlog the buffer was sized for is then dropped (``service.mavlink.dropped_kernel``)."""
    granted, asked = link.udp_rcvbuf_granted_bytes, link.settings.udp_rcvbuf_bytes
    if granted is not None and granted < asked:
        log.warning(
            "mavlink %s: the kernel granted %d bytes of receive buffer of the %d asked (udp_rcvbuf_bytes); "
            "net.core.rmem_max caps it: sysctl -w net.core.rmem_max=%d",
            link.settings.device, granted, asked, asked,
        )  # fmt: skip


async def _wait_any(a: asyncio.Event, b: asyncio.Event | None, *, timeout_s: float | None) -> None:
    """Wait until ``a`` or ``b`` is set, or ``timeout_s`` passes."""
    waits = [asyncio.create_task(a.wait())] + (
        [asyncio.create_task(b.wait())] if b is not None else []
    )
    try:
        await asyncio.wait(waits, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waits:
            w.cancel()
