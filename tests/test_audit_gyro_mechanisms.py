"""The gyro's deterministic mechanisms and the temperature panel (issue 31, items 1, 4 and 5).

A gyro that resolves the Earth rate (navigation grade) carries a bias step, a temperature hysteresis
and a rail in its scalar residual ``|ω − b − G f| = Ω``: each is named as its mechanism on its axis,
not as wander. A MEMS gyro does not resolve it: its blind-spot statement names these effects and the
audit states their minimum detectable sizes. benchmarks/bench_audit.py runs 20 trials per class.
"""

from dataclasses import replace

import matplotlib.image as mpimg
import numpy as np
import pytest

import estimators.audit.audit as audit_module
from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import (
    baseline_error_model,
    candidate_table,
    detectable_statements,
    extend_model,
    find_candidates,
    fit_baselines,
    structure_of,
)
from estimators.audit.candidates import clipping_candidates
from estimators.audit.hidden import (
    GYRO_MECHANISM_KINDS,
    TRIAL_UNITS,
    baseline_model,
    change_se,
    draw,
    hide,
    session_of,
    trial,
    trial_chain_config,
)
from estimators.audit.statistics import scalar_residuals
from estimators.chain import ChainConfig
from estimators.conventions import EARTH_RATE_RPS, Triad
from estimators.sim import Bias, BiasStep, ErrorModel, Grade, TemperatureHysteresis
from service.audit_report import temperature_panel, write_report

G = 9.80665
NAV = Grade.NAVIGATION


@pytest.mark.parametrize("kind", GYRO_MECHANISM_KINDS, ids=[k for k, _ in GYRO_MECHANISM_KINDS])
def test_each_gyro_mechanism_is_named_on_its_axis_where_the_gyro_resolves_the_earth_rate(kind):
    # 4 seeded trials at 10 SE: ≥ 3 of 4 passes a class named at the 90 % asked with probability 95 %
    # (binomial); before the gyro had these candidates a step and a hysteresis were named as
    # bias_instability or nothing.
    hits = [trial(draw(9900 + t, 10.0, kind, NAV), 9900 + t) for t in range(4)]
    assert sum(hits) >= 3, hits


def test_a_gyro_step_carries_its_size_and_turn_and_is_re_simulated():
    h = hide(9910, "bias_step", Triad.GYRO, "y", 10.0, grade=NAV)
    s, chain = session_of(h.model, 9910, grade=NAV)
    base = fit_baselines(s, chain, colour=False)
    cands = find_candidates(s, chain, base)
    (c,) = [c for c in cands if c.selected]
    assert (c.effect, c.triad, c.axis) == ("bias_step", Triad.GYRO, "y")
    # The hidden step (normalized by Ω) within 4 of its standard errors; the hidden time inside the named turn.
    p = c.params
    assert abs(p["step_rps"] - h.value * EARTH_RATE_RPS) < 4.0 * p["step_rps_se"], p
    step_t = h.model.gyro.find(BiasStep).t_step_s[1] - s.t_s[0]
    assert abs(step_t - p["t_change_s"]) <= p["t_change_se_s"], (step_t, p)
    # The extended model steps the gyro (not the accelerometers) by the fitted step at the fitted time.
    tab_a = candidate_table(chain, s, Triad.ACCEL, base[Triad.ACCEL])
    ext, _ = extend_model(baseline_error_model(base, G), base, cands, tab_a, G)
    assert ext.accel.find(BiasStep) is None
    np.testing.assert_allclose(ext.gyro.find(BiasStep).step_si, [0.0, p["step_rps"], 0.0])
    assert ext.gyro.find(BiasStep).t_step_s[1] == p["t_change_s"]


def test_a_gyro_rail_is_found_on_the_side_its_samples_stack():
    # The Earth rate projects on a gyro axis with either sign: symmetric rails clip both extremes, and the
    # stack can lie on the side of the smaller magnitude (here the maximum is one sample on the rail, the
    # stack at the minimum). Tried on the larger magnitude only, these rails went unnamed.
    for seed in (902003, 902008):
        h = hide(seed, "clipping", Triad.GYRO, "x", 10.0, grade=NAV)
        s, chain = session_of(h.model, seed, grade=NAV)
        cands = find_candidates(s, chain, fit_baselines(s, chain, colour=False))
        (c,) = [
            c for c in cands if c.effect == "clipping" and c.triad is Triad.GYRO and c.axis == "x"
        ]
        assert c.selected and abs(c.params["rail_si"]) == pytest.approx(h.value), c.reason


