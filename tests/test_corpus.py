"""The corpus harness (issue 30, item 1): every file under ``../shared/data``, every command that
applies, checked for invariants, not for today's numbers.

Logs (``.ulg``, ``.bin``, ``.log``, ``.tlog``): ``replay`` plain and with ``--json --report``
ends with a documented exit status (0-3) and no traceback, writes its report, reads as many IMU
samples as the format's own library (pyulog, pymavlink) holds of the messages it names as its
sources (those it leaves out counted), at the rate of the library's time stamps, one IMU per
instance, and names every other IMU message the log holds as left out (its count in the report).
Its firmware section reads every vibration message and batch-sampler header the library reads,
and nothing of it went unread.
Sessions (a folder whose sidecar says ``kind = "session"``): ``calibrate`` writes a passport
from the positions its SOURCE.md states, ``diagnose`` of the session against that passport fails
no F0 beyond its false-alarm rate, ``audit`` runs.

Adding a file to the folder adds it here: a log is found by its suffix; anything else must be
named by a sidecar, ``tests/corpus/<name>.toml`` (``<name>``: the file's or the session folder's
name without suffix), with what its SOURCE.md states where an invariant needs it (the options
its units need, the positions, the exit status, an IMU count, why a message is not listed yet).
The shared folder is read-only, so the sidecars live here.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.cli import main
from tests.real_data import DATA, needs

SIDECARS = Path(__file__).parent / "corpus"
LOG_SUFFIXES = (".ulg", ".bin", ".log", ".tlog")
DOCUMENTS = ("SOURCE.md", "LICENSE")
"""Files that describe data and are no data."""
IMU_SOURCES = (
    "IMU", "IMU2", "IMU3", "ACC", "GYR", "ISBH", "ISBD",
    "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU",
    "sensor_combined", "sensor_accel", "sensor_gyro", "vehicle_imu",
)  # fmt: skip
"""Message types and topics that carry IMU samples (a topic's ``.N`` instance stripped)."""
REPLICAS = "5"
"""The audit's Monte Carlo replicas here (its least): the invariants do not depend on their number."""


def sidecar(path: Path) -> dict[str, Any]:
    """What ``tests/corpus/<name>.toml`` states of ``path`` (empty without one)."""
    name = path.name if path.is_dir() else path.stem
    file = SIDECARS / f"{name}.toml"
    return tomllib.loads(file.read_text()) if file.exists() else {}


def _corpus() -> tuple[list[Path], list[Path], list[Path]]:
    """The logs, the session folders and the files no command reads (none may be)."""
    if not DATA.exists():
        return [], [], []
    logs, sessions, unread = [], [], []
    for path in sorted(DATA.rglob("*")):
        if path.is_dir():
            if sidecar(path).get("kind") == "session":
                sessions.append(path)
            continue
        if path.name in DOCUMENTS:
            continue
        if path.suffix.lower() in LOG_SUFFIXES:
            logs.append(path)
            continue
        folder = sidecar(path.parent)
        named = [folder.get("session"), *folder.get("companions", ())]
        if folder.get("kind") != "session" or path.name not in named:
            unread.append(path)
    return logs, sessions, unread


LOGS, SESSIONS, UNREAD = _corpus()
REFUSED = [log for log in LOGS if sidecar(log).get("exit_status") == 2]
"""Logs their SOURCE.md says hold no IMU data: replay refuses them, so there is nothing to compare."""
READ = [log for log in LOGS if log not in REFUSED]
pytestmark = needs(DATA)


def _ids(paths: list[Path]) -> list[str]:
    return [str(p.relative_to(DATA)) for p in paths]


@dataclass(frozen=True)
class Run:
    status: int
    out: str
    err: str


def _run(argv: list[str]) -> Run:
    """A command in this process, its output captured."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return Run(status, out.getvalue(), err.getvalue())


@functools.cache
def replayed(log: Path, folder: Path) -> tuple[Run, dict[str, Any] | None]:
    """``replay LOG --json --report FOLDER`` once per log, and its report.json (None: none)."""
    run = _run(["replay", str(log), "--json", "--report", str(folder)])
    report = folder / "report.json"
    return run, json.loads(report.read_text()) if report.exists() else None


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("corpus")
    return lambda log: replayed(log, root / log.stem)


def test_every_file_of_the_corpus_is_read_by_a_command():
    """A file that is no log and no session a sidecar names would go untested: name it."""
    assert LOGS or SESSIONS
    assert not UNREAD, (
        f"no command reads {_ids(UNREAD)}: add tests/corpus/<name>.toml (module docstring)"
    )


def _said(run: Run) -> str:
    return run.out + run.err


@pytest.mark.parametrize("log", LOGS, ids=_ids(LOGS))
def test_replay_with_json_and_report_ends_as_documented(log, reports):
    run, report = reports(log)
    # Unusable input (2) only where the sidecar says SOURCE.md makes it so (no IMU data).
    expected = sidecar(log).get("exit_status")
    assert run.status == expected if expected is not None else run.status in (0, 1, 3)
    assert "Traceback" not in _said(run)
    lines = [json.loads(line) for line in run.out.splitlines()]
    if run.status == 2:
        assert run.err.strip() and report is None
        return
    assert lines and lines[-1]["type"] == "ins.health.coverage"
    assert lines[-1]["exit_status"] == run.status
    assert report is not None and (Path(report["log"]["name"]).name == log.name)


@pytest.mark.slow
@pytest.mark.parametrize("log", LOGS, ids=_ids(LOGS))
def test_plain_replay_ends_as_with_json(log, reports):
    plain = _run(["replay", str(log)])
    assert "Traceback" not in _said(plain)
    assert plain.status == reports(log)[0].status


# --- what the format's own library reads ----------------------------------------------------


def _time_s(fields: dict[str, Any]) -> float:
    for key, scale in (("TimeUS", 1e-6), ("time_usec", 1e-6), ("time_boot_ms", 1e-3)):
        if key in fields:
            return float(fields[key]) * scale
    return float(fields["TimeMS"]) * 1e-3


def _mavlink_stamps(log: Path, sources: set[str]) -> dict[tuple[str, int], list[float]]:
    """pymavlink's read: the time stamps of each (message, instance ``I``) of ``sources``."""
    from pymavlink import mavutil

    stamps: dict[tuple[str, int], list[float]] = {}
    conn = mavutil.mavlink_connection(str(log))
    try:
        while (msg := conn.recv_match(type=sorted(sources))) is not None:
            fields = msg.to_dict()
            key = (msg.get_type(), int(fields.get("I", 0)))
            stamps.setdefault(key, []).append(_time_s(fields))
    finally:
        conn.close()
    return stamps


def _ulog_stamps(log: Path, sources: set[str]) -> dict[tuple[str, int], list[float]]:
    """pyulog's read: the time stamps of each (topic, multi_id) of ``sources``."""
    from pyulog import ULog

    ulog = ULog(str(log), sorted(sources))
    # From the first stamp, in integer µs: seconds since 1970 as floats would round the steps.
    return {
        (d.name, d.multi_id): list((d.data["timestamp"] - d.data["timestamp"][0]) * 1e-6)
        for d in ulog.data_list
    }


def _library_stamps(log: Path, report: dict[str, Any]) -> dict[tuple[str, int], np.ndarray]:
    sources = {imu["source"] for imu in report["imus"]}
    read = _ulog_stamps if log.suffix.lower() == ".ulg" else _mavlink_stamps
    return {k: np.asarray(v) for k, v in read(log, sources).items()}


def _library_stream(imu: dict[str, Any], report: dict[str, Any], stamps) -> np.ndarray:
    """The library's stamps of one replayed IMU: its source's instance numbered as the IMU when
    several IMUs share the source (DataFlash ``IMU`` with ``I``), else the source's one stream."""
    same_source = [i for i in report["imus"] if i["source"] == imu["source"]]
    keys = [k for k in stamps if k[0] == imu["source"]]
    if len(same_source) > 1:
        keys = [k for k in keys if k[1] == imu["imu"]]
    assert len(keys) == 1, f"IMU{imu['imu']} ({imu['source']}): library streams {keys}"
    return stamps[keys[0]]


def _replayed_report(log, reports) -> dict[str, Any]:
    run, report = reports(log)
    assert report is not None, f"replay wrote no report for {log.name} (status {run.status})"
    return report


IMU_NAME = re.compile(r"^(IMU\d?|ACC\d?|GYR\d?|RAW_IMU|SCALED_IMU\d?|HIGHRES_IMU)$")
"""IMU message names of DataFlash (current and legacy) and MAVLink, as pymavlink names them."""


@pytest.mark.parametrize("log", REFUSED, ids=_ids(REFUSED))
def test_a_log_replay_refuses_holds_no_imu_message_pymavlink_reads(log, reports):
    """The refusal is right: the format's own library finds no IMU message in it either."""
    from pymavlink import mavutil

    assert reports(log)[0].status == 2
    conn = mavutil.mavlink_connection(str(log))
    try:
        names = set()
        while (msg := conn.recv_match()) is not None:
            names.add(msg.get_type())
    finally:
        conn.close()
    assert names, f"pymavlink read nothing at all from {log.name}"
    assert not {n for n in names if IMU_NAME.match(n)}, sorted(names)


@pytest.mark.parametrize("log", READ, ids=_ids(READ))
def test_replay_reads_the_samples_and_instances_the_format_library_reads(log, reports):
    """Per source: the samples replayed plus those left out and counted are the library's
    messages; one IMU per library stream; the IMU count a sidecar states."""
    report = _replayed_report(log, reports)
    stamps = _library_stamps(log, report)
    read = sum(imu["n_samples"] for imu in report["imus"])
    dropped = sum(report["log"]["dropped_samples"].values())
    assert read + dropped == sum(s.size for s in stamps.values())
    assert len(report["imus"]) == len(stamps) == sidecar(log).get("imus", len(stamps))
    for imu in report["imus"]:
        assert imu["n_samples"] <= _library_stream(imu, report, stamps).size


@pytest.mark.parametrize("log", READ, ids=_ids(READ))
def test_replay_rates_are_the_library_stamps_rates(log, reports):
    """The report's rate is its typical step's (an interquartile mean, insensitive to gaps and
    bunched stamps): a step between the library's own 25th and 75th percentile steps."""
    report = _replayed_report(log, reports)
    stamps = _library_stamps(log, report)
    for imu in report["imus"]:
        steps = np.diff(np.sort(_library_stream(imu, report, stamps)))
        low, high = np.percentile(steps[steps > 0], [25, 75])
        assert low * (1 - 1e-9) <= 1.0 / imu["rate_hz"] <= high * (1 + 1e-9)


FIRMWARE_LEVELS = ("VIBE", "VIBRATION", "vehicle_imu_status")
"""The firmware's own vibration messages (protocols/firmware_health.py): one level a message."""


@pytest.mark.parametrize("log", READ, ids=_ids(READ))
def test_the_firmware_s_own_health_data_are_read_as_the_format_library_reads_them(log, reports):
    """Nothing of the firmware section went unread (its reader turns a decoding error into a line
    of the report, which would hide a reader gone wrong), every vibration message the library reads
    is a level of the report or left out as not finite, and the batch sampler's blocks are its
    ``ISBH`` headers with at most 32 samples an ``ISBD``."""
    report = _replayed_report(log, reports)
    firmware = report["firmware"]
    assert firmware["unread"] == ""
    read = _ulog_stamps if log.suffix.lower() == ".ulg" else _mavlink_stamps
    held: dict[str, int] = {}
    for (name, _), s in read(log, {*FIRMWARE_LEVELS, "ISBH", "ISBD"}).items():
        held[name] = held.get(name, 0) + len(s)
    levels: dict[str, int] = {}
    for v in firmware["vibration"]:
        levels[v["message"]] = levels.get(v["message"], 0) + v["accel"]["n"]
        levels[v["message"]] += v["accel"]["not_finite"]
    assert levels == {k: n for k, n in held.items() if k in FIRMWARE_LEVELS}
    assert sum(b["blocks"] for b in firmware["batches"]) == held.get("ISBH", 0)
    assert sum(b["samples"] for b in firmware["batches"]) <= 32 * held.get("ISBD", 0)


def _imu_keys(report: dict[str, Any]) -> dict[str, str]:
    """The IMU messages the log holds, each with the key the reader says it under: a ULog
    ``sensor_gyro.N`` is read paired with ``sensor_accel.N`` and said under it (protocols/ulog.py)."""
    return {
        k: k.replace("sensor_gyro.", "sensor_accel.")
        for k in report["log"]["holds"]
        if k.split(".")[0] in IMU_SOURCES
    }


@pytest.mark.parametrize(
    "log",
    [
        pytest.param(log, marks=pytest.mark.xfail(reason=why, strict=True))
        if (why := sidecar(log).get("unlisted_because"))
        else log
        for log in READ
    ],
    ids=_ids(READ),
)
def test_what_replay_leaves_out_is_said_with_a_count(log, reports):
    """Every IMU message the log holds is replayed or left out with why, its count in the
    report; every dropped sample's reason is counted on stderr."""
    run = reports(log)[0]
    report = _replayed_report(log, reports)
    replayed_sources = {imu["source"] for imu in report["imus"]}
    left_out = report["log"]["left_out"]
    for key, said_as in _imu_keys(report).items():
        assert key.split(".")[0] in replayed_sources or said_as in left_out, key
        assert report["log"]["holds"][key] > 0
    for key in left_out:
        assert f"not replayed: {key} " in run.err
    for reason, count in report["log"]["dropped_samples"].items():
        assert f"{reason} {count}" in run.err


GNSS_NOTE = re.compile(
    r"GNSS: (?P<used>\d+) epochs of (?P<source>\S+) at [^;]+; left out (?P<left>[^;\n]+)"
    r"(?:; not used: (?P<unused>[^(\n]+) \([^)]*\))?(?:; unreadable: (?P<unreadable>[^\n]+))?"
)
"""replay's note of the GNSS the thrust-axis check takes (service/pipeline/thrust_axis.py)."""
ULOGS = [log for log in READ if log.suffix.lower() == ".ulg"]


@pytest.mark.parametrize("log", ULOGS, ids=_ids(ULOGS))
def test_every_gnss_topic_pyulog_reads_is_used_or_said_not_used(log, reports):
    """Each PX4 GNSS topic instance pyulog reads is the one the check takes, its epochs plus those
    left out by reason being pyulog's messages of it, or is named as not used; without one the
    coverage says there is no GNSS; the source a sidecar states."""
    from protocols.gnss_logs import ULOG_GNSS_TOPICS

    run = reports(log)[0]
    held = {k: len(s) for k, s in _ulog_stamps(log, set(ULOG_GNSS_TOPICS)).items()}
    several = {name for name, multi_id in held if multi_id > 0}
    named = {f"{n}.{m}" if n in several else n: count for (n, m), count in held.items()}
    note = GNSS_NOTE.search(run.err)
    if not held:
        assert note is None and "thrust_axis: does not apply (no GNSS velocity" in run.err
        return
    assert note is not None, f"{log.name}: pyulog reads {sorted(named)}, replay says no GNSS"
    left = note["left"]
    left_out = 0 if left == "none" else sum(int(p.split()[-1]) for p in left.split(", "))
    assert int(note["used"]) + left_out == named.pop(note["source"])
    unused = note["unused"] or ""
    unreadable = re.findall(r"(\S+) \(", note["unreadable"] or "")
    assert {p.rsplit(" ", 2)[0] for p in unused.split(", ") if p} | set(unreadable) == set(named)
    assert note["source"] == sidecar(log).get("gnss_source", note["source"])


# --- sessions --------------------------------------------------------------------------------


def _session_argv(folder: Path) -> list[str]:
    stated = sidecar(folder)
    return [str(folder / stated["session"]), *stated["options"]]


@pytest.mark.slow
@pytest.mark.parametrize("folder", SESSIONS, ids=_ids(SESSIONS))
def test_a_session_calibrates_diagnoses_clean_against_its_passport_and_audits(folder, tmp_path):
    """calibrate: a passport from the positions SOURCE.md states; diagnose of the same session
    against it: no persistent F0 failure and no more failing samples than F0's false-alarm
    rate allows (the 0.999 quantile of their binomial count, 0 at 1e-9 a sample); audit runs."""
    argv, passport = _session_argv(folder), tmp_path / "own.json"
    cal = _run(["calibrate", *argv, "--out", str(passport), "--replicas", REPLICAS])
    assert cal.status == 0 and passport.exists() and "Traceback" not in _said(cal)
    assert f"calibrate: {sidecar(folder)['positions']} positions" in cal.err
    own = _run(["diagnose", *argv, "--passport", str(passport), "--json"])
    assert own.status in (0, 3) and "Traceback" not in _said(own)
    verdict = json.loads(own.out)
    assert not [f for f in verdict["faults"] if f["predicate"] == "F0"]
    for triad, f0 in verdict["f0"].items():
        if not f0["run"]:
            continue
        p = next(
            c["false_alarm_prob"]
            for c in verdict["coverage"]["checks"]
            if c["check"] == "F0" and c["triad"] == triad
        )
        allowed = f0["tested"] * p + 3.1 * math.sqrt(f0["tested"] * p * (1 - p))
        assert f0["failed"] <= math.floor(allowed), (triad, f0["failed"], f0["tested"])
    audit = _run(["audit", *argv, "--replicas", REPLICAS, "--json"])
    assert audit.status == 0 and "Traceback" not in _said(audit)
