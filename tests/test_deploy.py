"""Every file in deploy/ is loaded by the tool that will read it in production.

The units are started as systemd starts them in tests/test_deploy_units.py.
"""

from __future__ import annotations

import configparser
import json
import queue
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import zenoh
from service_support import free_tcp_port, wait_until, zenoh_client_config

from protocols.events import (
    Predicate,
    ServiceStatus,
    Severity,
    Status,
    StreamCause,
    encode_event,
    make_event,
)
from protocols.zenoh_adapter import (
    ZENOH_MAX_MESSAGE_BYTES,
    AckMode,
    EventPublisher,
    EventReceiver,
    FramePublisher,
    StatusPublisher,
    open_session,
    query_status,
    subscribe_alive,
    subscribe_service_status,
)
from service.cli import build_parser
from service.config import config_from_dict, load_config

DEPLOY = Path(__file__).parents[1] / "deploy"
FILES = sorted(p for p in DEPLOY.iterdir() if p.is_file())
INSTALLED_VENV_BIN = (
    Path(re.search(r"python3\.11 -m venv (\S+)", (DEPLOY / "INSTALL.md").read_text())[1]) / "bin"
)
"""Where INSTALL.md creates the virtual environment the units run from (read from it, not repeated)."""
TLS_DIR = "/etc/zenoh/tls/"
"""Where INSTALL.md puts the certificates the router and the service configurations name."""


def check_toml(path: Path, tmp_path: Path) -> None:
    cfg = load_config(path)
    assert cfg.zenoh.frames_key.startswith("ins/")


def check_json5(path: Path, tmp_path: Path) -> None:
    """The router configuration opens as a router; clients route ins/** through it, other keys are denied."""
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("mode")) == "router"
    port = free_tcp_port()
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    with (
        zenoh.open(conf),
        zenoh.open(zenoh_client_config(port)) as pub_s,
        zenoh.open(zenoh_client_config(port)) as sub_s,
    ):
        allowed, denied = queue.Queue(), queue.Queue()
        sub_s.declare_subscriber("ins/*/health/events", lambda s: allowed.put(s.payload.to_bytes()))
        sub_s.declare_subscriber("other/**", lambda s: denied.put(s.payload.to_bytes()))
        pub = pub_s.declare_publisher("ins/v1/health/events")
        other = pub_s.declare_publisher("other/x")
        wait_until(lambda: pub.matching_status.matching, timeout_s=5.0, what="a route for ins/**")
        pub.put(b"event")
        assert allowed.get(timeout=5.0) == b"event"
        # The denied key is published too; the allowed put that follows it on the same
        # session and link arrives after it would have, so its arrival ends the wait.
        other.put(b"must not pass")
        pub.put(b"after")
        assert allowed.get(timeout=5.0) == b"after"
        assert denied.empty(), f"other/x was routed: {denied.get()!r}"
        assert not other.matching_status.matching
        # A tool on the router's host (the loopback subject) sees the events but its
        # acknowledgement does not reach the service: only a ground station's certificate answers.
        event = make_event(vehicle="v1", imu=0, t_s=1.0, predicate=Predicate.STALE,
                           cause=StreamCause.STUCK_VALUE, severity=Severity.ERROR)  # fmt: skip
        seen = queue.Queue()
        with (
            EventReceiver(sub_s, seen.put, vehicles="v1", name="ground-station"),
            EventPublisher(pub_s, ack_timeout_s=1.0) as publisher,
            EventPublisher(pub_s, ack=AckMode.MATCHED) as probe,
        ):
            # Declared after the receiver's queryable on the same link: once it is routed, the
            # queryable would be too.
            sub_s.declare_subscriber("ins/v2/health/events", lambda s: None)
            wait_until(lambda: probe.ready("v2"), timeout_s=5.0, what="the events' route")
            assert not publisher.ready("v1")
            assert publisher.publish(event) is False
            assert seen.get(timeout=5.0) == event
        # A ground station sees a service's liveliness token come and go, and its own status; a
        # vehicle's last status is answered to a query (what ins-health publish reads at its end).
        alive, own = queue.Queue(), queue.Queue()
        subscribe_alive(sub_s, lambda name, up: alive.put((name, up)))
        subscribe_service_status(sub_s, own.put)
        status = StatusPublisher(pub_s, "onboard")
        assert alive.get(timeout=5.0) == ("onboard", True)
        wait_until(
            lambda: status._service_pub.matching_status.matching, timeout_s=5.0, what="a route"
        )
        status.publish_service(ServiceStatus("onboard", 1.0))
        status.publish(Status("v1", "onboard", 1.0, {"imu0.frames.dropped_overload": 2}))
        assert own.get(timeout=5.0).service == "onboard"
        [answer] = query_status(sub_s, "v1", timeout_s=5.0)
        assert answer.counters["imu0.frames.dropped_overload"] == 2
        status.close()
        assert alive.get(timeout=5.0) == ("onboard", False)


