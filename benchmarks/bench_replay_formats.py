"""Replay speed and peak memory per log format, next to the parser's own parse of the same file.

One IMU at 1 kHz for ``--minutes`` (default 60: 3.6 million samples), simulated a
minute at a time (the MEMS unit of the demo turned through ten positions a
minute, :mod:`benchmarks.bench_replay_memory`), written once in each format:
MAVLink ``.tlog`` (HIGHRES_IMU: float fields, so nothing is quantized away),
DataFlash ``.bin`` and text ``.log`` (``IMU`` with the instance field) and PX4
ULog (``sensor_combined``). Each measurement runs in a process of its own, so
its peak resident memory (``ru_maxrss`` of that child) is its own:

* ``parse``: the format's own parser over the IMU messages only — pymavlink
  (``mavlogfile.recv_match``, ``DFReader_binary``/``DFReader_text.recv_match``)
  or pyulog (``ULog(path, ["sensor_combined"])``, which holds the topic in memory);
* ``read``: :class:`protocols.logs.LogReader` (frames of 100 samples, as replay);
* ``replay``: ``ins-health replay LOG --json --report DIR`` (reader, the daemon's
  pipeline with the nominal passport, the health report), started in the child as the
  console script starts it (``ins_health.__main__.main``: the command is its own process).

Wall and CPU (user + system) times include each child's start (imports, about
1–2 s). Every module's bytecode is cached (``PYTHONPYCACHEPREFIX`` in the temporary
folder, filled by a first run of each child on a one-minute log of the same
format), as an installed copy runs: an editable install under
``PYTHONDONTWRITEBYTECODE=1`` compiles this repository's modules at every start,
and pyulog's, pymavlink's and numpy's come compiled either way
(:mod:`benchmarks.bench_sixpos_calibrate` does the same).

Printed per format: file size, then for each run the wall and CPU time, samples/s
of wall and of CPU time and peak RSS, and the ratio replay / parse of the CPU times (what the
pipeline and report cost on top of parsing; the machine may be shared, so CPU is
the steadier figure). Run: ``python benchmarks/bench_replay_formats.py [--minutes N]
[--formats ulg,bin]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RATE_HZ = 1000.0

PARSE = {
    "tlog": (
        "from protocols.mavlink_adapter import use_mavlink2\n"
        "from pymavlink import mavutil\n"
        "c = use_mavlink2(mavutil.mavlogfile(PATH, notimestamps=False))\n"
        "n = 0\n"
        "while c.recv_match(type=['HIGHRES_IMU']) is not None: n += 1\n"
    ),
    "bin": (
        "from pymavlink import DFReader\n"
        "r = DFReader.DFReader_binary(PATH)\n"
        "n = 0\n"
        "while r.recv_match(type=['IMU']) is not None: n += 1\n"
    ),
    "log": (
        "from pymavlink import DFReader\n"
        "r = DFReader.DFReader_text(PATH)\n"
        "n = 0\n"
        "while r.recv_match(type=['IMU']) is not None: n += 1\n"
    ),
    "ulg": (
        "from pyulog import ULog\n"
        "n = len(ULog(PATH, ['sensor_combined']).get_dataset('sensor_combined').data['timestamp'])\n"
    ),
}
READ = (
    "from protocols.logs import LogReader\n"
    "n = sum(b.n_samples for b in LogReader(PATH, batch_samples=100))\n"
)


def minute(k: int):
    from benchmarks.bench_replay_memory import minute as sim_minute

    s = sim_minute(k)
    return s.select(s.t_s < 60.0 * (k + 1))


def write_logs(folder: Path, minutes: int) -> dict[str, Path]:
    """The same simulated hour in the four formats, written a minute at a time (bounded memory)."""
    from protocols.logs import write_dataflash_bin, write_dataflash_text, write_tlog
    from protocols.mavlink_adapter import ImuMessage
    from protocols.ulog import SYNC_BYTES, write_ulog

    paths = {fmt: folder / f"hour.{fmt}" for fmt in PARSE}
    part = folder / "part"
    sync = b"\x08\x00S" + SYNC_BYTES
    for k in range(minutes):
        s = minute(k)
        chunks = {}
        write_tlog(part, {0: s}, messages={0: ImuMessage.HIGHRES_IMU})
        chunks["tlog"] = part.read_bytes()
        write_dataflash_bin(part, {0: s})
        data = part.read_bytes()
        # The FMT messages come first: two of them (FMT itself and IMU), 89 bytes each.
        chunks["bin"] = data if k == 0 else data[2 * 89 :]
        write_dataflash_text(part, {0: s})
        text = part.read_bytes()
        chunks["log"] = text if k == 0 else text.split(b"\n", 2)[2]
        write_ulog(part, {0: s}, topics=["sensor_combined"])
        data = part.read_bytes()
        chunks["ulg"] = data if k == 0 else data[data.index(sync) :]
        for fmt, chunk in chunks.items():
            with open(paths[fmt], "ab") as fh:
                fh.write(chunk)
    part.unlink()
    return paths


_PEAK = (
    "import sys\n"
    "peak = [l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1]\n"
    "print(n, int(peak) / 1024.0, file=sys.stderr)\n"
)
"""The child reports its own peak: ``ru_maxrss`` of a child starts from the parent's high-water mark
(Linux keeps it across fork and exec), ``VmHWM`` of the new process image does not."""

REPLAY = (
    "from ins_health.__main__ import main  # the console script's: the command is its process\n"
    "status = main(['replay', PATH, '--json', '--report', PATH + '.report'])\n"
    "assert status != 2, status  # a verdict (0, 1 or 3), not an unusable log\n"
    "n = -1\n"
)


def child_env(pycache: Path) -> dict[str, str]:
    """The children's environment: one thread, every module's bytecode cached in ``pycache``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPYCACHEPREFIX"] = str(pycache)
    return env


