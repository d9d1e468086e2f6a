"""The thrust-axis check on a live MAVLink link (issue 32): the autopilot's GPS_RAW_INT beside its IMU
messages, read by the link's reader process, into the fleet's check of the link's vehicle; a
thrust-axis fault in flight reaches the ground station as an event.

The flight: 5 s rest, 90 s of ``Fly``, 5 s rest, consumer MEMS at 25 Hz (the lowest rate of the
ones tried, 25/50/100 Hz, at which the fault is found as at 100 Hz: 6 s after its onset), a
receiver at 10 Hz (0.05 m/s, 0.15 s latency); z + 0.1 m/s² from 80 s, after the check's 60 s of
learning in flight.
"""

from __future__ import annotations

import functools

import numpy as np

from estimators.sim import Fly, flight_spec, simulate
from estimators.sim.gnss import gnss_velocity
from protocols.gnss_logs import gps_raw_int_si, gps_raw_int_track
from protocols.mavlink_adapter import LinkCounters
from protocols.mavlink_gnss import GpsRawIntStream

ONSET_S = 80.0


@functools.cache
def flight():
    res = simulate(flight_spec(fly=Fly(90.0), rest_s=5.0, rate_hz=25.0), 4)
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(4)
    )
    alt = 100.0 + np.r_[0.0, np.cumsum(0.5 * (gv[1:, 2] + gv[:-1, 2]) * np.diff(gt))]
    return res.session, gt, gv, alt


def test_gps_raw_int_in_pieces_gives_the_epochs_of_the_whole_track():
    """GPS_RAW_INT fields cut into pieces of 1 to 7 messages, with epochs without a fix, of unknown
    course and of a repeated time among them: the frames hold the whole track's epochs (the log's
    reading) but the last (its vertical waits for the next epoch), left-out epochs counted by the
    same reasons, and the receiver's rate."""
    rng = np.random.default_rng(1)
    _s, gt, gv, alt = flight()
    speed = np.hypot(gv[:, 0], gv[:, 1])
    cog = np.round(np.degrees(np.arctan2(gv[:, 0], gv[:, 1])) * 100) % 36000
    fix = np.where(rng.random(gt.size) < 0.05, 2, 3)
    fix[:4] = 1  # no fix at first
    raw = np.column_stack(
        [np.round(gt * 1e6), fix, np.round(speed * 100), cog, np.round(alt * 1e3)]
    )
    raw[rng.choice(gt.size, 10, replace=False), 3] = 65535
    raw = np.insert(raw, 300, raw[299], axis=0)
    whole = gps_raw_int_track(gps_raw_int_si(raw))
    counters = LinkCounters()
    stream = GpsRawIntStream("mav1", counters)
    frames, k = [], 0
    while k < len(raw):
        n = int(rng.integers(1, 8))
        frames += stream.frames(raw[k : k + n])
        k += n
    np.testing.assert_array_equal(np.concatenate([f.t_s for f in frames]), whole.t_s[:-1])
    np.testing.assert_allclose(
        np.concatenate([f.vel_enu_mps for f in frames]), whole.vel_enu_mps[:-1], rtol=0, atol=1e-12
    )
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert counters.rejected == {f"gnss_{k}": n for k, n in whole.rejected.items()}
    assert set(whole.rejected) == {"no_3d_fix", "not_finite"}  # the repeat has no vertical
    np.testing.assert_allclose([f.rate_hz for f in frames[5:]], 10.0, rtol=1e-6)
