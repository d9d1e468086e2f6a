"""The command line's own behaviour: a closed stdout, output files in missing folders, ``passport triad --plot``, ``store put --replace`` and ``store check``."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from protocols.passport_codec import write_passport_json
from service.cli import main
from service.demo import demo_passport
from service.passport_store import PassportStore

ROOT = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _run_with_stdout_closed(argv, *, buffered: bool) -> subprocess.CompletedProcess:
    """Run ``ins-health argv`` with a stdout whose reader has already gone (what ``| head`` leaves)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run(
            [sys.executable, "-m", "service.cli", *argv],
            cwd=ROOT,
            env=env,
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    finally:
        os.close(write_end)


@pytest.mark.parametrize(
    "argv",
    [
        ("--help",),
        ("simulate", "--help"),
        ("store", "check", "{tmp}"),
    ],
    ids=["help", "command help", "command output"],
)
@pytest.mark.parametrize("buffered", [True, False], ids=["buffered", "unbuffered"])
def test_a_reader_that_left_ends_the_command_quietly(argv, buffered, tmp_path):
    done = _run_with_stdout_closed([a.format(tmp=tmp_path) for a in argv], buffered=buffered)
    assert done.stderr == ""
    # 1 as Python's recipe exits; 0 when argparse's help already swallowed the failed write.
    assert done.returncode in (0, 1)


def _one_line_error(capsys, argv) -> str:
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    return err


def test_an_output_in_a_missing_folder_fails_before_the_work(tmp_path, capsys):
    missing = tmp_path / "no-such-folder"
    session = tmp_path / "s.csv"
    # Without the early check the session would be simulated and written, then the truth fail.
    err = _one_line_error(
        capsys,
        ["simulate", "--out", session, "--truth", missing / "t.json", "--profile", "static"],
    )
    assert err == (
        f"ins-health simulate: --truth {missing / 't.json'}: the folder {missing} does not exist\n"
    )
    assert not session.exists()
    # The folder is checked before the session is even read (it does not exist either).
    err = _one_line_error(
        capsys, ["calibrate", tmp_path / "absent.csv", "--out", missing / "p.json"]
    )
    assert f"--out {missing / 'p.json'}: the folder {missing} does not exist" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["passport", "tilt", "--simulate", "--out", "{missing}/p.json"],
        ["passport", "triad", "--simulate", "--plot", "{missing}/p.png"],
        ["passport", "temperature", "--simulate", "--save-session", "{missing}/s.csv"],
        ["sixpos", "static", "--simulate", "--report", "{missing}/r.json"],
        ["rocking", "--simulate", "--plot", "{missing}/r.png"],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
def test_every_command_checks_its_outputs(argv, tmp_path, capsys):
    missing = tmp_path / "no-such-folder"
    err = _one_line_error(capsys, [a.format(missing=missing) for a in argv])
    assert f"the folder {missing} does not exist" in err


def test_passport_triad_writes_its_plot(tmp_path, capsys):
    plot = tmp_path / "triad.png"
    argv = ["passport", "triad", "--simulate", "--runs", "2", "--latitude", "45"]
    assert main([*argv, "--plot", str(plot)]) in (0, 1)
    assert plot.read_bytes().startswith(PNG_SIGNATURE)
    capsys.readouterr()


@functools.cache
def _passport():
    return demo_passport()[0]


def test_store_put_keeps_an_existing_entry_unless_told_to_replace_it(tmp_path, capsys):
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    write_passport_json(_passport(), first)
    write_passport_json(dataclasses.replace(_passport(), unit_id="spare-unit"), second)
    root = tmp_path / "store"
    assert main(["store", "put", str(root), "uav-3", "1", str(first)]) == 0
    capsys.readouterr()
    err = _one_line_error(capsys, ["store", "put", root, "uav-3", "1", second])
    assert "uav-3 IMU1 already has an entry" in err and "--replace" in err
    assert PassportStore(root).get("uav-3", 1).unit_id == _passport().unit_id
    assert main(["store", "put", str(root), "uav-3", "1", str(second), "--replace"]) == 0
    assert "replaced the previous entry" in capsys.readouterr().out
    assert PassportStore(root).get("uav-3", 1).unit_id == "spare-unit"
    entry = json.loads(PassportStore(root).path_for("uav-3", 1).read_text())
    assert entry["passport"]["unit_id"] == "spare-unit"


def test_store_check_of_a_missing_folder_is_an_error(tmp_path, capsys):
    err = _one_line_error(capsys, ["store", "check", tmp_path / "nowhere"])
    assert (
        err
        == f"ins-health store: {tmp_path / 'nowhere'}: no such folder (the passport store is a folder)\n"
    )
    (tmp_path / "file").write_text("")
    _one_line_error(capsys, ["store", "check", tmp_path / "file"])


def test_progress_lines_come_only_after_a_while_and_then_at_most_every_period(monkeypatch, capsys):
    import service.cli as cli

    now = [100.0]
    monkeypatch.setattr(cli.time, "monotonic", lambda: now[0])
    say = cli.stderr_progress("audit")
    for t_s, line in ((101.0, "early"), (105.0, "first"), (107.0, "too soon"), (110.5, "second")):
        now[0] = t_s
        say(line)
    assert capsys.readouterr().err.splitlines() == [
        "ins-health audit: first",
        "ins-health audit: second",
    ]
