"""Zenoh transport: IMU frames in, fault events and status out (eclipse-zenoh 1.x).

Key expressions
---------------
=================================  ==========================================
``ins/<vehicle>/imu/<n>``          IMU frames (:mod:`protocols.frames`)
``ins/<vehicle>/gnss``             GNSS velocity frames (:mod:`protocols.gnss_frames`)
``ins/<vehicle>/health/events``    events (:mod:`protocols.events`), full stream
``ins/<vehicle>/health/ack``       event acknowledgement queries (below)
``ins/<vehicle>/health/status``    periodic :class:`~protocols.events.Status`
=================================  ==========================================

A frame subscription may cover the whole fleet (``ins/*/imu/*``) or a subset:
``ins/uav-7/imu/*``, or a prefix with Zenoh's in-chunk wildcard
``ins/fleetA-$*/imu/*``. Service instances share a fleet by taking disjoint key
expressions; the router is the distributed engine that routes each vehicle's
frames to the one instance that subscribed to them.

Back-pressure per stream
------------------------
* Frames: a :class:`FrameSource` copies each payload from Zenoh's callback
  thread into a bounded ring and hands it to asyncio through
  ``loop.call_soon_threadsafe``. When the ring is full the *oldest* frame is
  dropped and counted (fresh data is worth more to a health monitor; the seq
  gap shows the pipeline what was lost). Frames are published with
  ``CongestionControl.DROP``: a congested link sheds frames, never blocks the
  vehicle.
* Events: reliable, ``CongestionControl.BLOCK``; never dropped on purpose.

What "acknowledged by the transport" means
------------------------------------------
A Zenoh ``put`` returns as soon as the data is queued locally; it returns
without error even when no router is connected, so by itself it proves
nothing. :class:`EventPublisher.publish` therefore does two things:

1. ``put`` the event on ``ins/<vehicle>/health/events`` (reliable, BLOCK), so
   every subscriber (dashboards, loggers) sees the full stream;
2. with :attr:`AckMode.RECEIVER` (the default) it sends a query carrying the
   same encoded event to ``ins/<vehicle>/health/ack``. Each
   :class:`EventReceiver` with ``acknowledge=True`` decodes it, hands it to its
   application callback (exactly once per id: it deduplicates) and only once the
   callback has returned replies with the event id (a callback that raised gets
   the event again with the retry). The event counts as acknowledged when at least
   ``min_acks`` *distinct* receivers reply with its id within ``ack_timeout_s``: an
   end-to-end acknowledgement by the receiving application.

Who acknowledged: a receiver given a name answers on
``ins/<vehicle>/health/ack/<name>`` (the querier accepts replies on keys other
than the one asked), and Zenoh tells the answering session's id
(:class:`Acknowledgement`). One session answering twice, or under two names,
counts once; so do two sessions claiming one name (:func:`distinct_receivers`).
``ack_from`` names the receivers that count; others' answers are refused and
counted. A name alone is a claim; the router's access control binds it to a
certificate (``deploy/zenoh-router.json5``: a ground station's certificate may
answer only on the key of its own name). The certificate's name itself does not
reach the publisher: eclipse-zenoh's Python API exposes the certificate of a
*direct* link only (``Session.info.links()``, ``Link.auth_identifier``), and a
receiver's link ends at the router, not at the publisher.

With :attr:`AckMode.MATCHED` the acknowledgement is weaker: ``put`` returned
without error on the reliable/blocking publisher *and* Zenoh reported at least
one matching subscriber (a route exists). Use it only where every consumer is a
plain subscriber. Either way the caller (the outbox) retries what is not
acknowledged, and receivers deduplicate by id, so delivery is at-least-once on
the wire and exactly-once per id at the application.

Connection
----------
:func:`zenoh_config` builds a ``zenoh.Config`` from a plain dict (see
:class:`ZenohSettings`). A *client* session needs its router: ``zenoh.open``
blocks until it connects or ``connect_timeout_s`` passes (``None``: wait
forever); afterwards Zenoh reconnects by itself when the router restarts
(verified by ``tests/test_zenoh_adapter.py``), and declared subscribers,
queryables and publishers keep working.

Every session opened here asks Zenoh to bound what it reassembles:
``transport/link/rx/max_message_size`` = :data:`ZENOH_MAX_MESSAGE_BYTES`
(default 1 GiB). What eclipse-zenoh 1.10.2 does with it, measured
(``tests/test_service_hostile.py``): the *first* larger message on a link is
dropped while its fragments arrive, silently (nothing reaches the application,
nothing is logged at warning level), and the link stays up; later larger
messages on the same link are reassembled in full and delivered. So the bound
is not a limit to rely on: the decoders' own checks
(:data:`~protocols.frames.MAX_FRAME_BYTES`, before unpacking) still refuse and
count every oversized payload that gets through (``frames.rejected.too_large``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeAlias, TypeVar

import numpy as np
import zenoh
from numpy.typing import ArrayLike

from protocols._handoff import FairQueues
from protocols._schema import (
    MAX_IMU_INDEX,
    MAX_MESSAGE_BYTES,
    VEHICLE_ID_PATTERN,
    Reason,
    SchemaError,
    check_imu,
    check_vehicle,
)
from protocols.events import (
    Event,
    EventError,
    ServiceStatus,
    Status,
    decode_event,
    decode_service_status,
    decode_status,
    encode_event,
    encode_service_status,
    encode_status,
)
from protocols.frames import (
    MAX_FRAME_BYTES,
    BatchSource,
    FrameError,
    SampleBatch,
    SampleDtype,
    decode_frame,
    encode_frame,
)
from protocols.gnss_frames import GnssFrame, decode_gnss_frame, encode_gnss_frame
from protocols.zenoh_settings import (
    ALL_FRAMES,
    ROOT,
    AckMode,
    Mode,
    ZenohSettings,
    check_receiver_name,
    check_service_name,
)

_Decoded = TypeVar("_Decoded")

ALL_GNSS = f"{ROOT}/*/gnss"
ALL_EVENTS = f"{ROOT}/*/health/events"
ALL_STATUS = f"{ROOT}/*/health/status"
SERVICES = f"{ROOT}/_service"
"""Where the instances speak of themselves (a vehicle id cannot start with ``_``)."""
ALL_ALIVE = f"{SERVICES}/*/alive"
LEASE_MS = 2000
"""The Zenoh lease of every session opened here: a peer silent this long (killed, stopped, cut off)
is closed by the other side, and its liveliness tokens go with it. Zenoh's default, 10 s, made a
stopped daemon look alive for 10 s; keep-alives go every quarter of it."""
SHARED_MEMORY = False
"""Zenoh's shared-memory transport, off in every session opened here (``transport/shared_memory/enabled``;
``extra`` may set it). On, each client on the host puts payloads over 3 KB (a frame of 20 samples is
about 1 KB, of 100 about 5.6 KB) in a 16 MB pool of its own in ``/dev/shm``, and the router maps
every pool it routes from and keeps it mapped after the client has gone: the router's resident
memory grew by about 100 MB per six publishers of 4,000 frames each (51 → 363 MB after three
rounds of ``benchmarks/bench_memory.py --flood``), where without it it stays at 51–53 MB. Frames are
small; loopback TCP carries them without it."""
DRAIN_TIMEOUT_S = 5.0
"""How long :meth:`FramePublisher.drain` waits for the router's answer (it comes in milliseconds)."""
_IMU_INDEX = re.compile(r"0|[1-9][0-9]{0,3}", re.ASCII)

