"""The service's pipeline on the real Xsens multi-position session, against the passport calibrated from it.

A fault-free unit on its own calibration data: F0 on every static sample and
F1…F9 after the positions must stay silent. The session is hand-held (SOURCE.md)
and one position is knocked at 208.1 s (+0.17 m/s² on z for one sample, −0.17
on the next-but-one: docs/audit-xsens.md flags that position as disturbed).
"""

import numpy as np
import pytest
from real_data import XSENS, needs

from estimators.conventions import Triad
from estimators.static_detector import detect_static
from protocols.events import Predicate, StreamCause
from protocols.frames import SampleBatch
from protocols.passport_codec import read_passport_json
from protocols.session_file import load_session
from service.cli import main
from service.pipeline import FleetProcessor, PipelineOptions, detector_config

pytestmark = needs(XSENS)
G_XSENS = 9.81744  # SOURCE.md: the local gravity the original authors used
FRAME = 100  # 1 s at the session's 100 Hz


@pytest.fixture(scope="module")
def unit(tmp_path_factory):
    out = tmp_path_factory.mktemp("xsens") / "passport.json"
    assert main(["calibrate", str(XSENS), "--out", str(out), "--no-audit"]) == 0
    return load_session(str(XSENS)).session, read_passport_json(out)


def _run(session, passport, options):
    fleet = FleetProcessor(passports=lambda v, i: passport, options=options)
    events = []
    for k, i in enumerate(range(0, session.n_samples, FRAME)):
        sl = slice(i, i + FRAME)
        events += fleet.process(
            SampleBatch(
                "xsens", 0, k, session.t_s[sl], session.accel_mps2[sl], session.gyro_rps[sl]
            ),
            arrival_s=0.0,
        )
    return events + fleet.finish(), fleet.pipelines[("xsens", 0)]


def eroded_static_runs(session, passport, options) -> list[slice]:
    """The static runs of the *batch* detector (thresholds as the pipeline sets them for this unit),
    less the positions' trim at both ends: computed apart from the streaming gate the pipeline uses."""
    rate_hz = session.rate_hz
    config = detector_config(options, passport, rate_hz)
    det = detect_static(session, config=config, rate_hz=rate_hz)
    edges = np.flatnonzero(np.diff(np.r_[0, det.static.astype(np.int8), 0])).reshape(-1, 2)
    m = options.positions.trim_samples(rate_hz)
    return [slice(a + m, b - m) for a, b in edges if b - a > 2 * m]


def knock_t_s(session, runs) -> float:
    """When the specific force strays farthest from its position's median, over the static samples
    F0 tests: the raw data's own account of the knock (no passport, no F0)."""
    norm = np.linalg.norm(session.accel_mps2, axis=1)
    worst = (0.0, 0)
    for r in runs:
        excursion = np.abs(norm[r] - np.median(norm[r]))
        k = int(np.argmax(excursion))
        worst = max(worst, (float(excursion[k]), r.start + k))
    return float(session.t_s[worst[1]])


def test_the_unit_on_its_own_calibration_session_raises_nothing(unit):
    session, passport = unit
    options = PipelineOptions(gravity_mps2=G_XSENS, gravity_rel_err=1e-4)
    events, pipe = _run(session, passport, options)
    assert events == []
    # SOURCE.md: a ~50 s rest and ~37 positions; the batch detector finds the same 38.
    assert pipe.n_positions == len(detect_static(session).intervals) == 38
    assert set(pipe.checks) == {Triad.ACCEL}  # the MEMS gyros cannot be calibrated against Ω
    # Every static sample was tested: as many as the batch detector's eroded runs hold
    # (34882 of the 36832 static samples; 25 samples come off each end of each run).
    runs = eroded_static_runs(session, passport, options)
    assert pipe.counters["f0.accel.tests"] == sum(r.stop - r.start for r in runs) == 34882
    # The knock is the one sample out of the shell (its residual is 1.07 λ0: the next test);
    # the next largest excursion, the ring-down two samples later, is 0.08 m/s² against 0.11.
    assert pipe.counters["f0.accel.fail"] == 1


def test_the_bare_predicate_calls_the_knock_a_failure_which_the_diagnosis_then_clears(unit):
    session, passport = unit
    options = PipelineOptions(gravity_mps2=G_XSENS, gravity_rel_err=1e-4, f0_persistence_s=0.0)
    events, _ = _run(session, passport, options)
    assert [(e.predicate, e.cause) for e in events] == [
        (Predicate.F0, StreamCause.OUT_OF_SHELL),
        (Predicate.F0, StreamCause.RECOVERED),
    ]
    # At the raw data's largest excursion (208.109 s, inside the position docs/audit-xsens.md flags).
    assert events[0].t_s == knock_t_s(session, eroded_static_runs(session, passport, options))
    assert events[0].estimate > events[0].tolerance
    assert "9 parameters within tolerance" in events[1].text
