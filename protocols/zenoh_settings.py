"""The Zenoh transport's settings and names, without eclipse-zenoh.

:class:`ZenohSettings` (the ``[zenoh]`` table of the service configuration), :class:`Mode`,
:class:`AckMode`, the key root and the checks of a frame selector, receiver and instance name:
what the service's configuration shares with :mod:`protocols.zenoh_adapter`, without importing
zenoh (and asyncio and ssl with it: 0.02 s of CPU with the bytecode cached), which a replay,
reading its configuration, never uses.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from protocols._schema import VEHICLE_ID_PATTERN

ROOT = "ins"
ALL_FRAMES = f"{ROOT}/*/imu/*"


def check_receiver_name(name: str) -> str:
    """A receiver's name (one key chunk, the vehicle id's alphabet); ``ValueError`` naming the rule."""
    if not isinstance(name, str) or not VEHICLE_ID_PATTERN.fullmatch(name):
        raise ValueError(f"receiver name {name!r} must match {VEHICLE_ID_PATTERN.pattern}")
    return name


def check_service_name(name: str) -> str:
    """An instance name usable as one key chunk (no ``/``, wildcard or ``$?#``); ``ValueError`` otherwise."""
    if not name or any(c in name for c in "/*$?#") or name.strip() != name:
        raise ValueError(
            f"an instance name is one Zenoh key chunk: not empty, no '/', '*', '$', '?', '#' "
            f"or surrounding spaces, got {name!r}"
        )
    return name


def check_frames_selector(key_expr: str) -> str:
    """A frame key expression a service instance may subscribe to: under ``ins/``; ``ValueError`` otherwise."""
    if not key_expr.startswith(f"{ROOT}/"):
        raise ValueError(f"must be under '{ROOT}/' ({ROOT}/<vehicle>/imu/<n>), got {key_expr!r}")
    return key_expr


class Mode(StrEnum):
    PEER = "peer"
    CLIENT = "client"
    ROUTER = "router"


@dataclass(frozen=True)
class ZenohSettings:
    """Session settings; :meth:`from_dict` reads the ``[zenoh]`` table of the service configuration.

    Attributes
    ----------
    mode : peer, client or router.
    connect : endpoints to connect to, e.g. ``("tcp/10.0.0.1:7447",)`` or ``("tls/host:7447",)``.
    listen : endpoints to listen on.
    multicast_scouting : UDP multicast discovery; off by default (explicit endpoints on a vehicle network).
    connect_timeout_s : how long opening waits for the ``connect`` endpoints; ``None`` waits forever.
    tls : passed unchanged to Zenoh's ``transport/link/tls`` (``root_ca_certificate``,
        ``listen_certificate``, ``listen_private_key``, ``enable_mtls``, ``connect_certificate``, …).
    access_control : passed unchanged to Zenoh's ``access_control`` (``enabled``,
        ``default_permission``, ``rules``, ``subjects``, ``policies``).
    extra : any other Zenoh configuration, as ``{"json/key/path": value}``.
    """

    mode: Mode = Mode.PEER
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    connect_timeout_s: float | None = None
    tls: Mapping[str, Any] | None = None
    access_control: Mapping[str, Any] | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    _KEYS = (
        "mode",
        "connect",
        "listen",
        "multicast_scouting",
        "connect_timeout_s",
        "tls",
        "access_control",
        "extra",
    )

    @classmethod
    def from_dict(cls, table: Mapping[str, Any]) -> ZenohSettings:
        """Validate a plain dict (e.g. a TOML table); unknown keys are a ``ValueError`` naming them."""
        unknown = sorted(set(table) - set(cls._KEYS))
        if unknown:
            raise ValueError(f"unknown zenoh setting(s) {unknown}; allowed: {list(cls._KEYS)}")
        try:
            mode = Mode(table.get("mode", Mode.PEER.value))
        except ValueError:
            raise ValueError(
                f"zenoh mode must be one of {[m.value for m in Mode]}, got {table.get('mode')!r}"
            ) from None
        endpoints = {}
        for name in ("connect", "listen"):
            value = table.get(name, ())
            if isinstance(value, str) or not all(isinstance(e, str) and "/" in e for e in value):
                raise ValueError(
                    f"zenoh {name} must be a list of endpoints like 'tcp/127.0.0.1:7447', got {value!r}"
                )
            endpoints[name] = tuple(value)
        timeout = table.get("connect_timeout_s")
        if timeout is not None and (
            isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or timeout < 0
        ):
            raise ValueError(
                f"zenoh connect_timeout_s must be a number >= 0 or absent, got {timeout!r}"
            )
        for name in ("tls", "access_control", "extra"):
            if table.get(name) is not None and not isinstance(table[name], Mapping):
                raise ValueError(f"zenoh {name} must be a table, got {type(table[name]).__name__}")
        scouting = table.get("multicast_scouting", False)
        if not isinstance(scouting, bool):
            raise ValueError(f"zenoh multicast_scouting must be true or false, got {scouting!r}")
        return cls(
            mode=mode,
            connect=endpoints["connect"],
            listen=endpoints["listen"],
            multicast_scouting=scouting,
            connect_timeout_s=None if timeout is None else float(timeout),
            tls=table.get("tls"),
            access_control=table.get("access_control"),
            extra=dict(table.get("extra") or {}),
        )


class AckMode(StrEnum):
    """What makes :meth:`EventPublisher.publish` return True (module docstring)."""

    RECEIVER = "receiver"
    MATCHED = "matched"
