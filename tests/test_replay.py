"""``ins-health replay``: logs written from a simulated flight with a fault, and a real ArduPilot log."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import platform
import struct
import subprocess
import sys

import numpy as np
import pytest
from real_data import LOGS, REAL_BIN, REAL_TLOG, needs
from replay_support import replay_with_coverage

from estimators.conventions import Triad
from protocols.events import Predicate, event_from_json
from protocols.logs import write_dataflash_bin, write_dataflash_text, write_tlog
from protocols.passport_codec import write_passport_json
from protocols.ulog import write_ulog
from service.cli import EXIT_FAULT, EXIT_UNTESTED, main
from service.commands.replay import log_start
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore

REAL_ULOG = LOGS / "px4-events.ulg"
REAL_COPTER31 = LOGS / "ardupilot-copter31-no-imu.log"


@functools.cache
def flight():
    """From take-off on: the flight, the landing, the +3 % z scale-factor fault, the post-flight handling.

    IMU0 has the fault; IMU1 is a healthy twin.
    """
    passport, g = demo_passport()
    faulty, clean = demo_scenario(), demo_scenario(fault_magnitude=0.0)
    part = lambda sc: sc.session.select(sc.session.t_s >= sc.flight_start_s)  # noqa: E731
    return passport, g, faulty, part(faulty), part(clean)


def replay(capsys, *argv) -> tuple[int, list[str], str]:
    return replay_with_coverage(capsys, *argv)[:3]


@pytest.fixture
def passport_file(tmp_path):
    path = tmp_path / "unit.passport.json"
    write_passport_json(flight()[0], path)
    return path


@pytest.mark.parametrize(
    "writer, suffix, imus",
    [
        (write_tlog, "tlog", 1),
        (write_dataflash_bin, "bin", 2),
        (write_dataflash_text, "log", 1),
        (write_ulog, "ulg", 2),
    ],
)
def test_log_of_a_faulty_flight_gives_the_expected_events(
    writer, suffix, imus, tmp_path, capsys, passport_file
):
    _passport, g, faulty, faulty_part, clean_part = flight()
    log = tmp_path / f"flight.{suffix}"
    writer(log, {0: faulty_part, 1: clean_part} if imus == 2 else {0: faulty_part})
    status, lines, err = replay(capsys, log, "--json", "--passport", passport_file, "--gravity", g)
    assert status == EXIT_FAULT
    events = [event_from_json(line) for line in lines]
    # With the clean unit beside it, the two norms move apart too (issue 32): the log starts at
    # take-off, and the norm check tests from the end of its 20 s warm-up (7 s after the fault).
    norm = [e for e in events if e.predicate is Predicate.CROSS_IMU_NORM]
    assert [(e.imu, e.triad) for e in norm] == ([(1, Triad.ACCEL)] if imus == 2 else [])
    assert all(faulty.fault_s < e.t_s <= faulty.flight_start_s + 20.0 + 5.0 for e in norm)
    events = [e for e in events if e not in norm]
    assert [(e.imu, e.predicate, e.triad, e.axis) for e in events] == [
        (0, Predicate.F0, Triad.ACCEL, None),
        (0, Predicate.F6, Triad.ACCEL, "z"),
    ]
    f0, f6 = events
    assert faulty.fault_s <= f0.t_s < faulty.fault_s + 0.05
    assert abs(f6.estimate - (faulty.truth_accel[5] + 0.03)) < 4 * f6.sigma
    n = faulty_part.n_samples
    assert (
        f"({suffix})" in err
        and (f"samples IMU0 {n}, IMU1 {n};" if imus == 2 else f"samples IMU0 {n};") in err
    )


def test_the_same_log_always_gives_the_same_events(tmp_path, capsys, passport_file):
    _passport, g, faulty, *_ = flight()
    log = tmp_path / "landing.bin"
    write_dataflash_bin(
        log,
        {
            0: faulty.session.select(
                (faulty.session.t_s > faulty.landing_s) & (faulty.session.t_s < faulty.fault_s + 3)
            )
        },
    )
    first = replay(capsys, log, "--json", "--passport", passport_file, "--gravity", g)
    second = replay(capsys, log, "--json", "--passport", passport_file, "--gravity", g)
    assert first[1] == second[1] and [event_from_json(line).predicate for line in first[1]] == [
        Predicate.F0
    ]


def test_frames_the_pipeline_failed_on_are_named_and_exit_3(tmp_path, capsys):
    """A passport that reads (zero accelerometer noise passes its checks) but that the pipeline cannot
    use: every frame raised and was only counted, and replay said '0 events' with exit 0."""
    passport, g, faulty, *_ = flight()
    accel = passport.triads[Triad.ACCEL]
    broken = dataclasses.replace(
        passport,
        triads={**passport.triads, Triad.ACCEL: dataclasses.replace(accel, noise_std=np.zeros(3))},
    )
    path = tmp_path / "broken.passport.json"
    write_passport_json(broken, path)
    log = tmp_path / "landing.bin"
    write_dataflash_bin(log, {0: faulty.session.select(faulty.session.t_s < 20.0)})
    status, _, err = replay(capsys, log, "--passport", path, "--gravity", g)
    assert status == EXIT_UNTESTED
    frames = -(-faulty.session.select(faulty.session.t_s < 20.0).n_samples // 100)
    assert f"replay IMU0: the pipeline failed on {frames} frame(s) (ValueError: " in err
    assert "their samples were not tested" in err
    write_passport_json(passport, path)
    status, _, err = replay(capsys, log, "--passport", path, "--gravity", g)
    assert status == EXIT_UNTESTED and "the pipeline failed" not in err


def _imu_time_patched(path, k: int, add_us: int) -> None:
    """Add ``add_us`` to the TimeUS of IMU message ``k`` of a one-IMU DataFlash binary (fixed-size messages)."""
    data = bytearray(path.read_bytes())
    first = data.index(b"\xa3\x95\x81", 2 * 89)  # after the FMT messages of FMT and IMU
    size = data.index(b"\xa3\x95\x81", first + 3) - first
    (t_us,) = struct.unpack_from("<Q", data, first + k * size + 3)
    struct.pack_into("<Q", data, first + k * size + 3, t_us + add_us)
    path.write_bytes(bytes(data))


def test_one_time_stamp_gone_wrong_is_left_out_and_the_rest_replayed(
    tmp_path, capsys, passport_file
):
    """One TimeUS with a bit flipped (2^32 µs ahead) before the fault: the reader's running maximum
    refused every later sample as not increasing (no F0, no F6, exit 0). Now that one sample is
    left out as time_glitch and the events are those of the log without it."""
    _passport, g, faulty, faulty_part, _ = flight()
    log = tmp_path / "flight.bin"
    write_dataflash_bin(log, {0: faulty_part})
    clean = replay(capsys, log, "--json", "--passport", passport_file, "--gravity", g)
    before_fault = int(np.searchsorted(faulty_part.t_s, faulty.fault_s)) // 2
    _imu_time_patched(log, before_fault, 2**32)
    status, lines, err = replay(capsys, log, "--json", "--passport", passport_file, "--gravity", g)
    assert status == EXIT_FAULT and len(lines) == 2
    assert [event_from_json(e).predicate for e in lines] == [Predicate.F0, Predicate.F6]
    assert lines == clean[1]
    assert f"samples IMU0 {faulty_part.n_samples - 1}; left out time_glitch 1;" in err


def test_a_log_whose_clock_started_again_is_replayed_past_the_restart(
    tmp_path, capsys, passport_file
):
    """Two logs joined end to end (or an autopilot reboot): the second's samples are earlier than the
    first's last. They were all refused as not increasing; now they are replayed as a stream that
    restarted, which the pipeline detects (source_restarts), and the replay says so."""
    _passport, g, _faulty, faulty_part, clean_part = flight()
    first, second = tmp_path / "a.log", tmp_path / "b.log"
    write_dataflash_text(first, {0: clean_part.select(clean_part.t_s < clean_part.t_s[0] + 60.0)})
    write_dataflash_text(second, {0: faulty_part})
    joined = tmp_path / "joined.log"
    joined.write_text(first.read_text() + second.read_text())
    status, lines, err = replay(
        capsys, joined, "--json", "--passport", passport_file, "--gravity", g
    )
    assert status == EXIT_FAULT
    assert "joined.log: the time of the samples started again 1 time(s)" in err
    n = (
        clean_part.select(clean_part.t_s < clean_part.t_s[0] + 60.0).n_samples
        + faulty_part.n_samples
    )
    assert f"samples IMU0 {n}; left out none;" in err and "imu0.source_restarts 1" in err
    assert Predicate.F6 in [event_from_json(e).predicate for e in lines]


def test_passport_store_and_human_output(tmp_path, capsys):
    passport, g, _faulty, faulty_part, _ = flight()
    log = tmp_path / "flight.bin"
    write_dataflash_bin(log, {0: faulty_part})
    PassportStore(tmp_path / "store").put("uav-9", 0, passport)
    status, lines, _err = replay(
        capsys, log, "--passport-dir", tmp_path / "store", "--vehicle", "uav-9", "--gravity", g
    )
    assert status == EXIT_FAULT and len(lines) == 2
    assert (
        "WARNING" in lines[0] and "uav-9 IMU0 accelerometer: output off the unit sphere" in lines[0]
    )
    assert "ERROR" in lines[1] and "uav-9 IMU0 accelerometer z: scale factor error" in lines[1]


def _checks(coverage: dict, imu: int = 0) -> dict[str, dict]:
    """The coverage map's checks of one IMU by name ("accel F0", "stream", …)."""
    (entry,) = [e for e in coverage["imus"] if e["imu"] == imu]
    return {" ".join(filter(None, (c["triad"], c["check"]))): c for c in entry["checks"]}


