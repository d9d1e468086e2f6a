"""The Python API (``ins_health.replay``, README "Python API"): the command's replay as a value,
and the installed wheel beside a user's own ``service`` package."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import pytest
from real_data import REAL_BIN, REAL_TLOG, needs
from replay_support import replay_with_coverage

import ins_health
from protocols.events import event_to_json
from service.cli import EXIT_UNTESTED

ROOT = Path(__file__).resolve().parents[1]


@needs(REAL_TLOG)
def test_replay_through_the_api_is_the_commands_replay(capsys):
    """Same events, same summary line, same exit status as ``ins-health replay --json``; and
    nothing printed."""
    status, lines, _, summary = replay_with_coverage(capsys, REAL_TLOG, "--json")
    result = ins_health.replay(REAL_TLOG)
    assert capsys.readouterr() == ("", "")
    assert [event_to_json(e) for e in result.events] == lines
    assert result.summary() == summary and result.exit_status == status
    assert result.samples == {0: summary["samples"]["0"], 1: summary["samples"]["1"]}
    assert any(n.startswith("no passport: nominal passport") for n in result.notes)


@needs(REAL_BIN)
def test_replay_json_ends_with_one_summary_line_even_without_an_event(capsys):
    """Issue 34: with no event the machine reader had no summary of what was read and left out.
    The last line says it: samples per IMU, what was left out, the counts, the verdict."""
    status, lines, _, summary = replay_with_coverage(capsys, REAL_BIN, "--json")
    assert status == EXIT_UNTESTED and lines == []
    assert summary["v"] == 2 and summary["log"] == REAL_BIN.name
    assert summary["samples"] == {"0": 45, "1": 45} and summary["left_out"] == {}
    assert summary["events"] == summary["findings"] == 0
    assert summary["verdict"] == "no finding within coverage"


def test_an_option_the_command_refuses_is_a_usage_error(tmp_path):
    log = tmp_path / "x.tlog"
    log.write_bytes(b"")
    with pytest.raises(ins_health.UsageError):
        ins_health.replay(log, grade="no_such_grade")


@pytest.mark.slow
@needs(REAL_BIN)
def test_the_wheel_installs_under_ins_health_beside_a_users_service_package(tmp_path):
    """Issue 34: ``pip install ins-health`` put ``service``, ``protocols`` and ``estimators`` at the
    top level, where a user's own ``service`` collides. Built and installed offline (the
    dependencies are this environment's), the wheel adds only ``ins_health``; the user's
    ``service`` is the one imported, the API replays a shared log as the checkout does, and the
    console script and ``python -m ins_health.router`` run."""
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
         "--no-index", "-w", str(wheels), str(ROOT)],
        check=True, capture_output=True, cwd=tmp_path,
    )  # fmt: skip
    (wheel,) = wheels.glob("ins_health-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True, capture_output=True, text=True,
        ).stdout.strip()
    )  # fmt: skip
    # The dependencies from this environment (a path, not a site dir: its editable finder of the
    # checkout is not run), the wheel installed by this environment's pip into the new one.
    (site / "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
         "--no-index", str(wheel)],
        check=True, capture_output=True,
    )  # fmt: skip
    installed = sorted(p.name for p in site.iterdir() if not p.name.endswith((".pth", "-info")))
    assert "ins_health" in installed
    (top_level,) = site.glob("ins_health-*.dist-info/top_level.txt")
    assert top_level.read_text().split() == ["ins_health"]
    assert not {"service", "protocols", "estimators"} & set(installed)
    user = tmp_path / "project"
    (user / "service").mkdir(parents=True)
    (user / "service" / "__init__.py").write_text("WHOSE = 'the user'\n")
    script = textwrap.dedent(
        f"""
        import json, sys
        import service
        import ins_health
        result = ins_health.replay({str(REAL_BIN)!r})
        assert service.WHOSE == "the user", service.__file__
        assert not any(m == "protocols" or m.startswith(("protocols.", "estimators")) for m in sys.modules)
        print(json.dumps(result.summary()))
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [python, "-c", script], check=True, capture_output=True, text=True, cwd=user, env=env
    )
    summary = json.loads(out.stdout)
    assert summary["samples"] == {"0": 45, "1": 45} and summary["exit_status"] == EXIT_UNTESTED
    version = subprocess.run(
        [venv / "bin" / "ins-health", "--version"],
        capture_output=True,
        text=True,
        cwd=user,
        env=env,
    )
    assert version.stdout.strip() == "ins-health 0.1.0", version.stderr
    router = subprocess.run(
        [python, "-m", "ins_health.router", "--help"],
        capture_output=True,
        text=True,
        cwd=user,
        env=env,
    )
    assert "python -m ins_health.protocols.zenoh_router" in router.stdout, router.stderr


@needs(REAL_TLOG)
def test_the_readmes_ci_example_runs_as_written_and_fails_naming_the_finding(tmp_path):
    """The README's pytest example of a vehicle team's CI, on a shared flight log with the
    consumer-MEMS nominal passport as the unit's own: a passport file applies at any rate, so at
    the telemetry's 4 Hz F0 finds the flight's manoeuvres off the unit sphere (without one, replay
    holds the nominal passport back below 20 Hz): the build fails, the message names the events."""
    from estimators.nominal_passport import SensorClass, nominal_passport
    from protocols.passport_codec import write_passport_json

    readme = (ROOT / "README.md").read_text()
    block = readme.split("## Python API", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "flight-logs").mkdir()
    (tmp_path / "flight-logs" / REAL_TLOG.name).symlink_to(REAL_TLOG)
    write_passport_json(
        nominal_passport(SensorClass.CONSUMER_MEMS), tmp_path / "imu0.passport.json"
    )
    (tmp_path / "test_flight_logs.py").write_text(block)
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_flight_logs.py"],
        capture_output=True, text=True, cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 1 and "1 failed" in run.stdout, run.stdout + run.stderr
    assert "accelerometer: output off the unit sphere" in run.stdout and "[F0]" in run.stdout
