"""A restart inside a log (issue 30): an autopilot reboot in a ground station's tlog, logs joined end to end.

The time since boot starts again near zero. Every sample the reader passes reaches the pipeline (none
refused as out of order, no `rejected samples` warning), one reboot is said once however many IMUs
restarted, and the report keeps the runs apart (a block index repeats after the restart).
"""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np
from replay_support import replay_with_coverage

from estimators.log_health import ImuHealthAccumulator, pair_difference
from protocols.events import Predicate
from protocols.logs import read_log_sessions, write_dataflash_bin, write_tlog
from service.cli import EXIT_NO_FAULT
from service.demo import demo_passport, demo_scenario

BOOT_S = 3.0
"""Time since boot of the first sample after the reboot: the autopilot's start-up."""
UPTIME_S = 40.0
"""Time since boot of the log's first sample."""


@functools.cache
def boots():
    """A healthy two-IMU unit at telemetry rate (25 Hz), its session cut in two boots.

    The cut is not on a batch boundary of the replay (100 samples), so one batch would hold samples of
    both clocks."""
    s = demo_scenario(fault_magnitude=0.0).session.select(slice(0, None, 8))
    first, second = s.select(s.t_s < 61.3), s.select(s.t_s >= 61.3)
    first = dataclasses.replace(first, t_s=first.t_s + UPTIME_S)
    second = dataclasses.replace(second, t_s=second.t_s - second.t_s[0] + BOOT_S)
    return first, second


def rebooted_tlog(path):
    """The ground station logs on through the reboot: its wall-clock record stamps go on, ten
    seconds later, while the messages' time since boot starts again."""
    first, second = boots()
    a, b = path.with_suffix(".a"), path.with_suffix(".b")
    write_tlog(a, {0: first, 1: first}, wall_start_s=1.7e9)
    write_tlog(b, {0: second, 1: second}, wall_start_s=1.7e9 + first.t_s[-1] + 10.0)
    path.write_bytes(a.read_bytes() + b.read_bytes())


def joined_bin(path):
    """Two DataFlash logs of the two boots joined end to end."""
    first, second = boots()
    a, b = path.with_suffix(".a"), path.with_suffix(".b")
    write_dataflash_bin(a, {0: first, 1: first})
    write_dataflash_bin(b, {0: second, 1: second})
    path.write_bytes(a.read_bytes() + b.read_bytes())


def _counters(err: str) -> dict[str, int]:
    (line,) = [x for x in err.splitlines() if "replay: counters " in x]
    pairs = line.split("counters ", 1)[1].split(", ")
    return {k: int(v) for k, v in (p.rsplit(" ", 1) for p in pairs)}


def _check_reboot(capsys, log, out):
    first, second = boots()
    n = first.n_samples + second.n_samples
    sessions, stats = read_log_sessions(log)
    assert {imu: s.n_samples for imu, s in sessions.items()} == {0: n, 1: n}
    assert stats.clock_restarts == 1 and stats.dropped == {}
    status, events, err, coverage = replay_with_coverage(
        capsys, log, "--json", "--report", out, "--gravity", demo_passport()[1]
    )
    assert status == EXIT_NO_FAULT, err
    # One reboot restarts both IMUs' clocks: said once.
    assert f"{log.name}: the time of the samples started again 1 time(s)" in err
    c = _counters(err)
    for imu in (0, 1):
        # Every sample the reader passed reached the pipeline: none refused around the restart.
        assert c[f"imu{imu}.samples.accepted"] == n
        assert c[f"imu{imu}.source_restarts"] == 1 and c[f"imu{imu}.new_runs"] == 1
        assert not [k for k in c if k.startswith(f"imu{imu}.samples.rejected")]
        assert not [k for k in c if k.startswith(f"imu{imu}.frames.rejected")]
    assert coverage["samples"] == {"0": n, "1": n}
    assert not [e for e in events if Predicate.ERROR_DENSITY.value in e]
    report = json.loads((out / "report.json").read_text())
    assert [e["runs"] for e in report["imus"]] == [2, 2]
    assert report["log"]["clock_restarts"] == 1
    # The twins agree block by block within each run; the report has the blocks of both.
    (pair,) = report["pairs"]
    blocks_per_boot = [np.unique(np.floor(s.t_s / report["block_s"])).size for s in (first, second)]
    assert pair["common_blocks"] == sum(blocks_per_boot)
    assert pair["accel_mps2"]["flight"]["max"] == 0.0


def test_a_reboot_in_a_ground_station_tlog_loses_no_sample_and_is_said_once(tmp_path, capsys):
    log = tmp_path / "reboot.tlog"
    rebooted_tlog(log)
    _check_reboot(capsys, log, tmp_path / "report")


def test_two_dataflash_logs_joined_end_to_end_lose_no_sample_and_are_said_once(tmp_path, capsys):
    log = tmp_path / "joined.bin"
    joined_bin(log)
    _check_reboot(capsys, log, tmp_path / "report")


def test_the_health_figures_keep_the_runs_apart():
    """Blocks of a restarted clock repeat the block indices of the run before: a pair is compared
    on the same block of the same run, and the restart's step is no sample interval."""
    first, second = boots()
    acc = {imu: ImuHealthAccumulator() for imu in (0, 1)}
    for s in (first, second):
        for imu in (0, 1):
            acc[imu].update(s.t_s, s.accel_mps2, s.gyro_rps)
    h0, h1 = (a.result(9.81) for a in acc.values())
    assert h0.runs == 2 and h0.n_samples == first.n_samples + second.n_samples
    assert h0.gap_count == 0 and h0.rate_hz == 25.0
    span = lambda s: s.t_s[-1] - s.t_s[0]  # noqa: E731
    assert h0.duration_s == span(first) + span(second)
    assert np.unique(h0.blocks.k).size < h0.blocks.k.size  # the indices do repeat
    pair = pair_difference((0, 1), h0.blocks, h1.blocks, 0.5)
    assert pair.t_s.size == h0.blocks.k.size
    assert np.array_equal(pair.run, h0.blocks.run) and not pair.accel_mps2.any()
