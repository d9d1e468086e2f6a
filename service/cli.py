"""The ``ins-health`` console command.

Starting it stays cheap (``benchmarks/bench_startup.py``): this module and each
command's ``register`` import only the standard library, numpy and modules that
import nothing heavier; a command imports scipy, matplotlib, zenoh or pymavlink
inside the function that runs it (``tests/test_cli_startup.py`` checks it). A command line
naming a command builds that command's parser alone (:func:`build_parser`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from service import commands

OUTPUTS = "_outputs"
"""Namespace attribute listing the ``(dest, flag)`` of the options that name a file to write."""


EXIT_NO_FAULT = 0
"""Every check that applies ran and nothing was found."""
EXIT_FAULT = 1
"""A fault was found (a sensor finding: F0…F9, gross, stale); it outranks missing coverage."""
EXIT_UNUSABLE = 2
"""Unusable input: a log, passport, session or option the command cannot use (:class:`UsageError`)."""
EXIT_UNTESTED = 3
"""Not enough to test: a check that applies did not run (``no finding within coverage``), nothing found."""
EXIT_STATUS_HELP = (
    "exit status: 0 tested, no fault; 1 a fault found; 2 unusable input; "
    "3 not enough to test (no finding within coverage)"
)
"""The exit statuses of the verdict commands (``diagnose``, ``replay``), as their ``--help`` states them."""
EXIT_OF_VERDICT = {
    "fault": EXIT_FAULT,
    "no fault": EXIT_NO_FAULT,
    "no finding within coverage": EXIT_UNTESTED,
}
"""Exit status of each :class:`estimators.coverage.Verdict` (its values: this module imports no numerics)."""


class UsageError(Exception):
    """Unusable input to a command: reported as one line on stderr, exit status :data:`EXIT_UNUSABLE`."""


PROGRESS_EVERY_S = 5.0
"""A long command says how far it got at most this often, s (stderr)."""


def stderr_progress(command: str) -> Callable[[str], None]:
    """A progress callback printing ``ins-health COMMAND: line`` on stderr, at most every
    :data:`PROGRESS_EVERY_S` and not before that much has passed (a short run stays quiet)."""
    next_s = time.monotonic() + PROGRESS_EVERY_S

    def say(line: str) -> None:
        nonlocal next_s
        now = time.monotonic()
        if now >= next_s:
            next_s = now + PROGRESS_EVERY_S
            print(f"ins-health {command}: {line}", file=sys.stderr, flush=True)

    return say


PROGRESS_AFTER_S = 2.0
"""A step of a command still running after this long is named on stderr, s."""


@contextlib.contextmanager
def progress_step(command: str, what: str) -> Iterator[None]:
    """Say ``ins-health COMMAND: WHAT (N s)`` on stderr while a step runs longer than
    :data:`PROGRESS_AFTER_S`, then every :data:`PROGRESS_EVERY_S`: a long step is never silent.

    A thread keeps the time, so a step that never returns to Python code (one long numpy call)
    is named too; a step that ended past the bound before the thread said it is named at its end.
    """
    done = threading.Event()
    said = threading.Event()
    t0 = time.monotonic()

    def say() -> None:
        print(
            f"ins-health {command}: {what} ({time.monotonic() - t0:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
        said.set()

    def keep_time() -> None:
        wait_s = PROGRESS_AFTER_S
        while not done.wait(wait_s):
            say()
            wait_s = PROGRESS_EVERY_S

    thread = threading.Thread(target=keep_time, name=f"progress {what}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        if not said.is_set() and time.monotonic() - t0 >= PROGRESS_AFTER_S:
            say()


class _Version(argparse.Action):
    """``--version``: the installed package's version, read only when asked (importlib.metadata is not free)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *_: Any) -> None:
        from importlib.metadata import version

        print(f"{parser.prog} {version('ins-health')}")
        parser.exit()