def read_unit(path: Path) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # systemd keys are case-sensitive
    unit.read(path)
    return unit


def check_unit(path: Path, tmp_path: Path) -> None:
    """A unit runs a program of INSTALL.md's virtual environment as the service user; SIGTERM stops it."""
    unit = read_unit(path)
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    service = unit["Service"]
    argv = shlex.split(service["ExecStart"])
    assert Path(argv[0]).parent == INSTALLED_VENV_BIN
    assert Path(sys.executable).with_name(Path(argv[0]).name).exists(), argv[0]
    assert service["User"] == "ins-health" and service["KillSignal"] == "SIGTERM"
    if Path(argv[0]).name == "ins-health":
        args = build_parser().parse_args(argv[1:])
        assert args.command == "run" and Path(args.config).name in {p.name for p in FILES}


def check_markdown(path: Path, tmp_path: Path) -> None:
    {"SCALING.md": check_scaling, "INSTALL.md": check_install}[path.name](path)


def check_scaling(path: Path) -> None:
    """Each TOML example in the note is a valid configuration, and the shares it shows are disjoint."""
    blocks = re.findall(r"```toml\n(.*?)```", path.read_text(), flags=re.S)
    assert blocks, f"{path.name} shows no configuration"
    keys = [config_from_dict(tomllib.loads(b), base_dir=DEPLOY).zenoh.frames_key for b in blocks]
    for i, a in enumerate(keys):
        for b in keys[i + 1 :]:
            assert not zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)), (a, b)
    assert zenoh.KeyExpr(keys[0]).intersects(zenoh.KeyExpr("ins/alpha-07/imu/0"))


def check_install(path: Path) -> None:
    """The install steps are valid shell, name every other file of deploy/, and only files that exist."""
    text = path.read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    assert blocks, f"{path.name} shows no commands"
    for block in blocks:
        checked = subprocess.run(["sh", "-n"], input=block, text=True, capture_output=True)
        assert checked.returncode == 0, (block, checked.stderr)
    for name in re.findall(r"deploy/([\w.-]+)", text):
        assert (DEPLOY / name).is_file(), name
    assert {p.name for p in FILES if p != path} <= set(re.findall(r"[\w.-]+", text))


