"""GNSS frames of a live MAVLink link: its ``GPS_RAW_INT`` messages into the thrust-axis check.

The link keeps the GPS_RAW_INT fields of the system whose IMU messages it reads (their clock,
:meth:`~protocols.mavlink_adapter.ImuBatcher.take_gnss`); :class:`GpsRawIntStream` turns them
into :class:`~protocols.gnss_frames.GnssFrame` values as a telemetry log's are read
(:func:`protocols.gnss_logs.gps_raw_int_track`: velocity from ``vel`` along ``cog``, the vertical
the centred difference of ``alt``). An epoch's vertical needs the next epoch's altitude, so each
epoch is given when the next one has come (one receiver period late). Epochs left out are counted
on the link by reason, as ``gnss_<reason>`` of :attr:`~protocols.mavlink_adapter.LinkCounters.rejected`
(the status topic's ``service.mavlink.rejected.gnss_no_3d_fix`` …, logged with the link's other
rejections).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from protocols.gnss_frames import GnssFrame
from protocols.gnss_logs import (
    GPS_FIX_3D,
    gps_raw_int_altitudes,
    gps_raw_int_si,
    gps_raw_int_track,
)
from protocols.mavlink_adapter import LinkCounters, MavlinkSource

RATE_EPOCHS = 32
"""Epochs whose spacing gives the receiver's rate (the median)."""


class GpsRawIntStream:
    """GPS_RAW_INT fields (rows of :data:`~protocols.mavlink_settings.GPS_RAW_INT_FIELDS`) in, in
    arrival order, the GNSS frames of ``vehicle`` out; epochs left out counted in ``counters``."""

    def __init__(self, vehicle: str, counters: LinkCounters):
        self.vehicle = vehicle
        self.counters = counters
        self.seq = 0
        self._context = np.empty((0, 5))
        """The last two epochs with an altitude (the newest not given yet: its vertical waits for
        the next; the other its centred difference's earlier side)."""
        self._judged = 0
        """The first context epochs that were in a track already (their left-out counted)."""
        self._given_t = -np.inf
        self._times: deque[float] = deque(maxlen=RATE_EPOCHS)

    def frames(self, raw: np.ndarray) -> list[GnssFrame]:
        rows = np.vstack([self._context, gps_raw_int_si(raw)])
        good = gps_raw_int_altitudes(rows)
        if good.size < 3:
            # Too few altitudes for a centred difference: those wait for the next epochs, the
            # others are left out as the track leaves them (no fix; a clock not later: no vertical).
            fix = int((rows[:, 1] >= GPS_FIX_3D).sum())
            self._reject("no_3d_fix", len(rows) - fix)
            self._reject("not_finite", fix - good.size)
            self._context = rows[good]
            return []
        track = gps_raw_int_track(rows)
        judged = self._context[: self._judged]
        held = len(judged) - int(np.isin(judged[:, 0], track.t_s).sum())
        for reason, n in track.rejected.items():
            # A context epoch left out was counted when it was judged (the only reason it can have).
            self._reject(reason, n - held if reason == "not_finite" else n)
        self._context = rows[good[-2:]]
        self._judged = len(self._context)
        new = (track.t_s > self._given_t) & (track.t_s < rows[good[-1], 0])
        if not new.any():
            return []
        t, vel = track.t_s[new], track.vel_enu_mps[new]
        self._given_t = float(t[-1])
        self._times.extend(t.tolist())
        rate_hz = 1.0 / float(np.median(np.diff(np.r_[self._times, rows[good[-1], 0]])))
        frame = GnssFrame(self.vehicle, self.seq, rate_hz, t, vel)
        self.seq += 1
        return [frame]

    def _reject(self, reason: str, n: int) -> None:
        if n > 0:
            self.counters.reject(f"gnss_{reason}", n)


class MavlinkGnssSource:
    """The GNSS frames of a :class:`~protocols.mavlink_adapter.MavlinkSource`'s link, for
    :meth:`service.intake.Intake.gnss_frames` (the calls of
    :class:`protocols.zenoh_adapter.GnssSource` it uses)."""

    def __init__(self, source: MavlinkSource):
        self._source = source
        self._stream = GpsRawIntStream(source.link.settings.vehicle, source.link.counters)
        self._ready: deque[GnssFrame] = deque()

    @property
    def dropped(self) -> int:
        """Epochs dropped while the GNSS task lagged."""
        return self._source.gnss_rows.dropped

    async def get(self) -> GnssFrame:
        """The next frame (waits); ``EOFError`` once the source is closed and drained."""
        while not self._ready:
            self._ready.extend(self._stream.frames(await self._source.gnss_rows.get()))
        return self._ready.popleft()