Session: TypeAlias = zenoh.Session
"""An open Zenoh session (:func:`open_session`; a context manager that closes it)."""

ZenohError = zenoh.ZError
"""What Zenoh raises when an operation fails (e.g. a put on a session whose link is gone)."""

CongestionControl = zenoh.CongestionControl
"""What a publisher does when the link is congested: ``DROP`` (live data) or ``BLOCK`` (lossless)."""


# ----------------------------------------------------------------------------- keys


def frame_key(vehicle: str, imu: int) -> str:
    """``ins/<vehicle>/imu/<n>``."""
    return f"{ROOT}/{check_vehicle(vehicle, error=SchemaError)}/imu/{check_imu(imu, error=SchemaError)}"


def events_key(vehicle: str) -> str:
    """``ins/<vehicle>/health/events``."""
    return f"{ROOT}/{check_vehicle(vehicle, error=SchemaError)}/health/events"


def ack_key(vehicle: str) -> str:
    """``ins/<vehicle>/health/ack``: where acknowledgements are asked (and unnamed receivers answer)."""
    return f"{ROOT}/{check_vehicle(vehicle, error=SchemaError)}/health/ack"


def named_ack_key(vehicle: str, receiver: str) -> str:
    """``ins/<vehicle>/health/ack/<receiver>``: the key a named receiver answers on (module docstring)."""
    return f"{ack_key(vehicle)}/{check_receiver_name(receiver)}"


def status_key(vehicle: str) -> str:
    """``ins/<vehicle>/health/status``."""
    return f"{ROOT}/{check_vehicle(vehicle, error=SchemaError)}/health/status"


def alive_key(service: str, vehicle: str | None = None) -> str:
    """``ins/_service/<service>/alive``, the instance's liveliness token, or ``…/alive/<vehicle>``, one per vehicle it serves."""
    key = f"{SERVICES}/{check_service_name(service)}/alive"
    return key if vehicle is None else f"{key}/{check_vehicle(vehicle, error=SchemaError)}"


def service_status_key(service: str) -> str:
    """``ins/_service/<service>/status``."""
    return f"{SERVICES}/{check_service_name(service)}/status"


def frame_selectors(vehicles: Iterable[str] | None = None) -> tuple[str, ...]:
    """Frame key expressions for some vehicles (``None``: the whole fleet, ``ins/*/imu/*``)."""
    if vehicles is None:
        return (ALL_FRAMES,)
    return tuple(f"{ROOT}/{check_vehicle(v, error=SchemaError)}/imu/*" for v in vehicles)


def gnss_key(vehicle: str) -> str:
    """``ins/<vehicle>/gnss``."""
    return f"{ROOT}/{check_vehicle(vehicle, error=SchemaError)}/gnss"


def gnss_selector(frames_key: str) -> str:
    """The GNSS key expression beside a frame subscription: its vehicle chunk with ``gnss``
    (``ins/uav-7/imu/*`` → ``ins/uav-7/gnss``); the whole fleet's for any other shape."""
    parts = frames_key.split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[2] == "imu" and "*" not in parts[1][:1]:
        return f"{ROOT}/{parts[1]}/gnss"
    return ALL_GNSS


def parse_gnss_key(key: str) -> str:
    """The vehicle of a concrete GNSS key; :class:`~protocols.frames.FrameError` (``key_mismatch``) otherwise."""
    parts = str(key).split("/")
    if (
        len(parts) != 3
        or parts[0] != ROOT
        or parts[2] != "gnss"
        or not VEHICLE_ID_PATTERN.match(parts[1])
    ):
        raise FrameError(Reason.KEY_MISMATCH, f"{key!r} is not a GNSS key ins/<vehicle>/gnss")
    return parts[1]


def _frame_vehicle(key: str) -> str | None:
    """The vehicle of a frame key, None for a key that is not one (the decoder then says why)."""
    try:
        return parse_frame_key(key)[0]
    except FrameError:
        return None