def test_a_flight_every_check_ran_on_says_no_fault_with_what_it_tested(tmp_path, capsys):
    """The healthy twin against the nominal passport: F0 at rest and F1…F9 over its 13 positions ran,
    the gyro's checks cannot apply (a MEMS gyro cannot see the Earth rate), one IMU has no cross-check."""
    _passport, g, _faulty, _faulty_part, clean_part = flight()
    log = tmp_path / "clean.bin"
    write_dataflash_bin(log, {0: clean_part})
    status, lines, err, coverage = replay_with_coverage(capsys, log, "--json", "--gravity", g)
    assert status == 0 and lines == [] and coverage["verdict"] == "no fault"
    assert coverage["untested"] == [] and "verdict: no fault (every check that applies ran)" in err
    checks = _checks(coverage)
    f0, f19 = checks["accel F0"], checks["accel F1-F9"]
    assert f0["ran"] and f"imu0.f0.accel.tests {f0['samples']}," in err
    assert f19["ran"] and f19["positions"] == 13 and "imu0.positions 13," in err
    # F1…F9 detects λ + (z + 1.645)s: at least the tolerance, and no more than it plus a few of its
    # σ (0.6e-3 of the scale errors here).
    for mdf, tol in zip(f19["mdf_scale"], f19["tolerance_scale"], strict=True):
        assert tol < mdf < tol + 10 * 0.7e-3
    # F0's MDF is at least its shell λ0·g, a zero signal the nominal shell (±2.0 to ±2.2 m/s² from 50
    # to 200 Hz: the MPU-6000's worst unit plus the noise) lets through.
    assert all(2.0 < b < 2.6 for b in f0["mdf_bias_si"])
    assert not checks["gyro F0"]["applies"] and "Earth rate" in checks["gyro F0"]["reason"]
    assert (
        not checks["cross_imu"]["applies"] and checks["stream"]["samples"] == clean_part.n_samples
    )
    # The text says the JSON's figure; the x zero signal's tolerance is the MPU-6000's 50 mg.
    mdf_x = f19["mdf_bias_si"][0]
    assert 0.049 * 9.8 < mdf_x < 0.051 * 9.8 + 0.1
    assert (
        f"coverage IMU0 accel F1-F9: ran on 13 positions; min. detectable zero signal x {mdf_x:.3g} m/s²"
        in err
    )


