"""Replaying a log as a user does, for the tests: exit status, events, stderr and the coverage line."""

from __future__ import annotations

import json

from service.cli import EXIT_UNUSABLE, main


def replay_with_coverage(capsys, *argv) -> tuple[int, list[str], str, dict | None]:
    """Exit status, event lines, stderr and the coverage map (``--json``: the last line of stdout)."""
    status = main(["replay", *map(str, argv)])
    out = capsys.readouterr()
    lines = [line for line in out.out.splitlines() if line]
    coverage = None
    if "--json" in argv and status != EXIT_UNUSABLE:
        coverage = json.loads(lines.pop())
        assert coverage["type"] == "ins.health.coverage" and coverage["exit_status"] == status
    return status, lines, out.err, coverage
