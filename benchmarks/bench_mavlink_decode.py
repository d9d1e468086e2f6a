"""MAVLink input cost: the service's conversion to SampleBatch next to pymavlink's own parse of the same bytes.

For each IMU message type a byte stream of N MAVLink 2 packets is parsed by
pymavlink (``MAVLink.parse_buffer``: framing, CRC, unpacking); the parsed
messages are then converted to SI batches as the link's reader does
(:class:`~protocols.mavlink_adapter.ImuBatcher`: fields kept per message,
converted per group of ``GROUP`` messages, one validated ``SampleBatch`` per
group), and, for comparison, one message at a time
(``decode_imu_message``, the per-message path of the log readers). Printed: µs
per message for each step.

``--libmav``: the decision on ``libmav`` (a compiled MAVLink 2 parser from the package registry, not
a dependency: ``pip install libmav`` to run it). It owns its sockets, so both parsers are measured
as the service would use them, over UDP on 127.0.0.1, one HIGHRES_IMU packet per datagram (as
ArduPilot streams), sent in bursts of :data:`BURST` a reader keeps up with: libmav's receive thread
calling a Python callback per message that reads two fields, against a Python socket handed to
pymavlink's ``parse_buffer`` reading the same fields. Printed: process CPU time per message (the
sender's share included, the same in both) and messages received.
Run: ``python benchmarks/bench_mavlink_decode.py [N] [--libmav]``.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
from collections.abc import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from stopwatch import best_s

from protocols.mavlink_adapter import (
    ImuBatcher,
    ImuMessage,
    LinkCounters,
    MavlinkSettings,
    decode_imu_message,
    imu_message,
)

GROUP = 100
"""Messages per batch: 5 ms of a 20 kHz stream (the service gathers 5 ms)."""
BURST = 50
"""Datagrams sent before waiting for the reader (a socket's default buffer holds them all)."""


def _stream(kind: ImuMessage, n: int, rng: np.random.Generator) -> bytes:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    acc = rng.normal([0.0, 0.0, -9.8], 0.05, (n, 3))
    gyr = rng.normal(0.0, 0.01, (n, 3))
    return b"".join(
        imu_message(kind, t_s=k * 0.001, accel_mps2=acc[k], gyro_rps=gyr[k], temp_c=35.0).pack(mav)
        for k in range(n)
    )


def main(n: int = 20_000) -> int:
    rng = np.random.default_rng(0)
    print(f"MAVLink IMU input, {n} messages per type, best of 3 (µs per message)")
    print(
        f"{'message':<12} {'pymavlink parse':>16} {f'batches of {GROUP}':>15} {'per message':>12}"
    )
    settings = MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="bench")
    for kind in (ImuMessage.RAW_IMU, ImuMessage.SCALED_IMU2, ImuMessage.HIGHRES_IMU):
        data = _stream(kind, n, rng)
        messages = mavlink2.MAVLink(None).parse_buffer(data)
        assert len(messages) == n

        def batches() -> int:
            batcher = ImuBatcher(settings, LinkCounters())
            got = 0
            for k in range(0, n, GROUP):
                batcher.add(messages[k : k + GROUP])
                got += sum(b.n_samples for b in batcher.take())
            return got

        assert batches() == n
        parse_s = best_s(lambda: mavlink2.MAVLink(None).parse_buffer(data), 3)
        batch_s = best_s(batches, 3)
        single_s = best_s(lambda: [decode_imu_message(m) for m in messages], 3)
        p_us, b_us, s_us = (x / n * 1e6 for x in (parse_s, batch_s, single_s))
        print(f"{kind.value:<12} {p_us:16.2f} {b_us:15.2f} {s_us:12.2f}")
    return 0


def _paced(
    tx: socket.socket, packets: list[bytes], port: int, received: Callable[[], int]
) -> float:
    """Send ``packets`` a datagram each in bursts, each burst read before the next; CPU s used."""
    cpu = time.process_time()
    for k in range(0, len(packets), BURST):
        for packet in packets[k : k + BURST]:
            tx.sendto(packet, ("127.0.0.1", port))
        deadline = time.monotonic() + 2.0
        while received() < min(k + BURST, len(packets)) and time.monotonic() < deadline:
            time.sleep(0.0002)
    return time.process_time() - cpu


def libmav_against_pymavlink(n: int, port: int = 14_650) -> int:
    import libmav
    import pymavlink

    rng = np.random.default_rng(0)
    data = _stream(ImuMessage.HIGHRES_IMU, n + 1, rng)
    size = len(data) // (n + 1)
    packets = [data[k * size : (k + 1) * size] for k in range(n + 1)]
    xml = os.path.join(os.path.dirname(pymavlink.__file__), "dialects", "v20", "ardupilotmega.xml")
    messages = libmav.MessageSet(xml)  # kept referenced: the runtime does not own it
    server = libmav.UDPServer(port)
    runtime = libmav.NetworkRuntime(messages, server)
    # libmav's connection is its partner's address: every packet from the one socket.
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.sendto(packets[0], ("127.0.0.1", port))
    conn = runtime.await_connection(2000)
    got, sums = [0, 0], [0.0, 0.0]

    def on_message(msg) -> None:
        got[0] += 1
        sums[0] += msg["xacc"] + msg["ygyro"]

    conn.add_message_callback(on_message)
    cpu_libmav = _paced(tx, packets[1:], port, lambda: got[0])
    runtime.stop()
    server.close()

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", port + 1))
    rx.settimeout(1.0)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True

    def read() -> None:
        while got[1] < n:
            try:
                datagram = rx.recv(65_536)
            except TimeoutError:
                return
            for m in parser.parse_buffer(datagram) or []:
                got[1] += 1
                sums[1] += m.xacc + m.ygyro

    reader = threading.Thread(target=read)
    reader.start()
    cpu_pymavlink = _paced(tx, packets[1:], port + 1, lambda: got[1])
    reader.join()
    rx.close()
    tx.close()
    print(f"UDP, one HIGHRES_IMU a datagram, {n} messages (CPU µs per message, sender included)")
    for name, k, cpu in (("libmav", 0, cpu_libmav), ("pymavlink", 1, cpu_pymavlink)):
        print(f"{name:<10} {cpu / max(got[k], 1) * 1e6:8.1f}   received {got[k]}")
    print(f"same field sums: {abs(sums[0] - sums[1]) <= 1e-9 * max(1.0, abs(sums[1]))}")
    return 0


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--libmav"]
    if "--libmav" in sys.argv:
        sys.exit(libmav_against_pymavlink(*(int(a) for a in args)))
    sys.exit(main(*(int(a) for a in args)))
