"""``ins-health diagnose SESSION --passport PASSPORT.json [--json]``: the offline chain of methods.md M1.

Exit status (one set for every verdict command):

- 0: tested, no fault: every triad of the session was diagnosed and nothing failed;
- 1: a fault found (``FAULT`` lines): a predicate F1…F9, or F0 failing persistently
  (:attr:`~service.pipeline.PipelineOptions.f0_persistence_s` of failures in a row; shorter
  runs are knocks, counted and said) even when the nine parameters cannot be fitted;
- 2: unusable input (one line on stderr);
- 3: not enough to test, nothing found: ``NOT DIAGNOSED: …`` (no triad had a predicate F1…F9 it
  could evaluate: too few positions, their geometry, noise against the reference, positions it
  cannot be fitted from), ``SUSPECT`` (a triad with a passport whose fit left the physical
  domain), or something that applies not tested (``no finding within coverage``, what and why):
  a triad of the session or of the passport not diagnosed, or an F0 that found no sample at rest.

A fault outranks what was not tested. A session whose geometry M1's scalar fit cannot use (six
faces, with or without full turns) is diagnosed by the M4 fits that make a six-position passport,
the method named per parameter. When F0's persistent failure begins after the first positions,
the positions before and after it are fitted apart and the fault named in the later set.

The text output is headed with the session file's name (and the passport's unit); the JSON
output holds both (``session``, ``unit_id``). :func:`diagnose_session` is the diagnosis as a
value (:class:`DiagnoseResult`), behind ``ins_health.diagnose``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli import EXIT_FAULT, EXIT_NO_FAULT, EXIT_STATUS_HELP, EXIT_UNTESTED, UsageError
from service.session_args import add_session_arguments, load_session_input, time_gap_line

if TYPE_CHECKING:
    from estimators._typing import BoolArray
    from estimators.chain import ChainConfig, ChainResult, TriadResult
    from estimators.conventions import Triad
    from estimators.coverage import ImuCoverage
    from estimators.gross import GrossResult
    from estimators.passport import Passport
    from estimators.session import ImuSession
    from estimators.static_detector import StaticDetection
    from service.pipeline import PipelineOptions

DEFAULT_FALSE_ALARM_PROB = 1.0e-3
"""estimators.diagnosis.DEFAULT_FALSE_ALARM_PROB, stated here so that the parser does not load
scipy (tests/test_cli_startup.py checks they agree)."""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="static detection → positions → estimates → predicates F1…F9 against a passport",
        description="Exit status 0: tested, no fault (every triad diagnosed); 1: a fault found (FAULT lines: "
        "F1…F9, or F0 failing persistently, even when the nine parameters cannot be fitted); "
        "2: unusable input (one-line reason); 3: not enough to test, nothing found (NOT DIAGNOSED and why; "
        "SUSPECT: a triad with a passport whose fit left the physical domain; a triad of the session or "
        "the passport not diagnosed; or F0 without a sample at rest). "
        "A fault outranks what was not tested.",
        epilog=EXIT_STATUS_HELP,
    )
    add_session_arguments(p)
    p.add_argument("--passport", required=True, metavar="PASSPORT.json", help="the unit's passport")
    p.add_argument(
        "--false-alarm",
        type=float,
        default=DEFAULT_FALSE_ALARM_PROB,
        metavar="P",
        help=f"per-triad false-alarm probability of F1…F9 (default {DEFAULT_FALSE_ALARM_PROB})",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object (positions, estimates, predicates, faults, F0, the gross test, "
        "coverage, diagnosed/reason)",
    )
    p.set_defaults(func=run)


def f0_report(
    result: ChainResult, passport: Passport, config: ChainConfig
) -> dict[str, dict[str, Any]]:
    """F0 on every static sample against the passport, as the service runs it (service.pipeline).

    Static as the service's detector sees it: its thresholds raised to the passport's noise
    (:func:`~service.pipeline.detector_config`), as ``replay`` runs it. The chain's detector, whose
    thresholds come from the session's own noise, took a flight's manoeuvres for rest (a fault-free
    flight: 225 samples 'leaving the shell' that replay did not test). And each static run eroded
    as the service erodes it (:func:`_f0_static`): tested whole, the measured Xsens session's
    turn edges were 6 'knocks' and a flight's take-off one. Failures persist as the
    service declares them (:attr:`~service.pipeline.PipelineOptions.f0_persistence_s`,
    :func:`estimators.scalar.f0_session`).

    Per triad: static samples tested, how many leave the shell, the first such time and the
    worst ``|½(|ã|²−1)|``, the failing runs and which of them persist (a finding) and which are
    knocks; or why F0 is not run for the triad.
    """
    import numpy as np

    from estimators.scalar import f0_session
    from service.pipeline.triad_check import f0_config, f0_threshold

    clean, options, static, persist = _f0_tested(result, passport, config)
    out: dict[str, dict[str, Any]] = {}
    for triad, tp in passport.triads.items():
        x = clean.accel_mps2 if triad.value == "accel" else clean.gyro_rps
        if x is None:
            continue
        cfg, lambda0, note = f0_config(tp, options, clean.rate_hz)
        if cfg is None:
            out[triad.value] = {"run": False, "lambda0": lambda0, "note": note}
            continue
        f0 = f0_session(clean.t_s, x, static, cfg, persist)
        tested = x[static]
        norm = np.linalg.norm(tested, axis=1, keepdims=True)
        out[triad.value] = {
            # For the minimum detectable fault (estimators.coverage.f0_mdf): the largest share of
            # each axis in the tested outputs' direction, and the per-sample noise of s.
            "max_abs_u": (np.abs(tested) / np.maximum(norm, 1e-300)).max(axis=0).tolist()
            if tested.size
            else [0.0, 0.0, 0.0],
            "noise_std": f0_threshold(tp, options, clean.rate_hz).noise_std,
            "run": True,
            "lambda0": lambda0,
            "tested": f0.tested,
            "failed": f0.failed,
            "first_fail_t_s": f0.first_fail_t_s,
            "worst": f0.worst,
            "persistence_s": options.f0_persistence_s,
            "persist_samples": f0.persist,
            "runs": f0.runs,
            "persistent_runs": f0.persistent_runs,
            "knocks": f0.knocks,
            "persistent": f0.persistent,
            "persistent_failed": f0.persistent_failed,
            "persistent_worst": f0.persistent_worst,
            "onset_t_s": f0.onset_t_s,
            "onset_residual": f0.onset_residual,
            "note": note,
        }
    return out


def f0_clear_below_bound(result: ChainResult, passport: Passport, config: ChainConfig) -> bool:
    """True when F0 of :func:`f0_report` provably fails persistently on no triad, learnt without
    its exact λ0 (scipy's χ² tails, root finding and the tolerances' worst case); False when
    only :func:`f0_report` can tell.

    The same samples tested with λ0's lower bound in its place
    (:func:`estimators.scalar.lambda0_lower_bound`, ``f0_config(lower_bound=True)``): a sample
    failing the exact shell, ``|s| > λ0 ≥ bound``, fails this one too, so every run of failures
    in a row under λ0 lies within one under the bound, and no persistent run under the bound
    means none under λ0. A triad the bound does not run (above the shell limit) the exact λ0
    does not run either.
    """
    from estimators.scalar import f0_session
    from service.pipeline.triad_check import f0_config

    clean, options, static, persist = _f0_tested(result, passport, config)
    for triad, tp in passport.triads.items():
        x = clean.accel_mps2 if triad.value == "accel" else clean.gyro_rps
        if x is None:
            continue
        cfg, _, _ = f0_config(tp, options, clean.rate_hz, lower_bound=True)
        if cfg is not None and f0_session(clean.t_s, x, static, cfg, persist).persistent:
            return False
    return True


def _f0_tested(
    result: ChainResult, passport: Passport, config: ChainConfig
) -> tuple[ImuSession, PipelineOptions, BoolArray, int]:
    """What F0 of a session against ``passport`` tests, as :func:`f0_report` says: the session,
    the service's options, the static samples and the failures in a row that persist."""
    from estimators.scalar import persistence_samples
    from estimators.static_detector import detect_static
    from service.pipeline import PipelineOptions, detector_config

    clean = result.session
    if clean is None:
        raise ValueError("the chain result does not carry its session")
    options = PipelineOptions(gravity_mps2=config.gravity_mps2)
    static = _f0_static(
        clean,
        detect_static(clean, config=detector_config(options, passport, clean.rate_hz)),
        options.positions.trim_samples(clean.rate_hz),
    )
    return clean, options, static, persistence_samples(options.f0_persistence_s, clean.rate_hz)


