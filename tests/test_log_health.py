"""Log health numerics (estimators.log_health) and nominal passports (estimators.nominal_passport)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.signal import lfilter

from estimators import log_health
from estimators.conventions import EARTH_RATE_RPS, STANDARD_GRAVITY_MPS2, Triad
from estimators.log_health import (
    HealthConfig,
    ImuHealthAccumulator,
    pair_differences,
)
from estimators.nominal_passport import (
    CLASS_TOLERANCES,
    SensorClass,
    describe_class,
    nominal_passport,
)
from estimators.scalar import derive_lambda0
from service.log_report import health_findings

G = STANDARD_GRAVITY_MPS2
FS = 400.0


def _unit(seed=1, n_s=60.0, fly=(20.0, 40.0), accel_sd=0.02, gyro_sd=0.003, t0=0.123):
    """Rest, a vibrating stretch (50 Hz, 5 m/s² on x), rest; accel z reads g + 0.1 m/s²."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(int(n_s * FS)) / FS
    a = rng.normal(0.0, accel_sd, (t.size, 3))
    a[:, 2] += G + 0.1
    g = rng.normal(0.0, gyro_sd, (t.size, 3)) + np.array([0.01, 0.0, 0.0])
    moving = (t > fly[0]) & (t < fly[1])
    a[moving, 0] += 5.0 * np.sin(2 * np.pi * 50.0 * t[moving])
    return t, a, g


def _health(t, a, g, chunk=333, temp=None):
    acc = ImuHealthAccumulator(HealthConfig())
    for i in range(0, t.size, chunk):
        acc.update(
            t[i : i + chunk],
            a[i : i + chunk],
            g[i : i + chunk],
            None if temp is None else temp[i : i + chunk],
        )
    return acc.result(G)


def test_rest_noise_bias_and_residual_are_recovered():
    t, a, g = _unit()
    h = _health(t, a, g)
    assert h.noise_method == "rest" and h.rate_hz == 400.0 and h.n_samples == t.size
    # ~80 000 rest samples per axis: the noise estimate's relative sd is ~1/sqrt(2·80 000) ≈ 0.25 %.
    np.testing.assert_allclose(h.accel_noise_mps2, 0.02, rtol=0.01)
    np.testing.assert_allclose(h.gyro_noise_rps, 0.003, rtol=0.01)
    # Bias: sd of the mean 0.003/sqrt(80 000) ≈ 1e-5.
    np.testing.assert_allclose(h.gyro_bias_rps, [0.01, 0.0, 0.0], atol=5e-5)
    assert h.gravity_residual_median_mps2 == pytest.approx(0.1, abs=1e-3)
    # Rest is 40 s less the blocks the vibrating stretch touches.
    assert 39.0 <= h.rest_s <= 40.0


def test_ardupilot_vibe_and_px4_metric_of_a_sinusoid():
    t, a, g = _unit(accel_sd=0.0, gyro_sd=0.0)
    h = _health(t, a, g)
    # VIBE: rms of the 5 Hz high-passed signal; a 50 Hz sinusoid of amplitude A passes with gain
    # 50/sqrt(50² + 5²), so VIBE ≈ A/√2 · 0.995 = 3.52 m/s², less the ripple of the 2 Hz smoothing.
    assert h.vibe_median_mps2[0] == pytest.approx(5.0 / math.sqrt(2) * 0.995, rel=0.05)
    assert h.vibe_median_mps2[1] == pytest.approx(0.0, abs=1e-9)
    # PX4: EMA of |Δv_k − Δv_{k−1}| = |a_k − a_{k−1}|·dt; for the sinusoid the mean of
    # |a_k − a_{k−1}| is 2A·sin(π f dt)·2/π.
    dt = 1.0 / FS
    expected = 2 * 5.0 * math.sin(math.pi * 50.0 * dt) * 2 / math.pi * dt
    assert h.px4_accel_vibration_median_mps == pytest.approx(expected, rel=0.05)
    assert h.px4_gyro_vibration_median_rad == pytest.approx(0.0, abs=1e-12)