def measure(code: str, path: Path, env: dict[str, str]) -> tuple[float, float, int, float]:
    """(wall s, CPU s, samples, peak RSS MB) of ``code`` (which sets ``n``) run in a child with PATH set."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", f"PATH = {str(path)!r}\n{code}{_PEAK}"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        check=True,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    n, peak = proc.stderr.decode().strip().splitlines()[-1].split()
    return wall, cpu, int(n), float(peak)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=int, default=60, help="minutes of 1 kHz data (default 60)")
    ap.add_argument("--formats", default="ulg,bin,log,tlog", help="comma-separated subset")
    args = ap.parse_args()
    samples = int(args.minutes * 60 * RATE_HZ)
    formats = args.formats.split(",")
    with tempfile.TemporaryDirectory(prefix="bench_replay_") as tmp:
        folder = Path(tmp)
        env = child_env(folder / "pycache")
        (folder / "warm").mkdir()
        warm = write_logs(folder / "warm", 1)
        runs = (
            ("parse", PARSE),
            ("read", {f: READ for f in PARSE}),
            ("replay", {f: REPLAY for f in PARSE}),
        )
        for fmt in formats:  # fills the bytecode cache with every module each child imports
            for _, code in runs:
                measure(code[fmt], warm[fmt], env)
        t0 = time.perf_counter()
        paths = write_logs(folder, args.minutes)
        print(
            f"{args.minutes} min of one IMU at 1 kHz ({samples:,} samples) in four formats, written in {time.perf_counter() - t0:.0f} s"
        )
        print(
            f"{'format':6s} {'MB':>7s}  {'run':7s} {'wall s':>8s} {'CPU s':>8s} {'k samples/s':>12s} {'of CPU':>8s} {'peak MB':>8s}"
        )
        for fmt in formats:
            path = paths[fmt]
            size = path.stat().st_size / 2**20
            rows = []
            for run, code in runs:
                wall, cpu, n, rss = measure(code[fmt], path, env)
                rows.append((run, wall, cpu, rss, samples if n < 0 else n))
            for k, (run, wall, cpu, rss, n) in enumerate(rows):
                head = f"{fmt:6s} {size:7.0f}" if k == 0 else " " * 14
                print(
                    f"{head}  {run:7s} {wall:8.1f} {cpu:8.1f} {n / wall / 1e3:12.0f} {n / cpu / 1e3:8.0f} {rss:8.0f}",
                    flush=True,
                )
            print(
                f"{'':14s}  replay / parse: {rows[2][2] / rows[0][2]:.2f}× the CPU time", flush=True
            )
            path.unlink()


if __name__ == "__main__":
    main()
