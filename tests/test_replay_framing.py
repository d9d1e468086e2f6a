"""Replay's events and report do not depend on how the log's frames are grouped (issue 33).

Replay hands each IMU's pipeline its frames joined up to :data:`~service.commands.replay.REPLAY_GROUP_SAMPLES`
(it took them one by one before): every stage whose result depended on where the pipeline's batches
were cut would change its events or ``report.json``. The previous path, frame by frame, is the
oracle, run inside each test.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import pytest
from real_data import FIELD, LOGS, needs
from replay_support import replay_with_coverage

import service.commands.replay as replay_command
from estimators.log_health import ImuHealthAccumulator
from protocols.logs import write_dataflash_bin, write_dataflash_text, write_tlog
from protocols.passport_codec import write_passport_json
from protocols.ulog import SYNC_BYTES, write_ulog
from service.demo import DEMO_FAULT_MAGNITUDE, demo_passport, demo_scenario
from service.pipeline.imu_pipeline import ImuPipeline

FRAME_BY_FRAME = replay_command.REPLAY_BATCH_SAMPLES
"""A group of one frame: the path replay took before issue 33."""


WRITERS = {".bin": write_dataflash_bin, ".log": write_dataflash_text, ".tlog": write_tlog}


def _definitions(data, suffix):
    """Where a log's data starts after its definitions: a DataFlash log's two FMT messages (89
    bytes each, or two lines), a ULog's header up to its first sync message; a tlog has none."""
    if suffix == ".bin":
        return 2 * 89
    if suffix == ".log":
        return data.index(b"\n", data.index(b"\n") + 1) + 1
    return data.index(b"\x08\x00S" + SYNC_BYTES) if suffix == ".ulg" else 0


def _replay(capsys, monkeypatch, tmp_path, log, group_samples, *options):
    """Status, events, the coverage line and report.json of a replay whose pipelines take the frames
    in groups of ``group_samples`` (None: the command's own)."""
    out = tmp_path / f"report-{group_samples}"
    with monkeypatch.context() as m:
        if group_samples is not None:
            m.setattr(replay_command, "REPLAY_GROUP_SAMPLES", group_samples)
        status, lines, _, coverage = replay_with_coverage(
            capsys, log, "--json", "--report", out, *options
        )
    return status, lines, coverage, json.loads((out / "report.json").read_text())


@functools.cache
def _boots():
    """The demo unit at 100 Hz with its accelerometer fault, 2 s lost in flight, then the autopilot
    rebooted (the clock starts again at 3 s)."""
    s = demo_scenario(fault_magnitude=DEMO_FAULT_MAGNITUDE).session.select(slice(0, None, 2))
    s = s.select((s.t_s < 40.0) | (s.t_s >= 42.0))
    first, second = s.select(s.t_s < 81.3), s.select(s.t_s >= 81.3)
    return first, dataclasses.replace(second, t_s=second.t_s - second.t_s[0] + 3.0)


@pytest.mark.parametrize("suffix", [".bin", ".log", ".tlog", ".ulg"])
def test_events_and_report_are_the_same_however_the_frames_are_grouped(
    capsys, monkeypatch, tmp_path, suffix
):
    """A fault, a gap and a reboot in a log of each format: frame by frame, in groups of 1000
    and 4096 samples and of replay's own (more than a boot) give the same events (ids included),
    coverage line and report.json, to the bit. The reader joins the frames (but frame by frame)
    across the blocks its decoder reads."""
    parts = []
    for k, boot in enumerate(_boots()):
        part = tmp_path / f"boot{k}{suffix}"
        if suffix == ".ulg":
            write_ulog(part, {0: boot}, topics=["sensor_combined"])
        else:
            WRITERS[suffix](part, {0: boot})
        data = part.read_bytes()
        # The second boot's messages after the first's definitions (a tlog has none).
        parts.append(data[_definitions(data, suffix) :] if k else data)
    log = tmp_path / f"joined{suffix}"
    log.write_bytes(b"".join(parts))
    passport, g = demo_passport()
    pfile = tmp_path / "passport.json"
    write_passport_json(passport, pfile)
    options = ("--passport", pfile, "--gravity", g)
    runs = [
        _replay(capsys, monkeypatch, tmp_path, log, size, *options)
        for size in (FRAME_BY_FRAME, 1000, 4096, replay_command.REPLAY_GROUP_SAMPLES)
    ]
    status, lines, _, report = runs[0]
    # The log holds what the test is about: the fault found, the reboot and the gap seen.
    assert status == 1 and any('"predicate":"F0"' in line for line in lines)
    assert report["log"]["clock_restarts"] == 1 and report["imus"][0]["gaps"]["count"] >= 1
    assert all(run == runs[0] for run in runs[1:])


