"""``ins-health replay LOG --report DIR``: the same faulty flight in four formats, determinism, the real PX4 log."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from real_data import LOGS, needs

from estimators.log_health import ImuHealthAccumulator
from protocols.firmware_health import FirmwareHealth
from protocols.logs import write_dataflash_bin, write_dataflash_text, write_tlog
from protocols.ulog import write_ulog
from service import log_report
from service.cli import EXIT_FAULT, EXIT_NO_FAULT, EXIT_UNTESTED, main
from service.commands import replay as replay_command
from service.demo import demo_scenario

REAL_ULOG = LOGS / "px4-events.ulg"
REAL_COPTER31 = LOGS / "ardupilot-copter31-no-imu.log"
GROSS_SCALE_FAULT = 0.3
"""+30 % on the z accelerometer: beyond the consumer-MEMS class's ±3 % (and its F0 shell of ~2.3 m/s²)."""


@functools.cache
def flight():
    """The demo's flight from take-off on, IMU0 with the gross z scale fault after landing, IMU1 its healthy twin."""
    faulty = demo_scenario(fault_magnitude=GROSS_SCALE_FAULT)
    clean = demo_scenario(fault_magnitude=0.0)
    part = lambda sc: sc.session.select(sc.session.t_s >= sc.flight_start_s)  # noqa: E731
    return faulty, {0: part(faulty), 1: part(clean)}


def run_report(capsys, log, out, *extra):
    """The report of a replay; its coverage is the ``--json`` coverage line and states the exit status."""
    status = main(["replay", str(log), "--json", "--report", str(out), *map(str, extra)])
    captured = capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    assert status in (EXIT_FAULT, EXIT_UNTESTED, EXIT_NO_FAULT), captured.err
    assert json.loads(captured.out.splitlines()[-1]) == report["coverage"]
    assert report["coverage"]["exit_status"] == status
    return report, captured.err


def _key(finding):
    return (
        finding["source"],
        finding["imu"],
        finding["predicate"],
        finding.get("triad"),
        finding.get("axis"),
    )


@pytest.mark.slow
def test_the_same_faulty_flight_in_four_formats_gives_the_same_findings(tmp_path, capsys):
    faulty, sessions = flight()
    writers = {
        "tlog": write_tlog,
        "bin": write_dataflash_bin,
        "log": write_dataflash_text,
        "ulg": write_ulog,
    }
    findings = {}
    for suffix, writer in writers.items():
        log = tmp_path / f"flight.{suffix}"
        writer(log, sessions)
        report, err = run_report(capsys, log, tmp_path / suffix)
        assert "nominal passport of class consumer_mems" in err
        assert (
            report["passport"]["kind"] == "nominal" and report["passport"]["accel_scale_pct"] == 3.0
        )
        findings[suffix] = [_key(f) for f in report["findings"]]
        f0 = next(f for f in report["findings"] if f["predicate"] == "F0")
        assert faulty.fault_s <= f0["t_s"] < faulty.fault_s + 0.1
        f6 = next(f for f in report["findings"] if f["predicate"] == "F6")
        assert f6["estimate"] == pytest.approx(GROSS_SCALE_FAULT, abs=0.02)
        assert [e["imu"] for e in report["imus"]] == [0, 1]
        assert report["coverage"]["verdict"] == "fault"
        assert report["coverage"]["exit_status"] == EXIT_FAULT
    assert findings["tlog"] == findings["bin"] == findings["log"] == findings["ulg"]
    # Without a passport, from the class's tolerances: F0 then F6 (z scale factor) on IMU0, and the
    # disagreement with its healthy twin (the vector bins and, in flight, the norms: issue 32);
    # nothing on the healthy IMU of its own.
    assert ("pipeline", 0, "F0", "accel", None) in findings["bin"]
    assert ("pipeline", 0, "F6", "accel", "z") in findings["bin"]
    assert ("pipeline", 1, "cross_imu_norm", "accel", None) in findings["bin"]
    assert not [
        k for k in findings["bin"] if k[1] == 1 and k[2] not in ("cross_imu", "cross_imu_norm")
    ]


def test_report_is_deterministic_and_complete(tmp_path, capsys):
    _, sessions = flight()
    log = tmp_path / "flight.bin"
    write_dataflash_bin(log, sessions)
    run_report(capsys, log, tmp_path / "a")
    run_report(capsys, log, tmp_path / "b")
    first = (tmp_path / "a" / "report.json").read_bytes()
    assert first == (tmp_path / "b" / "report.json").read_bytes()
    report = json.loads(first)
    imu = report["imus"][0]
    for key in ("imu", "source", "n_samples", "rate_hz", "duration_s", "gaps", "accel_noise_mps2",
                "gyro_noise_rps", "noise_method", "vibration", "clipped_samples", "rest_s",
                "gravity_residual_mps2", "gyro_bias_rps", "temperature_c", "f0_accel"):  # fmt: skip
        assert key in imu
    assert imu["source"] == "IMU" and imu["rate_hz"] == pytest.approx(200.0)
    assert imu["noise_method"] == "rest" and imu["rest_s"] > 30.0
    pair = report["pairs"][0]
    assert pair["imus"] == [0, 1] and pair["accel_mps2"]["rest"]["max"] > 2.0  # the fault
    md = (tmp_path / "a" / "report.md").read_text()
    assert "## IMU0" in md and "## IMU1" in md and "![" in md
    # The class and its tolerances, as its datasheet states them (estimators.nominal_passport).
    assert "class `consumer_mems` (TDK InvenSense MPU-6000" in md
    assert (
        "Tolerances: accelerometer bias 50, 50, 80 mg, scale 3 %, cross-axis 2 %, noise 400 µg/√Hz"
        in md
    )
    for png in ("gravity_residual.png", "spectra.png", "cross_imu.png"):
        assert (tmp_path / "a" / png).stat().st_size > 1000