def test_spectrum_peaks_at_the_vibration():
    t, a, g = _unit()
    h = _health(t, a, g)
    assert h.freq_hz[np.argmax(h.accel_psd[:, 0])] == pytest.approx(50.0, abs=FS / 256)
    # Away from the peak: the white noise floor 2σ²/fs (one-sided density).
    floor = np.median(h.accel_psd[:, 1])
    assert floor == pytest.approx(2 * 0.02**2 / FS, rel=0.1)


def test_batching_does_not_change_the_figures():
    t, a, g = _unit(n_s=20.0, fly=(5.0, 10.0))
    one = _health(t, a, g, chunk=t.size)
    many = _health(t, a, g, chunk=37)
    assert one.rest_s == many.rest_s and one.gap_count == many.gap_count
    np.testing.assert_allclose(one.accel_noise_mps2, many.accel_noise_mps2, rtol=1e-12)
    np.testing.assert_allclose(one.vibe_max_mps2, many.vibe_max_mps2, rtol=1e-12)
    np.testing.assert_allclose(one.accel_psd, many.accel_psd, rtol=1e-12)
    np.testing.assert_array_equal(one.blocks.k, many.blocks.k)


def _frames(fly, seed=3):
    """Frames as a replay hands them: mostly 100 samples, some short, empty or of one sample,
    with a lost second, a frame without temperature and a clock that starts again."""
    t, a, g = _unit(n_s=30.0, fly=fly)
    t = np.concatenate([t[:4000], t[4400:8000], t[8000:] - 20.0])
    a, g = np.vstack([a[:4000], a[4400:]]), np.vstack([g[:4000], g[4400:]])
    temp = np.linspace(30.0, 35.0, t.size)
    sizes = np.random.default_rng(seed).choice([100, 100, 100, 37, 1, 0], size=t.size)
    cuts = np.unique(np.r_[np.cumsum(sizes)[np.cumsum(sizes) < t.size], 7600, t.size])
    lo = 0
    for k, hi in enumerate(cuts.tolist()):
        yield t[lo:hi], a[lo:hi], g[lo:hi], None if k % 17 == 0 else temp[lo:hi]
        lo = hi


def _figures(acc):
    h = acc.result(G)
    return h.to_dict(), [
        np.asarray(getattr(h.blocks, f)).tolist() for f in h.blocks.__dataclass_fields__
    ]


@pytest.mark.parametrize("fly", [(8.0, 16.0), (-1.0, 31.0)], ids=["rest", "no_rest"])
def test_frames_taken_in_passes_give_the_figures_of_a_pass_per_frame(monkeypatch, fly):
    """Consecutive frames are filtered, blocked and summed in one pass of PASS_SAMPLES: the same
    figures to the bit as a pass per frame (what a replay's report held before), restart included;
    without rest the noise is the first difference's, its sums those of a pass per frame."""
    calls = []
    per_frame = ImuHealthAccumulator(HealthConfig())
    monkeypatch.setattr(log_health, "PASS_SAMPLES", 1)
    for frame in _frames(fly):
        per_frame.update(*frame)
    monkeypatch.undo()
    passes = ImuHealthAccumulator(HealthConfig())
    vibration = passes._vibration
    passes._vibration = lambda *args: calls.append(args[0].shape[0]) or vibration(*args)
    frames = list(_frames(fly))
    for frame in frames:
        passes.update(*frame)
    assert _figures(passes) == _figures(per_frame)
    assert len(calls) < len(frames) / 10 and max(calls) >= log_health.PASS_SAMPLES


