"""``ins-health watch`` and ``ins-health publish`` against a real Zenoh router and the daemon on 127.0.0.1.

The commands run as their own processes, as an operator runs them; the router
and the daemon run in the test process (tests/service_support.py).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from service_support import (
    ServiceThread,
    free_tcp_port,
    service_config,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)

from estimators.conventions import Triad
from protocols.events import (
    EVENT_TYPE,
    STATUS_TYPE,
    Predicate,
    Severity,
    Status,
    StreamCause,
    event_from_json,
    make_event,
)
from protocols.frames import decode_frame, split_session
from protocols.logs import write_dataflash_bin
from protocols.session_file import load_session, write_csv_session
from protocols.zenoh_adapter import EventPublisher, EventReceiver, frame_key, subscribe_status
from service.cli import main
from service.commands import publish
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore
from service.pipeline import FleetProcessor, PipelineOptions

pytestmark = pytest.mark.network
ROOT = Path(__file__).resolve().parents[1]
QUIET = {"timeout_s": 60.0}
"""A long stream timeout: the end of a recording must not add a timeout event while the test looks."""


@functools.cache
def unit():
    passport, g = demo_passport()
    return passport, g, demo_scenario()


class Cli:
    """``ins-health ARGV`` as a child process; its stdout and stderr lines are collected as they come."""

    def __init__(self, *argv: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", *argv],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.out: list[str] = []
        self.err: list[str] = []
        self._readers = [
            threading.Thread(target=self._collect, args=(stream, lines), daemon=True)
            for stream, lines in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))
        ]
        for reader in self._readers:
            reader.start()

    @staticmethod
    def _collect(stream, lines: list[str]) -> None:
        for line in stream:
            lines.append(line.rstrip("\n"))

    def wait_ready(self) -> None:
        wait_until(
            lambda: any("waiting for events" in line for line in self.err),
            timeout_s=30,
            what=lambda: f"watch to subscribe (stderr {self.err})",
        )

    def stop(self, sig: int) -> int:
        """Send ``sig``, wait for the exit (30 s) and for the last lines; returns the exit status."""
        self.proc.send_signal(sig)
        status = self.proc.wait(30)
        for reader in self._readers:
            reader.join(10)
        return status

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def cli(*argv, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *map(str, argv)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def daemon_config(tmp_path, port: int, vehicles: list[str], imus=(0,)):
    passport, g, _ = unit()
    store = PassportStore(tmp_path / "passports")
    for v in vehicles:
        for imu in imus:
            store.put(v, imu, passport)
    return service_config(
        tmp_path, port=port, passport_dir=store.root, site={"gravity_mps2": g}, validity=QUIET
    )


def offline_events(batches) -> list:
    """What the pipeline says offline about the same frames (the daemon must say the same)."""
    passport, g, _ = unit()
    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
    )
    return [e for b in batches for e in fleet.process(b, arrival_s=float(b.t_s[-1]))]


# Failed once in several full-suite runs while other suites loaded the 2 cores (the second alert
# or the last status never came within the wait) and never alone; the cause is not found yet, so
# one rerun keeps CI from failing on it while the failure still shows in the report.
def test_a_published_session_s_fault_reaches_watch_which_acknowledges_it(tmp_path):
    v = "uav-7"
    session_csv = tmp_path / "faulty.csv"
    write_csv_session(session_csv, unit()[2].session)
    frames = list(
        split_session(load_session(session_csv).session, vehicle=v, imu=0, batch_samples=100)
    )
    want = offline_events(frames)
    assert [e.predicate for e in want] == [Predicate.F0, Predicate.F6]
    with zenoh_router() as port:
        router = f"tcp/127.0.0.1:{port}"
        with (
            ServiceThread(daemon_config(tmp_path, port, [v])) as daemon,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            seen = []
            subscribe_status(ground, seen.append)
            watch = Cli("watch", "--json", "--vehicle", v, "--router", router)
            try:
                watch.wait_ready()
                done = cli(
                    "publish", session_csv, "--vehicle", v, "--pace", "max", "--router", router
                )
                assert done.returncode == 0, done.stderr
                n = unit()[2].session.n_samples
                assert done.stdout.startswith(f"faulty.csv: {len(frames)} frames, {n} samples, ")
                wait_until(
                    lambda: sum('"ins.health.event"' in line for line in watch.out) >= len(want),
                    timeout_s=60,
                    what=lambda: f"the events on watch's stdout {watch.out[-3:]}",
                )

                # Acknowledged: watch is the only receiver, and the daemon's outbox holds nothing
                # undelivered (an unacknowledged event stays pending and is retried).
                def undelivered() -> int:
                    counts = daemon.call(lambda: daemon.service.outbox.counts())
                    return sum(counts.pending_by_sink.values())

                wait_until(
                    lambda: undelivered() == 0,
                    timeout_s=30,
                    what="the daemon's outbox to empty",
                )
                # Every sample reached the daemon (none lost when publish closed its session), and
                # several status messages have the same states, of which watch shows only the first.
                wait_until(
                    lambda: [s.counters.get("imu0.samples.accepted") for s in seen[-3:]] == [n] * 3,
                    timeout_s=30,
                    what="3 status messages with every sample counted",
                )
                status = watch.stop(signal.SIGTERM)
            finally:
                watch.kill()
    assert status == 0, watch.err
    lines = [json.loads(line) for line in watch.out]
    events = [event_from_json(json.dumps(o)) for o in lines if o["type"] == EVENT_TYPE]
    assert [e.event_id for e in events] == [e.event_id for e in want]
    statuses = [o for o in lines if o["type"] == STATUS_TYPE]
    assert statuses and {s["vehicle"] for s in statuses} == {v}
    # Summarized: a status line only when the states or the checks that ran change, and the last one
    # says FAULT, with what tested it.
    states = [tuple(i["state"] for i in s["imus"]) for s in statuses]
    ran = [
        tuple((c["triad"], c["check"], c["ran"]) for i in s["imus"] for c in i["coverage"])
        for s in statuses
    ]
    assert all(a != b for a, b in itertools.pairwise(zip(states, ran, strict=True)))
    assert states[-1] == ("fault",) and ("accel", "F0", True) in ran[-1]
    assert f"ins-health watch: {len(want)} events" in watch.err[-1]


def test_publish_of_a_flight_log_sends_only_the_chosen_imu(tmp_path):
    """A two-IMU DataFlash log (IMU0 faulty, IMU1 a healthy twin), published with --imu 0."""
    v = "uav-8"
    sc, clean = unit()[2], demo_scenario(fault_magnitude=0.0)
    after = lambda s: s.session.select(s.session.t_s >= s.flight_start_s)  # noqa: E731
    log = tmp_path / "flight.bin"
    write_dataflash_bin(log, {0: after(sc), 1: after(clean)})
    with zenoh_router() as port:
        with (
            ServiceThread(daemon_config(tmp_path, port, [v], imus=(0, 1))) as daemon,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            got = []
            with EventReceiver(ground, got.append, vehicles=v):
                done = cli(
                    "publish", log, "--vehicle", v, "--imu", "0", "--pace", "max",
                    "--batch", "50", "--router", f"tcp/127.0.0.1:{port}",
                )  # fmt: skip
                assert done.returncode == 0, done.stderr
                wait_until(lambda: len(got) >= 2, timeout_s=60, what="the F0 and F6 events")
                assert [(e.imu, e.predicate, e.triad, e.axis) for e in got] == [
                    (0, Predicate.F0, Triad.ACCEL, None),
                    (0, Predicate.F6, Triad.ACCEL, "z"),
                ]
            assert daemon.call(lambda: sorted(daemon.service.fleet.pipelines)) == [(v, 0)]
    n = after(sc).n_samples
    assert f"{-(-n // 50)} frames, {n} samples" in done.stdout


def test_watch_prints_an_event_once_acknowledges_every_delivery_and_stops_on_ctrl_c():
    event = make_event(
        vehicle="uav-9",
        imu=1,
        t_s=12.5,
        predicate=Predicate.TIMEOUT,
        cause=StreamCause.NO_DATA,
        severity=Severity.CRITICAL,
        text="IMU1 sent nothing for 2 s",
    )
    with zenoh_router() as port:
        watch = Cli("watch", "--router", f"tcp/127.0.0.1:{port}")
        try:
            watch.wait_ready()
            with (
                zenoh.open(zenoh_client_config(port)) as daemon_side,
                EventPublisher(daemon_side, ack_timeout_s=2.0) as publisher,
            ):
                wait_until(lambda: publisher.ready("uav-9"), timeout_s=10, what="watch's ack route")
                # A retry (as after a lost acknowledgement) is acknowledged again and printed once; each
                # delivery reaches watch twice (the stream and the acknowledgement query).
                assert publisher.publish(event) and publisher.publish(event)
            wait_until(lambda: len(watch.out) >= 1, timeout_s=10, what="the event line")
            status = watch.stop(signal.SIGINT)
        finally:
            watch.kill()
    assert status == 0
    assert len(watch.out) == 1
    assert watch.out[0].endswith("  uav-9 IMU1  CRITICAL  t=12.500 s  IMU1 sent nothing for 2 s")
    assert watch.err[-1].startswith("ins-health watch: 1 events (3 repeated copies ignored")


def test_publish_at_the_recorded_pace_sends_every_frame_in_order(tmp_path):
    """A 2 s session at the recorded rate to a plain subscriber of the frame key."""
    session = unit()[2].session.select(unit()[2].session.t_s < 2.0)
    csv = tmp_path / "short.csv"
    write_csv_session(csv, session)
    with zenoh_router() as port, zenoh.open(zenoh_client_config(port)) as bench:
        seqs = []
        sub = bench.declare_subscriber(
            frame_key("uav-5", 3), lambda s: seqs.append(decode_frame(s.payload.to_bytes()).seq)
        )
        done = cli(
            "publish", csv, "--vehicle", "uav-5", "--imu", "3", "--wait-s", "1",
            "--router", f"tcp/127.0.0.1:{port}",
        )  # fmt: skip
        frames = -(-session.n_samples // 100)
        wait_until(lambda: len(seqs) >= frames, timeout_s=10, what="every frame")
        sub.undeclare()
    # No daemon to say what it took: said, not taken for all of them.
    assert done.returncode == publish.EXIT_UNACCOUNTED, done.stderr
    assert seqs == list(range(frames))
    assert done.stdout.startswith(
        f"short.csv: {frames} frames, {session.n_samples} samples, 2.0 s of data"
    )


def test_each_publish_is_a_run_of_its_own(tmp_path):
    """Issue 34: publishing a session again mixed the two runs in the daemon. Each start of
    publish stamps its frames with a run id of its own (frame schema 2), the daemon's sign of a
    new run (its positions and diagnosis start afresh: tests/test_pipeline.py)."""
    session = unit()[2].session.select(unit()[2].session.t_s < 1.0)
    csv = tmp_path / "short.csv"
    write_csv_session(csv, session)
    frames = -(-session.n_samples // 100)
    with zenoh_router() as port, zenoh.open(zenoh_client_config(port)) as bench:
        got = []
        sub = bench.declare_subscriber(
            frame_key("uav-6", 0), lambda s: got.append(decode_frame(s.payload.to_bytes()))
        )
        # No daemon here, only a subscriber: publish cannot learn what a daemon took (exit 3).
        for _ in range(2):
            done = cli("publish", csv, "--vehicle", "uav-6", "--pace", "max", "--wait-s", "1",
                       "--router", f"tcp/127.0.0.1:{port}")  # fmt: skip
            assert done.returncode == publish.EXIT_UNACCOUNTED, done.stderr
        wait_until(lambda: len(got) >= 2 * frames, timeout_s=10, what="both runs' frames")
        sub.undeclare()
    runs = [b.run for b in got]
    assert None not in runs and len(set(runs[:frames])) == len(set(runs[frames:])) == 1
    assert runs[0] != runs[-1] and [b.seq for b in got] == 2 * list(range(frames))


def test_publish_leaves_out_unusable_samples_and_says_so(tmp_path):
    """A session with one NaN sample and one repeated time stamp: sent as they were, the daemon's
    decoder refused the two frames holding them whole (200 samples) while publish said nothing. They
    are left out and said in the summary line; every frame the subscriber gets is one the decoder takes."""
    session = unit()[2].session.select(unit()[2].session.t_s < 2.0)
    accel, t = session.accel_mps2.copy(), session.t_s.copy()
    accel[150, 1] = np.nan
    t[250] = t[249]
    csv = tmp_path / "damaged.csv"
    write_csv_session(csv, dataclasses.replace(session, t_s=t, accel_mps2=accel))
    with zenoh_router() as port, zenoh.open(zenoh_client_config(port)) as bench:
        frames = []
        sub = bench.declare_subscriber(
            frame_key("uav-5", 0), lambda s: frames.append(decode_frame(s.payload.to_bytes()))
        )
        done = cli(
            "publish",
            csv,
            "--vehicle",
            "uav-5",
            "--pace",
            "max",
            "--wait-s",
            "1",
            "--router",
            f"tcp/127.0.0.1:{port}",
        )
        n = session.n_samples - 2
        wait_until(lambda: sum(f.n_samples for f in frames) >= n, timeout_s=10, what="every sample")
        sub.undeclare()
    assert done.returncode == publish.EXIT_UNACCOUNTED, done.stderr
    assert sum(f.n_samples for f in frames) == n
    assert done.stdout.rstrip().endswith("; left out: non_finite 1, non_monotonic_time 1")


def test_publish_reports_its_progress_on_stderr(tmp_path, capsys, monkeypatch):
    session = unit()[2].session.select(unit()[2].session.t_s < 1.0)
    csv = tmp_path / "one-second.csv"
    write_csv_session(csv, session)
    monkeypatch.setattr(publish, "PROGRESS_PERIOD_S", 0.0)
    with zenoh_router() as port, zenoh.open(zenoh_client_config(port)) as bench:
        sub = bench.declare_subscriber(frame_key("uav-4", 0), lambda s: None)
        argv = ["publish", str(csv), "--vehicle", "uav-4", "--pace", "max", "--batch", "40"]
        argv += ["--wait-s", "1"]
        assert main([*argv, "--router", f"tcp/127.0.0.1:{port}"]) == publish.EXIT_UNACCOUNTED
        sub.undeclare()
    out, err = capsys.readouterr()
    frames = -(-session.n_samples // 40)
    progress = [
        line
        for line in err.splitlines()
        if line.startswith("ins-health publish: ") and "did not account" not in line
    ]
    assert [line.split(": ")[2].split(",")[0] for line in progress] == [
        f"{k} frames" for k in range(1, frames + 1)
    ]
    assert out.startswith(f"one-second.csv: {frames} frames, {session.n_samples} samples, ")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["watch", "--connect-timeout-s", "0.5"], "cannot open the zenoh session"),
        (["publish", "{tmp}/none.csv", "--vehicle", "v1"], "none.csv: no such file or folder"),
        (["publish", "{csv}", "--vehicle", "v1", "--wait-s", "0.3"], "nothing subscribes"),
        (["publish", "{csv}", "--vehicle", "bad/id"], "vehicle"),
    ],
    ids=["no router", "no file", "no subscriber", "bad vehicle"],
)
def test_unusable_input_is_a_one_line_error(argv, message, tmp_path):
    csv = tmp_path / "s.csv"
    write_csv_session(csv, unit()[2].session.select(unit()[2].session.t_s < 1.0))
    with zenoh_router() as port:
        # "no router" connects to a port where nothing listens.
        router = f"tcp/127.0.0.1:{free_tcp_port() if argv[0] == 'watch' else port}"
        args = [a.format(tmp=tmp_path, csv=csv) for a in argv]
        done = cli(*args, "--router", router)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and message in done.stderr, done.stderr


def test_a_status_line_says_when_the_outbox_is_unavailable():
    """The operator's line shows the condition the status counters carry (and nothing when it is fine)."""
    from service.commands.watch import status_line

    held = Status("uav-1", "onboard", 0.0, counters={"service.outbox.unavailable": 1,
                  "service.outbox.held_events": 3, "service.outbox.write_failures": 7})  # fmt: skip
    assert status_line(held, 0.0).endswith("; outbox unavailable (3 events held, 7 writes failed)")
    fine = Status("uav-1", "onboard", 0.0, counters={"service.outbox.unavailable": 0})
    assert "outbox" not in status_line(fine, 0.0)


