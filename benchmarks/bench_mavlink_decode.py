"""MAVLink input cost: the service's conversion to SampleBatch next to pymavlink's own parse of the same bytes.

For each IMU message type a byte stream of N MAVLink 2 packets is parsed by
pymavlink (``MAVLink.parse_buffer``: framing, CRC, unpacking); the parsed
messages are then converted to one-sample SI batches as the service does
(``MavlinkLink.to_batch``: unit conversion, IMU mapping, validated frozen
``SampleBatch``). Printed: µs per message for each step and their ratio.
Run: ``python benchmarks/bench_mavlink_decode.py [N]``.
"""

from __future__ import annotations

import sys

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from stopwatch import best_s

from protocols.mavlink_adapter import ImuMessage, MavlinkLink, MavlinkSettings, imu_message


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
    print(f"{'message':<12} {'pymavlink parse':>16} {'to SampleBatch':>15} {'ratio':>7}")
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="bench")) as link:
        for kind in (ImuMessage.RAW_IMU, ImuMessage.SCALED_IMU2, ImuMessage.HIGHRES_IMU):
            data = _stream(kind, n, rng)
            messages = mavlink2.MAVLink(None).parse_buffer(data)
            assert len(messages) == n
            assert all(link.to_batch(m) is not None for m in messages)
            parse_s = best_s(lambda: mavlink2.MAVLink(None).parse_buffer(data), 3)
            convert_s = best_s(lambda: [link.to_batch(m) for m in messages], 3)
            p_us, c_us = parse_s / n * 1e6, convert_s / n * 1e6
            print(f"{kind.value:<12} {p_us:16.2f} {c_us:15.2f} {c_us / p_us:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*(int(a) for a in sys.argv[1:])))