def test_a_mems_gyro_states_what_its_path_cannot_see_with_the_new_mechanisms():
    s, _ = session_of(baseline_model(np.random.default_rng(2)), 8500)
    res = run_audit(s, AuditConfig(trial_chain_config(Grade.MEMS, s), replicas=2))
    (blind,) = [st for st in res.statements if st.startswith("gyro blind spot")]
    assert "bias step" in blind and "temperature hysteresis" in blind, blind
    (gyro,) = [
        st for st in res.statements if st.startswith("minimum detectable on this session (gyro")
    ]
    for ax in "xyz":
        assert (
            f"bias_step {ax} step_rps" in gyro and f"temperature_hysteresis {ax} offset_rps" in gyro
        )


def test_a_temperature_hysteresis_report_shows_the_residual_against_temperature(tmp_path):
    h = hide(9920, "temperature_hysteresis", Triad.ACCEL, "z", 10.0)
    s, _ = session_of(h.model, 9920)
    res = run_audit(s, AuditConfig(ChainConfig(gravity_mps2=G), replicas=2))
    assert [(c.effect, c.triad, c.axis) for c in res.named] == [
        ("temperature_hysteresis", Triad.ACCEL, "z")
    ]
    c = res.named[0]
    (st,) = [x for x in res.structure if x.triad is Triad.ACCEL]
    panel = temperature_panel(c, st, G)
    assert panel is not None
    # Heating and cooling apart, each against its fitted level ±h (the baseline's bias takes their mean).
    h_si = c.params["offset_norm"] * G
    for side, level in ((panel.heating > 0, h_si), (panel.heating < 0, -h_si)):
        w = 1.0 / panel.sd_si[side] ** 2
        mean = np.sum(w * panel.effect_si[side]) / np.sum(w)
        assert abs(mean - level) < 4.0 / np.sqrt(np.sum(w)), (mean, level)
    assert [v.tolist() for v in panel.curve_si] == [[h_si, h_si], [-h_si, -h_si]]
    md = write_report(res, tmp_path, title="hysteresis").read_text()
    name = "mechanism_temperature_hysteresis_accel_z.png"
    assert f"]({name})" in md
    # Three panels: time, orientation, temperature (two without one, 1000 px at 100 dpi).
    assert mpimg.imread(tmp_path / name).shape[1] == 1500


def test_a_gyro_temperature_effect_has_its_panel_too():
    h = hide(9930, "temperature_hysteresis", Triad.GYRO, "x", 10.0, grade=NAV)
    s, chain = session_of(h.model, 9930, grade=NAV)
    base = fit_baselines(s, chain, colour=False)
    (c,) = [c for c in find_candidates(s, chain, base) if c.selected]
    assert (c.effect, c.triad, c.axis) == ("temperature_hysteresis", Triad.GYRO, "x")
    (st,) = [x for x in structure_of(s, chain, base) if x.triad is Triad.GYRO]
    panel = temperature_panel(c, st, G)
    assert panel is not None and panel.unit == "rad/s"
    hot, cold = panel.heating > 0, panel.heating < 0
    assert hot.any() and cold.any()
    # The rad/s of the points: heating minus cooling about twice the fitted offset, in its noise.
    diff = panel.effect_si[hot].mean() - panel.effect_si[cold].mean()
    sd = np.sqrt(
        np.mean(panel.sd_si[hot] ** 2) / hot.sum() + np.mean(panel.sd_si[cold] ** 2) / cold.sum()
    )
    assert abs(diff - 2.0 * c.params["offset_rps"]) < 4.0 * sd, (diff, c.params)