def test_the_figures_and_spectra_are_the_same_bits_in_any_framing():
    """Replay hands the accumulator frames of 100 samples or joined batches of 16,400: it sums its
    periodograms in groups counted from the run's start (PSD_GROUP_SAMPLES), not per pass of what
    it was handed, so the spectra, block table and figures are the same bits fed a sample at a
    time, in frames of 100, 4,096 or 16,384, or all at once, across a lost second and a restart."""
    t, a, g = _unit(n_s=45.0, fly=(10.0, 30.0))
    temp = np.linspace(30.0, 35.0, t.size)
    keep = np.r_[0:4000, 4400 : t.size]  # a lost second
    t, a, g, temp = t[keep], a[keep], g[keep], temp[keep]
    restart = 14_000  # three groups and a part, then a clock 40 s back
    t = np.r_[t[:restart], t[restart:] - 40.0]
    figures = []
    for size in (100, 1, 4096, 16_384, t.size):
        acc = ImuHealthAccumulator(HealthConfig())
        for run in (slice(0, restart), slice(restart, t.size)):
            for lo in range(run.start, run.stop, size):
                rows = slice(lo, min(lo + size, run.stop))
                acc.update(t[rows], a[rows], g[rows], temp[rows])
        h = acc.result(G)
        figures.append((_figures(acc), h.accel_psd.tobytes() + h.gyro_psd.tobytes()))
    assert h.runs == 2 and h.accel_psd.size
    assert all(f == figures[0] for f in figures[1:])


@pytest.mark.parametrize("fly", [(8.0, 16.0), (-1.0, 31.0)], ids=["rest", "no_rest"])
def test_the_vibration_filters_give_the_figures_lfilter_gives(monkeypatch, fly):
    """VIBE's floor and level and PX4's two metrics, first-order low-passes solved by
    estimators.first_order_filter (no scipy.signal to import), give the figures scipy.signal.lfilter
    gives, the block table and the report's plain form byte for byte (a zero's sign included),
    on a replay's frames with a restart."""

    def oracle(b0, a1, x, zi):
        return lfilter([b0], [1.0, a1], x, axis=0, zi=zi)

    results = []
    for solver in (log_health.first_order_filter, oracle):
        monkeypatch.setattr(log_health, "first_order_filter", solver)
        acc = ImuHealthAccumulator(HealthConfig())
        for frame in _frames(fly):
            acc.update(*frame)
        h = acc.result(G)
        table = [np.asarray(getattr(h.blocks, f)).tobytes() for f in h.blocks.__dataclass_fields__]
        results.append((json.dumps(h.to_dict()), table))
    assert results[0] == results[1]
    assert json.loads(results[0][0])["vibration"]["ardupilot_vibe_mps2"] is not None


def _stream(fly, seed=5):
    """A logger's stamps (jittered by 0.2 of a step, so a run's median step depends on which samples
    give it), a lost second and a clock that starts again."""
    t, a, g = _unit(n_s=30.0, fly=fly, seed=seed)
    t = t + np.random.default_rng(seed).uniform(-0.1, 0.1, t.size) / FS
    keep = np.r_[0:4000, 4400 : t.size]
    t, a, g = t[keep], a[keep], g[keep]
    t[7600:] -= 20.0
    return t, a, g


@pytest.mark.parametrize("fly", [(8.0, 16.0), (-1.0, 31.0)], ids=["rest", "no_rest"])
def test_the_figures_do_not_depend_on_the_frame_size(fly):
    """Replay's report is the same to the bit whether its frames hold 100 samples (what it fed the
    report before), 1000, 4096 or the whole log in one: the filters' sample interval is the median
    of each run's first RUN_START_SAMPLES steps and the first difference's squares are summed in
    blocks counted from the run's start, not per frame."""
    t, a, g = _stream(fly)
    temp = np.linspace(30.0, 35.0, t.size)
    figures = []
    for size in (100, 1000, 4096, t.size):
        acc = ImuHealthAccumulator(HealthConfig())
        # As the log reader cuts them: frames of `size` and a short one before the clock restart.
        for lo, hi in (r for run in ((0, 7600), (7600, t.size)) for r in _cuts(*run, size)):
            acc.update(t[lo:hi], a[lo:hi], g[lo:hi], temp[lo:hi])
        figures.append(_figures(acc))
    assert all(f == figures[0] for f in figures[1:])


