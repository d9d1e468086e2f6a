"""The README's trial as a new operator runs it: its commands as written, a data folder the user may
not create said in one line, and "running" only once an input is connected.

Run as root here: the trial's paths are under a temporary home, so nothing depends on root; the
unwritable data folder is one under a file, which root cannot create either.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

from service_support import free_tcp_port
from test_deploy_units import Lines

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DEPLOY_CONFIG = ROOT / "deploy" / "ins-health.toml"
README_PORT = "7447"


def trial_block() -> list[str]:
    """The commands of the README's trial section, one per line."""
    text = README.read_text(encoding="utf-8")
    section = text.split("## A trial of the daemon (no root)", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block is not None, "the README's trial section has no sh block"
    return [line for line in block.group(1).splitlines() if line.strip()]


def trial_env(home: Path) -> dict[str, str]:
    """A user's environment with make demo's .venv active and ``home`` as HOME."""
    venv_bin = Path(sys.executable).parent
    return {
        **os.environ,
        "HOME": str(home),
        "PATH": f"{venv_bin}{os.pathsep}{os.environ['PATH']}",
        "OPENBLAS_NUM_THREADS": "1",
        "OMP_NUM_THREADS": "1",
    }


def test_the_readme_trial_runs_as_written(tmp_path):
    """Each line of the block, with the README's port replaced by a free one and a temporary home: the
    router and the daemon in the background, the simulated vehicle published, every frame taken."""
    port = str(free_tcp_port())
    home = tmp_path / "home"
    home.mkdir()
    checkout = tmp_path / "checkout"
    (checkout / "deploy").mkdir(parents=True)
    (checkout / "deploy" / "ins-health.toml").write_text(
        DEPLOY_CONFIG.read_text(encoding="utf-8").replace(README_PORT, port), encoding="utf-8"
    )
    env = trial_env(home)
    background: list[tuple[subprocess.Popen[str], Lines]] = []
    ran: list[subprocess.CompletedProcess[str]] = []
    try:
        for line in trial_block():
            command = line.replace(README_PORT, port)
            if command.startswith("kill "):
                jobs = [int(job.lstrip("%")) for job in shlex.split(command)[1:]]
                for job in jobs:
                    background[job - 1][0].terminate()
                for job in jobs:
                    assert background[job - 1][0].wait(30) == 0, background[job - 1][1].seen
                continue
            if command.endswith("&"):
                # exec: the job's process is the command itself, as kill %N signals it.
                proc = subprocess.Popen(
                    ["sh", "-c", "exec " + command.removesuffix("&")], cwd=checkout, env=env,
                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                )  # fmt: skip
                lines = Lines(proc.stdout)
                background.append((proc, lines))
                if "router" in command:
                    lines.wait_for(lambda s: s.startswith("ready "), timeout_s=30, what="ready")
                continue
            done = subprocess.run(
                ["sh", "-c", command], cwd=checkout, env=env, capture_output=True, text=True,
                timeout=120,
            )  # fmt: skip
            assert done.returncode == 0, (command, done.stdout, done.stderr)
            ran.append(done)
    finally:
        for proc, _ in background:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
    assert background and all(proc.returncode == 0 for proc, _ in background)
    assert ran and "the daemon took all" in ran[-1].stderr, ran[-1].stderr
    daemon = background[1][1]
    daemon.wait_for(lambda s: s.endswith(" ins-health running"), timeout_s=5, what="running")
    assert (home / ".local" / "share" / "ins-health" / "outbox.sqlite").is_file()


def test_a_data_folder_the_user_cannot_make_is_a_configuration_error(tmp_path):
    """The deploy's configuration with a data_dir this user cannot create (under a file, as
    /var/lib/ins-health is to a normal user): one line naming the setting and the fix, status 2,
    not a traceback and status 1 that Restart=on-failure repeats."""
    (tmp_path / "a-file").write_text("", encoding="utf-8")
    config = tmp_path / "ins-health.toml"
    config.write_text(
        DEPLOY_CONFIG.read_text(encoding="utf-8").replace(
            '"/var/lib/ins-health"', f'"{tmp_path / "a-file" / "data"}"'
        ),
        encoding="utf-8",
    )
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
        cwd=ROOT, env=trial_env(tmp_path), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"ins-health run: [service] data_dir of {config} = "), lines
    assert "--data-dir DIR" in lines[0] and "Traceback" not in lines[0], lines