def test_a_flight_with_too_few_positions_is_no_finding_within_coverage(tmp_path, capsys):
    """Before the landing (the flight and two rests) the diagnosis has too few positions: not
    "no fault" but what was not tested, a warning, exit 3."""
    _passport, g, faulty, _faulty_part, clean_part = flight()
    log = tmp_path / "short.bin"
    write_dataflash_bin(log, {0: clean_part.select(clean_part.t_s < faulty.landing_s + 20.0)})
    status, lines, err, coverage = replay_with_coverage(capsys, log, "--json", "--gravity", g)
    assert status == EXIT_UNTESTED and lines == []
    assert coverage["verdict"] == "no finding within coverage"
    n = _checks(coverage)["accel F1-F9"]["positions"]
    assert 0 < n < 9
    assert coverage["untested"] == [f"IMU0 accel F1-F9: {n} positions at rest, 9 needed"]
    assert (
        f"WARNING  verdict: no finding within coverage; not tested: IMU0 accel F1-F9: {n} positions"
        in err
    )
    status, _, err = replay(capsys, log, "--gravity", g)
    assert status == EXIT_UNTESTED and "no finding within coverage" in err and "no fault" not in err


@needs(REAL_BIN)
def test_real_ardupilot_dataflash_log_gives_a_deterministic_event_list(capsys):
    """pymavlink's test.BIN: 45 samples of IMU and IMU2 over one second, on the ground, no fault.

    Without a passport the nominal passport of a consumer MEMS applies; the unit is not static long
    enough for F0 to release a sample or for a position, so the list is empty — every time, paced or not — and the counts are fixed.
    """
    fast = replay(capsys, REAL_BIN, "--json")
    again = replay(capsys, REAL_BIN, "--json")
    paced = replay(capsys, REAL_BIN, "--json", "--pace", "recorded")
    assert fast[0] == EXIT_UNTESTED and fast[1] == again[1] == paced[1] == []
    assert "(bin): samples IMU0 45, IMU1 45; left out none; 0 events" in fast[2]
    assert "imu0.samples.accepted 45" in fast[2] and "imu1.samples.accepted 45" in fast[2]
    # No passport: the nominal passport of the default class; too short for F0 to test a sample.
    assert "no passport: nominal passport of class consumer_mems" in fast[2]
    assert "f0.accel.tests" not in fast[2]
    # So F0 and F1…F9 were not tested, and the verdict says so (the MEMS gyros' checks cannot apply);
    # nor the thrust axis, though the log holds GNSS: none of its 5 epochs falls in the flight.
    assert (
        "not tested: IMU0 accel F0: no rest: the accelerometer was never static; IMU0 accel F1-F9: "
        "0 positions at rest, 9 needed; IMU0 accel gross: no rest in 1 window(s) of 25 samples: the gyro "
        "was never still with the accelerometer quiet; IMU0 gyro gross: no rest in 1 window(s) of 25 "
        "samples: the accelerometer was never quiet near g with the gyro quiet; IMU0 accel "
        "cross_imu_norm, gyro cross_imu_norm: 0 samples of IMU0 paired with IMU1; the test starts "
        "after 20 s of them; IMU0 accel thrust_axis: no GNSS epoch in flight; IMU1 accel F0:"
        in fast[2]
    )