def _cuts(lo, hi, size):
    return [(k, min(k + size, hi)) for k in range(lo, hi, size)]


def test_a_run_of_one_sample_is_counted_and_not_joined_to_the_next():
    """A reboot right after the logger's first IMU sample: that run has no interval to start the
    filters on. Joined to the next run it made a step back of 47 s: the duration came out
    negative (-17 s) and the restart went uncounted; a last run of one sample was not counted."""
    t, a, g = _stream((8.0, 16.0))
    acc = ImuHealthAccumulator(HealthConfig())
    acc.update(np.array([t[7599] + 47.0]), a[:1], g[:1])
    for lo, hi in _cuts(7600, t.size, 100):
        acc.update(t[lo:hi], a[lo:hi], g[lo:hi])
    acc.update(np.array([t[7600]]), a[:1], g[:1])
    h = acc.result(G)
    assert (h.n_samples, h.runs) == (t.size - 7600 + 2, 3)
    assert h.duration_s == pytest.approx(t[-1] - t[7600])


def test_a_block_still_settling_after_motion_is_no_noise():
    """The ringing after a landing (12 Hz, 0.3 m/s² decaying in 0.25 s on z) keeps the first block
    after it within a detector's spread (here 0.2 m/s², a replay raises it to the passport's noise)
    but at five times the noise: it is settling and left out of the noise figure, which then reads
    the white noise within its own scatter (~80 000 samples: 0.25 %)."""
    t, a, g = _unit()
    after = t - 40.0
    a[:, 2] += np.where(
        after > 0.0, 0.3 * np.exp(-after / 0.25) * np.sin(2 * np.pi * 12.0 * after), 0.0
    )
    acc = ImuHealthAccumulator(HealthConfig(accel_rest_mps2=0.2))
    acc.update(t, a, g)
    h = acc.result(G)
    assert h.settling_blocks == 1 and h.blocks.rest[h.blocks.k == 80].all()
    np.testing.assert_allclose(h.accel_noise_mps2, 0.02, rtol=0.01)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_signal_quantized_below_its_noise_has_no_settling_block(seed):
    """Two minutes at rest at 25 Hz in milli-g and mrad/s steps (a telemetry log's SCALED_IMU),
    the accelerometer's noise 0.2 of a step: most blocks never change a count, so one count's flip
    doubles a block's spread without any ringing. Taken for settling, up to 105 of 240 blocks were
    left out and the noise read 0 on two axes; the rest's own spread is the figure (pooled within
    blocks: the quantized samples' standard deviation within 10 %)."""
    rng = np.random.default_rng(seed)
    t = np.arange(3000) / 25.0
    mg, mrad = 1e-3 * G, 1e-3
    a = np.round((np.array([0.05, -0.1, G]) + rng.normal(scale=0.002, size=(t.size, 3))) / mg) * mg
    g = np.round((np.array([1e-3, 2e-3, -1e-3]) + rng.normal(scale=8e-4, size=(t.size, 3))) / mrad)
    acc = ImuHealthAccumulator()
    acc.update(t, a, g * mrad)
    h = acc.result(G)
    assert h.noise_method == "rest" and h.settling_blocks == 0
    np.testing.assert_allclose(h.accel_noise_mps2, a.std(axis=0), rtol=0.1)


def test_gaps_temperature_and_no_rest():
    t, a, g = _unit(n_s=10.0, fly=(-1.0, 11.0))
    keep = np.ones(t.size, bool)
    keep[1000:1400] = False  # one second lost
    keep[2000] = False  # one sample lost
    temp = np.linspace(30.0, 35.0, t.size)
    h = _health(t[keep], a[keep], g[keep], temp=temp[keep])
    assert h.gap_count == 2 and h.longest_gap_s == pytest.approx(401 / FS, abs=1e-6)
    assert h.temp_min_c == pytest.approx(30.0) and h.temp_max_c == pytest.approx(35.0)
    # Always vibrating: no rest; the noise comes from the first difference and says so.
    assert h.rest_s == 0.0 and h.noise_method == "first_difference"
    assert h.gravity_residual_median_mps2 is None and h.gyro_bias_rps is None


