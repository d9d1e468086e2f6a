"""The operator's view of a daemon (issue 34): a dead daemon is said by ``watch``, and frames it drops
are said (the log, the status topic, ``publish``'s exit status), a flood of one vehicle costing
another none. Real router, daemon and commands on 127.0.0.1."""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import replace

import pytest
import zenoh
from service_support import (
    ServiceThread,
    batches_of,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)
from test_cli_watch import Cli, cli, daemon_config, unit
from test_service_faults import ServiceProcess, put_store, write_config

from protocols.session_file import write_csv_session
from protocols.zenoh_adapter import FramePublisher, subscribe_status
from service.commands import publish

pytestmark = pytest.mark.network

LOST_BOUND_S = 5.0
"""The bound the README states for ``watch``'s ``lost`` after a kill -9 (issue 34)."""


def test_watch_says_a_killed_daemon_is_lost_and_back_after_its_restart(tmp_path):
    """Before any vehicle the daemon says it runs (its token and its own status); a kill -9 is said as
    ``lost`` within the bound, a restart as ``back``."""
    with zenoh_router() as port:
        config = write_config(tmp_path, port, put_store(tmp_path, [("uav-1", 0)]))
        watch = Cli("watch", "--router", f"tcp/127.0.0.1:{port}")
        daemon = ServiceProcess(config)
        try:
            watch.wait_ready()
            wait_until(
                lambda: (
                    any(line.endswith("daemon onboard alive") for line in watch.out)
                    and any(
                        line.endswith("daemon onboard serves no vehicle yet") for line in watch.out
                    )
                ),
                timeout_s=10,
                what=lambda: f"the daemon's liveliness and status on watch {watch.out}",
            )
            killed = time.monotonic()
            daemon.kill()
            wait_until(
                lambda: any(line.endswith("daemon onboard lost") for line in watch.out),
                timeout_s=LOST_BOUND_S,
                what=lambda: f"'lost' within {LOST_BOUND_S} s of the kill -9 {watch.out}",
            )
            print(f"lost said {time.monotonic() - killed:.2f} s after kill -9")
            daemon = ServiceProcess(config)
            wait_until(
                lambda: any(line.endswith("daemon onboard back") for line in watch.out),
                timeout_s=10,
                what=lambda: f"'back' after the restart {watch.out}",
            )
            # Stopped, its socket open: only the lease tells.
            stopped = time.monotonic()
            daemon.proc.send_signal(signal.SIGSTOP)
            try:
                wait_until(
                    lambda: sum(line.endswith("daemon onboard lost") for line in watch.out) == 2,
                    timeout_s=LOST_BOUND_S,
                    what=lambda: f"'lost' within {LOST_BOUND_S} s of SIGSTOP {watch.out}",
                )
                print(f"lost said {time.monotonic() - stopped:.2f} s after SIGSTOP")
            finally:
                daemon.proc.send_signal(signal.SIGCONT)
        finally:
            daemon.kill()
            watch.kill()


def test_a_flooded_daemon_logs_its_drops_and_publish_exits_non_zero_naming_them(tmp_path, caplog):
    """Frames of one sample as fast as the link takes them, against queues of four frames: the
    daemon falls behind, drops, logs them naming the vehicle and IMU, and publish says how many."""
    v = "uav-3"
    csv = tmp_path / "faulty.csv"
    session = unit()[2].session
    write_csv_session(csv, session.select(session.t_s < 5.0))
    with zenoh_router() as port:
        router = f"tcp/127.0.0.1:{port}"
        config = daemon_config(tmp_path, port, [v])
        config = replace(config, pipeline=replace(config.pipeline, queue_capacity=4))
        with caplog.at_level(logging.WARNING), ServiceThread(config):
            done = cli(
                "publish", csv, "--vehicle", v, "--pace", "max", "--batch", "1", "--router", router
            )
            wait_until(
                lambda: any("frames dropped" in r.getMessage() for r in caplog.records),
                timeout_s=5,
                what="the drops in the daemon's log",
            )
    print(done.stderr.strip().splitlines()[-1])
    assert done.returncode == publish.EXIT_DROPPED, done.stderr
    assert f"frames of {v} IMU0" in done.stderr.splitlines()[-1]
    logged = [r.getMessage() for r in caplog.records if "frames dropped" in r.getMessage()]
    assert f"of {v} IMU0" in logged[0]