def parse_frame_key(key: str) -> tuple[str, int]:
    """``(vehicle, imu)`` of a concrete frame key; raises :class:`~protocols.frames.FrameError` (``key_mismatch``) otherwise."""
    parts = str(key).split("/")
    # ASCII digits in canonical form only: str.isdigit() admits "²" (which int() refuses) and
    # "٣" or "03" (which int() reads as 3), aliases that access-control rules on plain keys miss.
    if (
        len(parts) != 4
        or parts[0] != ROOT
        or parts[2] != "imu"
        or _IMU_INDEX.fullmatch(parts[3]) is None
        or int(parts[3]) > MAX_IMU_INDEX
    ):
        raise FrameError(Reason.KEY_MISMATCH, f"{key!r} is not a frame key ins/<vehicle>/imu/<n>")
    if not VEHICLE_ID_PATTERN.match(parts[1]):
        raise FrameError(Reason.KEY_MISMATCH, f"{key!r} does not name a valid vehicle id")
    return parts[1], int(parts[3])


# --------------------------------------------------------------------------- config


ZENOH_MAX_MESSAGE_BYTES = MAX_MESSAGE_BYTES + 64 * 1024
"""Largest message a session reassembles: the largest payload a decoder accepts (frames, status)
plus room for Zenoh's own headers (key expression, encoding)."""


def zenoh_config(settings: ZenohSettings | Mapping[str, Any]) -> zenoh.Config:
    """A ``zenoh.Config`` from :class:`ZenohSettings` (or the plain dict it is read from)."""
    if not isinstance(settings, ZenohSettings):
        settings = ZenohSettings.from_dict(settings)
    entries: dict[str, Any] = {
        "mode": settings.mode.value,
        "scouting/multicast/enabled": settings.multicast_scouting,
    }
    if settings.connect:
        entries["connect/endpoints"] = list(settings.connect)
        # Keep trying instead of failing the service when the router is late.
        entries["connect/exit_on_failure"] = False
        entries["connect/timeout_ms"] = (
            -1 if settings.connect_timeout_s is None else int(settings.connect_timeout_s * 1000)
        )
    if settings.listen:
        entries["listen/endpoints"] = list(settings.listen)
    entries["transport/link/rx/max_message_size"] = ZENOH_MAX_MESSAGE_BYTES
    entries["transport/link/tx/lease"] = LEASE_MS
    entries["transport/shared_memory/enabled"] = SHARED_MEMORY
    if settings.tls is not None:
        entries["transport/link/tls"] = dict(settings.tls)
    if settings.access_control is not None:
        entries["access_control"] = dict(settings.access_control)
    entries.update(settings.extra)
    config = zenoh.Config()
    for key, value in entries.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            raise ValueError(f"zenoh rejects configuration {key} = {value!r}: {exc}") from None
    return config


def open_session(settings: ZenohSettings | Mapping[str, Any]) -> zenoh.Session:
    """Open a Zenoh session (a context manager: ``with open_session(cfg) as session``).

    Blocks in client mode until a router answers (module docstring); raises
    ``ConnectionError`` if ``connect_timeout_s`` passes first.
    """
    config = zenoh_config(settings)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ConnectionError(f"cannot open the zenoh session: {exc}") from None


def open_session_within(settings: ZenohSettings, timeout_s: float) -> zenoh.Session:
    """One attempt at opening a session that waits at most ``timeout_s`` for the ``connect`` endpoints.

    ``ConnectionError`` when no router answered in time (whatever ``settings.connect_timeout_s``
    says). ``zenoh.open`` cannot be interrupted, so a caller that must stay responsive while the
    router is away (the daemon: other inputs, SIGTERM) runs bounded attempts like this one in a
    worker thread, in a loop.
    """
    return open_session(dataclasses.replace(settings, connect_timeout_s=timeout_s))


def connected_nodes(session: zenoh.Session) -> list[str]:
    """The Zenoh ids of the routers and peers ``session`` is connected to now (empty: no link)."""
    info = session.info
    return [str(zid) for zid in [*info.routers_zid(), *info.peers_zid()]]


@contextmanager
def open_router(
    listen_endpoint: str,
    *,
    connect: Sequence[str] = (),
    extra: Mapping[str, Any] | None = None,
) -> Iterator[zenoh.Session]:
    """An in-process Zenoh router listening on ``listen_endpoint`` (e.g. ``tcp/127.0.0.1:7447``).

    ``connect`` lists other routers' endpoints to mesh with (SCALING.md).
    Multicast scouting is off; closing the context closes the router.
    """
    settings = ZenohSettings(
        mode=Mode.ROUTER, listen=(listen_endpoint,), connect=tuple(connect), extra=dict(extra or {})
    )
    session = open_session(settings)
    try:
        yield session
    finally:
        session.close()


def router_config_from_file(
    path: str | Path, *, listen: Sequence[str] = (), connect: Sequence[str] = ()
) -> zenoh.Config:
    """A router's ``zenoh.Config`` from a zenohd-style JSON5 file (``deploy/zenoh-router.json5``: its
    listen endpoints, TLS certificates, access control), ``listen`` and ``connect`` in place of its
    endpoints when given (zenohd's ``--listen`` and ``--connect``).

    Zenoh's shared memory is off whatever the file says (:data:`SHARED_MEMORY`). ``ValueError``
    naming the file for one Zenoh cannot read or that sets a mode other than router.
    """
    try:
        config = zenoh.Config.from_file(str(path))
        mode = json.loads(config.get_json("mode") or "null")
        if mode not in (None, Mode.ROUTER.value):
            raise ValueError(
                f'{path}: mode {mode!r}; a router\'s configuration says mode: "router"'
            )
        config.insert_json5("mode", json.dumps(Mode.ROUTER.value))
        # Whatever the file says (zenohd's default is on): the project's router bounds its memory.
        config.insert_json5("transport/shared_memory/enabled", json.dumps(SHARED_MEMORY))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except zenoh.ZError as exc:
        raise ValueError(f"{path}: not a Zenoh configuration Zenoh can use: {exc}") from None
    return config


