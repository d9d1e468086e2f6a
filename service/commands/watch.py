"""``ins-health watch [--vehicle V] [--receiver NAME] [--json] [--router ENDPOINT]``: a deployed daemon's events and status, as a ground station sees them.

Connects to the Zenoh router, subscribes to the events and the status of the
vehicles ``V`` (a vehicle id or a pattern such as ``fleetA-$*``; default all)
and acknowledges each event the way a ground station does
(:class:`protocols.zenoh_adapter.EventReceiver`): the daemon counts an event as
delivered once a receiver acknowledged it and retries it until then, and the
receiver drops repeats by id, so each event is printed once. With ``--receiver
NAME`` it acknowledges as that ground station (a daemon's ``[zenoh] ack_from``
counts only the names it lists).

One line per event: the time it arrived (UTC), vehicle, IMU, severity, its data
time and its text; with ``--json`` the event as one JSON object per line (the
event schema of :mod:`protocols.events`, ``"type": "ins.health.event"``).
Status messages are summarized: a line when a service first reports a vehicle
and whenever the states of its IMUs change, a check starts or stops running on
one of them (each IMU's line says which checks have tested it and which have not,
and why), or its outbox becomes unavailable (the line then says so, with the
events held) or available again (``--json``: the status map, ``"type":
"ins.health.status"``). Frames the daemon dropped, its queue of the IMU full, are said on the
vehicle's line (``frames dropped: IMU0 152``), and a line comes whenever more are.

Each daemon instance is followed by its Zenoh liveliness token: ``daemon NAME alive`` when first
seen, ``daemon NAME lost`` within the 2 s Zenoh lease of a kill -9, a stopped process (SIGSTOP)
or a network cut (measured: 0.02 s after kill -9, 2.0 s after SIGSTOP), ``daemon NAME back``
when it returns. An instance's own status (the vehicles it serves, none
at first) is summarized as ``daemon NAME serves …`` when first seen and when its vehicles change.

Runs until Ctrl-C or SIGTERM, then prints what it received on stderr. Exit
status 0; 2 when the router cannot be reached or an option is unusable.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, NamedTuple

from service.router_args import add_router_arguments, open_router_session

if TYPE_CHECKING:
    from queue import SimpleQueue

    from protocols.events import Event, ServiceStatus, Status


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "watch",
        help="print a deployed daemon's events (acknowledged as a ground station does) and status changes",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--vehicle",
        default="*",
        metavar="V",
        help="a vehicle id or a pattern such as 'fleetA-$*' (default: every vehicle)",
    )
    p.add_argument(
        "--receiver",
        metavar="NAME",
        help="acknowledge as this ground station (counted by a daemon whose [zenoh] ack_from names "
        "it; under the fleet router's access control, the name of this host's certificate); "
        "default: unnamed",
    )
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    add_router_arguments(p)
    p.set_defaults(func=run)


class _Stop:
    """Put on the queue by the SIGINT/SIGTERM handler: the watch ends after what came before it."""


class _Alive(NamedTuple):
    """An instance's liveliness token came (``alive``) or went."""

    service: str
    alive: bool


def _utc(t_unix_s: float) -> str:
    return (
        time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t_unix_s))
        + f".{int(t_unix_s % 1 * 1000):03d}Z"
    )


def event_line(event: Event, arrived_unix_s: float) -> str:
    """The human line of an event: arrival (UTC), vehicle, IMU, severity, data time, text."""
    return (
        f"{_utc(arrived_unix_s)}  {event.vehicle} IMU{event.imu}  {event.severity.name:<8s}"
        f"  t={event.t_s:.3f} s  {event.text}"
    )


def status_line(status: Status, arrived_unix_s: float) -> str:
    """The human summary of a status: each IMU's state, samples and positions, and its coverage."""
    from estimators.coverage import ImuCoverage

    imus = "; ".join(
        f"IMU{s.imu} {s.state.value} ({s.samples} samples, {s.positions} positions"
        + (f", {s.detail}" if s.detail else "")
        + (f"; {ImuCoverage(s.imu, s.coverage).summary()}" if s.coverage else "")
        + (
            "; checks unknown to this watch (a newer daemon's): "
            + ", ".join(str(c["check"]) for c in s.unknown_coverage)
            if s.unknown_coverage
            else ""
        )
        + ")"
        for s in status.imus
    )
    line = f"{_utc(arrived_unix_s)}  {status.vehicle} status from {status.service}: {imus or 'no IMU yet'}"
    if dropped := frames_dropped(status):
        line += "; frames dropped: " + ", ".join(f"IMU{i} {n}" for i, n in dropped.items())
    if status.counters.get("service.outbox.unavailable"):
        line += (
            f"; outbox unavailable ({status.counters.get('service.outbox.held_events', 0)} events held,"
            f" {status.counters.get('service.outbox.write_failures', 0)} writes failed)"
        )
    return line