def _f0_static(clean: ImuSession, detection: StaticDetection, margin: int) -> BoolArray:
    """The samples F0 tests: the detector's static samples less ``margin`` at both ends of every
    static run, where the slow start and end of a motion still sit in a quiet window. The
    service's own gate (:class:`~service.pipeline.static_gate.StaticGate`) decides, given the
    whole session at once; the last ``margin`` samples, which it holds for a later frame, have no
    window after them and are not static for it either."""
    import numpy as np

    from estimators.static_detector import FinalDecisions
    from service.pipeline.static_gate import StaticGate

    accepted = detection.accepted
    ends = np.append(detection.segment_start[1:], False)
    rows = np.zeros((accepted.size, 3))
    released = StaticGate(margin).push(
        clean.t_s[accepted], rows, rows, FinalDecisions(0, detection.static[accepted], ends)
    )[3]
    out = np.zeros(clean.n_samples, dtype=bool)
    out[accepted[: released.size]] = released
    return out


def f0_faults(f0: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The persistent F0 failures as findings (``faults`` of the JSON), in the form of F1…F9's:
    their samples and worst value; the knocks only counted."""
    return [
        {
            "predicate": "F0",
            "triad": name,
            "axis": None,
            "cause": "out_of_shell",
            "estimate": f["onset_residual"],
            "nominal": 0.0,
            "tolerance": f["lambda0"],
            "sigma": None,
            "failed": f["persistent_failed"],
            "tested": f["tested"],
            "first_t_s": f["onset_t_s"],
            "worst": f["persistent_worst"],
            "knocks": f["knocks"],
        }
        for name, f in f0.items()
        if f["run"] and f["persistent"]
    ]


def not_tested(result: ChainResult, passport: Passport, f0: dict[str, dict[str, Any]]) -> list[str]:
    """What applies and was not tested, and why: a triad of the session or of the passport not
    diagnosed, and an F0 that could run but found no sample at rest to test."""
    out = [
        f"{t.value}: {r.reason}"
        for t, r in result.triads.items()
        if not r.diagnosed and cannot_apply(t, r, passport) is None
    ]
    out += [
        f"{t.value}: the session has no {t.value} samples"
        for t in passport.triads
        if t not in result.triads
    ]
    out += [
        f"F0 {name}: no static sample (the service's detector, its thresholds from the passport's "
        "noise, saw no rest)"
        for name, f in f0.items()
        if f["run"] and f["tested"] == 0
    ]
    return out


def cannot_apply(triad: Triad, r: TriadResult, passport: Passport) -> str | None:
    """Why F1…F9 (and F0) cannot apply to a triad at all, or None: a gyro that cannot see the Earth
    rate, as its passport says (no parameter resolved) or, without a gyro passport, as the session
    shows (its position means too noisy against Ω for any scheme). Not having run then leaves
    nothing the verdict rests on untested; its zero signal is the gross test's."""
    import numpy as np

    from estimators.conventions import Triad

    if triad is not Triad.GYRO:
        return None
    tp = passport.triads.get(triad)
    if tp is not None and not np.any(tp.observable):
        return "gyro cannot see the Earth rate: its passport resolves no parameter"
    if tp is None and r.estimate.reference_unresolvable:
        return (
            "gyro cannot see the Earth rate: this session's position means are too noisy against it"
        )
    return None


def gross_faults(gross: GrossResult) -> list[dict[str, Any]]:
    """The gross test's declared failures as findings (``faults`` of the JSON), in SI: the window
    mean (``|ā| − g`` or a gyro axis's mean), its nominal, the bound it crossed and the mean's σ."""
    return [
        {
            "predicate": "gross",
            "triad": c.triad.value,
            "axis": c.axis,
            "cause": "gravity_magnitude" if c.triad.value == "accel" else "zero_signal",
            "estimate": c.value_si,
            "nominal": c.nominal_si,
            "tolerance": c.bound_si,
            "sigma": c.sigma_si,
            "unit": "m/s^2" if c.triad.value == "accel" else "rad/s",
            "first_t_s": c.t_s,
            "duration_s": c.duration_s,
        }
        for c in gross.changes
        if c.raised
    ]


def coverage(
    result: ChainResult,
    passport: Passport,
    f0: dict[str, dict[str, Any]],
    gross: GrossResult,
    gravity_mps2: float,
) -> ImuCoverage:
    """What the diagnosis tested (:mod:`estimators.coverage`), per triad: F0 on the static samples,
    F1…F9 on the positions, the gross test on its windows at rest; with each one's minimum
    detectable fault, or why it did not run (a MEMS gyro's F0 and F1…F9 cannot apply)."""

    from estimators.conventions import Triad, reference_magnitude
    from estimators.coverage import (
        Check,
        CheckCoverage,
        ImuCoverage,
        f0_mdf,
        ninepar_coverage,
        tolerance_triples,
    )
    from estimators.gross import tolerance_passports
    from estimators.scalar import persistence_samples
    from service.pipeline import PipelineOptions

    options = PipelineOptions(gravity_mps2=gravity_mps2)
    assert result.session is not None
    persist = persistence_samples(options.f0_persistence_s, result.session.rate_hz)
    checks: list[CheckCoverage] = []
    for triad in (Triad.ACCEL, Triad.GYRO):
        tp = passport.triads.get(triad)
        r = result.triads.get(triad)
        why_not = None if r is None else cannot_apply(triad, r, passport)
        if tp is None and why_not is not None:
            checks += [
                CheckCoverage(c, triad, ran=False, applies=False, reason=why_not)
                for c in (Check.F0, Check.F1_F9)
            ]
            continue
        if tp is None or r is None:
            why = (
                f"the passport has no {triad.value} triad"
                if tp is None
                else f"the session has no {triad.value} samples"
            )
            checks += [
                CheckCoverage(c, triad, ran=False, reason=why) for c in (Check.F0, Check.F1_F9)
            ]
            continue
        ref = reference_magnitude(triad, gravity_mps2)
        f = f0[triad.value]
        tol_bias, tol_scale = tolerance_triples(tp.tolerance, tp.reference)
        if not f["run"]:
            checks.append(
                CheckCoverage(Check.F0, triad, ran=False, applies=triad is Triad.ACCEL, reason=f["note"])
            )  # fmt: skip
        elif not f["tested"]:
            checks.append(CheckCoverage(Check.F0, triad, ran=False, reason="no static sample"))
        else:
            bias, scale = f0_mdf(
                lambda0=f["lambda0"], noise_std=f["noise_std"], persist=persist,
                max_abs_u=f["max_abs_u"], reference=ref,
            )  # fmt: skip
            checks.append(
                CheckCoverage(
                    Check.F0, triad, ran=True, samples=f["tested"], mdf_bias_si=bias, mdf_scale=scale,
                    false_alarm_prob=options.false_alarm_probability, tolerance_bias_si=tol_bias,
                    tolerance_scale=tol_scale,
                )
            )  # fmt: skip
        if why_not is not None:
            checks.append(
                CheckCoverage(Check.F1_F9, triad, ran=False, applies=False, reason=why_not)
            )
        elif r.diagnosis is None or not r.diagnosed:
            checks.append(
                CheckCoverage(Check.F1_F9, triad, ran=False, positions=r.estimate.n_positions, reason=r.reason)
            )  # fmt: skip
        else:
            checks.append(
                ninepar_coverage(
                    r.diagnosis, positions=r.estimate.n_positions, reference=ref,
                    passport_observable=tp.observable,
                )
            )  # fmt: skip
    tps, _ = tolerance_passports(passport, gravity_mps2=gravity_mps2)
    checks += [
        gross.coverage[t].check(tps[t], gravity_mps2=gravity_mps2, total_windows=gross.windows)
        for t in (Triad.ACCEL, Triad.GYRO)
    ]
    return ImuCoverage(0, tuple(checks))


def exit_status(result: ChainResult, faults: list[dict[str, Any]], untested: list[str]) -> int:
    """:data:`EXIT_FAULT` when anything failed, else :data:`EXIT_UNTESTED` when something that
    applies was not tested (:func:`not_tested`) or a triad is SUSPECT, else :data:`EXIT_NO_FAULT`
    (module docstring)."""
    if faults:
        return EXIT_FAULT
    if result.suspects or untested:
        return EXIT_UNTESTED
    return EXIT_NO_FAULT


@dataclass(frozen=True)
class DiagnoseResult:
    """What :func:`diagnose_session` found (``ins_health.diagnose``).

    ``exit_status`` as the command's (module docstring); ``faults``: each fault found (F0's
    persistent failures, F1…F9, the gross test's) as the ``--json`` output has them;
    ``untested``: what applies and was not tested, why; ``coverage``: what each check tested;
    ``chain``, ``f0``, ``gross``: the offline chain's result, F0's and the gross test's.
    """

    session: str
    unit_id: str
    exit_status: int
    faults: tuple[dict[str, Any], ...]
    untested: tuple[str, ...]
    coverage: ImuCoverage
    chain: ChainResult
    f0: dict[str, dict[str, Any]]
    gross: GrossResult
    gravity_mps2: float
    gravity_source: str

    @property
    def verdict(self) -> str:
        """The verdict as replay names it: ``fault``, ``no fault`` or ``no finding within coverage``."""
        return {EXIT_FAULT: "fault", EXIT_NO_FAULT: "no fault"}.get(
            self.exit_status, "no finding within coverage"
        )

    def to_dict(self) -> dict[str, Any]:
        """The ``--json`` output."""
        out = self.chain.to_dict()
        out["session"] = self.session
        out["unit_id"] = self.unit_id
        out["gravity_source"] = self.gravity_source
        out["f0"] = self.f0
        out["faults"] = list(self.faults)
        out["not_tested"] = list(self.untested)
        out["gross"] = {
            "windows": self.gross.windows,
            "source": self.gross.config.source,
            "rejected": self.gross.rejected,
        }
        out["coverage"] = self.coverage.to_dict()
        out["exit_status"] = self.exit_status
        return out


def diagnose_session(args: argparse.Namespace) -> DiagnoseResult:
    """The diagnosis of ``args`` (this command's options) as a value."""
    from estimators.chain import ChainConfig, run_chain, split_at_onset
    from estimators.conventions import Triad
    from estimators.coverage import Check
    from estimators.gross import gross_batch
    from estimators.passport import PassportError, check_references
    from protocols.passport_codec import read_passport_json

    passport = read_passport_json(args.passport)
    # A dead accelerometer is what the verdict is for, not unusable input.
    inp = load_session_input(args, faulty_accel_ok=True)
    config = ChainConfig(
        gravity_mps2=inp.gravity_mps2, false_alarm_prob=args.false_alarm, detector=inp.detector,
        accel_limit_mps2=inp.accel_limit_mps2, gyro_limit_rps=inp.gyro_limit_rps,
    )  # fmt: skip
    # A reference in other units would be diagnosed as bias faults on every axis: refuse it instead.
    try:
        check_references(passport, gravity_mps2=inp.gravity_mps2)
    except PassportError as exc:
        raise UsageError(f"{args.passport}: {exc}") from None
    result = run_chain(inp.session, config, passport)
    f0 = f0_report(result, passport, config)
    onsets = [(f["onset_t_s"], name) for name, f in f0.items() if f["run"] and f["persistent"]]
    if onsets:
        t_s, name = min(onsets)
        result = split_at_onset(result, t_s, Triad(name), config, passport)
    faults = f0_faults(f0) + [
        {**f.to_dict(), **({"positions": "after onset"} if result.onset else {})}
        for f in result.faults
    ]
    faults += [{**f.to_dict(), "positions": "before onset"} for f in result.faults_before]
    gross = gross_batch(inp.session, passport, gravity_mps2=inp.gravity_mps2)
    faults += gross_faults(gross)
    cover = coverage(result, passport, f0, gross, inp.gravity_mps2)
    untested = not_tested(result, passport, f0) + [
        f"{c.name}: {c.reason}" for c in cover.untested if c.check is Check.GROSS
    ]
    return DiagnoseResult(
        session=session_name(args),
        unit_id=passport.unit_id,
        exit_status=exit_status(result, faults, untested),
        faults=tuple(faults),
        untested=tuple(untested),
        coverage=cover,
        chain=result,
        f0=f0,
        gross=gross,
        gravity_mps2=inp.gravity_mps2,
        gravity_source=inp.gravity_source,
    )


def session_name(args: argparse.Namespace) -> str:
    """The session as its verdict is headed: the file's name (an Xsens pair: both files')."""
    names = [Path(args.session).name] + ([Path(args.gyro_file).name] if args.gyro_file else [])
    return " + ".join(names)


def run(args: argparse.Namespace) -> int:
    d = diagnose_session(args)
    if args.json:
        json.dump(d.to_dict(), sys.stdout, indent=1)
        print()
        return d.exit_status
    _print_text(d)
    for fault in gross_faults(d.gross):
        print(
            f"  FAULT gross: {' '.join(filter(None, (fault['triad'], fault['axis'])))} {fault['cause']}: window mean "
            f"{fault['estimate']:+.4g} {fault['unit']} vs nominal {fault['nominal']:.4g} beyond "
            f"±{fault['tolerance']:.3g} (σ {fault['sigma']:.2g}) from {fault['first_t_s']:.3f} s "
            f"for {fault['duration_s']:.1f} s at rest (tolerances: {d.gross.config.source})"
        )
    for line in d.coverage.lines():
        print(f"  coverage: {line}")
    return d.exit_status


def _print_text(d: DiagnoseResult) -> None:
    result, f0, untested = d.chain, d.f0, list(d.untested)
    print(
        f"{d.session}: {len(result.positions)} positions, against the passport of {d.unit_id}, "
        f"g = {d.gravity_mps2:.5f} m/s² ({d.gravity_source})"
    )
    if result.sample_rejections.total:
        counts = ", ".join(f"{k} {n}" for k, n in sorted(result.sample_rejections.counts.items()))
        print(f"  rejected samples: {counts}")
    if (gaps := time_gap_line(result.detection)) is not None:
        print(gaps)
    onset = result.onset
    if onset is not None:
        print(
            f"  F0's persistent failure began at {onset.t_s:.3f} s, mid-session: the {onset.n_before} positions "
            f"before and the {onset.n_after} after it are fitted apart"
            + (f" ({onset.n_straddling} holding it in neither)" if onset.n_straddling else "")
        )
        if onset.changed_after:
            print(
                "  the positions after it are not explained by one set of parameters either: the unit "
                "changed again, or the fault came and went; their estimates mix what it was"
            )
        _print_triads(onset.before, "before the onset: ")
        _print_findings(onset.before, "before the onset")
    _print_triads(result.triads, "after the onset: " if onset else "")
    for name, f in f0.items():
        if not f["run"]:
            print(f"  F0 {name}: not run ({f['note']})")
        elif not f["tested"]:
            print(f"  F0 {name}: not tested: no static sample (λ0 {f['lambda0']:.3g})")
        elif f["persistent"]:
            print(
                f"  FAULT F0: {name} leaves the shell (λ0 {f['lambda0']:.3g}) on {f['persistent_failed']} of "
                f"{f['tested']} static samples, {f['persistent_runs']} runs of {f['persistence_s']:g} s or more "
                f"from {f['onset_t_s']:.3f} s; worst |½(|ã|²−1)| {f['persistent_worst']:.3g}"
                + (f", and {_knocks(f['knocks'])}" if f["knocks"] else "")
            )
        elif f["failed"]:
            print(
                f"  F0 {name}: {f['failed']} of {f['tested']} static samples leave the shell (λ0 {f['lambda0']:.3g}) "
                f"in {_knocks(f['knocks'])} shorter than {f['persistence_s']:g} s, first at {f['first_fail_t_s']:.3f} s, "
                f"worst |½(|ã|²−1)| {f['worst']:.3g}: not a fault"
            )
        else:
            print(
                f"  F0 {name}: {f['tested']} static samples inside the shell (λ0 {f['lambda0']:.3g})"
            )
    for triad in result.suspects:
        print(
            f"SUSPECT {triad.value}: its positions determine the nine parameters but the fit left the physical "
            "domain (above): a fault far beyond the scheme's, values in other units or another unit's session; "
            "not diagnosed, and not 'no fault'"
        )
    f0_fault = any(f["run"] and f["persistent"] for f in f0.values())
    if not result.diagnosed:
        print(f"NOT DIAGNOSED{' after the onset' if onset else ''}: {'; '.join(untested)}")
        return
    if not (result.faults or result.faults_before or result.suspects or f0_fault):
        print(
            f"  no finding within coverage; not tested: {'; '.join(untested)}"
            if untested
            else "  no fault"
        )
    _print_findings(result.triads, "after the onset" if onset else "")
    if result.passport_of_another_unit:
        failed, evaluated = result.predicate_counts()
        print(
            f"  hint: {failed} of {evaluated} predicates fail at once: the passport is probably not this unit's "
            f"(passport of {d.unit_id!r})"
        )


def _knocks(n: int) -> str:
    return f"{n} knock" + ("" if n == 1 else "s")


def _print_triads(triads: dict[Triad, TriadResult], prefix: str) -> None:
    for triad, r in triads.items():
        state = "diagnosed" if r.diagnosed else f"NOT DIAGNOSED: {r.reason}"
        print(f"  {prefix}{triad.value}: {r.estimate.verdict.value} — {r.estimate.reason}; {state}")


def _print_findings(triads: dict[Triad, TriadResult], where: str) -> None:
    for r in triads.values():
        if r.diagnosis is None:
            continue
        sources = r.estimate.sources
        for fault in r.diagnosis.findings:
            j = int(fault.predicate[1:]) - 1
            method = "" if sources is None else f", {sources[j]}"
            print(
                f"  FAULT {fault.predicate}: {fault.triad.value} {fault.axis} {fault.cause.value}: estimate {fault.estimate:.4g} "
                f"vs nominal {fault.nominal:.4g} ± {fault.tolerance:.3g} (σ {fault.sigma:.2g}{method})"
                + (f" [{where}]" if where else "")
            )
