"""report.md: the plain-text twin of report.html, the verdict first, a unit on every number.

Each parameter is shown in the multiple of its SI unit that reads best
(:func:`esmm.pipeline.htmlreport.readable_unit`: 0.666 Pa, not 6.66e-07 MPa).
"""

from __future__ import annotations

from .. import __version__
from ..htmlreport import DIMENSIONLESS, format_number, quantity_text, readable_unit
from .calibration import Calibration
from .failure import FailureTest
from .inputs import columns_text, how_read


def parameter_row(e) -> tuple[str, str, str, str]:
    """(value, 95 % interval, unit, determined) of an estimate, in its readable unit."""
    unit, fac = readable_unit([e.value], e.unit)
    shown = "–" if unit == DIMENSIONLESS else unit
    flag = " (at bound)" if e.at_bound else ""
    interval = f"[{format_number(e.lower / fac)}, {format_number(e.upper / fac)}]"
    return f"{format_number(e.value / fac, 6)}{flag}", interval, shown, "yes" if e.identifiable else "no"


def markdown_report(cal: Calibration, *, plot_name: str | None = "fit.png") -> str:
    """report.md of a calibration."""
    r, v = cal.result, cal.verdict
    n_fit = sum(t.n for t in cal.fitted)
    lines = [f"# Calibration report: {r.model}", "", f"**Verdict: {v.level.upper()}.** {v.headline}", ""]
    lines += [f"- {x.text}" for x in v.reasons]
    if v.advice():
        lines += ["", "What to do:", ""] + [f"- {a}" for a in v.advice()]
    lines += ["", f"esmm {__version__}; {len(cal.tests)} file(s), {n_fit} samples fitted "
              f"(of {sum(t.n for t in cal.tests)}); loss `{r.loss}`; {r.n_starts} starts; fit time {r.seconds:.2f} s.",
              "", "## Parameters (95 % confidence intervals)", "",
              "| parameter | value | 95 % interval | unit | determined by the data |", "| --- | --- | --- | --- | --- |"]
    for e in r.estimates:
        lines.append(f"| {e.key} | " + " | ".join(parameter_row(e)) + " |")
    for k, val, si in r.held():
        unit, fac = readable_unit([val], si)
        lines.append(f"| {k} | {format_number(val / fac, 6)} (fixed) | – | {'–' if unit == DIMENSIONLESS else unit} | – |")
    lines += _errors(cal) + _failures(cal) + _inputs(cal)
    if r.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in r.warnings]
    rng = r.drucker.get("range") if r.drucker else None
    if rng:
        stable = r.drucker.get("stable", True)
        lines += ["", "## Stability", "", f"Drucker stability over stretch λ ∈ [{rng[0]:.3g}, {rng[1]:.3g}] "
                  f"(dimensionless): {'stable' if stable else 'NOT stable: ' + str(r.drucker.get('detail', ''))}."]
    if plot_name:
        lines += ["", "## Plots", "", "One row per loading mode; residual = model − data.", "",
                  f"![data vs model and residuals]({plot_name})"]
    return "\n".join(lines) + "\n"


def _errors(cal: Calibration) -> list[str]:
    r, v = cal.result, cal.verdict
    unit, fac = readable_unit([float(abs(t.stress).max()) for t in cal.fitted], "Pa")
    lines = ["", "## Errors", "",
             f"Overall: RMSE {quantity_text(r.rmse, 'Pa')}, NRMSE (RMSE / range of the measured stress) "
             f"{r.nrmse:.2%}, R² {r.r2:.4f} (dimensionless). Resolution r: the larger of the record's own measurement "
             "noise and 0.5 % of its RMS stress (a class 0.5 testing machine's accuracy); RMSE/r near 1 means the "
             "misfit is what the measurement cannot resolve.", "",
             f"| file | mode | orientation | samples fitted | RMSE [{unit}] | NRMSE [%] | R² [–] | resolution r [{unit}] | "
             f"RMSE/r [–] | max abs error [{unit}] | verdict |", "| --- |" * 1 + " --- |" * 10]
    for fe, t in zip(r.files, cal.fitted):
        nz = v.noise.get(t.name, {})
        lines.append(f"| {t.name} | {fe.mode} | {fe.orientation or '–'} | {fe.n} | {format_number(fe.rmse / fac)} | "
                     f"{format_number(100 * fe.nrmse, 3)} | {fe.r2:.4f} | {format_number(nz.get('resolution_Pa', float('nan')) / fac, 3)} | "
                     f"{format_number(nz.get('ratio'), 3)} | {format_number(fe.max_abs / fac)} | {v.files.get(t.name, '–')} |")
    return lines


