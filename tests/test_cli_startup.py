"""What ``ins-health`` loads to start: the parser imports no heavy module, and the defaults it states agree with the library's.

The time itself is measured by ``benchmarks/bench_startup.py``; here only the
import structure is checked, in a fresh interpreter.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from service.cli import build_parser, command_modules, main

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("scipy", "matplotlib", "zenoh", "pymavlink", "filterpy")


def _in_a_fresh_interpreter(code: str, *args: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )


LOADED_BY_THE_PARSER = """
import json, sys
from service.cli import build_parser
build_parser()
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""


def test_building_the_parser_imports_no_heavy_module():
    out = subprocess.run(
        [sys.executable, "-c", LOADED_BY_THE_PARSER],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    loaded = set(json.loads(out))
    # The probe sees imports at all: the parser does load the commands' own light modules.
    assert {"service", "argparse", "numpy"} <= loaded
    assert loaded.isdisjoint(HEAVY), sorted(loaded & set(HEAVY))


def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) of every command that runs (the leaves of the sub-command tree)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, child in subs[0].choices.items():
        yield from _leaves(child, (*path, name))


def _action(path: tuple[str, ...], dest: str) -> argparse.Action:
    leaf = dict(_leaves(build_parser()))[path]
    (action,) = [a for a in leaf._actions if a.dest == dest]
    return action


def test_the_defaults_the_parser_states_are_the_library_s():
    from estimators.audit import DEFAULT_REPLICAS
    from estimators.diagnosis import DEFAULT_FALSE_ALARM_PROB
    from estimators.rocking import PAPER_REL_SIGMA
    from estimators.sim import GRADES, OrientationScheme, Rounding
    from estimators.temperature import DEFAULT_REFERENCE_TEMP_C, ORDERS
    from service.demo import DEFAULT_SPEED

    assert _action(("audit",), "replicas").default == DEFAULT_REPLICAS
    assert _action(("diagnose",), "false_alarm").default == DEFAULT_FALSE_ALARM_PROB
    assert _action(("demo",), "speed").default == DEFAULT_SPEED
    assert _action(("rocking",), "amplitude_rel_sigma").default == PAPER_REL_SIGMA
    assert _action(("rocking",), "frequency_rel_sigma").default == PAPER_REL_SIGMA
    rounding = _action(("passport", "tilt"), "rounding")
    assert list(rounding.choices) == [r.value for r in Rounding]
    assert rounding.default == Rounding.TOWARD_ZERO.value
    temperature = ("passport", "temperature")
    assert _action(temperature, "orders").default == ",".join(map(str, ORDERS))
    assert _action(temperature, "reference_temp_c").default == DEFAULT_REFERENCE_TEMP_C
    # One grade vocabulary, the sensor classes (service/grades.py), mapped onto the library's grades.
    from estimators.conventions import Grade
    from estimators.nominal_passport import SensorClass
    from service.grades import FLOOR_GRADE, SENSOR_CLASSES

    assert SENSOR_CLASSES == tuple(c.value for c in SensorClass)
    assert set(FLOOR_GRADE) == set(SENSOR_CLASSES) and {Grade(g) for g in FLOOR_GRADE.values()}
    simulated = _action(("simulate",), "grade").choices
    assert [FLOOR_GRADE[c] for c in simulated] == [g.value for g in GRADES]
    for command in (("calibrate",), ("replay",), ("passport", "tilt")):
        assert list(_action(command, "grade").choices) == list(SENSOR_CLASSES)
    assert list(_action(("simulate",), "orientations").choices) == [
        s.value for s in OrientationScheme
    ]


FILE_OUTPUTS = {"--out", "--plot", "--truth", "--save-session", "--save-csv", "--report"}


@pytest.mark.parametrize("path", [p for p, _ in _leaves(build_parser())], ids=" ".join)
def test_every_option_naming_a_file_to_write_is_checked_before_the_work(path):
    leaf = dict(_leaves(build_parser()))[path]
    writes = {
        a.option_strings[0]
        for a in leaf._actions
        if a.option_strings and a.option_strings[0] in FILE_OUTPUTS
    }
    # audit --report names a folder, which the report creates.
    writes -= {"--report"} if path == ("audit",) else set()
    checked = {flag for _, flag in leaf.get_default("_outputs") or ()}
    assert writes == checked