@needs(REAL_TLOG)
def test_real_vtol_telemetry_log_gives_a_deterministic_event_list(capsys, tmp_path):
    """ArduPlane SITL VTOL flight (SOURCE.md): RAW_IMU as IMU0 and SCALED_IMU2 as IMU1, ~4 Hz over 208 s, no fault.

    Stream checks only (no passport); the two IMUs agree within the cross-IMU limits all flight: no event.
    Two RAW_IMU messages repeat their time stamp and are left out, counted.
    """
    fast = replay(capsys, REAL_TLOG, "--json")
    again = replay(capsys, REAL_TLOG, "--json")
    assert fast[0] == EXIT_UNTESTED and fast[1] == again[1] == [] and fast[2] == again[2]
    assert "(tlog): samples IMU0 794, IMU1 795; left out time_not_increasing 2; 0 events" in fast[2]
    # At 4 Hz the static detector's window holds two samples: no nominal passport, stream checks only.
    assert "IMU0: sampled at 4.13 Hz, too slow to tell rest from steady flight" in fast[2]
    assert (
        "not tested: IMU0 accel F0, accel F1-F9, gyro F0, gyro F1-F9: sampled at 4.13 Hz" in fast[2]
    )
    assert "coverage IMU1 cross_imu: ran on 795 samples" in fast[2]
    assert "imu0.samples.accepted 794" in fast[2] and "imu1.samples.accepted 795" in fast[2]
    # Its first samples come at two rates (0.24 s and 0.5 s steps): the probe keeps 4.1 Hz, which
    # the rate watch finds again over the flight: no re-size.
    assert "rate_changes" not in fast[2]
    # The comparison does run, bin for bin, on this log's 25 s frames: with limits below the IMUs' real differences it fires.
    tight = tmp_path / "tight.toml"
    tight.write_text("[validity]\ncross_imu_accel_mps2 = 0.01\ncross_imu_gyro_rps = 0.0005\n")
    status, lines, _ = replay(capsys, REAL_TLOG, "--json", "--config", str(tight))
    events = [event_from_json(line) for line in lines]
    assert (
        status == EXIT_UNTESTED
        and {e.predicate for e in events} == {Predicate.CROSS_IMU}
        and len(events) >= 4
    )


