"""The cross-IMU norm check of one vehicle in the streaming chain (:mod:`estimators.cross_imu_norm`).

The vehicle's two lowest-numbered IMUs are compared (IMU 0 and IMU 1 of a log), sample by sample
on the check's per-sample path, from the frames each pipeline accepted; its settings follow the
slower stream's rate (:meth:`~estimators.cross_imu_norm.NormCheckConfig.for_rate`). An alarm is
an event of predicate ``cross_imu_norm`` on the second IMU of the pair, naming both: a norm
difference cannot tell which of the two moved (the scalar checks of each, F0 at rest and the
gross test, can). Its state goes into the vehicle's cross-IMU checkpoint (key ``norm``:
:meth:`VehicleNorm.state_dict`), so a restarted daemon goes on with the lever arm, the units'
differences and the CUSUMs where they were, and raises nothing twice.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from estimators.conventions import Triad
from estimators.coverage import CheckCoverage, norm_coverage
from estimators.cross_imu_norm import (
    CrossImuNorm,
    NormAlarm,
    NormBlock,
    NormChannel,
    NormCheckConfig,
)
from protocols.events import Event, Predicate, StreamCause, make_event
from protocols.frames import SampleBatch
from service.pipeline.options import SEVERITY

NormBlockSink = Callable[[str, tuple[int, int], NormBlock], None]
"""Told ``(vehicle, pair, block)`` of every evaluated block (a replay's report plots them)."""

_WORDS = {
    NormChannel.ACCEL: (Triad.ACCEL, "specific force", "m/s^2"),
    NormChannel.GYRO: (Triad.GYRO, "angular rate", "rad/s"),
}


class VehicleNorm:
    """The cross-IMU norm check between the IMUs ``pair`` of ``vehicle`` (module docstring)."""

    def __init__(
        self,
        vehicle: str,
        pair: tuple[int, int],
        rate_hz: float,
        *,
        gravity_mps2: float,
        on_block: NormBlockSink | None = None,
        state: dict[str, Any] | None = None,
    ) -> None:
        self.vehicle = vehicle
        self.pair = pair
        self.rate_hz = rate_hz
        self.check = (
            CrossImuNorm(NormCheckConfig.for_rate(rate_hz))
            if state is None
            else CrossImuNorm.from_state(state)
        )
        self.config = self.check.config
        self._gravity = gravity_mps2
        self._on_block = on_block
        # Per IMU of the pair: sums of (f/|f|)² per axis and their count, for the share of the
        # specific force each axis carries (the axes the norm sees: coverage).
        self.accel_share_sums = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        self.accel_share_n = [0, 0]

    def state_dict(self) -> dict[str, Any]:
        """The pair, the check's state (:meth:`~estimators.cross_imu_norm.CrossImuNorm.state_dict`)
        and the axes' shares of the specific force so far."""
        return {
            "pair": list(self.pair),
            "rate_hz": self.rate_hz,
            "state": self.check.state_dict(),
            "accel_share_sums": self.accel_share_sums,
            "accel_share_n": self.accel_share_n,
        }

    @classmethod
    def from_state(
        cls,
        vehicle: str,
        saved: dict[str, Any],
        *,
        gravity_mps2: float,
        on_block: NormBlockSink | None = None,
    ) -> VehicleNorm:
        """Resume from :meth:`state_dict`; ``ValueError`` for a state it cannot resume."""
        try:
            i0, i1 = (int(i) for i in saved["pair"])
            rate = float(saved["rate_hz"])
            state = saved["state"]
            # A checkpoint written before the shares were kept starts them afresh.
            sums = [
                [float(v) for v in row] for row in saved.get("accel_share_sums", [[0.0] * 3] * 2)
            ]
            counts = [int(n) for n in saved.get("accel_share_n", [0, 0])]
            if [len(row) for row in sums] != [3, 3] or len(counts) != 2:
                raise ValueError(f"shares {sums!r}, {counts!r}")
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"cross-IMU norm checkpoint is malformed: {exc}") from None
        norm = cls(
            vehicle, (i0, i1), rate, gravity_mps2=gravity_mps2, on_block=on_block, state=state
        )
        norm.accel_share_sums, norm.accel_share_n = sums, counts
        return norm

    def add(self, batch: SampleBatch, offsets_s: Mapping[int, float]) -> list[Event]:
        """One IMU's accepted samples; the events of the blocks they completed. ``offsets_s``: per
        IMU on another clock its clock minus the reference's (the cross-IMU check's,
        :attr:`~estimators.stream_validity.CrossImuMonitor.clock_offsets_s`): the pair is compared
        on one clock, and each event is stamped on its own IMU's."""
        if batch.imu not in self.pair:
            return []
        slot = self.pair.index(batch.imu)
        f = batch.accel_mps2
        mag2 = np.einsum("ij,ij->i", f, f)
        seen = mag2 > 0.0
        sums = (f[seen] ** 2 / mag2[seen, None]).sum(axis=0)
        self.accel_share_sums[slot] = [
            a + float(b) for a, b in zip(self.accel_share_sums[slot], sums, strict=True)
        ]
        self.accel_share_n[slot] += int(seen.sum())
        blocks = self.check.add(
            slot, batch.t_s - offsets_s.get(batch.imu, 0.0), batch.accel_mps2, batch.gyro_rps
        )
        events: list[Event] = []
        for block in blocks:
            if self._on_block is not None:
                self._on_block(self.vehicle, self.pair, block)
            events += [self._event(a, offsets_s.get(self.pair[1], 0.0)) for a in block.alarms]
        return events

    def _event(self, alarm: NormAlarm, offset_s: float) -> Event:
        triad, word, unit = _WORDS[alarm.channel]
        i0, i1 = self.pair
        text = (
            f"{self.vehicle} IMU{i1} against IMU{i0}: the norm of the {word} moved by "
            f"{alarm.shift_si:+.3g} {unit} in flight (noise {alarm.sigma_si:.2g}, "
            f"MDF {alarm.mdf_si:.2g}) [cross_imu_norm]"
        )
        return make_event(vehicle=self.vehicle, imu=i1, t_s=alarm.t_s + offset_s, predicate=Predicate.CROSS_IMU_NORM,
                          cause=StreamCause.DISAGREEMENT, severity=SEVERITY[Predicate.CROSS_IMU_NORM],
                          triad=triad, estimate=alarm.shift_si, tolerance=alarm.mdf_si,
                          sigma=alarm.sigma_si, unit=unit, text=text)  # fmt: skip

    def coverage(self, imu: int) -> tuple[CheckCoverage, CheckCoverage]:
        """Both channels' coverage of ``imu`` (one of the pair) now: seconds tested and the MDF
        (the accelerometer's per axis by its share of the specific force), or why not yet."""
        slot = self.pair.index(imu)
        n = self.accel_share_n[slot]
        share = np.sqrt(np.asarray(self.accel_share_sums[slot]) / n) if n else None
        tested = self.check.tested_s()
        mdf_a, mdf_g = self.check.mdf()
        cfg = self.config
        reason = (
            ""
            if tested
            else f"{self.check.counts.paired:,} samples of IMU{self.pair[0]} paired with "
            f"IMU{self.pair[1]}; the test starts after {cfg.warmup_blocks * cfg.block_s:.3g} s of them"
        )

        def of(
            triad: Triad, mdf_si: float, reference_si: float | None, share: np.ndarray | None
        ) -> CheckCoverage:
            return norm_coverage(
                triad,
                tested_s=tested,
                mdf_si=mdf_si,
                reference_si=reference_si,
                false_alarms_per_hour=cfg.false_alarms_per_hour,
                pair=self.pair,
                reason=reason,
                share=share,
            )

        # The accelerometers' scale MDF is stated at g, the thrust of a hover.
        return of(Triad.ACCEL, mdf_a, self._gravity, share), of(Triad.GYRO, mdf_g, None, None)
