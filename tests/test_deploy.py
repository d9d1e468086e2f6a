"""Every file in deploy/ is loaded by the tool that will read it in production."""

from __future__ import annotations

import configparser
import json
import queue
import re
import shlex
import tomllib
from pathlib import Path

import pytest
import zenoh
from service_support import free_tcp_port, wait_until, zenoh_client_config

from service.cli import build_parser
from service.config import config_from_dict, load_config

DEPLOY = Path(__file__).parents[1] / "deploy"
FILES = sorted(p for p in DEPLOY.iterdir() if p.is_file())


def check_toml(path: Path) -> None:
    cfg = load_config(path)
    assert cfg.zenoh.frames_key.startswith("ins/")


def check_json5(path: Path) -> None:
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


def check_unit(path: Path) -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(path)
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    argv = shlex.split(unit["Service"]["ExecStart"])
    assert Path(argv[0]).name == "ins-health"
    args = build_parser().parse_args(argv[1:])
    assert args.command == "run" and Path(args.config).name in {p.name for p in FILES}
    assert unit["Service"]["KillSignal"] == "SIGTERM"


def check_markdown(path: Path) -> None:
    """Each TOML example in the note is a valid configuration, and the shares it shows are disjoint."""
    blocks = re.findall(r"```toml\n(.*?)```", path.read_text(), flags=re.S)
    assert blocks, f"{path.name} shows no configuration"
    keys = [config_from_dict(tomllib.loads(b), base_dir=DEPLOY).zenoh.frames_key for b in blocks]
    for i, a in enumerate(keys):
        for b in keys[i + 1 :]:
            assert not zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)), (a, b)
    assert zenoh.KeyExpr(keys[0]).intersects(zenoh.KeyExpr("ins/alpha-07/imu/0"))


CHECKS = {".toml": check_toml, ".json5": check_json5, ".service": check_unit, ".md": check_markdown}


@pytest.mark.parametrize("path", FILES, ids=[p.name for p in FILES])
def test_deploy_file_loads(path):
    assert path.suffix in CHECKS, (
        f"no loader for {path.name}: every file in deploy/ must be checked"
    )
    CHECKS[path.suffix](path)