def test_waiting_for_the_router_then_running(tmp_path):
    """No router at the configured endpoint: the daemon says what it waits for, and "running" only
    once the router is there and the session open."""
    from protocols.zenoh_router import RouterProcess

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    config = tmp_path / "ins-health.toml"
    config.write_text(
        f'[service]\nname = "onboard"\ndata_dir = "data"\npassport_dir = "passports"\n'
        f'[zenoh]\nconnect = ["{endpoint}"]\n',
        encoding="utf-8",
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
        cwd=ROOT, env=trial_env(tmp_path), stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    log = Lines(proc.stderr)
    try:
        log.wait_for(
            lambda s: s.endswith(
                f"INFO ins-health: onboard waiting for the Zenoh router at {endpoint}"
            ),
            timeout_s=60,
            what="the waiting line",
        )
        assert not any(line.endswith(" running") for line in log.seen), log.seen
        with RouterProcess(endpoint):
            log.wait_for(lambda s: s.endswith(" onboard running"), timeout_s=60, what="running")
            proc.terminate()
            assert proc.wait(30) == 0, log.seen
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)


def test_the_fleet_router_from_its_json5_configuration_over_tls(tmp_path):
    """The project's router started from deploy/zenoh-router.json5 (its TLS certificates those
    make-certs.sh makes, its endpoints on free loopback ports: the only changes), the daemon connected
    with the deploy's client certificate, and a frame of vehicle uav-1 (its own certificate) taken."""
    import numpy as np
    import zenoh
    from service_support import wait_until

    from protocols.zenoh_adapter import FramePublisher, open_session, query_status
    from service.config import config_from_dict

    certs = tmp_path / "tls"
    subprocess.run(
        ["sh", str(ROOT / "deploy" / "make-certs.sh"), str(certs)],
        env={"PATH": "/usr/bin:/bin", "ROUTER_NAME": "localhost"},
        check=True,
        capture_output=True,
    )
    tls_port, tcp_port = free_tcp_port(), free_tcp_port()
    router_config = tmp_path / "zenoh-router.json5"
    router_config.write_text(
        (ROOT / "deploy" / "zenoh-router.json5")
        .read_text(encoding="utf-8")
        .replace("/etc/zenoh/tls/", f"{certs}/")
        .replace("tls/0.0.0.0:7448", f"tls/localhost:{tls_port}")
        .replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{tcp_port}"),
        encoding="utf-8",
    )
    tls = {
        "root_ca_certificate": str(certs / "ca.pem"),
        "enable_mtls": True,
        "connect_certificate": str(certs / "ins-health-cert.pem"),
        "connect_private_key": str(certs / "ins-health-key.pem"),
    }
    config = tmp_path / "ins-health.toml"
    config.write_text(
        '[service]\nname = "fleet"\ndata_dir = "data"\npassport_dir = "passports"\n'
        f'[zenoh]\nconnect = ["tls/localhost:{tls_port}"]\n'
        f"tls = {{ {', '.join(f'{k} = {v!r}'.replace(chr(39), chr(34)) for k, v in tls.items())} }}\n"
        .replace("True", "true"),
        encoding="utf-8",
    )  # fmt: skip
    env = trial_env(tmp_path)
    router = subprocess.Popen(
        [sys.executable, "-m", "ins_health.router", "--config", str(router_config)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    daemon = None
    try:
        ready = Lines(router.stdout).wait_for(
            lambda s: s.startswith("ready "), timeout_s=30, what="ready"
        )
        assert ready == f"ready tcp/127.0.0.1:{tcp_port} tls/localhost:{tls_port}"
        daemon = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
            cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        Lines(daemon.stderr).wait_for(
            lambda s: s.endswith(" fleet running"), timeout_s=60, what="running"
        )
        vehicle_tls = {
            **tls,
            "connect_certificate": str(certs / "uav-1-cert.pem"),
            "connect_private_key": str(certs / "uav-1-key.pem"),
        }
        raw = {"zenoh": {"connect": [f"tls/localhost:{tls_port}"], "tls": vehicle_tls}}
        with open_session(config_from_dict(raw).zenoh.session) as vehicle:
            frames = FramePublisher(
                vehicle, "uav-1", 0, congestion_control=zenoh.CongestionControl.BLOCK
            )
            t = np.arange(100) / 100.0
            frames.add(t, np.tile([0.0, 0.0, 9.81], (100, 1)), np.zeros((100, 3)))

            def taken() -> bool:
                return any(
                    s.counters.get("imu0.frames.received", 0) >= 1
                    for s in query_status(vehicle, "uav-1", timeout_s=2.0)
                )

            wait_until(taken, timeout_s=30.0, what="the daemon's status counting the frame")
    finally:
        for proc in (daemon, router):
            if proc is not None:
                proc.terminate()
                proc.wait(30)