def test_slow_logs_have_no_rest():
    """Four samples a second: a 0.5 s block holds two, which cannot tell rest from a steady turn."""
    rng = np.random.default_rng(2)
    t = np.arange(400) / 4.0
    a = rng.normal(0, 0.01, (t.size, 3)) + np.array([0, 0, G])
    h = _health(t, a, np.zeros((t.size, 3)), chunk=50)
    assert h.rate_hz == 4.0 and h.rest_s == 0.0
    assert not h.blocks.full.any()


def test_the_report_tells_a_log_too_short_to_judge_from_one_never_at_rest():
    """45 samples at 400 Hz (0.11 s): too short to fill a block, which is not "never at rest"."""
    t, a, g = _unit(n_s=60.0, fly=(-1.0, 61.0))
    short = _health(t[:45], a[:45], g[:45])
    (finding,) = health_findings(0, short, None)
    assert finding["predicate"] == "too_short"
    assert "45 samples over 0.11 s at 400 Hz: no 0.5 s block held samples enough" in finding["text"]
    vibrating = _health(t, a, g)
    assert vibrating.blocks.full.any()
    assert [f["predicate"] for f in health_findings(0, vibrating, None)][-1] == "no_rest"


def test_pair_differences_in_flight_and_at_rest():
    t, a, g = _unit(n_s=30.0, fly=(10.0, 20.0))
    b = a.copy()
    b[:, 2] += 0.5  # IMU1 reads 0.5 m/s² more on z, always
    blocks = {0: _health(t, a, g).blocks, 1: _health(t, b, g).blocks}
    (pair,) = pair_differences(blocks, 0.5)
    d = pair.to_dict()
    assert (
        d["imus"] == [0, 1] and d["common_blocks"] == 61
    )  # 0.123 … 30.12 s: partial blocks at both ends
    assert d["accel_mps2"]["rest"]["max"] == pytest.approx(0.5, abs=1e-9)
    assert d["accel_mps2"]["flight"]["p99"] == pytest.approx(0.5, abs=1e-9)
    assert d["gyro_rps"]["rest"]["max"] == pytest.approx(0.0, abs=1e-12)


def test_health_config_is_validated():
    with pytest.raises(ValueError, match="block_s"):
        HealthConfig(block_s=0.0)
    with pytest.raises(ValueError, match="nfft"):
        HealthConfig(nfft=4)


# ------------------------------------------------------------------ nominal passports


@pytest.mark.parametrize("cls", list(SensorClass))
def test_nominal_passports_carry_the_class_tolerances(cls):
    p = nominal_passport(cls, gravity_mps2=9.81)
    f = CLASS_TOLERANCES[cls]
    acc, gyr = p.triads[Triad.ACCEL], p.triads[Triad.GYRO]
    np.testing.assert_allclose(acc.tolerance[:3], np.array(f.accel.bias_si) / 9.81)
    np.testing.assert_allclose(acc.tolerance[3:6], f.accel.scale)
    np.testing.assert_allclose(gyr.tolerance[:3], np.array(f.gyro.bias_si) / EARTH_RATE_RPS)
    assert not acc.nominal.any() and acc.observable.all()
    # Only a gyro whose bias tolerance is below the Earth rate can be checked against it (M1).
    assert gyr.observable.all() == (max(f.gyro.bias_si) < EARTH_RATE_RPS)
    assert cls.value in acc.provenance.procedure and describe_class(cls)["class"] == cls.value