def failure_cells(f: FailureTest, fac: float) -> list[str]:
    """The cells of a failure test's row (stresses divided by *fac*)."""
    ge = "≥ " if f.censored else ""

    def num(x, scale=1.0, digits=4):
        return format_number(None if x is None else x / scale, digits)

    linear = "–" if f.linear_from is None else f"{f.linear_from:.5g}–{f.linear_to:.5g}"
    return [f.file, f.kind, ge + num(f.ultimate_stress, fac), num(f.ultimate_stretch), num(f.rupture_stretch),
            num(f.toe_end_stretch), num(f.toe_modulus, fac), num(f.linear_modulus, fac), linear]


def _failures(cal: Calibration) -> list[str]:
    tests = cal.failure_tests
    if not tests:
        return []
    unit, fac = readable_unit([f.ultimate_stress for f in tests], "Pa")
    lines = ["", "## Failure tests", "",
             "Ultimate stress: the largest nominal stress of the last loading; stretch at failure: the stretch there; "
             "linear modulus: dP/dλ of the steepest straight 20 % of the last loading's stretch span up to the "
             "ultimate stress; toe: a continuous two-segment line up to the top of that region, its breakpoint the "
             "toe end and its first slope the toe modulus. Censored: the test stopped at its largest stress without "
             "failing (a force or extension limit): its ultimate stress is a lower bound. The fit uses each failed "
             "record up to its ultimate stress.", "",
             f"| file | result | ultimate stress [{unit}] | stretch at ultimate [–] | stretch at rupture [–] | "
             f"toe end stretch [–] | toe modulus [{unit}] | linear modulus [{unit}] | linear region, stretch [–] |",
             "| --- |" + " --- |" * 8]
    lines += ["| " + " | ".join(failure_cells(f, fac)) + " |" for f in tests]
    return lines + [""] + group_sentences(cal)


def group_sentences(cal: Calibration) -> list[str]:
    """The group's failure statistics in words, with units (mean ± SD over the tests that failed)."""
    s = cal.failure_summary
    out = []
    if s["failed"] or s["censored"]:
        names = {"ultimate_stress": "ultimate stress", "ultimate_stretch": "stretch at ultimate",
                 "linear_modulus": "linear modulus", "toe_modulus": "toe modulus"}
        parts = []
        for key, label in names.items():
            st = s["stats"][key]
            if st["n"]:
                sd = "" if st["sd"] is None else " ± " + quantity_text(st["sd"], st["unit"]).replace(
                    " (dimensionless)", "")
                parts.append(f"{label} {quantity_text(st['mean'], st['unit']).replace(' (dimensionless)', '')}{sd} "
                             f"(n = {st['n']})")
        if parts:
            out.append("Mean ± SD (n: the tests each rests on; strengths over the tests that failed, moduli over "
                       "every failure test): " + "; ".join(parts) + ".")
    if s["censored"]:
        lo = min(s["censored_at"])
        out.append(f"{s['censored']} test(s) stopped before failing (censored, at least "
                   f"{quantity_text(lo, 'Pa')}): not averaged, since their strength is only a lower bound.")
    return out


def _inputs(cal: Calibration) -> list[str]:
    lines = ["", "## How each file was read", "", "| file | stretch from | stress from | columns used |",
             "| --- | --- | --- | --- |"]
    for t in cal.tests:
        h = how_read(t)
        lines.append(f"| {t.name} | {h['stretch_from'] or '–'} | {h['stress_from'] or '–'} | {columns_text(t) or '–'} |")
    notes = [f"- {w}" for t in cal.tests for w in how_read(t)["warnings"]]  # each names its file
    return lines + (["", "Reader warnings:", ""] + notes if notes else [])