def check_certificates(path: Path, tmp_path: Path) -> None:
    """The certificate script's output is what the fleet router (zenoh-router.json5) and the service need,
    and the router's access control holds for the keys of ins-health.

    A TLS router opened from the shipped configuration, with the script's files in
    place of /etc/zenoh/tls, admits the members by the common names of their
    certificates. Vehicle uav-1 puts frames on its own key; the same put on uav-2's
    key and a forged event on its events key are not routed (both are put before
    its own frame on the same link, so they would arrive before it; and before the
    service's event, which the frame's arrival causes). The service (with the TLS
    settings of the example configuration) takes the frame, and its event reaches
    the ground station and is acknowledged by it; a member whose name the router
    does not list, with a certificate of the same authority, is routed nothing.
    """
    certs = tmp_path / "tls"
    env = {"PATH": "/usr/bin:/bin", "ROUTER_NAME": "localhost"}
    subprocess.run(["sh", str(path), str(certs)], env=env, check=True, capture_output=True)
    # A later run adds members with the same authority.
    subprocess.run(
        ["sh", str(path), str(certs), "uav-2", "intruder"], env=env, check=True, capture_output=True
    )
    members = ("ins-health", "uav-1", "ground-station", "uav-2", "intruder")
    keys = ["ca-key.pem", "router-key.pem", *(f"{m}-key.pem" for m in members)]
    public = ["ca.pem", "router-cert.pem", *(f"{m}-cert.pem" for m in members)]
    assert sorted(p.name for p in certs.glob("*.pem")) == sorted(keys + public)
    assert {oct(p.stat().st_mode & 0o777) for p in map(certs.joinpath, keys)} == {"0o600"}
    verify = subprocess.run(
        ["openssl", "verify", "-CAfile", "ca.pem", *public[1:]],
        cwd=certs,
        capture_output=True,
        text=True,
    )
    assert verify.returncode == 0 and verify.stdout.count(": OK") == len(public) - 1, verify.stdout

    conf = zenoh.Config.from_file(str(DEPLOY / "zenoh-router.json5"))
    assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == (
        ZENOH_MAX_MESSAGE_BYTES
    )
    port = free_tcp_port()
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/localhost:{port}"]))
    for key, value in json.loads(conf.get_json("transport/link/tls")).items():
        if isinstance(value, str) and value.startswith(TLS_DIR):
            conf.insert_json5(
                f"transport/link/tls/{key}", json.dumps(str(certs / value[len(TLS_DIR) :]))
            )
    # Every connection here comes in on the loopback, which the configuration admits as a
    # service and a ground station: without that subject, only the certificates' names decide.
    subjects = [
        {k: v for k, v in s.items() if v is not None}
        for s in json.loads(conf.get_json("access_control/subjects"))
    ]
    named = [s for s in subjects if s.get("cert_common_names")]
    assert len(named) == len(subjects) - 1
    names = {s["id"] for s in named}
    policies = [
        {**{k: v for k, v in p.items() if v is not None}, "subjects": [s for s in p["subjects"] if s in names]}
        for p in json.loads(conf.get_json("access_control/policies"))
        if set(p["subjects"]) & names
    ]  # fmt: skip
    conf.insert_json5("access_control/subjects", json.dumps(named))
    conf.insert_json5("access_control/policies", json.dumps(policies))
    example_tls = tomllib.loads(
        re.search(r"^# (tls = \{.*?\})", (DEPLOY / "ins-health.toml").read_text(), flags=re.M)[1]
    )["tls"]

    def member(name: str) -> zenoh.Session:
        tls = {
            k: str(certs / v[len(TLS_DIR) :].replace("ins-health", name))
            if isinstance(v, str)
            else v
            for k, v in example_tls.items()
        }
        raw = {
            "zenoh": {"connect": [f"tls/localhost:{port}"], "tls": tls, "connect_timeout_s": 10.0}
        }
        return open_session(config_from_dict(raw).zenoh.session)

    def route(publisher, what: str) -> None:
        wait_until(lambda: publisher.matching_status.matching, timeout_s=10.0, what=what)

    forged, real = (
        make_event(vehicle="uav-1", imu=0, t_s=t_s, predicate=Predicate.STALE,
                   cause=StreamCause.STUCK_VALUE, severity=Severity.ERROR, text=text)
        for t_s, text in ((1.0, "forged"), (2.0, "real"))
    )  # fmt: skip
    with (
        zenoh.open(conf),
        member("ins-health") as service,
        member("ground-station") as ground,
        member("ground-station") as second_ground,
        member("uav-1") as vehicle,
        member("intruder") as intruder,
    ):
        frames, events = queue.Queue(), queue.Queue()
        service.declare_subscriber("ins/*/imu/*", lambda s: frames.put(s.payload.to_bytes()))
        receiver = EventReceiver(ground, lambda e: events.put(e.text), name="ground-station")
        # The same certificate under a name not its own (a second holder): the router drops its
        # answers, so it never counts as a second receiver.
        other_name = EventReceiver(second_ground, lambda e: None, name="gs-other")
        own = vehicle.declare_publisher("ins/uav-1/imu/0")
        other = vehicle.declare_publisher("ins/uav-2/imu/0")
        fake = vehicle.declare_publisher("ins/uav-1/health/events")
        publisher = EventPublisher(
            service, ack=AckMode.RECEIVER, ack_timeout_s=5.0, ack_from=["ground-station"]
        )
        two = EventPublisher(service, ack=AckMode.RECEIVER, ack_timeout_s=1.0, min_acks=2)
        route(own, "the vehicle's frames to the service")
        route(fake, "the declaration of the ground station's subscriber")
        other.put(b"frame of uav-2")
        fake.put(encode_event(forged))
        own.put(b"frame of uav-1")
        assert frames.get(timeout=5.0) == b"frame of uav-1"
        # The router answers the vehicle's question whether it holds its frames (the query
        # FramePublisher.close drains with), or every publish would wait out the timeout.
        assert FramePublisher(vehicle, "uav-1", 0).drain(timeout_s=5.0)
        assert publisher.publish(real), "the ground station did not acknowledge the event"
        assert events.get(timeout=5.0) == "real"
        assert not two.publish(real), "an answer under a name not the certificate's counted"
        assert publisher.refused == 0
        assert frames.empty() and events.empty() and receiver.rejected == {}
        # An unlisted member of the same authority is routed nothing, frames or events.
        assert not intruder.declare_publisher("ins/uav-1/imu/0").matching_status.matching
        assert not intruder.declare_publisher("ins/uav-1/health/events").matching_status.matching
        for entity in (publisher, two, receiver, other_name):
            entity.close()


CHECKS = {
    ".toml": check_toml,
    ".json5": check_json5,
    ".service": check_unit,
    ".md": check_markdown,
    ".sh": check_certificates,
}


@pytest.mark.parametrize("path", FILES, ids=[p.name for p in FILES])
def test_deploy_file_loads(path, tmp_path):
    assert path.suffix in CHECKS, (
        f"no loader for {path.name}: every file in deploy/ must be checked"
    )
    CHECKS[path.suffix](path, tmp_path)