CITED = {
    # class: (accel bias mg, scale %, cross-axis %, noise µg/√Hz; gyro bias °/h, scale %, cross-axis %,
    # noise °/s/√Hz), each as its source states it (the module docstring names part and document).
    # Biases per axis x, y, z.
    SensorClass.CONSUMER_MEMS: ((50.0, 50.0, 80.0), 3.0, 2.0, 400.0, (20.0 * 3600.0,) * 3, 3.0, 2.0, 0.005),
    SensorClass.INDUSTRIAL_MEMS: ((2.0,) * 3, 0.2, 100.0 * math.radians(0.1), 100.0, (20.0,) * 3, 0.2, 100.0 * math.radians(0.1), 0.008),
    SensorClass.TACTICAL: ((1.0,) * 3, 0.03, 0.02, 0.065 * 0.3048 / 60.0 / 9.80665 * 1e6, (1.0,) * 3, 0.03, 0.02, 0.125 / 60.0),
    SensorClass.NAVIGATION: ((0.025,) * 3, 0.01, 0.005, 10.0, (0.0035,) * 3, 0.0005, 0.002, 0.002 / 60.0),
}  # fmt: skip


@pytest.mark.parametrize("cls", list(SensorClass))
def test_the_class_figures_are_the_cited_ones(cls):
    d = describe_class(cls)
    keys = ("accel_bias_mg", "accel_scale_pct", "accel_cross_axis_pct", "accel_noise_ug_per_rthz",
            "gyro_bias_dph", "gyro_scale_pct", "gyro_cross_axis_pct", "gyro_noise_dps_per_rthz")  # fmt: skip
    flat = [np.ravel(d[k]) for k in keys]
    for got, cited in zip(flat, CITED[cls], strict=True):
        np.testing.assert_allclose(got, np.ravel(cited), rtol=1e-12)


def test_the_classes_shells_are_ordered_and_the_consumer_shell_is_its_datasheet():
    """λ0 from each class's tolerances (F0's shell): tighter for better classes; consumer MEMS ≈ 0.2."""
    lam = {}
    for cls in SensorClass:
        tp = nominal_passport(cls).triads[Triad.ACCEL]
        lam[cls] = derive_lambda0(
            noise_std_norm=tp.noise_std * math.sqrt(250.0 / tp.sample_rate_hz),
            false_alarm_prob=1e-9,
            tolerance_norm=tp.tolerance,
        ).lambda0
    order = [
        SensorClass.CONSUMER_MEMS,
        SensorClass.INDUSTRIAL_MEMS,
        SensorClass.TACTICAL,
        SensorClass.NAVIGATION,
    ]
    assert [lam[c] for c in order] == sorted(lam.values(), reverse=True)
    # 50/50/80 mg (106 mg along their common direction) + 3 % scale + 2 % cross-axis per sensor: ≈ 0.2.
    assert 0.18 < lam[SensorClass.CONSUMER_MEMS] < 0.26


def test_vibe_filters_have_ardupilots_corners_and_px4s_smoothing():
    """A 5 Hz vibration sits on VIBE's 5 Hz floor: the first-order high-pass passes 1/√2 of it; PX4's
    metric (an EMA with α = 0.01) rises over 1/α samples: averaged over the first 200 samples of the
    vibration it reaches 1 − (1 − 0.99²⁰⁰)/(200·0.01) = 0.567 of its steady value."""
    t = np.arange(int(30 * FS)) / FS
    a = np.zeros((t.size, 3)) + np.array([0.0, 0.0, G])
    on = t >= 10.0
    a[on, 1] += 2.0 * np.sin(2 * np.pi * 5.0 * (t[on] - 10.0))
    h = _health(t, a, np.zeros((t.size, 3)))
    assert h.vibe_median_mps2[1] == pytest.approx(2.0 / math.sqrt(2) / math.sqrt(2), rel=0.05)
    b = h.blocks
    steady = np.median(b.px4_accel[b.k >= 30])
    onset = b.px4_accel[b.k == 20][0]
    assert onset / steady == pytest.approx(1 - (1 - 0.99**200) / 2.0, abs=0.03)
