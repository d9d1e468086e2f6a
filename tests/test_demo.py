"""The demo runs end to end (router, simulated vehicle, service) and finds and names its fault."""

from __future__ import annotations

import asyncio
import io

import pytest

from estimators.conventions import Triad
from estimators.sim import GRADES, Grade
from protocols.events import Predicate, Severity
from service.cli import main
from service.demo import DEMO_FAULT_MAGNITUDE, demo_passport, demo_scenario, run_demo

pytestmark = pytest.mark.network


def test_demo_detects_and_names_the_injected_fault():
    out = io.StringIO()
    result = asyncio.run(run_demo(out=out, speed=40.0))
    text = out.getvalue()
    assert result.detected and result.named
    assert [(e.predicate, e.severity) for e in result.events] == [
        (Predicate.F0, Severity.WARNING),
        (Predicate.F6, Severity.ERROR),
    ]
    assert (
        "passport: calibrated from the unit's own fault-free 18-position handling session" in text
    )
    assert (
        "router: tcp/127.0.0.1:" in text
        and "progress: t =  117.0 / 117.0 s  post-flight handling" in text
    )
    assert (
        "demo-uav IMU0 accelerometer z: scale factor error" in text
        and "named: accelerometer z, scale factor error" in text
    )


def test_demo_passport_is_the_units_own_calibration():
    """The passport calibrated from the simulated handling session recovers the simulator's truth.

    Scale errors and non-orthogonality within 4σ; the zero signals within 4σ plus half a count of
    the simulated converter (a truncating quantizer shifts the mean output by up to half a step,
    M2's half-pulse correction, and that shift belongs to the unit as the service sees it).
    """
    passport, g = demo_passport()
    truth = demo_scenario(fault_magnitude=0.0).truth_accel
    assert list(passport.triads) == [Triad.ACCEL]
    accel = passport.triads[Triad.ACCEL]
    err = abs(accel.nominal - truth)
    half_count = 0.5 * GRADES[Grade.MEMS].accel.quant_step_si / g
    assert (err[3:] < 4 * accel.sigma[3:]).all()
    assert (err[:3] < 4 * accel.sigma[:3] + half_count).all()
    assert DEMO_FAULT_MAGNITUDE > 5 * accel.tolerance[5]


def test_demo_speed_is_validated(capsys):
    assert main(["demo", "--speed", "1000"]) == 2
    assert "--speed must be within 0.5..100" in capsys.readouterr().err


def test_make_demo_installs_the_package_alone_and_make_test_the_test_extras(tmp_path):
    """Issue 34: ``make demo`` installed the test extras (MAVProxy brings OpenCV and VTK: a 1.7 GB
    ``.venv`` against 495 MB) and said nothing while it did. What make would run for a new venv:"""
    import shutil
    import subprocess
    from pathlib import Path

    make = shutil.which("make")
    if make is None:
        pytest.skip("make is not installed")
    root = Path(__file__).resolve().parents[1]

    def planned(target):
        return subprocess.run(
            [make, "-n", "-C", str(root), target, f"VENV={tmp_path / 'venv'}"],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip

    demo, test = planned("demo"), planned("test")
    install = [line for line in demo.splitlines() if "pip install" in line]
    assert len(install) == 1 and install[0].endswith("-e .") and "[test]" not in demo
    assert "installing ins-health" in demo
    assert "-e '.[test]'" in test
