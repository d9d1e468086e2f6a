"""Start-up cost of the CLI: ``ins-health --help`` against ``python -c "import numpy"``, whole processes.

Both commands run as new processes of this interpreter (the installed
``ins-health`` script is ``python -c "from ins_health.__main__ import main; main()"``
with its arguments), so the figures include the interpreter's own start. The
two are interleaved, each run ``N`` times (default 21): the median of each and
their ratio are printed. The goal (issue 10) is a ratio of at most 2; the heavy
modules (scipy, matplotlib, zenoh, pymavlink) are loaded only by the commands
that use them (``tests/test_cli_startup.py`` checks the import structure).
Run: ``python benchmarks/bench_startup.py [N]``.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOAL_RATIO = 2.0

COMMANDS = {
    "python -c 'import numpy'": [sys.executable, "-c", "import numpy"],
    "ins-health --help": [
        sys.executable,
        "-c",
        "import sys; from ins_health.__main__ import main; sys.exit(main(['--help']))",
    ],
}


def _wall_s(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def main(n: int = 21) -> int:
    for argv in COMMANDS.values():  # warm the file cache before timing
        _wall_s(argv)
    runs: dict[str, list[float]] = {name: [] for name in COMMANDS}
    for _ in range(n):
        for name, argv in COMMANDS.items():
            runs[name].append(_wall_s(argv))
    medians = {name: float(np.median(v)) for name, v in runs.items()}
    print(f"start-up, whole process, median of {n} interleaved runs")
    for name, m in medians.items():
        print(f"  {name:<28} {m * 1e3:8.1f} ms")
    ratio = medians["ins-health --help"] / medians["python -c 'import numpy'"]
    print(
        f"  ratio {ratio:.2f} (goal ≤ {GOAL_RATIO:g}: {'met' if ratio <= GOAL_RATIO else 'NOT met'})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(*(int(a) for a in sys.argv[1:2])))