def test_watch_prints_a_status_when_a_check_starts_running_with_what_was_not_tested(capsys):
    """Same states, but F1…F9 ran at last: a new line; the same coverage again: none."""
    import queue

    from estimators.conventions import Triad
    from estimators.coverage import Check, CheckCoverage
    from protocols.events import ImuState, ImuStatus
    from service.commands.watch import _show, _Stop

    f0 = CheckCoverage(Check.F0, Triad.ACCEL, ran=True, samples=500)
    waiting = CheckCoverage(
        Check.F1_F9, Triad.ACCEL, ran=False, positions=4, reason="4 positions at rest, 9 needed"
    )
    ran = CheckCoverage(Check.F1_F9, Triad.ACCEL, ran=True, positions=9)
    inbox = queue.SimpleQueue()
    for cov in ((f0, waiting), (f0, waiting), (f0, ran)):
        inbox.put(Status("uav-1", "onboard", 0.0, imus=(ImuStatus(0, ImuState.OK, coverage=cov),)))
    inbox.put(_Stop())
    assert _show(inbox, as_json=False) == (0, 3)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert lines[0].endswith(
        "tested: accel F0; untested: accel F1-F9 (4 positions at rest, 9 needed))"
    )
    assert lines[1].endswith("tested: accel F0, accel F1-F9)")
