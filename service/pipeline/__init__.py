"""The streaming pipeline: one :class:`ImuPipeline` per (vehicle, IMU), a :class:`FleetProcessor` over them.

Modules: :mod:`~service.pipeline.options` (shared options, severities, thresholds),
:mod:`~service.pipeline.static_gate`, :mod:`~service.pipeline.triad_check` (F0 and the diagnosis of one
triad), :mod:`~service.pipeline.imu_pipeline`, :mod:`~service.pipeline.fleet`.

Per batch of samples, in this order (docs/architecture.md):

1. **Order.** Frames are taken in ``seq`` order: a repeated ``seq`` is a
   duplicate, a smaller one is out of order (both rejected and counted), a gap
   counts the missing frames; a frame with no sample later than the last
   accepted one is rejected (``no_new_samples``), and so are single samples
   that go back in time or are not finite. Frames that do not follow the
   stream are held: three in a row that form a consistent new stream
   (consecutive ``seq``, increasing time) are taken as a restart of the source
   and become the new stream's first frames (nothing rejected, no error
   density); otherwise they are rejected as above. A restart whose ``seq`` or
   time went back (to before where the stream was ahead of its last jump
   forward), or a frame carrying a new run id (:mod:`protocols.frames`
   version 2: its first frame is the restart), is a new run (``new_runs``):
   positions and diagnosis start afresh, as for a unit switched on, and a
   fault raised stays until the new run's diagnosis clears it; a stream that
   goes on from before a jump (a frame or the clock stamped ahead, then as
   before) is the same run on a stepped clock and keeps the estimates. A step forward of more than
   :data:`TIME_JUMP_PERIODS` sample periods is counted as a ``time_jump``; the
   static detector starts a new segment there by itself.
2. **Stream validity** (:mod:`estimators.stream_validity`): stale axes, error
   density; the timeout is checked by :meth:`FleetProcessor.tick`.
3. **Temperature.** When the frame carries temperature and the passport's
   triad has a temperature model (methods.md M3) the samples are brought to the
   passport's reference temperature
   (:func:`estimators.temperature.to_reference_temperature`) before anything
   else sees them; the status says so. Beyond the range the model was fitted on
   the model is held at the nearer edge (not extrapolated), which leaves an
   unmodelled error: a ``temperature`` event (cause ``temperature_range``) is
   raised when a sample leaves the range and a ``recovered`` one when the
   temperature is back inside by :data:`TEMPERATURE_HYSTERESIS_C`; F0 does not
   test samples taken outside the range (``f0.<triad>.skipped_temperature``) and
   positions whose mean temperature is outside do not enter the diagnosis
   (``positions.skipped_temperature.<triad>``). A schema-1 passport's model has
   no range: it is used at any temperature, and the status says so.
4. **Static detection and positions**
   (:class:`estimators.positions.PositionAccumulator`, per sample), with the
   detector's thresholds raised to the unit's own noise at the stream's rate
   (:func:`detector_config`; for a gyro F0 tests against the Earth rate, a
   static window's mean rate is bounded at F0's shell: the MEMS spread
   threshold let turn edges count as rest). The rate is measured from the first
   :data:`RATE_PROBE_SAMPLES` samples (their median step) and again over every
   :data:`RATE_CHECK_SAMPLES` steps after them (the interquartile mean step,
   :func:`estimators.stream_validity.typical_step_s`): when
   :data:`RATE_CHECK_BLOCKS` blocks in a row are off by more than
   :data:`RATE_CHECK_TOLERANCE`, the detector and F0 are sized again for the
   new rate at the sample that completes the last of them, whatever the
   framing (``rate_changes``; the status names both rates; the watch's
   progress is in the checkpoint), the pending position is ended and the
   diagnosis keeps its positions. A start-up burst at another spacing had
   sized the detector for good and silently turned fault detection off.
5. **F0 on every static sample** (methods.md M1) with
   :func:`estimators.scalar.f0_batch` over the samples :class:`StaticGate`
   releases (documented to give the per-sample
   :class:`~estimators.scalar.F0Monitor`'s decisions), centred on the
   passport's nominal errors, λ0 from :func:`estimators.scalar.derive_lambda0`
   with the passport's noise and tolerances at the configured false-alarm
   probability. The first run of FAILs lasting ``f0_persistence_s`` without a
   break (:func:`estimators.scalar.persistent_failure`) raises an event dated at
   the run's first sample: a knock on the resting vehicle fails a few samples
   and is only counted (``f0.<triad>.fail``); the measured Xsens session has one
   such knock at 208.1 s. M1's flow "on failure, run the
   diagnosis" is implemented literally: the failed triad's recursive estimate
   restarts from the positions *after* the failure, so F1…F9 describe the
   faulty sensor, not an average of before and after.
6. **Recursive re-estimation** (:class:`estimators.ninepar.RecursiveNineParam`)
   with each new position, and **diagnosis** (:func:`estimators.diagnosis.diagnose`)
   against the unit's passport once ``min_positions`` positions are in.
7. **Events** (:mod:`protocols.events`) on transitions only: a condition that
   stays raised gives one event, its end gives one ``recovered`` event.

Everything here is synchronous and deterministic: the same batches with the
same arrival times give the same events (ids included), which is what makes
``ins-health replay`` reproducible and lets the daemon re-derive, after a crash,
events whose ids the outbox already holds.

The submodules load on first use of one of their names: ``calibrate`` and ``diagnose`` take F0's
configuration from :mod:`~service.pipeline.options` and :mod:`~service.pipeline.triad_check`
and do not pay for importing the fleet's monitors (thrust axis, cross-IMU norm).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.pipeline.fleet import FleetProcessor, PassportLookup
    from service.pipeline.imu_pipeline import ImuPipeline
    from service.pipeline.options import PipelineOptions, detector_config
    from service.pipeline.static_gate import StaticGate

__all__ = [
    "PIPELINE_IMPORTS",
    "FleetProcessor",
    "ImuPipeline",
    "PassportLookup",
    "PipelineOptions",
    "StaticGate",
    "detector_config",
]

PIPELINE_IMPORTS = ("scipy.special", "scipy.optimize")
"""Modules a unit's pipeline loads on first use, not with its modules (the F0 threshold's λ0 is derived
with scipy.special and scipy.optimize): the daemon and replay load them first and freeze them with
the rest (:func:`service.commands.run.freeze_imports`, :func:`service.commands.replay.freeze_imports`)."""

_SUBMODULE_NAMES = {
    "fleet": ("FleetProcessor", "PassportLookup"),
    "imu_pipeline": ("ImuPipeline",),
    "options": ("PipelineOptions", "detector_config"),
    "static_gate": ("StaticGate",),
}


def __getattr__(name: str) -> Any:
    module = next((m for m, names in _SUBMODULE_NAMES.items() if name in names), None)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