def test_a_gyro_step_in_the_first_or_last_turn_is_named_for_the_triad_not_on_an_axis_it_missed():
    # A step in the first (last) turn moves one position against the rest: once the baseline's bias is
    # fitted, every axis' column explains that one scalar datum alike. The first axis tried won the tie:
    # a z step of 10 SE was named on x (first turn: x on 5 of 8 seeds, the last turn: 7 of 8).
    seed = 360000
    m = baseline_model(np.random.default_rng(seed), NAV)
    s, chain = session_of(m, seed, grade=NAV)
    base = fit_baselines(s, chain, colour=False)
    tab = candidate_table(chain, s, Triad.GYRO, base[Triad.GYRO])
    jac = scalar_residuals(base[Triad.GYRO].params, tab)[2]
    n = len(chain.positions)
    for after in (1, n - 1):
        step = np.zeros(3)
        step[2] = 10.0 * change_se(s, chain, jac[:, [2]], after, Triad.GYRO)[0] * EARTH_RATE_RPS
        t = 0.5 * (chain.positions[after - 1].t_end_s + chain.positions[after].t_start_s)
        s2, chain2 = session_of(
            m.with_effect(BiasStep(np.full(3, t), step), Triad.GYRO), seed, grade=NAV
        )
        cands = find_candidates(s2, chain2, fit_baselines(s2, chain2, colour=False))
        (c,) = [c for c in cands if c.selected]
        assert (c.effect, c.triad, c.axis) == ("bias_step", Triad.GYRO, None), c.reason
        assert "z" in c.params["axes_alike"] and c.params["after_position"] == after, c.params
        assert "not identifiable" in c.reason
        # What each axis could see is still said per axis, the step's fitted one included.
        (gyro,) = [m for m in detectable_statements(cands) if "(gyro" in m]
        assert all(f"bias_step {ax} step_rps" in gyro for ax in "xyz"), gyro


@pytest.mark.parametrize(("seed", "axis"), [(350002, "y"), (370000, "x")])
def test_a_step_s_stated_minimum_detectable_size_holds_at_every_turn_tried(seed, axis):
    # The stated size is at 95 % power: 1.5x it at the turn hardest to see is named, 0.5x the size at the
    # easiest turn is not (its LR ≈ 3² against the known-scale threshold ≈ 4.5² the step meets once it
    # structures the residual). Stated from one break's standard error (the break the noise peaked at;
    # for 350002 the first turn's, 9.4e-6 rad/s), 0.5x of it was named at a middle turn (6 of 10 seeds);
    # stated at the effect-free session's F threshold (32.6, not 20.0), 0.5x was named at 370000's best.
    i = "xyz".index(axis)
    m = baseline_model(np.random.default_rng(seed), NAV)
    s, chain = session_of(m, seed, grade=NAV)
    base = fit_baselines(s, chain, colour=False)
    (c,) = [
        c
        for c in find_candidates(s, chain, base)
        if (c.effect, c.triad, c.axis) == ("bias_step", Triad.GYRO, axis)
    ]
    tab = candidate_table(chain, s, Triad.GYRO, base[Triad.GYRO])
    jac = scalar_residuals(base[Triad.GYRO].params, tab)[2]
    n = len(chain.positions)
    se = {b: change_se(s, chain, jac[:, [i]], b, Triad.GYRO)[0] for b in range(2, n - 1)}
    p = c.params
    for after, size, named in (
        (max(se, key=se.get), 1.5 * p["step_rps_min_detectable"], True),
        (
            min(se, key=se.get),
            0.5 * p.get("step_rps_min_detectable_best", p["step_rps_min_detectable"]),
            False,
        ),
    ):
        t = 0.5 * (chain.positions[after - 1].t_end_s + chain.positions[after].t_start_s)
        step = BiasStep(np.full(3, t), size * np.eye(3)[i])
        s2, chain2 = session_of(m.with_effect(step, Triad.GYRO), seed, grade=NAV)
        got = find_candidates(s2, chain2, fit_baselines(s2, chain2, colour=False))
        # Named on its axis, or for the triad where the axes' columns are alike at that turn (it among them).
        hit = any(
            c.effect == "bias_step"
            and c.selected
            and (c.axis == axis or axis in c.params.get("axes_alike", ()))
            for c in got
        )
        assert hit is named, (after, size, p)


def test_only_a_change_is_named_for_the_triad_when_its_axes_explain_it_alike():
    # A temperature scale another axis explains nearly as well is still named on the axis fitted: the
    # turn of a change is what leaves one position on one side (here a false alarm of a gyro that
    # barely resolves the Earth rate, 1 of 40 seeds, was named with no axis at all).
    seed = 410038
    unit = replace(TRIAL_UNITS[NAV], gyro_sd_rps=1.5e-4)
    s, chain = session_of(baseline_model(np.random.default_rng(seed), NAV, unit), seed, grade=NAV)
    named = [
        c for c in find_candidates(s, chain, fit_baselines(s, chain, colour=False)) if c.selected
    ]
    assert all(c.axis is not None for c in named), [(c.effect, c.axis) for c in named]