def router_endpoints(config: zenoh.Config) -> list[str]:
    """The endpoints a router configuration listens on."""
    endpoints = json.loads(config.get_json("listen/endpoints") or "[]")
    # zenohd's form per mode ({"router": [...]}) as well as the plain list.
    if isinstance(endpoints, dict):
        endpoints = endpoints.get(Mode.ROUTER.value) or []
    return [str(e) for e in endpoints]


class _Declared(Protocol):
    """A declared Zenoh entity (subscriber, queryable, publisher): undeclared when done."""

    def undeclare(self) -> None: ...


def _matching(entity: zenoh.Publisher | zenoh.Querier) -> bool:
    # The stub says bool; zenoh 1.x returns a MatchingStatus carrying ``matching``.
    status: object = entity.matching_status
    return bool(getattr(status, "matching", status))


# ---------------------------------------------------------------------- frames in


@dataclass(frozen=True)
class SourceCounters:
    """A snapshot of what a source saw (all monotonic counts)."""

    received: int = 0
    accepted: int = 0
    dropped_overload: int = 0
    rejected: Mapping[str, int] = field(default_factory=dict)

    def as_dict(self, prefix: str = "frames") -> dict[str, int]:
        """Flat counters for the status topic: ``frames.received``, ``frames.rejected.non_finite``, …"""
        out = {
            f"{prefix}.received": self.received,
            f"{prefix}.accepted": self.accepted,
            f"{prefix}.dropped_overload": self.dropped_overload,
        }
        out.update(
            {f"{prefix}.rejected.{reason}": n for reason, n in sorted(self.rejected.items())}
        )
        return out


class _Subscriptions:
    """Zenoh subscribers feeding one set of queues (:class:`FrameSource`, :class:`GnssSource`)."""

    _subscribers: list[zenoh.Subscriber[None]]
    _ring: FairQueues[Any, Any]

    def close(self) -> None:
        """Undeclare the subscribers; a waiting consumer finishes what is queued, then stops."""
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []
        self._ring.close()


class FrameSource(_Subscriptions, BatchSource):
    """IMU frames from Zenoh as validated :class:`~protocols.frames.SampleBatch` values, for asyncio.

    Use as ``async for batch in source`` or ``await source.get()``; create it
    inside the running loop (or pass ``loop``). Payloads are copied out of
    Zenoh's callback thread into one queue per (vehicle, IMU) of its key
    (:class:`~protocols._handoff.FairQueues`: the drop policy) and decoded by the
    consumer, the units taken in turn, so a flood costs the receiving thread only a
    copy and no other unit its frames. Rejected frames (bad bytes, or a payload whose vehicle/imu differ
    from its key: ``key_mismatch``; a vehicle of ``refused_vehicles``, fed by another input: ``other_source``,
    refused unread) are counted by reason in :attr:`counters`
    and reported to ``on_reject`` (an ``(key, FrameError)`` callable, called in
    the consumer); they never stop the source.

    Parameters
    ----------
    session : an open Zenoh session.
    key_exprs : frame key expressions, default the whole fleet (:func:`frame_selectors`).
    capacity : frames held per (vehicle, IMU) between Zenoh and the pipeline; beyond it new frames are
        dropped and counted (:attr:`dropped_by_unit`).
    total : frames held for all units together; beyond it a unit over its fair share loses its newest.
    max_frame_bytes : size limit passed to :func:`~protocols.frames.decode_frame`.
    refused_vehicles : vehicles whose frames are refused here: another input owns their streams
        (the vehicle the daemon's MAVLink link feeds), and frames from anyone on the router would be
        merged into them. Held, not copied: a vehicle added later is refused from then on.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_exprs: Sequence[str] = (ALL_FRAMES,),
        *,
        capacity: int = 256,
        total: int = 4096,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        on_reject: Callable[[str, FrameError], None] | None = None,
        loop: asyncio.AbstractEventLoop | None = None,
        refused_vehicles: Collection[str] = (),
    ):
        self._refused_vehicles = refused_vehicles
        self._ring: FairQueues[tuple[str, int] | None, tuple[str, bytes]] = FairQueues(
            capacity, total, loop or asyncio.get_running_loop()
        )
        self._max_bytes = int(max_frame_bytes)
        self._on_reject = on_reject
        self._accepted = 0
        self._rejected: dict[str, int] = {}
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in key_exprs]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            unit: tuple[str, int] | None = parse_frame_key(key)
        except FrameError:
            # Queued together, and refused by the decoder in turn.
            unit = None
        if unit is not None and unit[0] in self._refused_vehicles:
            # Refused in turn too (the consumer counts and reports), never in the owner's queue.
            unit = None
        self._ring.put(unit, (key, sample.payload.to_bytes()))

    @property
    def counters(self) -> SourceCounters:
        received, dropped = self._ring.counts()
        return SourceCounters(
            sum(received.values()), self._accepted, sum(dropped.values()), dict(self._rejected)
        )

    def unit_counts(self) -> tuple[dict[tuple[str, int], int], dict[tuple[str, int], int]]:
        """Frames that came for each (vehicle, IMU), dropped ones included, and those dropped
        (its queue, or the instance's, full)."""
        received, dropped = self._ring.counts()
        return (
            {k: n for k, n in received.items() if k is not None},
            {k: n for k, n in dropped.items() if k is not None},
        )

    def queued_of(self, vehicle: str, imu: int) -> int:
        """Frames of the unit waiting to be taken."""
        return self._ring.queued((vehicle, imu))

    async def get(self) -> SampleBatch:
        """The next valid frame (waits; rejected frames are counted and skipped); ``EOFError`` after :meth:`close`."""
        while True:
            batch = self._decode(*await self._ring.get())
            if batch is not None:
                return batch

    def get_nowait(self) -> SampleBatch | None:
        """The next valid frame if one is queued, else ``None``."""
        while (item := self._ring.get_nowait()) is not None:
            batch = self._decode(*item)
            if batch is not None:
                return batch
        return None

    def _decode(self, key: str, payload: bytes) -> SampleBatch | None:
        try:
            owner = _frame_vehicle(key)
            if owner in self._refused_vehicles:
                raise FrameError(
                    Reason.OTHER_SOURCE,
                    f"vehicle {owner} is fed by another input (MAVLink): its frames on Zenoh are refused",
                )
            batch = decode_frame(payload, max_bytes=self._max_bytes)
            if parse_frame_key(key) != (batch.vehicle, batch.imu):
                raise FrameError(
                    Reason.KEY_MISMATCH,
                    f"frame of {batch.vehicle}/imu {batch.imu} published on {key}",
                )
        except FrameError as exc:
            self._rejected[exc.reason.value] = self._rejected.get(exc.reason.value, 0) + 1
            if self._on_reject is not None:
                self._on_reject(key, exc)
            return None
        self._accepted += 1
        return batch

    @property
    def queued(self) -> int:
        return len(self._ring)


class GnssSource(_Subscriptions):
    """GNSS frames from Zenoh as validated :class:`~protocols.gnss_frames.GnssFrame` values, for
    asyncio: payloads copied from Zenoh's thread into one bounded queue per vehicle (its newest
    dropped when full, counted) and decoded by the consumer; a frame that fails its check, or names
    another vehicle than its key, is counted by reason and told to ``on_reject``."""

    def __init__(
        self,
        session: zenoh.Session,
        key_exprs: Iterable[str],
        *,
        capacity: int = 1024,
        total: int = 16384,
        on_reject: Callable[[str, FrameError], None] | None = None,
        loop: asyncio.AbstractEventLoop | None = None,
    ):
        # A frame is a few hundred bytes: 100 s of a 10 Hz receiver's single-epoch frames a vehicle
        # ride out the IMU frames' groups that hold the fleet's lock.
        self._ring: FairQueues[str, tuple[str, bytes]] = FairQueues(
            capacity, total, loop or asyncio.get_running_loop()
        )
        self._on_reject = on_reject
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in key_exprs]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        self._ring.put(key, (key, sample.payload.to_bytes()))

    @property
    def dropped(self) -> int:
        return sum(self._ring.counts()[1].values())

    async def get(self) -> GnssFrame:
        """The next valid frame (waits); ``EOFError`` after :meth:`close`."""
        while True:
            key, payload = await self._ring.get()
            try:
                frame = decode_gnss_frame(payload)
                if parse_gnss_key(key) != frame.vehicle:
                    raise FrameError(
                        Reason.KEY_MISMATCH, f"GNSS frame of {frame.vehicle} published on {key}"
                    )
            except FrameError as exc:
                self.rejected[exc.reason.value] = self.rejected.get(exc.reason.value, 0) + 1
                if self._on_reject is not None:
                    self._on_reject(key, exc)
                continue
            self.accepted += 1
            return frame