@pytest.mark.parametrize(
    "log",
    [
        pytest.param(path, marks=needs(path), id=path.name)
        for path in (
            LOGS / "px4-events.ulg",
            FIELD / "px4-fmuv3-10hz.ulg",
            FIELD / "px4-fmuv5-knock.ulg",
            LOGS / "ardupilot-test.BIN",
        )
    ],
)
def test_a_shared_log_replays_as_it_did_frame_by_frame(log, capsys, monkeypatch, tmp_path):
    """The shared logs of one IMU (grouped) and a small one of two (frame by frame): replay's
    events, coverage line and report.json are those of the previous path. The SITL tlog of two
    IMUs goes frame by frame as before; it is left to the replay tests' own checks."""
    before = _replay(capsys, monkeypatch, tmp_path, log, FRAME_BY_FRAME)
    assert _replay(capsys, monkeypatch, tmp_path, log, None) == before


def test_frames_lost_to_a_pipeline_error_in_a_group_are_all_counted(capsys, monkeypatch, tmp_path):
    """The chain raises on the samples of one second of flight: replay names as many frames as the
    failing calls took (frame by frame a few; grouped, the whole group of about 41 frames is lost,
    not one frame as the count of calls says)."""
    log = tmp_path / "boot.bin"
    write_dataflash_bin(log, {0: _boots()[0]})
    lost: list[int] = []
    process = ImuPipeline.process

    def failing(self, batch, *, arrival_s, frames=1):
        if ((batch.t_s >= 30.0) & (batch.t_s < 31.0)).any():
            lost.append(frames)
            raise ValueError("injected")
        return process(self, batch, arrival_s=arrival_s, frames=frames)

    monkeypatch.setattr(ImuPipeline, "process", failing)
    for size in (FRAME_BY_FRAME, replay_command.REPLAY_GROUP_SAMPLES):
        lost.clear()
        with monkeypatch.context() as m:
            m.setattr(replay_command, "REPLAY_GROUP_SAMPLES", size)
            *_, err, _ = replay_with_coverage(capsys, log, "--gravity", demo_passport()[1])
        assert f"the pipeline failed on {sum(lost)} frame(s) (ValueError: injected)" in err
    assert max(lost) > 1  # the grouped run lost a joined batch of several frames


def test_the_reports_spectra_are_those_of_the_frames_one_by_one(capsys, monkeypatch, tmp_path):
    """The report's accumulator summed its periodograms per pass of the frames it queued (about
    4,096 samples): fed the reader's joined batches (16,400 samples) it summed them in other
    passes, and the spectra (the report's figure) moved in their last bits. It sums them in groups
    counted from the run's start: fed the joined batches, the spectra of the demo-fault ULog's
    first 100 s (a batch of 163 frames, then 37 joined) are the bits of the frame-by-frame replay."""
    log = tmp_path / "demo.ulg"
    session = demo_scenario(fault_magnitude=DEMO_FAULT_MAGNITUDE).session.select(slice(0, 20_000))
    write_ulog(log, {0: session}, topics=["sensor_combined"])
    spectra: list[bytes] = []
    result = ImuHealthAccumulator.result

    def kept(self, gravity_mps2):
        health = result(self, gravity_mps2)
        spectra.append(health.accel_psd.tobytes() + health.gyro_psd.tobytes())
        return health

    monkeypatch.setattr(ImuHealthAccumulator, "result", kept)
    runs = [_replay(capsys, monkeypatch, tmp_path, log, size) for size in (FRAME_BY_FRAME, None)]
    assert len(spectra) == 2 and spectra[1] == spectra[0]
    assert runs[1] == runs[0]
