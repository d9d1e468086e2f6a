"""MAVLink input cost: the service's conversion to SampleBatch next to pymavlink's own parse of the same bytes.

For each IMU message type a byte stream of N MAVLink 2 packets is parsed by
pymavlink (``MAVLink.parse_buffer``: framing, CRC, unpacking); the parsed
messages are then converted to SI batches as the link's reader does
(:class:`~protocols.mavlink_adapter.ImuBatcher`: fields kept per message,
converted per group of ``GROUP`` messages, one validated ``SampleBatch`` per
group), and, for comparison, one message at a time
(``decode_imu_message``, the per-message path of the log readers). Printed: µs
per message for each step.
Run: ``python benchmarks/bench_mavlink_decode.py [N]``.
"""

from __future__ import annotations

import sys

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


if __name__ == "__main__":
    sys.exit(main(*(int(a) for a in sys.argv[1:])))