def frames_dropped(status: Status) -> dict[int, int]:
    """IMU → frames the daemon dropped, its queue full (``imu<n>.frames.dropped_overload``), those with any."""
    out = {}
    for name, n in status.counters.items():
        imu, _, rest = name.partition(".")
        if rest == "frames.dropped_overload" and n and imu[3:].isdigit():
            out[int(imu[3:])] = n
    return dict(sorted(out.items()))


def service_line(status: ServiceStatus, arrived_unix_s: float) -> str:
    """The human summary of an instance's own status: the vehicles it serves."""
    served = ", ".join(status.vehicles) if status.vehicles else "no vehicle yet"
    return f"{_utc(arrived_unix_s)}  daemon {status.service} serves {served}"


def _show(inbox: SimpleQueue[object], *, as_json: bool) -> tuple[int, int]:
    """Print what arrives until a :class:`_Stop`; returns (events, status messages) received."""
    import json

    from protocols.events import Event, ServiceStatus, Status, event_to_json, status_to_dict

    states: dict[tuple[str, str], tuple[object, ...]] = {}
    alive: dict[str, bool] = {}
    served: dict[str, tuple[str, ...]] = {}
    events = statuses = 0
    while not isinstance(item := inbox.get(), _Stop):
        now = time.time()
        if isinstance(item, _Alive):
            word = "alive" if item.service not in alive else ("back" if item.alive else "lost")
            if alive.get(item.service) != item.alive:
                alive[item.service] = item.alive
                print(
                    json.dumps(
                        {"type": "ins.health.liveliness", "service": item.service, "state": word}
                    )
                    if as_json
                    else f"{_utc(now)}  daemon {item.service} {word}",
                    flush=True,
                )
        elif isinstance(item, ServiceStatus):
            if served.get(item.service) != item.vehicles:
                served[item.service] = item.vehicles
                print(
                    json.dumps({"type": "ins.health.service_status", "service": item.service,
                                "vehicles": list(item.vehicles), "counters": dict(item.counters)})
                    if as_json
                    else service_line(item, now),
                    flush=True,
                )  # fmt: skip
        elif isinstance(item, Event):
            events += 1
            print(event_to_json(item) if as_json else event_line(item, now), flush=True)
        elif isinstance(item, Status):
            statuses += 1
            summary = (
                tuple((s.imu, s.state.value) for s in item.imus),
                tuple((s.imu, c.name, c.ran) for s in item.imus for c in s.coverage),
                item.counters.get("service.outbox.unavailable", 0),
                tuple(frames_dropped(item).items()),
            )
            if states.get((item.vehicle, item.service)) != summary:
                states[(item.vehicle, item.service)] = summary
                line = (
                    json.dumps(status_to_dict(item), sort_keys=True)
                    if as_json
                    else status_line(item, now)
                )
                print(line, flush=True)
    return events, statuses


def run(args: argparse.Namespace) -> int:
    import queue
    import signal

    from protocols.events import EventError
    from protocols.zenoh_adapter import (
        EventReceiver,
        subscribe_alive,
        subscribe_service_status,
        subscribe_status,
    )

    # Handed over from Zenoh's threads and from the signal handler (SimpleQueue.put is reentrant).
    inbox: queue.SimpleQueue[object] = queue.SimpleQueue()
    bad_status: list[EventError] = []
    previous = {
        sig: signal.signal(sig, lambda *_: inbox.put(_Stop()))
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        with (
            open_router_session(args) as session,
            EventReceiver(
                session, inbox.put, vehicles=args.vehicle, name=args.receiver
            ) as receiver,
        ):
            subs = [
                subscribe_status(
                    session, inbox.put, vehicles=args.vehicle, on_reject=bad_status.append
                ),
                subscribe_service_status(session, inbox.put, on_reject=bad_status.append),
                subscribe_alive(session, lambda service, up: inbox.put(_Alive(service, up))),
            ]
            print(
                f"ins-health watch: {args.router}, vehicles {args.vehicle}: waiting for events",
                file=sys.stderr,
                flush=True,
            )
            try:
                events, statuses = _show(inbox, as_json=args.json)
            finally:
                for sub in subs:
                    sub.undeclare()
            rejected = dict(receiver.rejected)
            duplicates = receiver.duplicates
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(
        f"ins-health watch: {events} events ({duplicates} repeated copies ignored, rejected {rejected or 'none'}), "
        f"{statuses} status messages ({len(bad_status)} rejected)",
        file=sys.stderr,
    )
    return 0