class GnssPublisher:
    """Publishes one vehicle's receiver velocity as GNSS frames (``seq`` +1 a frame; DROP, as IMU
    frames: a congested link sheds them rather than block the vehicle)."""

    def __init__(self, session: zenoh.Session, vehicle: str, *, rate_hz: float):
        self.vehicle, self.rate_hz, self.seq = vehicle, float(rate_hz), 0
        self._publisher = session.declare_publisher(
            gnss_key(vehicle), congestion_control=zenoh.CongestionControl.DROP
        )

    def publish(self, t_s: np.ndarray, vel_enu_mps: np.ndarray) -> None:
        frame = GnssFrame(self.vehicle, self.seq, self.rate_hz, t_s, vel_enu_mps)
        self._publisher.put(encode_gnss_frame(frame))
        self.seq += 1

    def close(self) -> None:
        self._publisher.undeclare()


# ---------------------------------------------------------------------- frames out


class FramePublisher:
    """Publishes one IMU's samples as frames of up to ``batch_samples`` samples.

    :meth:`add` buffers samples and publishes every full batch; :meth:`flush`
    publishes the rest (also done by :meth:`close`). ``seq`` counts frames from
    ``first_seq``. Frames use ``CongestionControl.DROP`` (module docstring).
    :meth:`close` also waits for the router to hold every frame (:meth:`drain`),
    so closing the session next loses none.
    """

    def __init__(
        self,
        session: zenoh.Session,
        vehicle: str,
        imu: int,
        *,
        batch_samples: int = 100,
        dtype: SampleDtype = SampleDtype.F64,
        first_seq: int = 0,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.DROP,
    ):
        if batch_samples < 1:
            raise ValueError(f"batch_samples must be >= 1, got {batch_samples}")
        self.vehicle, self.imu = vehicle, imu
        self._session = session
        self._key = frame_key(vehicle, imu)
        self._publisher = session.declare_publisher(
            self._key, congestion_control=congestion_control
        )
        self._batch = int(batch_samples)
        self._dtype = SampleDtype(dtype)
        self.seq = int(first_seq)
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._buffered = 0
        self.frames_published = 0
        self.confirmed: bool | None = None

    def add(
        self,
        t_s: ArrayLike,
        accel_mps2: ArrayLike,
        gyro_rps: ArrayLike,
        temp_c: ArrayLike | None = None,
    ) -> int:
        """Buffer samples (one: scalars and (3,) vectors; many: (N,), (N, 3)); returns frames published."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        a = np.asarray(accel_mps2, dtype=float).reshape(-1, 3)
        g = np.asarray(gyro_rps, dtype=float).reshape(-1, 3)
        tc = None if temp_c is None else np.atleast_1d(np.asarray(temp_c, dtype=float))
        if not (
            a.shape[0] == g.shape[0] == t.shape[0] and (tc is None or tc.shape[0] == t.shape[0])
        ):
            raise ValueError(
                f"sample counts differ: t_s {t.shape[0]}, accel {a.shape[0]}, gyro {g.shape[0]}"
            )
        if self._parts and (self._parts[0][3] is None) != (tc is None):
            raise ValueError("temperature must be given for every sample of a frame or for none")
        self._parts.append((t, a, g, tc))
        self._buffered += t.shape[0]
        if self._buffered < self._batch:
            return 0
        # Join once, then cut full frames: cost linear in the samples however they arrive.
        t, a, g, tc = self._joined()
        n_full = self._buffered // self._batch
        for k in range(n_full):
            cut = slice(k * self._batch, (k + 1) * self._batch)
            self.publish(
                SampleBatch(
                    self.vehicle,
                    self.imu,
                    self.seq,
                    t[cut],
                    a[cut],
                    g[cut],
                    None if tc is None else tc[cut],
                )
            )
        rest = slice(n_full * self._batch, None)
        self._parts = (
            [(t[rest], a[rest], g[rest], None if tc is None else tc[rest])]
            if self._buffered % self._batch
            else []
        )
        self._buffered %= self._batch
        return n_full

    def flush(self) -> int:
        """Publish buffered samples as one frame (if any); returns frames published."""
        if not self._buffered:
            return 0
        t, a, g, tc = self._joined()
        self._parts, self._buffered = [], 0
        self.publish(SampleBatch(self.vehicle, self.imu, self.seq, t, a, g, tc))
        return 1

    def _joined(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        t, a, g = (np.concatenate([p[i] for p in self._parts]) for i in range(3))
        return (
            t,
            a,
            g,
            None if self._parts[0][3] is None else np.concatenate([p[3] for p in self._parts]),
        )

    @property
    def matched(self) -> bool:
        """Whether Zenoh currently routes these frames to at least one subscriber."""
        return _matching(self._publisher)

    def publish(self, batch: SampleBatch) -> None:
        """Publish one ready batch as it is (its own ``seq``); advances :attr:`seq` past it."""
        self._publisher.put(encode_frame(batch, dtype=self._dtype))
        self.seq = batch.seq + 1
        self.frames_published += 1

    def drain(self, timeout_s: float = DRAIN_TIMEOUT_S) -> bool:
        """Wait until the router holds every frame published so far: True, or False after ``timeout_s``.

        False means no router or peer is connected, or none answered in time.

        ``put`` returns once a frame is in the session's transmission queue, and
        closing a session drops what that queue still holds: measured on
        127.0.0.1, 0 to 35 of 500 queued 6 kB frames had reached the router when
        ``put`` of the last returned, and with a subscriber taking 2 ms a frame the
        tail of 108 frames was lost in 4 of 70 closes. Zenoh has no flush, but a
        query on the frame key travels on the same link and priority behind the
        frames, and the router answers it (a final reply, no queryable needed)
        only after it has taken them.
        """
        info = self._session.info
        if not (info.routers_zid() or info.peers_zid()):
            return False  # with no link, the query is answered at once, by this session
        return all(
            reply.ok is not None for reply in self._session.get(self._key, timeout=timeout_s)
        )

    def close(self) -> None:
        """Publish the rest, :meth:`drain` (its answer in :attr:`confirmed`), undeclare."""
        self.flush()
        self.confirmed = self.drain()
        self._publisher.undeclare()

    def __enter__(self) -> FramePublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------- events out


@dataclass(frozen=True)
class Acknowledgement:
    """Who answered an acknowledgement query.

    Attributes
    ----------
    receiver : the receiver's name, the last chunk of the key it answered on
        (``ins/<vehicle>/health/ack/<receiver>``); ``None`` for an unnamed receiver
        (``ins/<vehicle>/health/ack``). Under the deploy's access control a name is bound to a
        certificate: only that certificate's holder may answer on that key.
    zid : the Zenoh id of the answering session (``Reply.replier_id``).
    """

    receiver: str | None
    zid: str

    def __str__(self) -> str:
        name = "an unnamed receiver" if self.receiver is None else self.receiver
        return f"{name} (zenoh id {self.zid})"


def _acknowledgement(reply: zenoh.Reply, vehicle: str) -> Acknowledgement | None:
    """Who answered, from the reply's key; None for a key that is not the vehicle's acknowledgement key."""
    assert reply.ok is not None
    key, own = str(reply.ok.key_expr), ack_key(vehicle)
    replier = reply.replier_id
    zid = "unknown" if replier is None else str(replier.zid)
    if key == own:
        return Acknowledgement(None, zid)
    name = key[len(own) + 1 :]
    if key.startswith(own + "/") and VEHICLE_ID_PATTERN.fullmatch(name):
        return Acknowledgement(name, zid)
    return None


def distinct_receivers(acks: Iterable[Acknowledgement]) -> int:
    """How many distinct receivers answered: a receiver is new only with a name *and* a Zenoh id not
    counted yet (one session answering under two names counts once, and so do two sessions
    claiming one name); an unnamed receiver is named by its Zenoh id."""
    acks = list(acks)
    names = {a.receiver if a.receiver is not None else f"zid:{a.zid}" for a in acks}
    return min(len(names), len({a.zid for a in acks}))


class EventPublisher:
    """Publishes events reliably (``CongestionControl.BLOCK``) and reports whether each was acknowledged.

    :meth:`publish` blocks (up to ``ack_timeout_s`` plus the BLOCK wait):
    call it from a worker thread (``asyncio.to_thread``) in a service.

    ``min_acks`` distinct receivers (:func:`distinct_receivers`) must acknowledge an event; with
    ``ack_from`` only receivers of those names count, and any other answer is refused: counted in
    :attr:`refused`, the last one kept in :attr:`last_refused`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        *,
        ack: AckMode = AckMode.RECEIVER,
        ack_timeout_s: float = 1.0,
        min_acks: int = 1,
        ack_from: Iterable[str] = (),
    ):
        if min_acks < 1 or ack_timeout_s <= 0:
            raise ValueError(
                f"need min_acks >= 1 and ack_timeout_s > 0, got {min_acks}, {ack_timeout_s}"
            )
        self._session = session
        self._ack = AckMode(ack)
        self._timeout_s = float(ack_timeout_s)
        self._min_acks = int(min_acks)
        self._ack_from = frozenset(check_receiver_name(n) for n in ack_from)
        self._entities: dict[str, tuple[zenoh.Publisher, zenoh.Querier]] = {}
        self._lock = threading.Lock()
        self.refused = 0
        self.last_refused: Acknowledgement | None = None

    def _declared(self, vehicle: str) -> tuple[zenoh.Publisher, zenoh.Querier]:
        with self._lock:
            pair = self._entities.get(vehicle)
            if pair is None:
                pair = (
                    self._session.declare_publisher(
                        events_key(vehicle),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        reliability=zenoh.Reliability.RELIABLE,
                        priority=zenoh.Priority.DATA_HIGH,
                    ),
                    # Named receivers answer on a key below the one asked (EventReceiver).
                    self._session.declare_querier(
                        ack_key(vehicle),
                        accept_replies=zenoh.ReplyKeyExpr.ANY,
                        target=zenoh.QueryTarget.ALL,
                        consolidation=zenoh.ConsolidationMode.NONE,
                        timeout=self._timeout_s,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        priority=zenoh.Priority.DATA_HIGH,
                    ),
                )
                self._entities[vehicle] = pair
            return pair

    def ready(self, vehicle: str) -> bool:
        """Whether Zenoh currently routes this vehicle's events to anyone who can acknowledge them.

        :attr:`AckMode.RECEIVER`: an acknowledging :class:`EventReceiver` is
        reachable; :attr:`AckMode.MATCHED`: a subscriber is. (A hint for the
        status topic and for waiting in tests; :meth:`publish` is the proof.)
        """
        pub, querier = self._declared(vehicle)
        return _matching(querier if self._ack is AckMode.RECEIVER else pub)

    def publish(self, event: Event, *, on_put: Callable[[], None] | None = None) -> bool:
        """Put the event on its events key and return True iff it is acknowledged (:class:`AckMode`).

        ``on_put`` is called once the put has returned, before the wait for acknowledgements.
        """
        payload = encode_event(event)
        pub, querier = self._declared(event.vehicle)
        pub.put(payload)
        if on_put is not None:
            on_put()
        if self._ack is AckMode.MATCHED:
            return _matching(pub)
        expected = event.event_id.encode()
        counted = []
        for reply in querier.get(payload=payload):
            if reply.ok is None or reply.ok.payload.to_bytes() != expected:
                continue
            ack = _acknowledgement(reply, event.vehicle)
            if ack is None:
                continue
            if self._ack_from and ack.receiver not in self._ack_from:
                with self._lock:
                    self.refused += 1
                    self.last_refused = ack
                continue
            counted.append(ack)
        return distinct_receivers(counted) >= self._min_acks

    def close(self) -> None:
        with self._lock:
            for pub, querier in self._entities.values():
                pub.undeclare()
                querier.undeclare()
            self._entities.clear()

    def __enter__(self) -> EventPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventReceiver:
    """The receiving side of events: subscribes, deduplicates by id, acknowledges (module docstring).

    ``on_event`` is called once per event id (from a Zenoh thread; keep it
    short or hand over to your own queue). An event is taken, and acknowledged, only once
    ``on_event`` has returned: if it raises, the event is not remembered, the acknowledgement
    query is answered with an error (the publisher retries) and the next copy is handed over
    again; such failures are counted in :attr:`failed`. Ids are remembered up to
    ``dedup_capacity`` (oldest forgotten first). Undecodable payloads are
    counted in :attr:`rejected` by reason and answered with an error reply.

    Parameters
    ----------
    vehicles : a vehicle id or a chunk pattern (``"*"``, ``"fleetA-$*"``) selecting whose events to receive.
    acknowledge : declare the ack queryable (be one of the ``min_acks`` receivers).
    name : answer as this receiver: on ``ins/<vehicle>/health/ack/<name>`` (:class:`Acknowledgement`),
        not on the key asked; a publisher's ``ack_from`` counts only named receivers it lists.
        ``None``: unnamed (and counted by its Zenoh id).
    """

    def __init__(
        self,
        session: zenoh.Session,
        on_event: Callable[[Event], None],
        *,
        vehicles: str = "*",
        acknowledge: bool = True,
        name: str | None = None,
        dedup_capacity: int = 100_000,
    ):
        self._on_event = on_event
        self._seen: OrderedDict[str, None] = OrderedDict()
        self._capacity = int(dedup_capacity)
        self._lock = threading.Lock()
        self.name = None if name is None else check_receiver_name(name)
        self.received = 0
        self.duplicates = 0
        self.failed = 0
        self.rejected: dict[str, int] = {}
        self._entities: list[_Declared] = [
            session.declare_subscriber(f"{ROOT}/{vehicles}/health/events", self._on_sample)
        ]
        if acknowledge:
            self._entities.append(
                session.declare_queryable(f"{ROOT}/{vehicles}/health/ack", self._on_query)
            )

    def _accept(self, payload: bytes) -> Event | None:
        """The event, once handed over (now or before); None when ``on_event`` raised."""
        event = decode_event(payload)
        # One lock around check-and-deliver: the subscriber and the queryable
        # threads may carry the same event at the same time.
        with self._lock:
            if event.event_id in self._seen:
                self.duplicates += 1
                return event
            try:
                self._on_event(event)
            except Exception:  # the application did not take it: not remembered, asked again
                self.failed += 1
                return None
            self._seen[event.event_id] = None
            if len(self._seen) > self._capacity:
                self._seen.popitem(last=False)
            self.received += 1
        return event

    def _reject(self, exc: EventError) -> None:
        with self._lock:
            self.rejected[exc.reason.value] = self.rejected.get(exc.reason.value, 0) + 1

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self._accept(sample.payload.to_bytes())
        except EventError as exc:
            self._reject(exc)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        if payload is None:
            query.reply_err(b"no event in the acknowledgement query")
            return
        try:
            event = self._accept(payload.to_bytes())
        except EventError as exc:
            self._reject(exc)
            query.reply_err(str(exc).encode())
            return
        if event is None:
            query.reply_err(b"the application did not take the event")
            return
        key = (
            ack_key(event.vehicle) if self.name is None else named_ack_key(event.vehicle, self.name)
        )
        query.reply(key, event.event_id.encode())

    @property
    def seen_ids(self) -> set[str]:
        with self._lock:
            return set(self._seen)

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()
        self._entities = []

    def __enter__(self) -> EventReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------- status