def test_a_second_vehicle_s_frames_are_all_taken_while_a_first_floods(tmp_path):
    """uav-1 floods (frames of one sample, as fast as the link takes them) while uav-2 streams at
    its recorded rate (frames of 0.1 s): uav-1's queue drops, uav-2 loses none of its frames."""
    flooder, steady = "uav-1", "uav-2"
    session = unit()[2].session
    steady_frames = list(
        batches_of(session.select(session.t_s < 2.0), vehicle=steady, imu=0, batch_samples=20)
    )
    flood_frames = list(batches_of(session, vehicle=flooder, imu=0, batch_samples=1))
    with zenoh_router() as port:
        config = daemon_config(tmp_path, port, [flooder, steady])
        config = replace(config, pipeline=replace(config.pipeline, queue_capacity=8))
        with (
            ServiceThread(config),
            zenoh.open(zenoh_client_config(port)) as a,
            zenoh.open(zenoh_client_config(port)) as b,
        ):
            seen: dict[str, list[dict[str, int]]] = {flooder: [], steady: []}
            subscribe_status(b, lambda st: seen[st.vehicle].append(dict(st.counters)))
            stop, flooding_now = threading.Event(), threading.Event()

            def flood() -> None:
                with FramePublisher(
                    a, flooder, 0, congestion_control=zenoh.CongestionControl.BLOCK
                ) as pub:
                    wait_until(lambda: pub.matched, timeout_s=10, what="the daemon's subscription")
                    for k, frame in enumerate(flood_frames):
                        if stop.is_set():
                            return
                        pub.publish(frame)
                        if k == 1000:
                            flooding_now.set()

            flooding = threading.Thread(target=flood, daemon=True)
            flooding.start()
            try:
                with FramePublisher(
                    b, steady, 0, congestion_control=zenoh.CongestionControl.BLOCK
                ) as pub:
                    wait_until(lambda: pub.matched, timeout_s=10, what="the daemon's subscription")
                    assert flooding_now.wait(30)
                    for frame in steady_frames:
                        pub.publish(frame)
                        time.sleep(float(frame.t_s[-1] - frame.t_s[0]))
            finally:
                stop.set()
                flooding.join(30)

            # Every frame that came is taken or dropped, and three statuses in a row agree (a status
            # may come while a group of frames is half through the pipelines).
            def frames_and_samples(counters: dict[str, int]) -> dict[str, int]:
                return {k: n for k, n in counters.items() if ".frames." in k or ".samples." in k}

            def settled(vehicle: str) -> bool:
                last = seen[vehicle][-3:]
                c = last[-1].get if last else {}.get
                return (
                    len(last) == 3
                    and all(frames_and_samples(x) == frames_and_samples(last[0]) for x in last)
                    and c("service.frames.received", -1)
                    == c("service.frames.accepted", 0) + c("service.frames.dropped_overload", 0)
                )

            wait_until(
                lambda: settled(flooder) and settled(steady),
                timeout_s=30,
                what=lambda: f"the daemon to take or drop every frame {seen[steady][-1:]}",
            )
            flooded, kept = seen[flooder][-1], seen[steady][-1]
    print(
        f"flooder: {flooded.get('imu0.frames.dropped_overload')} of {flooded.get('imu0.frames.received')} "
        f"frames dropped; steady: {kept.get('imu0.frames.dropped_overload')} of {len(steady_frames)}; "
        f"instance: {kept['service.frames.dropped_overload']} of {kept['service.frames.received']}"
    )
    assert kept["service.frames.dropped_overload"] > 0
    assert kept["imu0.samples.accepted"] == sum(f.n_samples for f in steady_frames)
    assert flooded["imu0.frames.dropped_overload"] > 0
    assert kept["imu0.frames.dropped_overload"] == 0
