"""ins-health as a library: replay a flight log or diagnose a session from Python (README "Python API").

``replay(path, passport=None, ...)`` → :class:`ReplayResult`: the events, each IMU's coverage, the
verdict and exit status ``ins-health replay`` gives, and what the reader left out.
``diagnose(session_path, passport_path, ...)`` → :class:`DiagnoseResult`: the offline chain's
faults, coverage and exit status, as ``ins-health diagnose`` gives them. Both take the command's
options as keyword arguments and raise :class:`UsageError` for input the command refuses (exit
status 2). Importing this package is cheap: the numerics load on the first call.

Installed from a wheel, the project's folders live under this package (``ins_health.service``,
``ins_health.protocols``, ``ins_health.estimators``: setup.py), so a user's own ``service``
package is left alone.
"""

from __future__ import annotations

from os import PathLike
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

    from protocols.events import Event
    from service.cli import UsageError
    from service.commands.diagnose import DiagnoseResult
    from service.commands.replay import ReplayResult

__all__ = ["DiagnoseResult", "ReplayResult", "UsageError", "diagnose", "replay"]

StrPath = str | PathLike[str]


def _options(**options: Any) -> list[str]:
    """Keyword options as the command's flags (``gravity_mps2`` → ``--gravity``, see ``_FLAGS``)."""
    argv: list[str] = []
    for name, value in options.items():
        if value is None or value is False:
            continue
        flag = _FLAGS.get(name, "--" + name.replace("_", "-"))
        argv += [flag] if value is True else [flag, str(value)]
    return argv


_FLAGS = {"gravity_mps2": "--gravity", "latitude_deg": "--latitude", "height_m": "--height"}


def _parse(argv: list[str]) -> Any:
    """The command's options from ``argv``; :class:`UsageError` where the command would exit 2
    (argparse has said why on stderr)."""
    from service.cli import UsageError, build_parser

    try:
        return build_parser().parse_args(argv)
    except SystemExit:
        raise UsageError(f"options the command refuses: {' '.join(argv)}") from None


def replay(
    path: StrPath,
    passport: StrPath | None = None,
    *,
    passport_dir: StrPath | None = None,
    grade: str | None = None,
    vehicle: str | None = None,
    config: StrPath | None = None,
    gravity_mps2: float | None = None,
    latitude_deg: float | None = None,
    height_m: float | None = None,
    report: StrPath | None = None,
    on_event: Callable[[Event], None] | None = None,
) -> ReplayResult:
    """Replay a flight log (``.tlog``, DataFlash ``.bin``/``.log``, ULog ``.ulg``) through the
    daemon's pipeline, as ``ins-health replay`` does; nothing is printed.

    ``passport``: a passport JSON for every IMU of the log; ``passport_dir``: a passport store;
    neither: the nominal passport of ``grade`` (default consumer MEMS). ``report``: a folder to
    write the IMU health report into. ``on_event`` sees each event as it is raised.
    """
    from service.commands.replay import replay_log

    options = _options(
        passport=passport, passport_dir=passport_dir, grade=grade, vehicle=vehicle,
        config=config, gravity_mps2=gravity_mps2, latitude_deg=latitude_deg,
        height_m=height_m, report=report,
    )  # fmt: skip
    return replay_log(_parse(["replay", str(path), *options]), on_event=on_event)


def diagnose(
    session_path: StrPath,
    passport_path: StrPath,
    *,
    gyro_file: StrPath | None = None,
    gravity: float | None = None,
    latitude: float | None = None,
    height: float | None = None,
    false_alarm: float | None = None,
    **units: Any,
) -> DiagnoseResult:
    """Diagnose a session file against its unit's passport (the offline chain, methods.md M1), as
    ``ins-health diagnose`` does; nothing is printed.

    ``units``: the command's other options by name (``accel_unit="g"``, ``accel_noise=…``).
    """
    from service.commands.diagnose import diagnose_session

    options = _options(
        gyro_file=gyro_file, gravity=gravity, latitude=latitude, height=height,
        false_alarm=false_alarm, **units,
    )  # fmt: skip
    return diagnose_session(
        _parse(["diagnose", str(session_path), "--passport", str(passport_path), *options])
    )


def __getattr__(name: str) -> Any:
    """The result types and :class:`UsageError`, imported when first asked for."""
    if name == "ReplayResult":
        from service.commands.replay import ReplayResult

        return ReplayResult
    if name == "DiagnoseResult":
        from service.commands.diagnose import DiagnoseResult

        return DiagnoseResult
    if name == "UsageError":
        from service.cli import UsageError

        return UsageError
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
