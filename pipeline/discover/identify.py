"""What the data can show: the identifiability rule of every candidate (docs/design/discovery.md, "The extended model").

:func:`identifiability` says, per candidate, whether it applies to these data
at all and whether the data can tell it from the rest of the model, with the
reason in words. Candidates that fail are reported, never fitted.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..materials.terms import TERMS
from .covariates import reverses
from .model import CANDIDATES
from .records import (
    Record,
    largest_span,
    offset_applicable,
    reloads_below_max,
    repeated_cycles,
    scale_applicable,
    set_applicable,
    slack_applicable,
    slip_applicable,
    strain_softening,
    stretch_levels,
)

Verdict = tuple[bool, bool, str]  # (applicable, identifiable, reason)


def identifiability(records: Sequence[Record]) -> dict[str, Verdict]:
    """Can the data show each candidate? name -> (applicable, identifiable, reason)."""
    out: dict[str, Verdict] = {}
    out["viscoelastic"] = _viscoelastic(records)
    out["nonlinear_viscoelastic"] = _nonlinear(records, out["viscoelastic"])
    cyclic = [r.name for r in records if not r.history and reverses(r.x)]
    out["mullins"] = _untimed_cycles(cyclic, _mullins(records))
    out["damage"] = _untimed_cycles(cyclic, _damage(records))
    out["cyclic_softening"] = _untimed_cycles(cyclic, _cyclic(records))
    out["permanent_set"] = _untimed_cycles(cyclic, _set(records, out["viscoelastic"]))
    out.update(_artefacts(records))
    for n, t in TERMS.items():
        out[n] = (True, True, f"a strain-energy term ({t.addresses}); identifiable from the shape of the "
                  "stress-stretch curves")
    assert set(out) == set(CANDIDATES)
    return out


def _untimed_cycles(cyclic: list[str], verdict: Verdict) -> Verdict:
    """A rate-independent history effect that is not identifiable, where files without time go back and forth
    (*cyclic*, their names: :func:`~esmm.pipeline.discover.covariates.reverses`): the reason says why their rows
    are not read as the loading history, and what would make the effect identifiable."""
    if verdict[1] or not cyclic:
        return verdict
    return (verdict[0], False, f"not identifiable from these data: {', '.join(cyclic)} "
            f"{'goes' if len(cyclic) == 1 else 'go'} back and forth, but without a time column the rows are not "
            "read as the loading history: there a relaxation's loop and its recovery after unloading look like "
            "Mullins softening, damage, a permanent set or cyclic softening (docs/design/discovery-results.md, "
            "\"Records without time\"); export the time column with the test")


def _rate_groups(records: Sequence[Record]) -> list[float]:
    """The distinct loading rates of the timed records (within a factor 1.5 of each other: one)."""
    rates = sorted({v for r in records if r.history for v in r.cov.rates()})
    groups: list[float] = []
    for v in rates:
        if not groups or v / groups[-1] >= 1.5:
            groups.append(v)
    return groups


def _viscoelastic(records: Sequence[Record]) -> Verdict:
    timed = [r for r in records if r.history]
    if not timed:
        return (True, False, "not identifiable from these data: no time column, so no rate, hold or loading history")
    rates = _rate_groups(timed)
    several_rates = len(rates) >= 2
    unloading = any(r.cov.has_unloading for r in timed)
    holds = any(_loaded_hold(r) for r in timed)
    if not (several_rates or unloading or holds):
        return (True, False, "not identifiable from these data: one monotonic ramp at one rate "
                f"({rates[0] if rates else float('nan'):.3g} /s) cannot separate a rate effect from the elastic "
                "curve; test at a second rate, or add an unloading or a hold")
    why = [w for w, ok in (("several rates", several_rates), ("unloading", unloading), ("holds", holds)) if ok]
    return (True, True, "identifiable: " + ", ".join(why))


def _loaded_hold(r: Record) -> bool:
    """A hold of five samples or more once the record has been loaded (its largest stretch so far 1 % of its
    span past the reference). A machine record often starts at rest before the crosshead moves: a hold there
    has no stress to relax, and says nothing of a relaxation (a hold at the reference state after a loading
    does: the stress recovers)."""
    c = r.cov
    if not c.has_hold:
        return False
    loaded = c.max_so_far > 1.0 + 0.01 * (float(np.max(c.drive)) - 1.0)
    held = np.where((c.direction == 0) & loaded, np.nan_to_num(c.hold_time), 0.0)
    return float(np.max(held)) >= 5 * float(np.median(np.diff(r.t)))


def _nonlinear(records: Sequence[Record], ve: Verdict) -> Verdict:
    """Holds or turning points at two stretch levels or more, or loadings at two rates or more. Between two
    rates to one peak the stretch changes while the stress relaxes, so a relaxed share or a relaxation time
    that follows the stretch shapes each rate's curve differently. The strength form alone also takes up
    there what the law and the Prony terms leave between the rates; it is the rate form, searched beside it,
    that names such records, and neither is kept on plain relaxations or clean records at several rates
    (docs/design/discovery.md, "Stretch-dependent relaxation")."""
    if not ve[1]:
        return (True, False, "not identifiable from these data: relaxation itself is not (" + ve[2] + ")")
    levels = stretch_levels(records)
    rates = len(_rate_groups([r for r in records if r.history]))
    if levels < 2 and rates < 2:
        return (True, False, "not identifiable from these data: the records turn or hold at one stretch level only, "
                "at one rate; a stretch-dependent relaxation needs holds or cycles at two levels or more, or "
                "loadings at two rates or more")
    why = f"turn or hold at {levels} stretch levels" if levels >= 2 else f"load at {rates} rates"
    return (True, True, f"identifiable once relaxation is in the model: the records {why}")


def _mullins(records: Sequence[Record]) -> Verdict:
    timed = [r for r in records if r.history]
    if not timed:
        return (True, False, "not identifiable from these data: without a time column the row order is not a "
                "loading history")
    if not any(np.any(r.cov.below_max > 0.02) for r in timed):
        return (True, False, "not identifiable from these data: every sample is on the primary loading path; "
                "Mullins softening shows only on unloading or reloading below a previous maximum")
    return (True, True, "identifiable: unloading or reloading below a previous maximum")


def _damage(records: Sequence[Record]) -> Verdict:
    """Damage lowers the curve past an onset, for good: on a first loading alone that is a softer elastic law
    (the library's terms make any stable shape), unless the curve turns down (strain softening)."""
    if largest_span(records) < 0.01:
        return (True, False, "not identifiable from these data: the deformation stays below 1 %")
    below = any(r.history and np.any(r.cov.below_max > 0.02) for r in records)
    down = [r.name for r in records if r.history and strain_softening(r)]
    if below:
        return (True, True, "identifiable: unloading or reloading below a previous maximum shows what is lost for good")
    if down:
        return (True, True, f"identifiable: the stress falls while the stretch still increases ({', '.join(down)}), "
                "which no stable elastic law does")
    return (True, False, "not identifiable from these data: on a first loading alone, damage is a softer elastic "
            "law; it shows on unloading and reloading below a previous maximum, or as a falling stress at "
            "increasing stretch")


def _cyclic(records: Sequence[Record]) -> Verdict:
    if any(repeated_cycles(r) for r in records):
        return (True, True, "identifiable: cycles repeated to the same maximum")
    return (True, False, "not identifiable from these data: no two cycles reach the same maximum, so softening "
            "from cycle to cycle cannot be told from Mullins softening or the elastic law")


def _set(records: Sequence[Record], ve: Verdict) -> Verdict:
    if any(set_applicable(r) for r in records):
        reload = any(set_applicable(r) and reloads_below_max(r) for r in records)
        if ve[1] and len(_rate_groups(records)) < 2 and not reload:
            return (True, False, "not identifiable from these data: at one loading rate a residual strain cannot be "
                    "told from slow viscoelastic recovery (the specimen may recover given time); test at a second "
                    "rate, reload after unloading, or wait at zero force before reloading")
        why = ("; they reload below the previous maximum, where a set gives one path down and up and relaxation "
               "a loop between them" if reload else "")
        return (True, True, "identifiable: tension records unload back towards the reference state" + why)
    return (True, False, "not identifiable from these data: no tension record with time unloads back towards its "
            "reference state, where a residual strain would show")


def _artefacts(records: Sequence[Record]) -> dict[str, Verdict]:
    machine = any(r.history for r in records)
    processed = ("not applicable: artefacts are corrected on machine records (with a time column); a curve "
                 "without time has been processed already (digitised or averaged)")
    out: dict[str, Verdict] = {}
    slack_files = sum(1 for r in records if slack_applicable(r))
    if slack_files >= 2:
        out["slack"] = (True, True, f"applicable: {slack_files} tension tests from the undeformed state (each "
                        "mounting has its own slack)")
    elif slack_files == 1:
        out["slack"] = (True, False, "not identifiable from these data: in one test a slack (a specimen that "
                        "carries no load until taut, or whose fibres become taut one after another) is the same "
                        "curve as a material whose fibres start to straighten above the reference length; "
                        "tests whose slacks differ (another mounting) would tell them apart")
    else:
        out["slack"] = (False, False, processed if not machine else "not applicable: slack is an artefact of "
                        "tension tests that start from zero displacement; these data have none")
    if any(offset_applicable(r) for r in records):
        out["sensor_offset"] = (True, True, "applicable: the data pass through the undeformed state, where the "
                                "true force is zero")
    else:
        out["sensor_offset"] = (machine, False, processed if not machine else "not identifiable from these data: "
                                "no sample near the undeformed state, where the true force is known to be zero")
    if scale_applicable(records):
        out["specimen_scale"] = (True, True, "applicable: several specimens (files with different specimen ids)")
    else:
        out["specimen_scale"] = (False, False, "not applicable: one specimen; its stress scale is the material's "
                                 "modulus" + ("" if machine else " (processed curves count as specimens where "
                                              "their files name them)"))
    if any(slip_applicable(r) for r in records):
        n = sum(len(r.slips) for r in records)
        out["grip_slip"] = (True, True, f"applicable: {n} sudden drop(s) of stress during loading")
    else:
        out["grip_slip"] = (False, False, processed if not machine else "not applicable: no sudden drop of stress "
                            "during loading")
    return out