def test_version_is_the_installed_package_s():
    out = subprocess.run(
        [sys.executable, "-m", "service.cli", "--version"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert out == f"ins-health {version('ins-health')}\n"


COLLECTOR_AFTER_START_UP = """
import contextlib, gc, io
from {module} import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
    main(["calibrate", "--help"])
print(gc.isenabled(), gc.get_freeze_count())
"""


@pytest.mark.parametrize(
    ("module", "own_process"), [("ins_health.__main__", True), ("service.cli", False)]
)
def test_the_command_as_its_own_process_freezes_what_its_start_up_made(module, own_process):
    """The console script's start-up (the command's modules, numpy) is frozen out of the cyclic
    collector's passes, the collector on again after it; :func:`service.cli.main` called within
    a process leaves the collector as it was (a freeze would keep that process's garbage too)."""
    enabled, frozen = _in_a_fresh_interpreter(
        COLLECTOR_AFTER_START_UP.format(module=module)
    ).stdout.split()
    assert enabled == "True"
    # numpy alone leaves some 19,000 objects tracked; a fresh interpreter has none frozen.
    assert (int(frozen) > 20_000) == own_process, frozen


COLLECTOR_OFF_THROUGH_REPLAY_S_IMPORTS = """
import gc
from service.commands.replay import freeze_imports
gc.disable()
freeze_imports(report=False)
print(gc.isenabled())
"""


def test_replay_s_imports_leave_a_collector_the_process_turned_off_off():
    """A process that runs without the cyclic collector (a ``sitecustomize`` turning it off, as
    :func:`service.cli._start_up` respects) keeps it off through replay's own imports."""
    assert _in_a_fresh_interpreter(COLLECTOR_OFF_THROUGH_REPLAY_S_IMPORTS).stdout.split() == [
        "False"
    ]


def test_the_parser_s_options_name_a_command_within_a_process():
    """What :func:`build_parser` parses runs through the command's own function as :func:`main`
    runs it within a process (``ins_health``'s API parses so): the command leaves the collector
    and malloc alone unless :func:`main` says it is the whole of its process."""
    for command in command_modules():
        assert build_parser(command).get_default("own_process") is False, command


LOADED_BY_CALIBRATE = """
import json, sys
from service.cli import main
status = main(["calibrate", sys.argv[1], "--out", sys.argv[2]])
print(json.dumps({"status": status, "loaded": sorted({name.split(".")[0] for name in sys.modules}),
                  "modules": sorted(sys.modules)}))
"""


def test_calibrate_of_a_six_position_session_imports_no_heavy_module(tmp_path):
    # Six faces are too few positions for the model audit (on by default), which then concludes
    # nothing: the default command must not pay for importing the simulator for it
    # (benchmarks/bench_sixpos_calibrate.py). Nor scipy: the passport is checked against its own
    # session's F0 before it is written (issue 30), and F0's λ0 is a non-central χ² quantile, but
    # its session stays inside the shell of λ0's lower bound, which needs none (issue 33). And of
    # the service's pipeline only F0's configuration, not the fleet's monitors (thrust axis,
    # cross-IMU norm).
    import numpy as np

    from estimators.conventions import Grade
    from estimators.sim import grade_error_model, simulate
    from estimators.sixpos import ferraris_spec
    from protocols.session_file import write_csv_session

    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    res = simulate(ferraris_spec(model, static_s=6.0, transition_s=4.0, turn_s=6.0), seed=1)
    write_csv_session(tmp_path / "six.csv", res.session)
    run = subprocess.run(
        [
            sys.executable,
            "-c",
            LOADED_BY_CALIBRATE,
            str(tmp_path / "six.csv"),
            str(tmp_path / "p.json"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )
    out = json.loads(run.stdout)
    assert out["status"] == 0 and (tmp_path / "p.json").exists()
    assert "audit concluded nothing" in run.stderr and "white-noise model kept" in run.stderr
    assert set(out["loaded"]).isdisjoint(HEAVY), sorted(set(out["loaded"]) & set(HEAVY))
    not_needed = {"estimators.sim", "service.pipeline.fleet"}
    # Nor the audit's statistics (and their noise analysis): calibrate asks only its minimum of
    # positions, which the package states itself.
    not_needed |= {"estimators.audit.statistics", "estimators.noise"}
    # Nor the events' schemas and coverage: F0's configuration names predicates and severities only.
    not_needed |= {"protocols.events", "estimators.coverage"}
    # Nor the diagnosis F1…F9: there is no passport to diagnose against.
    not_needed |= {"estimators.diagnosis"}
    # Nor M2's repeatability: the six-position fit needs its least squares alone.
    not_needed |= {"estimators.repeatability"}
    # Nor the stream checks: a session's plausible rates and the options need their limits alone.
    not_needed |= {"estimators.stream_validity"}
    # Nor the other commands' modules (the parser of the command named alone), nor pkgutil (the
    # commands listed from their folder), nor tomllib (a sidecar's, and the session has none).
    not_needed |= {f"service.commands.{name}" for name in command_modules()} - {
        "service.commands.calibrate",
        "service.commands.diagnose",  # the passport against its own session, as diagnose runs F0
    }
    not_needed |= {"pkgutil", "tomllib"}
    # Nor numpy.ma: np.median's NaN check and np.quantile's np.unique load it (estimators.quantiles).
    not_needed |= {"numpy.ma"}
    assert not_needed.isdisjoint(out["modules"]), sorted(not_needed & set(out["modules"]))


def test_the_modules_listed_as_commands_are_pkgutil_s_and_each_registers_its_name():
    import pkgutil

    from service import commands

    names = command_modules()
    assert names == sorted(m.name for m in pkgutil.iter_modules(commands.__path__))
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    assert list(sub.choices) == names


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit):
        main(argv)
    return capsys.readouterr().out


@pytest.mark.parametrize("command", command_modules())
def test_a_command_s_help_is_the_same_from_its_parser_alone(command, capsys, monkeypatch):
    # main builds the named command's parser alone; the whole parser says the same.
    (alone,) = [
        a for a in build_parser(command)._actions if isinstance(a, argparse._SubParsersAction)
    ]
    assert list(alone.choices) == [command]
    whole = build_parser()
    monkeypatch.setattr("service.cli.build_parser", lambda command=None: whole)
    said_by_the_whole = _help([command, "--help"], capsys)
    monkeypatch.undo()
    assert _help([command, "--help"], capsys) == said_by_the_whole
    (sub,) = [a for a in whole._actions if isinstance(a, argparse._SubParsersAction)]
    for leaf in [
        a for a in sub.choices[command]._actions if isinstance(a, argparse._SubParsersAction)
    ]:
        for name in leaf.choices:
            monkeypatch.setattr("service.cli.build_parser", lambda command=None: whole)
            said_by_the_whole = _help([command, name, "--help"], capsys)
            monkeypatch.undo()
            assert _help([command, name, "--help"], capsys) == said_by_the_whole


LOADED_BY_A_UNIT = """
import json, sys
import numpy as np
from service.commands.run import freeze_imports
from service.daemon import Service
from estimators.passport import Passport
from protocols.frames import SampleBatch
from service.pipeline import FleetProcessor, PipelineOptions
passport = Passport.from_dict(json.loads(open(sys.argv[1]).read()))
data = dict(np.load(sys.argv[2]))
freeze_imports()
before = set(sys.modules)
fleet = FleetProcessor(passports=lambda v, i: passport,
                       options=PipelineOptions(gravity_mps2=float(data["g"]), gravity_rel_err=1e-4))
predicates = set()
for k, start in enumerate(range(0, len(data["t_s"]), 20)):
    sl = slice(start, start + 20)
    batch = SampleBatch("v", 0, k, data["t_s"][sl], data["accel_mps2"][sl], data["gyro_rps"][sl], None)
    predicates |= {e.predicate.value for e in fleet.process(batch, arrival_s=float(batch.t_s[-1]))}
print(json.dumps({"predicates": sorted(predicates), "new": sorted(set(sys.modules) - before),
                  "modules": sorted(sys.modules)}))
"""


def test_a_unit_s_first_fault_loads_no_module_the_daemon_did_not_freeze(tmp_path):
    """What a pipeline loads on first use is loaded (and frozen) before the daemon runs.

    A module loaded after ``freeze_imports`` stays in the collector's full passes for the
    daemon's life (scipy.stats loaded so made 44,000 of their objects).
    """
    import numpy as np

    from service.demo import demo_passport, demo_scenario

    passport, g = demo_passport()
    session = demo_scenario().session
    (tmp_path / "p.json").write_text(json.dumps(passport.to_dict()))
    np.savez(
        tmp_path / "s.npz",
        g=g,
        t_s=session.t_s,
        accel_mps2=session.accel_mps2,
        gyro_rps=session.gyro_rps,
    )
    out = _in_a_fresh_interpreter(LOADED_BY_A_UNIT, tmp_path / "p.json", tmp_path / "s.npz").stdout
    result = json.loads(out)
    # The unit went the whole way: F0 on the fault, then the diagnosis that names it.
    assert result["predicates"] == ["F0", "F6"]
    assert result["new"] == []
    # filterpy, whose package loads scipy.stats and scipy.ndimage (0.26 s of CPU and most of what the
    # collector's passes walked), is not among them: the diagnosis's streaming filter updates
    # through estimators.kalman_update.
    filterpy = {"filterpy", "scipy.stats", "scipy.ndimage"}
    assert filterpy.isdisjoint(result["modules"]), sorted(filterpy & set(result["modules"]))


LOADED_BY_REPLAY = """
import gc, json, sys
from ins_health.__main__ import main  # the console script's: the command is its own process
status = main(["replay", sys.argv[1], "--json", "--report", sys.argv[2]])
heavy = ("numpy", "scipy.optimize", "scipy.special", "matplotlib.figure", "service.log_report")
walked = {id(o) for o in gc.get_objects()}  # every generation but the frozen objects
print(json.dumps({"status": status, "modules": sorted(sys.modules),
                  "walked": [n for n in heavy if id(vars(sys.modules[n])) in walked]}))
"""


def test_replay_of_a_ulog_imports_neither_the_daemon_nor_pymavlink_zenoh_scipy_signal_pyplot_filterpy(
    tmp_path,
):
    # Replay runs the daemon's pipeline on a log, not the daemon: its options come from the
    # pipeline's own module (service.pipeline.options), so the service's start-up (the outbox, the
    # intake, the sinks) is not paid by every replay (benchmarks/bench_replay_formats.py). Nor
    # pymavlink and its dialects (about 40 ms of CPU, bytecode cached) where the log is no
    # MAVLink or DataFlash one: the configuration's MAVLink settings come from
    # protocols.mavlink_settings, and the readers of the other formats import pymavlink where
    # they read one.
    import numpy as np

    from estimators.conventions import Grade
    from estimators.sim import grade_error_model, simulate
    from estimators.sixpos import ferraris_spec
    from protocols.ulog import write_ulog

    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    res = simulate(ferraris_spec(model, static_s=6.0, transition_s=4.0, turn_s=6.0), seed=1)
    write_ulog(tmp_path / "six.ulg", {0: res.session})
    run = _in_a_fresh_interpreter(LOADED_BY_REPLAY, tmp_path / "six.ulg", tmp_path / "r")
    out = json.loads(run.stdout.splitlines()[-1])
    assert (tmp_path / "r" / "report.json").exists(), run.stderr
    not_needed = {"service.daemon", "service.supervisor", "service.outbox", "service.intake"}
    not_needed |= {"service.delivery", "service.sinks", "protocols.mavlink_process"}
    not_needed |= {"pymavlink", "protocols.mavlink_adapter", "protocols.dataflash_numpy"}
    assert not_needed.isdisjoint(out["modules"]), sorted(not_needed & set(out["modules"]))
    # Nor zenoh, with asyncio and ssl (0.02 s of CPU): the configuration's Zenoh settings come from
    # protocols.zenoh_settings.
    transport = {"zenoh", "protocols.zenoh_adapter", "asyncio", "ssl"}
    assert transport.isdisjoint(out["modules"]), sorted(transport & set(out["modules"]))
    # Nor scipy.signal (0.43 s of CPU): the report's low-passes are estimators.first_order_filter,
    # and welch is imported for a log's batch-sampler blocks only. Nor pyplot: the report's figures
    # are Figures on Agg.
    report_not_needed = {"scipy.signal", "matplotlib.pyplot"}
    assert "matplotlib.figure" in out["modules"]  # the report was drawn in this process
    assert report_not_needed.isdisjoint(out["modules"]), sorted(
        report_not_needed & set(out["modules"])
    )
    # Nor filterpy, whose package loads scipy.stats and scipy.ndimage (0.26 s of CPU): the
    # accelerometer's streaming nine-parameter filter updates through estimators.kalman_update,
    # filterpy's equations.
    filterpy = {"filterpy", "scipy.stats", "scipy.ndimage"}
    assert filterpy.isdisjoint(out["modules"]), sorted(filterpy & set(out["modules"]))
    # What the imports made lives as long as the process: frozen, the collector's full passes do
    # not walk it again (one at the report's first figure and the interpreter's last at exit, about
    # 0.1 s of CPU in a five-minute replay). A module's namespace stands for what its import made.
    assert out["walked"] == []


REPLAY_WITHOUT_MATPLOTLIB = """
import sys
sys.modules["matplotlib"] = None  # not installed: importing it raises ImportError
from ins_health.__main__ import main
try:
    main(["replay", sys.argv[1], "--report", sys.argv[2]])
except ImportError as exc:
    print("report:", exc, file=sys.stderr)
"""


def test_replay_as_its_own_process_says_its_verdict_before_a_report_it_cannot_draw(tmp_path):
    # Without matplotlib, --report fails where the report is drawn, after the replay has said its
    # events, coverage and verdict. Loading the report's modules ahead (freeze_imports) must not
    # fail the replay before it has read the log.
    import numpy as np

    from estimators.conventions import Grade
    from estimators.sim import grade_error_model, simulate
    from estimators.sixpos import ferraris_spec
    from protocols.ulog import write_ulog

    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    res = simulate(ferraris_spec(model, static_s=6.0, transition_s=4.0, turn_s=6.0), seed=1)
    write_ulog(tmp_path / "six.ulg", {0: res.session})
    run = _in_a_fresh_interpreter(REPLAY_WITHOUT_MATPLOTLIB, tmp_path / "six.ulg", tmp_path / "r")
    said = run.stderr.splitlines()
    assert any(" verdict: " in line for line in said), run.stderr
    assert said[-1].startswith("report: "), run.stderr