@needs(REAL_ULOG)
def test_real_px4_ulog_replays_its_primary_imu(capsys):
    """PX4 SITL flight (SOURCE.md): sensor_combined at 250 Hz; the per-instance topics (1–2 Hz) are left out."""
    status, lines, err = replay(capsys, REAL_ULOG, "--json")
    assert status == EXIT_UNTESTED and lines == []
    assert "(ulg): samples IMU0 7783; left out none; 0 events" in err
    # F0 tested the samples at rest, the unit level: only z saw gravity; one position, no diagnosis.
    assert (
        "coverage IMU0 accel F0: ran on 7,034 samples; min. detectable zero signal x not seen, "
        "y not seen, z 2.27 m/s²" in err
    )
    assert "not tested: IMU0 accel F1-F9: 1 position at rest, 9 needed" in err
    assert "rate_changes" not in err


@needs(REAL_COPTER31)
def test_real_copter31_log_without_imu_data_says_what_it_holds(capsys):
    status, lines, err = replay(capsys, REAL_COPTER31)
    assert status == 2 and lines == [] and len(err.splitlines()) == 1
    assert (
        "no IMU data (messages IMU, IMU2, IMU3)" in err and "ATT 1100" in err and "CTUN 1100" in err
    )


@pytest.mark.parametrize(
    "argv, match",
    [
        (["/nonexistent/flight.bin"], "no such log file"),
        ([__file__], "not a MAVLink .tlog, a DataFlash .bin/.log or a PX4 ULog"),
        (["LOG", "--passport", "/nonexistent.json"], "nonexistent.json"),
        (["LOG", "--gravity", "3.7"], "gravity"),
    ],
)
def test_unusable_input_is_a_one_line_error(argv, match, capsys, tmp_path):
    """A readable log (LOG: one second of the demo flight) with an unusable option is refused the same way."""
    log = tmp_path / "flight.bin"
    session = flight()[3]
    write_dataflash_bin(log, {0: session.select(session.t_s < session.t_s[0] + 1.0)})
    status, lines, err = replay(capsys, *(str(log) if a == "LOG" else a for a in argv))
    assert status == 2 and match in err and lines == []