class StatusPublisher:
    """Publishes :class:`~protocols.events.Status` on ``ins/<vehicle>/health/status`` and the
    instance's :class:`~protocols.events.ServiceStatus` on ``ins/_service/<service>/status``, and
    answers a query of a vehicle's status (:func:`query_status`) with the last one published.

    Liveliness: the instance's token (:func:`alive_key`) from the start, and one per vehicle once
    its status is published; Zenoh withdraws them when the session ends or its lease expires
    (:data:`LEASE_MS`), so a subscriber (:func:`subscribe_alive`) sees a killed or stopped
    instance go.

    Status is periodic and the latest one supersedes the others, so it uses
    ``CongestionControl.DROP``; the service's clock decides the period.
    """

    def __init__(self, session: zenoh.Session, service: str):
        self._session = session
        self._service = service
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._last: dict[str, bytes] = {}
        self._tokens = [session.liveliness().declare_token(alive_key(service))]
        self._vehicle_tokens: dict[str, zenoh.LivelinessToken] = {}
        self._service_pub = session.declare_publisher(
            service_status_key(service), congestion_control=zenoh.CongestionControl.DROP
        )
        self._queryable = session.declare_queryable(ALL_STATUS, self._answer)

    def publish(self, status: Status) -> None:
        pub = self._publishers.get(status.vehicle)
        if pub is None:
            pub = self._session.declare_publisher(
                status_key(status.vehicle), congestion_control=zenoh.CongestionControl.DROP
            )
            self._publishers[status.vehicle] = pub
            self._vehicle_tokens[status.vehicle] = self._session.liveliness().declare_token(
                alive_key(self._service, status.vehicle)
            )
        payload = encode_status(status)
        self._last[status.vehicle] = payload
        pub.put(payload)

    def publish_service(self, status: ServiceStatus) -> None:
        self._service_pub.put(encode_service_status(status))

    def _answer(self, query: zenoh.Query) -> None:
        # Zenoh's thread: the payload is bytes already encoded by the loop.
        key = str(query.key_expr)
        parts = key.split("/")
        payload = self._last.get(parts[1]) if len(parts) == 4 else None
        if payload is not None:
            query.reply(key, payload)

    def close(self) -> None:
        self._queryable.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        self._service_pub.undeclare()
        for token in [*self._tokens, *self._vehicle_tokens.values()]:
            token.undeclare()
        self._tokens, self._vehicle_tokens = [], {}

    def __enter__(self) -> StatusPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def subscribe_status(
    session: zenoh.Session,
    on_status: Callable[[Status], None],
    *,
    vehicles: str = "*",
    on_reject: Callable[[EventError], None] | None = None,
) -> zenoh.Subscriber[None]:
    """Subscribe to status messages (``ins/<vehicles>/health/status``); undecodable ones go to ``on_reject``.

    Returns the subscriber (undeclare it, or use it as a context manager, to stop).
    """

    return _decoding_subscriber(
        session, f"{ROOT}/{vehicles}/health/status", decode_status, on_status, on_reject
    )


