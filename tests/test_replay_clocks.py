"""A log whose IMUs stamp time on different clocks (issue 29, class 6, offline): ArduPilot's RAW_IMU
carries a 64-bit microsecond time (a Unix time on some boards), SCALED_IMU2 a 32-bit time since boot.

``replay`` compares the two IMUs at the offset of their clocks, which it measures from the rotation
both saw: the same events as the log whose IMUs share one clock, each at its own IMU's time, and no
flapping cross-IMU events.
"""

from __future__ import annotations

import dataclasses
import json
import struct

from pymavlink import mavutil
from replay_support import replay_with_coverage

from protocols.events import Predicate
from protocols.logs import write_tlog
from service.demo import demo_passport, demo_scenario

UNIX_S = 1.7e9
"""Where IMU0's clock starts when it stamps Unix time."""
BOOT_S = 40.0
"""Where IMU1's clock (time since boot) starts."""


def _two_imu_tlog(path, imu0_start_s: float) -> None:
    """IMU0 the demo's session without its fault (RAW_IMU, its clock from ``imu0_start_s``), IMU1
    with z 0.1 g off from 66.5 s (SCALED_IMU2, since boot): the records interleaved by the ground
    station's wall clock, as a real tlog's."""
    clean = demo_scenario(fault_magnitude=0.0).session
    bad = demo_scenario(fault_index=2, fault_magnitude=0.1).session
    records = []
    for imu, session, start_s in ((0, clean, imu0_start_s), (1, bad, BOOT_S)):
        part = path.with_suffix(f".imu{imu}")
        moved = dataclasses.replace(session, t_s=session.t_s + start_s)
        write_tlog(part, {imu: moved}, wall_start_s=UNIX_S - start_s)
        log = mavutil.mavlink_connection(str(part), dialect="ardupilotmega")
        while (msg := log.recv_match()) is not None:
            records.append((msg._timestamp, msg.get_msgbuf()))
        log.close()
    records.sort(key=lambda r: r[0])
    path.write_bytes(b"".join(struct.pack(">Q", round(t * 1e6)) + buf for t, buf in records))


def test_imus_on_a_unix_and_a_boot_clock_are_compared_as_on_one_clock(tmp_path, capsys):
    gravity = str(demo_passport()[1])
    one, two = tmp_path / "one.tlog", tmp_path / "two.tlog"
    _two_imu_tlog(one, BOOT_S)
    _two_imu_tlog(two, UNIX_S)
    got = {}
    for log in (one, two):
        status, lines, err, coverage = replay_with_coverage(
            capsys, log, "--json", "--gravity", gravity
        )
        got[log] = status, [json.loads(line) for line in lines], coverage
    (s1, on_one, _), (s2, on_two, coverage) = got[one], got[two]
    assert s2 == s1
    assert [(e["predicate"], e["imu"]) for e in on_two] == [
        (e["predicate"], e["imu"]) for e in on_one
    ]
    # The 0.1 g disagreement once per IMU, not flapping.
    cross = [e for e in on_two if e["predicate"] == Predicate.CROSS_IMU.value]
    assert [e["imu"] for e in cross] == [0, 1]
    # Each event at its own IMU's time: the offset is measured to a sample (5 ms).
    base = {0: UNIX_S, 1: BOOT_S}
    for e1, e2 in zip(on_one, on_two, strict=True):
        assert abs((e2["t_s"] - base[e2["imu"]]) - (e1["t_s"] - BOOT_S)) <= 0.005, (e1, e2)
    ran = {
        (imu["imu"], c["ran"])
        for imu in coverage["imus"]
        for c in imu["checks"]
        if c["check"] == "cross_imu"
    }
    assert ran == {(0, True), (1, True)}
    # As a person reads it: each IMU's times from its own clock's start (IMU0's were 1.7e9 s off).
    _, lines, err, _ = replay_with_coverage(capsys, two, "--gravity", gravity)
    assert "IMU1 stamps another clock (or started late): it starts at 40.000 s of its clock" in err
    assert [line[:14] for line in lines if "[cross_imu]" in line] == ["t=    66.500 s"] * 2