def test_the_spectra_s_log_axes_are_labelled_in_plain_text(tmp_path, monkeypatch):
    """1e−05, not mathtext's $10^{-5}$: its parser was built for these labels at every replay
    (0.07 s of CPU)."""
    drawn = []

    def keep(fig, path, **kwargs):
        save_figure(fig, path, **kwargs)
        drawn.append(fig)

    save_figure = log_report.save_figure
    monkeypatch.setattr(log_report, "save_figure", keep)
    rng = np.random.default_rng(2)
    acc = ImuHealthAccumulator()
    acc.update(
        np.arange(4000) / 400.0, rng.normal(0.0, 0.02, (4000, 3)), rng.normal(0.0, 0.003, (4000, 3))
    )
    assert log_report._spectra_plot({0: acc.result(9.81)}, FirmwareHealth(), tmp_path / "s.png")
    labels = [t.get_text() for ax in drawn[0].axes for t in ax.get_yticklabels(which="both")]
    assert [s for s in labels if s] and not [s for s in labels if "$" in s], labels


def test_progress_lines_on_stderr(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(replay_command, "PROGRESS_EVERY_S", 0.0)
    _, sessions = flight()
    log = tmp_path / "flight.ulg"
    write_ulog(log, sessions)
    main(["replay", str(log), "--json"])
    err = capsys.readouterr().err
    assert "% of flight.ulg read" in err and "samples" in err


@needs(REAL_ULOG)
def test_real_px4_log_report_is_pinned(tmp_path, capsys):
    """PX4 SITL (SOURCE.md): one IMU, 250 Hz, 31 s, mostly on the ground; no finding."""
    report, _ = run_report(capsys, REAL_ULOG, tmp_path / "px4")
    assert report["log"]["system"] == "PX4 PX4_SITL"
    assert report["log"]["left_out"] == {
        "sensor_accel.0": "logged at 1 Hz, below 20 Hz",
        "vehicle_imu.0": "logged at 2 Hz, below 20 Hz",
    }
    (imu,) = report["imus"]
    assert imu["source"] == "sensor_combined" and imu["n_samples"] == 7783
    assert imu["rate_hz"] == pytest.approx(250.0) and imu["duration_s"] == pytest.approx(
        31.128, abs=1e-3
    )
    assert imu["gaps"] == {"count": 0, "longest_s": 0.0}
    assert imu["clipped_samples"] == 0 and imu["temperature_c"] is None
    assert imu["noise_method"] == "rest" and imu["rest_s"] == pytest.approx(27.98, abs=0.01)
    # SITL's simulated noise: about 0.03 m/s² and 0.006 rad/s per axis, once the 4 blocks still
    # settling after motion are left out (z read 0.0371 with them).
    assert imu["settling_blocks"] == 4
    assert imu["accel_noise_mps2"] == pytest.approx([0.02965, 0.02951, 0.03228], abs=1e-4)
    assert imu["gyro_noise_rps"] == pytest.approx([0.006060, 0.006284, 0.005817], abs=1e-5)
    assert abs(imu["gravity_residual_mps2"]["median"]) < 0.01
    assert imu["f0_accel"]["tests"] == 7034 and imu["f0_accel"]["fails"] == 0
    assert report["findings"] == [] and report["pairs"] == []
    # No finding, but not "no fault": one position at rest, the diagnosis was not run; it flew
    # 3 s with GNSS, too short for the thrust-axis check's windows.
    cov = report["coverage"]
    assert cov["verdict"] == "no finding within coverage" and cov["exit_status"] == EXIT_UNTESTED
    assert cov["untested"] == [
        "IMU0 accel F1-F9: 1 position at rest, 9 needed",
        "IMU0 accel thrust_axis: no epoch judged (history 335, rest 49): mostly a flight shorter "
        "than the windows' span",
    ]
    md = (tmp_path / "px4" / "report.md").read_text()
    assert "## Verdict and coverage\n\n**no finding within coverage**." in md
    assert "- IMU0 accel F1-F9: 1 position at rest, 9 needed" in md
    assert "- IMU0 accel F0: ran on 7,034 samples; min. detectable zero signal x not seen" in md


@needs(REAL_COPTER31)
def test_a_log_without_imu_data_writes_no_report(tmp_path, capsys):
    status = main(["replay", str(REAL_COPTER31), "--report", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert status == 2 and "no IMU data" in err and not (tmp_path / "r").exists()


def test_the_grade_choices_are_the_sensor_classes():
    from estimators.nominal_passport import SensorClass

    assert replay_command.SENSOR_CLASSES == tuple(c.value for c in SensorClass)


def test_a_cut_and_damaged_log_says_in_its_report_what_was_not_read(tmp_path, capsys):
    _, sessions = flight()
    whole = tmp_path / "whole.bin"
    write_dataflash_bin(whole, sessions)
    data = bytearray(whole.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 4096] = bytes(4096)  # a zeroed flash page
    cut = len(data) - 7  # the recorder lost power mid-message
    log = tmp_path / "damaged.bin"
    log.write_bytes(bytes(data[:cut]))
    report, _ = run_report(capsys, log, tmp_path / "r")
    assert report["schema_version"] == 6
    assert report["log"]["skipped_bytes"] >= 4096 - 255
    assert cut - 255 < report["log"]["cut_at_byte"] < cut
    md = (tmp_path / "r" / "report.md").read_text()
    assert "bytes that start no message" in md
    assert f"the file is cut mid-message at byte {report['log']['cut_at_byte']}" in md
