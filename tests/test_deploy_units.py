"""The systemd units started as systemd starts them: the single vehicle's router, then the service.

Each unit's ``ExecStart`` is run as written, with two changes a test must make: the
program comes from this virtual environment instead of INSTALL.md's
``/opt/ins-health/.venv``, and what the files name on the machine (the router's
port, the configuration's folders) is moved to a temporary folder and a free
port. The service reads the example configuration ``deploy/ins-health.toml``
with only those values changed, from the working directory of its unit.
"""

from __future__ import annotations

import os
import queue
import shlex
import signal
import socket
import stat
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from service_support import free_tcp_port
from test_deploy import DEPLOY, INSTALLED_VENV_BIN, read_unit

ROUTER = "tcp/127.0.0.1:7447"
"""The router endpoint of the router unit and of the example configuration."""


class Lines:
    """The lines a child process writes on one stream, read by a thread; waits have deadlines."""

    def __init__(self, stream) -> None:
        self.seen: list[str] = []
        self._q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            self._q.put(line.rstrip("\n"))
        self._q.put(None)

    def wait_for(self, wanted: Callable[[str], bool], *, timeout_s: float, what: str) -> str:
        try:
            while (line := self._q.get(timeout=timeout_s)) is not None:
                self.seen.append(line)
                if wanted(line):
                    return line
        except queue.Empty:
            raise AssertionError(f"no {what} within {timeout_s} s; saw {self.seen}") from None
        raise AssertionError(f"the process ended before {what}; saw {self.seen}")


def exec_start(unit_name: str, replace: dict[str, str]) -> tuple[list[str], dict]:
    """The unit's command line, its program taken from this virtual environment, values replaced."""
    unit = read_unit(DEPLOY / unit_name)
    argv = shlex.split(unit["Service"]["ExecStart"])
    assert Path(argv[0]).parent == INSTALLED_VENV_BIN
    argv[0] = str(Path(sys.executable).with_name(Path(argv[0]).name))
    for old, new in replace.items():
        assert old in argv, (old, argv)
        argv[argv.index(old)] = new
    return argv, dict(unit["Service"])


def stop(proc: subprocess.Popen, service: dict) -> int:
    """Stop as systemd does: KillSignal, then wait up to TimeoutStopSec."""
    proc.send_signal(getattr(signal, service["KillSignal"]))
    return proc.wait(timeout=float(service["TimeoutStopSec"]))


def test_the_router_and_the_service_start_and_stop_as_their_units_say(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router_argv, router_unit = exec_start("ins-health-router.service", {ROUTER: endpoint})

    # The example configuration as written, but for what names this machine.
    text = (DEPLOY / "ins-health.toml").read_text()
    moved = {
        '"/var/lib/ins-health"': tmp_path / "var-lib-ins-health",
        '"/etc/ins-health/passports"': tmp_path / "etc-ins-health" / "passports",
        f'"{ROUTER}"': endpoint,
    }
    for old, new in moved.items():
        assert text.count(old) == 1, old
        text = text.replace(old, f'"{new}"')
    config = tmp_path / "etc-ins-health" / "ins-health.toml"
    config.parent.mkdir()
    config.write_text(text)
    service_argv, service_unit = exec_start(
        "ins-health.service", {"/etc/ins-health/ins-health.toml": str(config)}
    )
    # systemd makes the state directory (StateDirectory=, StateDirectoryMode=) and starts there.
    state = tmp_path / "var-lib-ins-health"
    assert service_unit["WorkingDirectory"] == "/var/lib/ins-health"
    state.mkdir(mode=int(service_unit["StateDirectoryMode"], 8))

    router = subprocess.Popen(router_argv, stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        Lines(router.stdout).wait_for(
            lambda line: line == f"ready {endpoint}", timeout_s=30, what="the router's ready line"
        )
        # Type=notify: systemd names its notification socket and the watchdog period.
        assert service_unit["Type"] == "notify" and int(service_unit["WatchdogSec"]) > 0
        manager = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        manager.bind(str(tmp_path / "notify"))
        manager.settimeout(60)
        env = {
            **os.environ,
            "NOTIFY_SOCKET": str(tmp_path / "notify"),
            "WATCHDOG_USEC": str(int(service_unit["WatchdogSec"]) * 1_000_000),
        }
        service = subprocess.Popen(
            service_argv, stderr=subprocess.PIPE, text=True, cwd=state, env=env
        )
        try:
            log = Lines(service.stderr)
            log.wait_for(
                # Time-stamped here; under journald the journal shows the line as it ends.
                lambda line: line.endswith(" INFO ins-health: ins-health running"),
                timeout_s=60,
                what="'ins-health: ins-health running'",
            )
            assert manager.recv(4096) == b"READY=1\nSTATUS=ins-health running"
        finally:
            status = stop(service, service_unit)
        assert status == 0, log.seen
        # Pings (every WatchdogSec / 2) may come before it: the last word is STOPPING=1.
        said = []
        while (datagram := manager.recv(4096)) != b"STOPPING=1":
            said.append(datagram)
        assert set(said) <= {b"WATCHDOG=1"}
        manager.close()
    finally:
        assert stop(router, router_unit) == 0
    assert sorted(p.name for p in state.iterdir() if p.suffix == ".sqlite") == [
        "checkpoints.sqlite",
        "outbox.sqlite",
    ]
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in state.iterdir()} == {"0o600"}