def add_output(parser: argparse._ActionsContainer, *flags: str, **kwargs: Any) -> argparse.Action:
    """Add an option naming a file the command writes (a ``Path``).

    :func:`main` checks that its folder exists before the command starts, so a
    typo in a folder fails at once, not after the work.
    """
    action = parser.add_argument(*flags, type=Path, **kwargs)
    known = parser.get_default(OUTPUTS) or ()
    parser.set_defaults(**{OUTPUTS: (*known, (action.dest, action.option_strings[0]))})
    return action


def check_outputs(args: argparse.Namespace) -> None:
    """Raise :class:`UsageError` if an output file of ``args`` (see :func:`add_output`) is in a missing folder."""
    for dest, flag in getattr(args, OUTPUTS, ()):
        path = getattr(args, dest)
        if path is not None and not path.parent.is_dir():
            raise UsageError(f"{flag} {path}: the folder {path.parent} does not exist")


def command_modules() -> list[str]:
    """The modules of :mod:`service.commands`, sorted: what ``pkgutil.iter_modules`` lists of a
    folder of plain modules, without the import of ``inspect`` it costs (about 5 ms)."""
    return sorted(
        name.removesuffix(".py")
        for folder in commands.__path__
        for name in os.listdir(folder)
        if name.endswith(".py") and not name.startswith("_")
    )


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or of ``command`` alone when it names one.

    Each module of :mod:`service.commands` registers the command of its name: a command line
    that names one parses the same with that module alone, and the other modules are neither
    imported nor built (about 10 ms of a command's start).
    """
    parser = argparse.ArgumentParser(
        prog="ins-health",
        description="Streaming fault detection for strapdown IMUs (scalar method).",
    )
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    # Options parsed here and run through args.func within a process (ins_health's API, a
    # library user) leave the process's collector and malloc alone; _run says when it is its own.
    parser.set_defaults(own_process=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    names = command_modules()
    for name in [command] if command in names else names:
        importlib.import_module(f"{commands.__name__}.{name}").register(sub)
    return parser


@contextlib.contextmanager
def _start_up(own_process: bool) -> Iterator[None]:
    """The command's modules imported with the cyclic collector paused, what they made then
    frozen (:func:`gc.freeze`), when the command is the whole of its process.

    What a start-up imports (modules, classes, numpy's tables) lives as long as the process, yet
    the collector walked it: its passes during the imports, the full ones over it after, and those
    at the interpreter's exit, about 47 M instructions of calibrate's 1,126 M (4 %; callgrind).
    The few hundred objects the imports leave as cyclic garbage (about 90 KB) stay frozen. In a
    process that calls :func:`main` among other work (the tests, a library user) the collector
    is left as it is: a freeze would keep that process's garbage too.
    """
    if not own_process or not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        gc.enable()


def _run(argv: list[str] | None, own_process: bool) -> int:
    argv = sys.argv[1:] if argv is None else argv
    with _start_up(own_process):
        parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    # Whether the command may set what holds for the whole process (the collector, malloc's
    # thresholds: replay's freeze_imports and keep_batch_temporaries_on_heap), as _start_up does.
    args.own_process = own_process
    try:
        check_outputs(args)
        return int(args.func(args) or 0)
    except BrokenPipeError:
        raise
    except (UsageError, ValueError, OSError) as exc:
        for line in str(exc).splitlines() or [""]:
            print(f"ins-health {args.command}: {line}", file=sys.stderr)
        return EXIT_UNUSABLE


def main(argv: list[str] | None = None, *, own_process: bool = False) -> int:
    """``ins-health`` with ``argv`` (default: the process's); its exit status. ``own_process``:
    the command is the whole of its process (the console script, ``python -m``), which lets it
    keep its start-up out of the cyclic collector's passes (:func:`_start_up`)."""
    try:
        try:
            return _run(argv, own_process)
        finally:
            sys.stdout.flush()
    except BrokenPipeError:
        # The reader of stdout has gone (``| head``): not an error worth a word. Python's
        # recipe (docs: signal, "Note on SIGPIPE"): point stdout at devnull so that the
        # flush at exit does not fail again, and exit 1.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    # ``python -m service.cli`` runs this file as __main__: call the main of the imported
    # module, whose UsageError is the one the commands raise.
    from service.cli import main as _main

    sys.exit(_main(own_process=True))