def test_a_mems_gyro_mechanism_without_a_plot_says_so_in_the_report(tmp_path):
    # A MEMS gyro's means carry the Earth rate as noise: no scalar residual, so no mechanism plot. The
    # report listed none and said nothing (issue 31, item 5: one plot per named effect).
    seed = 430000
    m = baseline_model(np.random.default_rng(seed), Grade.MEMS)
    model = m.with_effect(TemperatureHysteresis([3.0e-4, 0.0, 0.0]), Triad.GYRO)
    s, _ = session_of(model, seed)
    res = run_audit(s, AuditConfig(trial_chain_config(Grade.MEMS, s), replicas=2))
    assert ("temperature_hysteresis", Triad.GYRO, "x") in {
        (c.effect, c.triad, c.axis) for c in res.named
    }
    md = write_report(res, tmp_path, title="mems gyro").read_text()
    assert not (tmp_path / "mechanism_temperature_hysteresis_gyro_x.png").exists()
    assert (
        "no mechanism plot for temperature_hysteresis (gyro x)" in md
        and "earth_rate_as_noise" in md
    )


def test_a_gyro_mechanism_plot_puts_the_earth_rate_on_its_orientation_axis(tmp_path, monkeypatch):
    # A gyro's scalar residual is plotted against its means' direction (the Earth rate's), which the
    # label called gravity's.
    import service.audit_report as report

    h = hide(9930, "temperature_hysteresis", Triad.GYRO, "x", 10.0, grade=NAV)
    s, _ = session_of(h.model, 9930, grade=NAV)
    res = run_audit(s, AuditConfig(trial_chain_config(NAV, s), replicas=2))
    labels = {}

    def keep_labels(fig, path, **_):
        labels[path.name] = [a.get_xlabel() for a in fig.axes]

    monkeypatch.setattr(report, "save_figure", keep_labels)
    write_report(res, tmp_path, title="gyro")
    xlabels = labels["mechanism_temperature_hysteresis_gyro_x.png"]
    assert "u_x (the Earth rate on the axis)" in xlabels, xlabels


def _gyro_steps_at_10_se(seed: int, after: int) -> tuple[ErrorModel, float, np.ndarray]:
    """A navigation unit's model, the time of the turn before position ``after`` (s) and, per gyro axis,
    a step of 10 of its standard errors at that turn (rad/s)."""
    m = baseline_model(np.random.default_rng(seed), NAV)
    s, chain = session_of(m, seed, grade=NAV)
    base = fit_baselines(s, chain, colour=False)
    jac = scalar_residuals(
        base[Triad.GYRO].params, candidate_table(chain, s, Triad.GYRO, base[Triad.GYRO])
    )[2]
    step = np.array(
        [
            10.0 * change_se(s, chain, jac[:, [i]], after, Triad.GYRO)[0] * EARTH_RATE_RPS
            for i in range(3)
        ]
    )
    t = 0.5 * (chain.positions[after - 1].t_end_s + chain.positions[after].t_start_s)
    return m, t, step


def test_a_step_on_two_axes_at_one_turn_has_a_time_interval_that_holds_the_turn():
    # Steps of 10 SE on x and y in the turn before position 13: each axis' break was profiled with the
    # other's held where forward selection had put it, so the profile peaked there and both intervals
    # (130.5 ± 5.8 s and 134.5 ± 1.8 s) excluded the turn (102.5 s); re-profiled with the other refitted
    # at each of its breaks, every interval holds it (12 of 12 on seeds 390000-390005, 7 of 12 before).
    seed = 390004
    m, t, step_10se = _gyro_steps_at_10_se(seed, after=13)
    step = np.array([step_10se[0], step_10se[1], 0.0])
    s2, chain2 = session_of(
        m.with_effect(BiasStep(np.full(3, t), step), Triad.GYRO), seed, grade=NAV
    )
    named = [
        c
        for c in find_candidates(s2, chain2, fit_baselines(s2, chain2, colour=False))
        if c.selected
    ]
    assert {(c.effect, c.axis) for c in named} == {("bias_step", "x"), ("bias_step", "y")}
    for c in named:
        p = c.params
        assert abs(t - s2.t_s[0] - p["t_change_s"]) <= p["t_change_se_s"], (c.axis, p)


