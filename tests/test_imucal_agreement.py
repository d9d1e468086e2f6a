"""Against an independent implementation: imucal's Ferraris calibration (mad-lab-fau/imucal, a
test-only dependency) on the same simulated six-position session with full turns.

imucal needs the regions marked by hand; here the simulator's truth marks them (each hold, each
turn from the end of the hold before to the start of the hold after). ins-health finds them
itself. Both see the same samples, so they must agree within the noise.
"""

import numpy as np
import pytest

from estimators.chain import ChainConfig, calibration_estimates, run_chain
from estimators.conventions import Triad
from estimators.sim import Grade, grade_error_model, simulate
from estimators.sixpos import face_positions, ferraris_spec
from estimators.static_detector import StaticDetectorConfig

imucal = pytest.importorskip("imucal", reason="imucal (test extra) is not installed")

FACES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")


def imucal_regions(res):
    """imucal's regions from the simulator's truth: holds in face order, turns between holds."""
    truth, s = res.truth, res.session
    holds = truth.static_intervals_s
    # ferraris_spec: +x hold, turn about x, +x hold, −x, +y, turn about y, +y, −y, +z, turn, +z, −z.
    face_holds = [holds[i] for i in (0, 2, 3, 5, 6, 8)]
    turn_spans = [(holds[i][1], holds[i + 1][0]) for i in (0, 3, 6)]

    def take(t0, t1):
        m = (s.t_s >= t0) & (s.t_s <= t1)
        return s.accel_mps2[m], s.gyro_rps[m]

    fields = {}
    for name, (t0, t1) in zip(FACES, face_holds, strict=True):
        fields[f"acc_{name}"], fields[f"gyr_{name}"] = take(t0, t1)
    for axis, (t0, t1) in zip("xyz", turn_spans, strict=True):
        fields[f"acc_{axis}_rot"], fields[f"gyr_{axis}_rot"] = take(t0, t1)
    return imucal.FerrarisSignalRegions(**fields)


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_zero_signals_scale_errors_and_gyro_scale_factors_agree_with_imucal(seed):
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    res = simulate(ferraris_spec(model, static_s=8.0), seed=seed)
    g = res.truth.gravity_mps2
    config = ChainConfig(gravity_mps2=g, detector=StaticDetectorConfig.from_session(res.session))
    result = run_chain(res.session, config)
    cal = calibration_estimates(result)
    acc, gyr = cal.estimates[Triad.ACCEL], cal.estimates[Triad.GYRO]

    # The simulated spin is counter-clockwise: +2π (imucal's default is a clockwise −360°).
    theirs = imucal.FerrarisCalibration(grav=g, expected_angle=2.0 * np.pi).compute(
        imucal_regions(res), res.spec.rate_hz, from_acc_unit="m/s^2", from_gyr_unit="rad/s"
    )
    # imucal: raw = K·R·a + b, K = diag(1 + e), R with unit rows (the sensitive axes).
    acc_theirs = np.concatenate([theirs.b_a / g, np.diag(theirs.K_a) - 1.0, _cosines(theirs.R_a)])
    gyr_theirs = np.concatenate([np.diag(theirs.K_g) - 1.0, _cosines(theirs.R_g)])
    # Same samples, different regions and estimators: within a few standard deviations of the
    # less precise of the two. imucal's bias of axis i is the mean of the two faces with i
    # vertical (ours uses all six), so its σ is the noise of those two means; elsewhere ours.
    faces = face_positions(result.positions)
    assert faces is not None
    var = np.array([np.diag(p.accel_cov_mps2) for p in faces])
    up = np.argmax(np.abs([p.accel_mean_mps2 for p in faces]), axis=1)
    sigma_theirs = np.sqrt([var[up == i, i].sum() / 4.0 for i in range(3)]) / g
    bound = acc.sigma.copy()
    bound[:3] = np.maximum(bound[:3], sigma_theirs)
    np.testing.assert_array_less(np.abs(acc.params - acc_theirs), 4.0 * bound)
    np.testing.assert_array_less(np.abs(gyr.params[3:] - gyr_theirs), 4.0 * gyr.sigma[3:])
    # And both are near the truth (a sanity check of the region marking).
    assert np.max(np.abs(acc_theirs[3:6] - res.truth.accel_params[3:6])) < 5e-4


def _cosines(rows):
    r = np.asarray(rows) / np.linalg.norm(rows, axis=1, keepdims=True)
    return np.array([r[0] @ r[1], r[0] @ r[2], r[1] @ r[2]])
