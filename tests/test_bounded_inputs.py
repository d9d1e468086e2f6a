"""Nested and oversized inputs offline (issue 29, class 10): refused with one line, as the daemon's
passport store refuses them, never a traceback nor a gigabyte spent first."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators.session import ImuSession
from protocols.session_file import MAX_LINE_BYTES, SessionFileError, read_session, write_csv_session

ROOT = Path(__file__).parents[1]
DEPTH = 100_000
"""Far beyond Python's recursion limit (1,000): the JSON parser gave up with a RecursionError."""


@pytest.fixture
def deep_passport(tmp_path: Path) -> Path:
    path = tmp_path / "deep.passport.json"
    path.write_text("[" * DEPTH + "]" * DEPTH)
    return path


@pytest.fixture
def session_csv(tmp_path: Path) -> Path:
    n = 200
    path = tmp_path / "rest.csv"
    write_csv_session(
        path,
        ImuSession(
            t_s=np.arange(n) / 100.0,
            accel_mps2=np.tile([0.0, 0.0, 9.81], (n, 1)),
            gyro_rps=np.zeros((n, 3)),
        ),
    )
    return path


@pytest.mark.parametrize(
    "command",
    [
        ["diagnose", "{session}", "--passport", "{passport}"],
        ["store", "put", "{store}", "uav-1", "0", "{passport}"],
        ["replay", "{session}", "--passport", "{passport}"],
    ],
    ids=["diagnose", "store-put", "replay"],
)
def test_a_deeply_nested_passport_is_one_line_and_exit_2(
    command, deep_passport, session_csv, tmp_path
):
    """Each command in a process of its own, as a user runs it."""
    argv = [
        a.format(session=session_csv, passport=deep_passport, store=tmp_path / "store")
        for a in command
    ]
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", *argv],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines() == [
        f"ins-health {command[0]}: {deep_passport}: JSON nested too deeply to parse"
    ]


def test_a_session_line_beyond_the_limit_is_refused_before_the_file_is_read(tmp_path):
    """A line one byte over MAX_LINE_BYTES (a 200 MB one took 1.4 GB before: the whole file was read
    and split first) is refused naming it; the scan holds 1 MiB at a time whatever the line."""
    path = tmp_path / "long.csv"
    with open(path, "w") as f:
        f.write("t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n")
        f.write("1" * (MAX_LINE_BYTES + 1) + "\n")
    with pytest.raises(SessionFileError, match=r"line 3 is longer than 65536 bytes"):
        read_session(path)
    # The longest line allowed still reads (then fails as any line of one field would).
    path.write_text("t,ax,ay,az,gx,gy,gz\n" + "1" * (MAX_LINE_BYTES - 1) + "\n")
    with pytest.raises(SessionFileError, match=r"line 2: expected 7 fields"):
        read_session(path)
    # A last line without its newline counts too.
    path.write_text("t,ax,ay,az,gx,gy,gz\n" + "2" * (3 * 2**20))
    with pytest.raises(SessionFileError, match=r"line 2 is longer than 65536 bytes"):
        read_session(path)
