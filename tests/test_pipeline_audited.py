"""The service's thresholds come from the audited noise model carried by the passport (issue 4)."""

from __future__ import annotations

import dataclasses

import numpy as np

from estimators.conventions import Triad
from service.demo import demo_passport
from service.pipeline import PipelineOptions
from service.pipeline.triad_check import f0_config

RATE_HZ = 200.0


def _accel_lambda0(passport, g):
    _, lambda0, _ = f0_config(
        passport.triads[Triad.ACCEL], PipelineOptions(gravity_mps2=g), RATE_HZ
    )
    return lambda0


def _with_wander(passport, wander_norm):
    tp = dataclasses.replace(
        passport.triads[Triad.ACCEL], bias_instability_std=np.full(3, wander_norm)
    )
    return dataclasses.replace(passport, triads={**passport.triads, Triad.ACCEL: tp})


def test_f0_threshold_grows_with_the_audited_bias_wander():
    passport, g = demo_passport()
    white = _accel_lambda0(passport, g)
    wander = passport.triads[Triad.ACCEL].noise_std.max()  # a wander as large as the white noise
    audited = _accel_lambda0(_with_wander(passport, wander), g)
    assert audited > white
    # A zero wander is the white-noise model exactly.
    assert _accel_lambda0(_with_wander(passport, 0.0), g) == white
