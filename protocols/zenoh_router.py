"""A Zenoh router as its own process: ``python -m protocols.zenoh_router --listen tcp/127.0.0.1:PORT``
(installed from the wheel: ``python -m ins_health.router``).

``--connect ENDPOINT`` (repeatable) meshes it with other routers. ``--config FILE.json5`` reads a
zenohd-style configuration (``deploy/zenoh-router.json5``: TLS listen endpoints with their
certificates, access control), so that the fleet's router can be tried without zenohd;
``--listen`` and ``--connect`` then replace its endpoints. A file Zenoh cannot use is one line on
stderr, exit 2.

The process prints one line ``ready <endpoint> …`` (the endpoints it listens on) on stdout once it listens,
and runs until SIGTERM or SIGINT (or its stdin closes, when ``--stdin`` is
given, so a parent that dies takes its router with it). Tests that must stop
and restart the router (reconnection) use :class:`RouterProcess`.
"""

from __future__ import annotations

import argparse
import select
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import zenoh

from protocols.zenoh_adapter import open_router, router_config_from_file, router_endpoints


def free_local_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to port 0, read it, release it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RouterProcess:
    """A router child process on ``endpoint``; :meth:`start` waits for its ``ready`` line.

    ``with RouterProcess(endpoint) as router: ...`` starts and stops it;
    :meth:`stop` (SIGTERM) and :meth:`kill` (SIGKILL) end it, :meth:`start`
    starts it again on the same endpoint.
    """

    def __init__(
        self, endpoint: str, *, connect: Sequence[str] = (), ready_timeout_s: float = 20.0
    ):
        self.endpoint = endpoint
        self.connect = tuple(connect)
        self._timeout_s = float(ready_timeout_s)
        self._proc: subprocess.Popen[str] | None = None

    def start(self) -> RouterProcess:
        if self.running:
            raise RuntimeError("the router is already running")
        proc = self._proc = subprocess.Popen(
            [sys.executable, "-m", __spec__.name, "--listen", self.endpoint, "--stdin"]
            + [arg for peer in self.connect for arg in ("--connect", peer)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            # Where the top package of this module's name is found, installed (ins_health) or not.
            cwd=Path(__file__).resolve().parents[__spec__.name.count(".")],
        )
        if proc.stdout is None:
            raise RuntimeError("the router's stdout is not a pipe")
        ready, _, _ = select.select([proc.stdout], [], [], self._timeout_s)
        line = proc.stdout.readline().strip() if ready else ""
        if line != f"ready {self.endpoint}":
            self.kill()
            raise RuntimeError(
                f"zenoh router on {self.endpoint} did not become ready (got {line!r})"
            )
        return self

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def stop(self) -> int:
        """SIGTERM and wait; returns the exit status (0 if it was not running)."""
        return self._end(signal.SIGTERM)

    def kill(self) -> int:
        """SIGKILL and wait; returns the exit status (0 if it was not running)."""
        return self._end(signal.SIGKILL)

    def _end(self, sig: signal.Signals) -> int:
        if self._proc is None:
            return 0
        if self._proc.poll() is None:
            self._proc.send_signal(sig)
        status = self._proc.wait(timeout=self._timeout_s)
        for stream in (self._proc.stdin, self._proc.stdout):
            if stream is not None:
                stream.close()
        self._proc = None
        return status

    def __enter__(self) -> RouterProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        help="endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    parser.add_argument(
        "--config",
        help="zenohd-style JSON5 configuration (deploy/zenoh-router.json5); --listen and --connect replace its endpoints",
    )
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        help="another router's endpoint to mesh with (repeatable)",
    )
    parser.add_argument(
        "--stdin", action="store_true", help="also stop when stdin reaches end of file"
    )
    args = parser.parse_args(argv)
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    if args.stdin:

        def stop_at_eof() -> None:
            sys.stdin.read()
            done.set()

        threading.Thread(target=stop_at_eof, daemon=True).start()
    if args.config is not None:
        try:
            config = router_config_from_file(args.config, listen=args.listen, connect=args.connect)
        except ValueError as exc:
            print(f"{parser.prog}: {exc}", file=sys.stderr)
            return 2
        listen = router_endpoints(config)
    elif len(args.listen) == 1:
        listen = args.listen
    else:
        parser.error("give one --listen endpoint, or --config FILE.json5")
    if not listen:
        parser.error(f"{args.config} listens on no endpoint: give --listen")
    router = (
        zenoh.open(config)
        if args.config is not None
        else open_router(listen[0], connect=args.connect)
    )
    with router:
        print(f"ready {' '.join(listen)}", flush=True)
        # wait() with a timeout in a loop so the main thread stays responsive to signals.
        while not done.wait(timeout=0.5):
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