@needs(REAL_TLOG)
def test_a_telemetry_log_reads_in_times_from_its_start_and_its_report_says_no_passport_applied(
    capsys, tmp_path
):
    """Issue 34: event times were Unix epochs (``t=1710773374.854 s``, plot axes offset by
    1.7107733e9) and the report said "Passport: nominal" where replay applied none (4 Hz). The
    start is said once; the events and the plots count from it; the report says what applied."""
    import re

    tight = tmp_path / "tight.toml"
    tight.write_text("[validity]\ncross_imu_accel_mps2 = 0.01\ncross_imu_gyro_rps = 0.0005\n")
    status = main(
        ["replay", str(REAL_TLOG), "--config", str(tight), "--report", str(tmp_path / "r")]
    )
    out = capsys.readouterr()
    times = [float(re.match(r"t=\s*(-?[\d.]+) s ", line)[1]) for line in out.out.splitlines()]
    assert status == EXIT_UNTESTED and len(times) >= 4
    assert all(0.0 <= t <= 210.0 for t in times)  # the flight's 208 s
    (start,) = re.findall(
        r"ardupilot-sitl-vtol\.tlog starts at ([\d.]+) s of the log's clock: times count", out.err
    )
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert report["log"]["start_t_s"] == pytest.approx(float(start), abs=5e-4)
    md = (tmp_path / "r" / "report.md").read_text()
    assert "Passport: nominal" not in md
    assert "No passport applied, stream checks only: replay IMU0: sampled at 4.13 Hz" in md
    assert f"Starts at {start} s of the log's clock" in md
    # This log counts from the autopilot's boot; a Unix clock is dated as well.
    assert (
        log_start(1710773374.854)
        == "1710773374.854 s of the log's clock, 2024-03-18T14:49:34.854 UTC"
    )


@pytest.mark.filterwarnings("error::RuntimeWarning")  # said by replay, not by numpy
def test_a_sample_too_large_for_the_reports_figures_leaves_the_verdict_said_and_the_report_refused(
    tmp_path, capsys, passport_file
):
    """A text DataFlash log carries float64: one accelerometer value of 1e300 m/s² is rejected by
    the pipeline (implausible, counted) but reaches the report's figures, whose squares overflow.
    Before the report's low-passes were first_order_filter the verdict was said and report.json
    then failed on its NaNs (status 2); with them the replay stopped at that frame, the coverage
    and the verdict unsaid. The verdict is said, and the report refused naming why (status 2);
    numpy's overflow warning is not printed beside it."""
    _passport, g, _faulty, _part, clean = flight()
    session = clean.select(clean.t_s < clean.t_s[0] + 40.0)  # past a pass of the figures
    accel = session.accel_mps2.copy()
    accel[500, 0] = 1e300
    log = tmp_path / "big.log"
    write_dataflash_text(log, {0: dataclasses.replace(session, accel_mps2=accel)})
    status, _, err = replay(
        capsys, log, "--passport", passport_file, "--gravity", g, "--report", tmp_path / "r"
    )
    assert status == 2
    assert "imu0.samples.rejected.implausible_value 1" in err and "verdict: " in err
    assert "report not written: IMU0's figures: first_order_filter: an output is not finite" in err
    assert not (tmp_path / "r" / "report.json").exists()


BATCHES_FAULTS = """
import json, resource, sys
import numpy as np
if sys.argv[1] == "set":
    from service.commands.replay import keep_freed_memory
    keep_freed_memory()
def batch():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones(1 << 17) for _ in range(6)]  # a batch's temporaries: six of 1 MiB
    del arrays
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(json.dumps([batch() for _ in range(4)]))
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc thresholds")
def test_replay_s_process_keeps_the_memory_its_batches_free():
    # glibc maps each temporary above its mmap threshold afresh and returns a heap top beyond its
    # trim threshold: every batch faulted its temporaries in again, page by page (system time).
    # With replay's thresholds the first batch's pages serve the next ones. In a fresh interpreter,
    # so that nothing before has raised glibc's own.

    def faults(mode: str) -> list[int]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        run = subprocess.run(
            [sys.executable, "-c", BATCHES_FAULTS, mode],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        return json.loads(run.stdout)

    pages = (6 << 20) // 4096
    assert min(faults("default")[1:]) >= pages // 2  # what the test tells apart: glibc's default
    assert faults("set")[1:] == [0, 0, 0]