def _decoding_subscriber(
    session: zenoh.Session,
    key: str,
    decode: Callable[[bytes], _Decoded],
    on_value: Callable[[_Decoded], None],
    on_reject: Callable[[EventError], None] | None,
) -> zenoh.Subscriber[None]:
    """A subscriber on ``key`` handing each sample ``decode``d to ``on_value``, what does not decode to
    ``on_reject`` (or nowhere)."""

    def callback(sample: zenoh.Sample) -> None:
        try:
            value = decode(sample.payload.to_bytes())
        except EventError as exc:
            if on_reject is not None:
                on_reject(exc)
            return
        on_value(value)

    return session.declare_subscriber(key, callback)


def query_status(session: zenoh.Session, vehicle: str, *, timeout_s: float) -> list[Status]:
    """The last status of ``vehicle`` from each instance that serves it (:class:`StatusPublisher`),
    asked now; empty when none answers within ``timeout_s`` (undecodable answers are left out)."""
    statuses = []
    for reply in session.get(status_key(vehicle), timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            statuses.append(decode_status(reply.ok.payload.to_bytes()))
        except EventError:
            continue
    return statuses


def subscribe_alive(
    session: zenoh.Session, on_change: Callable[[str, bool], None]
) -> zenoh.Subscriber[None]:
    """Follow the instances' liveliness (:func:`alive_key`): ``on_change(service, alive)`` for each
    instance alive when subscribing, and each time one goes (``False``) or comes (``True``)."""

    def callback(sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).split("/")[2]
        on_change(service, sample.kind == zenoh.SampleKind.PUT)

    return session.liveliness().declare_subscriber(ALL_ALIVE, callback, history=True)


def subscribe_service_status(
    session: zenoh.Session,
    on_status: Callable[[ServiceStatus], None],
    *,
    on_reject: Callable[[EventError], None] | None = None,
) -> zenoh.Subscriber[None]:
    """Subscribe to the instances' service status (``ins/_service/*/status``)."""
    return _decoding_subscriber(
        session, f"{SERVICES}/*/status", decode_service_status, on_status, on_reject
    )