def test_a_step_whose_axis_is_not_told_is_re_simulated_as_the_smallest_step_that_explains_it():
    # A y step of 10 SE in the first turn moves one position: every axis explains it alike, the step on
    # each the datum over that axis' column. The first axis tried (x) won the tie and was re-simulated
    # at 2.0e-4 rad/s, 30 times the hidden 6.6e-6, an excess on the per-axis gyro statistics; the step
    # on any alike axis is at most the hidden axis' own (within its noise: 10 SE ± 4).
    seed = 360000
    m, t, step_10se = _gyro_steps_at_10_se(seed, after=1)
    hidden = step_10se[1]
    s2, chain2 = session_of(
        m.with_effect(BiasStep(np.full(3, t), [0.0, hidden, 0.0]), Triad.GYRO), seed, grade=NAV
    )
    base2 = fit_baselines(s2, chain2, colour=False)
    cands = find_candidates(s2, chain2, base2)
    (c,) = [c for c in cands if c.selected]
    assert c.axis is None, c.params
    tab_a = candidate_table(chain2, s2, Triad.ACCEL, base2[Triad.ACCEL])
    ext, _ = extend_model(baseline_error_model(base2, G), base2, cands, tab_a, G)
    simulated = ext.gyro.find(BiasStep).step_si
    assert np.linalg.norm(simulated) <= 1.4 * abs(hidden), (simulated, hidden)
    assert c.params["simulated_axis"] in c.params["axes_alike"], c.params
    assert simulated["xyz".index(c.params["simulated_axis"])] == c.params["simulated_step_rps"]


def _gyro_positions(seed, mean_rps, sd_rps=8.75e-4, step_rps=1.3316e-4, n_pos=20, n=1000):
    """Static gyro positions on an output grid (x_si, spans): white noise about ``mean_rps`` on every axis."""
    rng = np.random.default_rng(seed)
    x = np.round((mean_rps + sd_rps * rng.standard_normal((n_pos * n, 3))) / step_rps) * step_rps
    spans = np.array([(k * n, (k + 1) * n) for k in range(n_pos)])
    return x, spans, np.full(3, sd_rps), np.full(3, step_rps)


def test_a_turns_tail_held_on_a_level_far_out_is_not_a_rail():
    # The 48-position session of bench_audit: a position's span began with two samples of the turn's tail
    # on one grid level 8.8 sd above its mean. Two samples where 4e-14 are expected stack beyond chance, but
    # no rail there clips anything the noise reaches (a rail holds the samples beyond it): named as a rail,
    # the extended model's replicas clipped every position's y there and the chain refused them.
    x, spans, sd, step = _gyro_positions(48, -7.0e-3)
    a = spans[7, 0]
    x[a : a + 4, 1] = (
        np.round((-7.0e-3 + np.array([8.8, 8.8, 6.0, 3.0]) * sd[1]) / step[1]) * step[1]
    )
    (c,) = [c for c in clipping_candidates(Triad.GYRO, x, spans, sd, step, 160) if c.axis == "y"]
    assert c.lr > c.threshold and not c.selected, c.reason
    # A rail inside the noise on the same session is named: it holds what the noise put beyond it.
    rail = -7.0e-3 + 1.0 * sd[1]
    x[:, 1] = np.minimum(x[:, 1], rail)
    (c,) = [c for c in clipping_candidates(Triad.GYRO, x, spans, sd, step, 160) if c.axis == "y"]
    assert c.selected and c.params["rail_si"] == pytest.approx(rail, abs=step[1]), c.reason


def test_replicas_the_chain_refuses_are_a_stated_outcome_not_unusable_input(monkeypatch):
    # A rail named near zero clips every replica position's gyro y flat on one side (a MEMS bias of 14 noise
    # sd): the chain refuses each such replica. The session itself is valid: the audit completes and says the
    # extension went unchecked, where it stopped with the chain's ValueError.
    found = audit_module.clipping_candidates

    def rail_on_gyro_y(triad, *args):
        cands = found(triad, *args)
        if triad is not Triad.GYRO:
            return cands
        return [
            replace(c, selected=True, params={**c.params, "rail_si": 1e-9}) if c.axis == "y" else c
            for c in cands
        ]

    monkeypatch.setattr(audit_module, "clipping_candidates", rail_on_gyro_y)
    model = baseline_model(np.random.default_rng(2)).with_effect(Bias((0.0, 0.02, 0.0)), Triad.GYRO)
    s, _ = session_of(model, 8500)
    res = run_audit(s, AuditConfig(trial_chain_config(Grade.MEMS, s), replicas=2))
    assert any(c.effect == "clipping" for c in res.named)
    (st,) = [st for st in res.statements if st.startswith("extended model: the chain refused")]
    assert "2 of its 2 replicas" in st and "no spread" in st, st
    assert "extended" not in res.replica_stats and res.extended_cmp == res.baseline_cmp
