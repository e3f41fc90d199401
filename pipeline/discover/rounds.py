"""One round of the search, pairs, and the backward elimination (docs/design/discovery.md, "The loop").

A round (:func:`run_round`): diagnose the current model; fit every candidate
whose first-order gain can pay for one parameter (:func:`candidate_order`), in
each of its variants, and the richer variants of kept effects; those whose
fitted improvement passes the pre-screen go, best first, to the held-out test
at the round's level (:mod:`.levels`); the first that passes is kept (a
history effect only if its path-dependent part explains the residual's too,
:mod:`.history`). When none passes, the residual is not noise and two more
effects are allowed, pairs of effects and artefacts are tested at the pairs'
level. The state of
the search is :class:`~esmm.pipeline.discover.search.Search`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ..errors import FitError
from ..materials.terms import TERMS
from .artefacts import artefact_reason, shared_slack_reason
from .diagnose import Diagnosis, diagnose
from .fitted import Fitted, effect_params, fit_spec
from .heldout import FoldSet, cached_heldout
from .history import applies, history_test
from .levels import Levels, round_levels
from .model import ALTERNATIVE_VARIANTS, VARIANTS
from .records import Record
from .state import Candidate, Criteria, Search, start_search
from .statistics import REPLICATION_LEVEL
from .trials import (
    Trial,
    adds_nothing,
    best_variant,
    check_heldout,
    compared,
    failing_checks,
    judged_on,
    noise_taus,
    passes,
)

#: the most strain-energy terms fitted per round (the best by their first-order gain)
TERMS_PER_ROUND = 3
#: the most candidates checked on held-out data per round (the best by their fitted improvement)
CHECKS_PER_ROUND = 5
#: the pair pool: the most single candidates pairs are formed from
PAIR_POOL = 4


def run_round(s: Search, rnd: int, rep) -> bool:
    """Diagnose, try every candidate (and richer variants of kept effects), keep the first that passes.

    Returns False when the search is over.
    """
    blocked = _alternatives_of_kept(s)
    remaining = [n for n in s.testable if n not in s.kept and n not in blocked]
    diag = diagnose(s.current.problem, s.current.z, candidates=remaining, errors=s.current.errors)
    s.diagnoses.append(diag)
    upgradable = [n for n in s.kept if n in VARIANTS and s.current.spec.variant(n) < max(VARIANTS[n])]
    if (not remaining and not upgradable) or len(s.kept) >= s.crit.max_effects:
        return False
    pairable = len(s.kept) + 2 <= s.crit.max_effects
    fallbacks = sum(1 for n in remaining if len(VARIANTS.get(n, (1,))) > 1)  # a simpler variant checked too
    # in pairs, each form of an effect with alternative forms is a candidate of its own (:func:`_try_pairs`)
    others = sum(2 if n in ALTERNATIVE_VARIANTS and len(VARIANTS[n]) > 1 else 1 for n in remaining if n not in TERMS)
    term_pairs = sum(1 for n in remaining if n in TERMS) * others if pairable else 0
    lv = round_levels(s.crit.alpha, rnd, len(remaining) + len(upgradable) + fallbacks,
                      others if pairable else 0, term_pairs)
    s.levels.append(lv)
    order = candidate_order(s, remaining, diag, rnd)
    with rep.task(f"round {rnd}: trying {', '.join(order + [u + ' (more terms)' for u in upgradable])}",
                  total=len(order) + len(upgradable)) as adv:
        trials, singles = _try_candidates(s, order, rnd, adv)
        trials += _try_upgrades(s, upgradable, adv)
    trials = elastic_first(trials)
    winner = _heldout_winner(s, trials, rnd, lv)
    for t in trials:  # candidates never reached by the held-out check this round
        c = s.candidates[t.name]
        if winner is not None and t.name != winner.name and t.name not in s.kept and c.reason.endswith("pending"):
            c.reason = f"fitted improvement Δχ² {t.noise['dchi2']:.4g}, but {winner.name} was kept first in round {rnd}"
    if winner is None and not diag.white and lv.pairs:
        pair = _try_pairs(singles, s, lv)
        if pair is not None:
            _keep_pair(s, pair, rnd, rep)
            return True
    if winner is None:
        return False
    _keep(s, winner, rnd, rep)
    return True


def _alternatives_of_kept(s: Search) -> set[str]:
    """The terms no longer tried because another form of them is kept
    (:attr:`~esmm.pipeline.materials.terms.Term.alternatives`: one toe, not two); each candidate's reason says so."""
    blocked = set()
    for n in s.testable:
        if n in s.kept or n not in TERMS:
            continue
        k = next((k for k in s.kept if k in TERMS[n].alternatives), None)
        if k is not None:
            blocked.add(n)
            s.candidates[n].reason = f"not tried after round {s.kept_round[k]}: {k}, another form of the same term, was kept"
    return blocked


def elastic_first(trials: list[Trial]) -> list[Trial]:
    """The order of the held-out checks: strain-energy terms first, then effects and artefacts, each by
    fitted improvement (of two nested candidates the simpler first).

    Elastic first: the base law is an approximation of the material's, and a
    history effect or an artefact fitted to an elastic misfit also predicts
    held-out data of the same kind (the same stretch range, the same protocol)
    better; a residual that a strain-energy term explains on held-out data
    needs no history, and that explanation is the simpler one. A history
    effect is then judged on what the richer law leaves.
    """
    terms = sorted((t for t in trials if t.name in TERMS), key=lambda t: t.dbic)
    rest = sorted((t for t in trials if t.name not in TERMS), key=lambda t: t.dbic)
    _nested_after(rest, "nonlinear_viscoelastic", "viscoelastic")
    return terms + rest


def _nested_after(trials: list[Trial], rich: str, simple: str) -> None:
    """Check the simpler of two nested candidates first, where the richer one ranks: the richer one (which
    always fits at least as well) is kept only when the simpler one does not pass, and the pair is checked
    at the rank of its better fit (the simpler one moved up, not the richer one down behind candidates that
    fit worse than it)."""
    names = [t.name for t in trials]
    if rich in names and simple in names and names.index(rich) < names.index(simple):
        trials.insert(names.index(rich), trials.pop(names.index(simple)))


def candidate_order(s: Search, remaining: list[str], diag: Diagnosis, rnd: int) -> list[str]:
    """Candidates to fit this round, best first-order gain first; those that cannot pay are not fitted.

    A candidate whose first-order gain (in noise variances, divided by the
    noise's autocorrelation time at the fitting spacing, as the pre-screen) is
    below the Schwarz penalty of one parameter (ln N) cannot pay for itself; of
    the strain-energy terms only the :data:`TERMS_PER_ROUND` best are fitted
    (they overlap: the score test ranks them).
    """
    n_fit = sum(r.fit_idx.size for r in s.current.problem.records)
    penalty = math.log(max(n_fit, 2))
    tau = float(np.median(noise_taus(s.current))) if s.current.problem.records else 1.0
    order, n_terms = [], 0
    for n in sorted(remaining, key=lambda n: -diag.gains.get(n, 0.0)):
        c = s.candidates[n]
        c.round, c.score, c.gain_chi2 = rnd, diag.scores.get(n, 0.0), diag.gains.get(n, 0.0)
        if c.gain_chi2 / tau < penalty:
            _too_small(c, s.kept, rnd, penalty, tau)
            continue
        if n in TERMS:
            n_terms += 1
            if n_terms > TERMS_PER_ROUND:
                c.reason = (f"not fitted in round {rnd}: {TERMS_PER_ROUND} strain-energy terms with larger "
                            "first-order gains were tried first")
                continue
        order.append(n)
    return order


def _try_candidates(s: Search, order: list[str], rnd: int, advance) -> tuple[list[Trial], dict[str, Trial]]:
    """Fit every candidate of this round; those that pass the pre-screen go to the held-out check (the trials)."""
    trials: list[Trial] = []
    singles: dict[str, Trial] = {}
    for n in order:
        c = s.candidates[n]
        variants = [v for v in VARIANTS.get(n, (1,)) if not adds_nothing(n, v, s.current)]
        if not variants:
            advance(1)
            c.reason = ("not fitted: every reading at rest is the tared zero, so the offset held there is the "
                        "current model; no record drifts where a drift could be told")
            continue
        t = best_variant(n, variants, s.current, warm=s.warm)
        advance(1)
        if t is not None:
            s.remember(t.fit)
        if t is None:
            c.reason = "the fit with this candidate failed"
            continue
        _record(c, t)
        singles[n] = t
        if not math.isfinite(t.dbic):
            c.reason = "rejected: the fit's improvement could not be computed"
        elif t.dbic >= 0:
            c.reason = (f"rejected by the pre-screen: its fitted improvement (Δχ² {t.noise['dchi2']:.1f} noise "
                        f"variances, the noise's correlation counted) does not pay for its parameters (penalty "
                        f"{t.noise['penalty']:.1f}): it fits noise")
        else:
            c.reason = (f"fitted improvement Δχ² {t.noise['dchi2']:.4g} (penalty {t.noise['penalty']:.1f}); "
                        "held-out check pending")
            trials.append(t)
    return trials, singles


def _too_small(c: Candidate, kept: list[str], rnd: int, penalty: float, tau: float) -> None:
    """The verdict on a candidate whose first-order gain cannot pay for one parameter."""
    why = (f"its first-order signature would remove {c.gain_chi2 / tau:.3g} noise variances (the noise's "
           f"correlation counted), less than the penalty of one parameter ({penalty:.1f})")
    if c.dbic_noise is not None or c.reason.startswith("rejected"):
        c.reason = f"{c.reason.split('; in round')[0]}; in round {rnd}, after {', '.join(kept) or 'the base'}, {why}"
    else:
        c.reason = f"rejected without a fit: {why}"


def _record(c: Candidate, t: Trial) -> None:
    """Write a fitted candidate's variant, statistics and parameters into its verdict."""
    c.variant = t.fit.spec.variant_text(c.name)
    c.delta_aicc = t.d_aicc if math.isfinite(t.d_aicc) else None
    c.delta_bic = t.d_bic if math.isfinite(t.d_bic) else None
    c.dbic_noise = t.dbic if math.isfinite(t.dbic) else None
    c.dchi2 = t.noise["dchi2"]
    c.params = effect_params(t.fit, c.name)
    c.heldout_nrmse = c.heldout_gain = c.heldout_z = c.heldout_noise_units = c.heldout_p = None
    c.heldout_level = c.heldout_p_replication = c.history_p = c.history_share = None


def _try_upgrades(s: Search, upgradable: list[str], advance) -> list[Trial]:
    """Richer variants (another Prony term, beta, a drift) of the kept effects that pass the pre-screen."""
    trials = []
    for n in upgradable:
        nxt = [v for v in VARIANTS[n] if v > s.current.spec.variant(n)]
        t = best_variant(n, nxt, s.current, upgrade=True, warm=s.warm)
        advance(1)
        if t is not None:
            s.remember(t.fit)
        if t is not None and t.screened:
            trials.append(t)
    return trials


def _check(s: Search, t: Trial, names) -> dict:
    """The held-out test of *t* against the current model, on the fold set its names are judged on."""
    return check_heldout(t, s.current, judged_on(names, s.material, s.artefact))


def _heldout_winner(s: Search, trials: list[Trial], rnd: int, lv: Levels) -> Trial | None:
    """The held-out check, best pre-screen first: the first trial that passes wins (None: none passes).

    The terms (at most :data:`TERMS_PER_ROUND` fitted) and at most
    :data:`CHECKS_PER_ROUND` others are checked (each check refits every
    fold); the family-wise level counts every candidate of the round all the
    same. A candidate whose richer variant fails the held-out check, or passes
    it but not the path-dependence check, has its simplest screened variant
    checked instead (:func:`_simpler_variant`): a load cell's drift that only
    takes up an elastic misfit over the record's time leaves the offset it
    contains to be judged on its own.
    """
    n_terms = sum(1 for t in trials if t.name in TERMS)
    checked, skipped = trials[:n_terms + CHECKS_PER_ROUND], trials[n_terms + CHECKS_PER_ROUND:]
    for t in skipped:
        if t.name not in s.kept:
            s.candidates[t.name].reason = (
                f"fitted improvement Δχ² {t.noise['dchi2']:.4g}, but not checked on held-out data in round {rnd}: "
                f"{CHECKS_PER_ROUND} candidates with larger fitted improvements were checked first")
    for t in checked:
        h = _check(s, t, t.name)
        ok = passes(h, lv.single, s.crit.min_resolution_units)
        fallback = t.fallback if t.name not in s.kept else None
        if not ok and fallback is not None:
            t, h = _simpler_variant(s, t, h, lv)
            ok = passes(h, lv.single, s.crit.min_resolution_units)
            if ok:
                _record(s.candidates[t.name], t)
                fallback = None
        if t.name in s.kept:  # a variant upgrade of a kept effect
            if ok:
                s.upgrades.append(f"round {rnd}: {t.name} extended to {t.fit.spec.variant_text(t.name)} "
                                  f"(held-out p {h['p']:.2g} at level {lv.single:.2g})")
                return t
            continue
        c = s.candidates[t.name]
        _heldout_fields(c, t, lv.single, s)
        if not ok:
            c.reason = _rejected_text(t, h, lv.single, s)
            continue
        shared = shared_slack_reason(t.fit) if t.name == "slack" else None
        if shared:
            c.reason = f"not kept: {shared}"
            continue
        if _path_dependent(s, t, [t.name]):
            return t
        if fallback is not None:  # the richer variant's path-dependent part is not history: the simpler one
            f = fallback
            if passes(_check(s, f, f.name), lv.single, s.crit.min_resolution_units):
                _record(c, f)
                _heldout_fields(c, f, lv.single, s)
                if _path_dependent(s, f, [f.name]):  # writes its verdict on the candidate as recorded
                    return f
    return None


def _simpler_variant(s: Search, t: Trial, h: dict, lv: Levels) -> tuple[Trial, dict]:
    """The simpler variant of a candidate whose chosen (richer) variant failed the held-out check, and its
    check, when it passes (else *t* and *h* as they were).

    In-sample the richer variant always fits at least as well, and it may pay
    for its parameters there by fitting what does not hold out (a load cell's
    drift taking up an elastic misfit over the record's time); the variant it
    contains is a hypothesis of its own, checked at the same level and counted
    in the round's family (:func:`run_round`)."""
    f = t.fallback
    h2 = _check(s, f, f.name)
    if passes(h2, lv.single, s.crit.min_resolution_units):
        return f, h2
    return t, h


def _path_dependent(s: Search, t: Trial, names: list[str]) -> bool:
    """A history effect's (or a pair's) improvement must be history: its path-dependent part explains the
    residual's, one-sided at :data:`REPLICATION_LEVEL`, and reaches the measurement's resolution
    (:mod:`.history`). A load cell's drift is judged the same way: its change in time is all it adds to an
    offset (a constant is a function of the stretch), and on a record that returns to the same stretches it
    must explain what the residual does there over time, not an elastic law's misfit. Like the replication
    check it only removes candidates (the search-wide bound is the held-out test's), so it is not adjusted
    for multiplicity. Writes the verdict on a single that fails."""
    drift = "sensor_offset" in names and t.fit.spec.sensor_offset == 2 and s.current.spec.sensor_offset != 2
    if not (applies(names, s.current.problem.records) or drift):
        return True
    h = history_test(s.current, t.fit)
    if len(names) == 1:
        s.candidates[names[0]].history_p, s.candidates[names[0]].history_share = h["p"], h["share"]
    if h["p"] <= REPLICATION_LEVEL and h["peak_resolutions"] >= 1.0:
        return True
    why = (f"not kept: it predicts held-out data better (p {t.heldout['p']:.2g}), but not by what depends on the "
           f"path: the part of its change that no function of the stretch alone gives ({h['share']:.2g} of it) "
           f"explains the part of the residual that none gives with one-sided p {h['p']:.2g} (t {h['t']:+.2f} on "
           f"{h['dof']:.1f} degrees of freedom; needs <= {REPLICATION_LEVEL:g}), reaching {h['peak_resolutions']:.3g} "
           "resolutions of the measurement at most (needs 1): on these data it stands for an elastic law the "
           "library does not hold")
    if len(names) == 1:  # a pair that fails is one of many formed; its members keep their own verdicts
        s.candidates[names[0]].reason = why
    return False


def _heldout_fields(c: Candidate, t: Trial, level: float, s: Search) -> None:
    h = t.heldout
    e = t.fit.cv.get(h["fold_set"])
    c.heldout_nrmse = e.nrmse if e is not None else None
    ref = s.current.cv.get(h["fold_set"])
    c.heldout_gain = 1.0 - e.nrmse / max(ref.nrmse, 1e-300) if e is not None and ref is not None else None
    c.heldout_z, c.heldout_p, c.heldout_level = h["t"], h["p"], level
    c.heldout_p_replication = h["p_replication"]
    c.heldout_noise_units = h["noise_units"]


def _rejected_text(t: Trial, h: dict, level: float, s: Search) -> str:
    ref = s.current.cv[h["fold_set"]].nrmse
    new = t.fit.cv[h["fold_set"]].nrmse
    return (f"rejected: the fit improves (Δχ² {t.noise['dchi2']:.4g}) but it does not predict data it was not "
            f"fitted to well enough ({h['scheme']}): held-out NRMSE {ref:.2%} -> {new:.2%}; beyond the noise "
            f"p {h['p']:.2g} (needs <= {level:.2g}); replicated across the held-out segments p "
            f"{h['p_replication']:.2g} (t {h['t_replication']:+.2f} on {h['dof']:.1f} degrees of freedom; needs <= "
            f"{REPLICATION_LEVEL:g}); {h['resolution_units']:+.3g} squared resolutions per sample (needs "
            f"{s.crit.min_resolution_units:g})")


def _keep(s: Search, t: Trial, rnd: int, rep) -> None:
    """Make the trial's model (the current model plus its candidate) the current model."""
    f, winner = t.fit, t.name
    if winner in s.kept:
        rep.step(s.upgrades[-1])
        s.current = f
        return
    c = s.candidates[winner]
    c.kept = True
    kind = {"artefact": "corrected in the data", "material": "added to the material",
            "elastic": "added to the strain energy"}[c.kind]
    h = t.heldout
    ref, new = s.current.cv[h["fold_set"]].nrmse, f.cv[h["fold_set"]].nrmse
    c.reason = (f"kept ({kind}) in round {rnd}: fitted Δχ² {t.noise['dchi2']:.4g} noise variances; held-out NRMSE "
                f"{ref:.2%} -> {new:.2%} ({h['scheme']}); beyond the noise p {h['p']:.2g} <= {c.heldout_level:.2g}, "
                f"replicated p {h['p_replication']:.2g} <= {REPLICATION_LEVEL:g}; {h['resolution_units']:.3g} "
                "squared resolutions per sample")
    rep.step(f"round {rnd}: kept {winner} ({c.variant}): NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {ref:.2%} -> {new:.2%} (p {h['p']:.2g})")
    s.kept.append(winner)
    s.kept_round[winner] = rnd
    s.current = f
    sync_kept(s, rnd)


def sync_kept(s: Search, rnd: int) -> None:
    """Name what the current model holds without having been kept by name: the relaxation that
    stretch-dependent relaxation brings with it."""
    for n in s.current.spec.names():
        if n not in s.kept:
            c = s.candidates[n]
            c.kept, c.variant = True, s.current.spec.variant_text(n)
            c.reason = f"kept in round {rnd}: brought in by nonlinear_viscoelastic, which contains it"
            s.kept.append(n)
            s.kept_round[n] = rnd


def _try_pairs(singles: dict[str, Trial], s: Search, lv: Levels):
    """When no single candidate passes and the residual is not noise, two effects or artefacts at once
    (effects that mask each other's signature: slack hiding a rate effect, specimen scales hiding a
    relaxation), from a pool of the two whose held-out error fell most alone and the two that fitted best;
    and the strain-energy term whose held-out error fell most alone with each of that pool (an elastic
    law's misfit masks an effect or an artefact too: each alone leaves the other's residual, over which no
    single candidate's improvement replicates).

    Each pair is tested at the pairs' level, whose family counts every pair the round's effects and
    artefacts could form and every pair of a term and one of them (:mod:`.levels`); a pair holding a
    history effect must also explain history (:mod:`.history`). Returns ((a, b), trial) of the passing pair
    with the smallest p-value, or None.
    """
    current = s.current
    fitted = [n for n, t in singles.items() if t.screened and n not in TERMS]
    by_gain = sorted((n for n in fitted if singles[n].heldout),
                     key=lambda n: -singles[n].heldout["noise_units"])
    by_fit = sorted(fitted, key=lambda n: singles[n].dbic)
    pool = list(dict.fromkeys(by_gain[:PAIR_POOL // 2] + by_fit[:PAIR_POOL // 2]))
    terms = sorted((n for n, t in singles.items() if n in TERMS and t.screened and t.heldout),
                   key=lambda n: -singles[n].heldout["gain"])[:1]
    pairs = [(pool[i], pool[j]) for i in range(len(pool)) for j in range(i + 1, len(pool))]
    pairs += [(term, n) for term in terms for n in pool]
    passed = []
    for a, b in pairs:
        for va, vb in _pair_forms(singles[a], singles[b]):
            spec = current.spec.with_(a, va).with_(b, vb)
            if spec.viscoelastic and (singles[a].fit.spec.compression or singles[b].fit.spec.compression):
                spec = replace(spec, compression=1)  # as the relaxation's single trial chose
            try:
                t = compared(f"{a}+{b}", fit_spec(spec, current, init_from=s.warm.get(spec)), current)
            except FitError:
                continue
            s.remember(t.fit)
            if t.screened and passes(_check(s, t, [a, b]), lv.pair, s.crit.min_resolution_units) \
                    and not ("slack" in (a, b) and shared_slack_reason(t.fit)) \
                    and _path_dependent(s, t, [a, b]):
                passed.append(((a, b), t))
                break
    return min(passed, key=lambda p: p[1].heldout["p"]) if passed else None


def _pair_forms(ta: Trial, tb: Trial) -> list[tuple[int, int]]:
    """The variants a pair of single trials is tried in: each member's best, then, for a member with
    alternative forms (:data:`~esmm.pipeline.discover.model.ALTERNATIVE_VARIANTS`), its other screened form
    (counted as a candidate of its own in the pairs' family, :func:`run_round`)."""
    va, vb = ta.fit.spec.variant(ta.name), tb.fit.spec.variant(tb.name)
    out = [(va, vb)]
    for t, first in ((ta, True), (tb, False)):
        f = t.fallback
        if t.name in ALTERNATIVE_VARIANTS and f is not None:
            v = f.fit.spec.variant(t.name)
            out.append((v, vb) if first else (va, v))
    return out


def _keep_pair(s: Search, pair, rnd: int, rep) -> None:
    """Keep two candidates that only passed together."""
    (a, b), t = pair
    f, h = t.fit, t.heldout
    ref, new = s.current.cv[h["fold_set"]].nrmse, f.cv[h["fold_set"]].nrmse
    for n, other in ((a, b), (b, a)):
        c = s.candidates[n]
        c.kept = True
        c.variant = f.spec.variant_text(n)
        _heldout_fields(c, t, s.levels[-1].pair, s)
        kind = {"artefact": "corrected in the data", "material": "added to the material",
                "elastic": "added to the strain energy"}[c.kind]
        c.reason = (f"kept ({kind}) in round {rnd} together with {other}: neither alone passed, together fitted "
                    f"Δχ² {t.noise['dchi2']:.4g} and held-out NRMSE {ref:.2%} -> {new:.2%} ({h['scheme']}), "
                    f"one-sided p {h['p']:.2g} <= {s.levels[-1].pair:.2g}")
        s.kept_round[n] = rnd
    rep.step(f"round {rnd}: kept {a} and {b} together: NRMSE {s.current.errors.nrmse:.2%} -> "
             f"{f.errors.nrmse:.2%}, held-out {ref:.2%} -> {new:.2%} (p {h['p']:.2g})")
    s.kept += [a, b]
    s.current = f
    sync_kept(s, rnd)


def backward(s: Search, rep) -> None:
    """Backward elimination: a kept candidate that, given the others, no longer passes goes.

    The forward search adds one candidate at a time, and what was kept early
    (or in a pair) may have been only a proxy for what came later. Each kept
    candidate, latest first, is judged again against the model without it, at
    the level it was kept at. A relaxation that a stretch-dependent one brought
    in is judged with it; where that one goes, the relaxation is judged on its
    own next (it was never tested alone). After a removal, those already judged
    are judged again: they passed beside what has gone, and the final model is
    one in which every kept candidate passes given the others.
    """
    seen: set[str] = set()
    removed = False
    while len(s.kept) >= 2 or (removed and s.kept):
        name = next((n for n in reversed(s.kept) if n not in seen
                     and not (n == "viscoelastic" and "nonlinear_viscoelastic" in s.kept)), None)
        if name is None:
            break
        seen.add(name)
        judged = _judged_without(s, name, s.current)
        if judged is None:
            continue
        ok, reduced, h, level = judged
        fs = judged_on(name, s.material, s.artefact)
        c = s.candidates[name]
        if ok:
            if name == "viscoelastic" and "nonlinear_viscoelastic" in seen:
                c.reason += (f"; judged on its own once nonlinear_viscoelastic was removed: held-out NRMSE "
                             f"{reduced.cv[fs.key].nrmse:.2%} without it, {s.current.cv[fs.key].nrmse:.2%} with it "
                             f"(p {h['p']:.2g}, level {level:.2g})")
            continue
        c.kept = False
        others = ", ".join(n for n in s.kept if n != name) or "the base law alone, once the others had gone"
        c.reason = (f"kept in round {c.round}, then removed: given {others}, it "
                    f"no longer passes the held-out test (held-out NRMSE {reduced.cv[fs.key].nrmse:.2%} without "
                    f"it, {s.current.cv[fs.key].nrmse:.2%} with it; {failed_checks(h, level, s.crit.min_resolution_units)})")
        rep.step(f"removed {name}: " + ("the others explain what it did" if len(s.kept) > 1 else
                                         "on its own it does not pass"))
        s.kept.remove(name)
        s.current = reduced
        sync_kept(s, c.round)
        seen, removed = {name}, True


def failed_checks(h: dict, level: float, min_units: float) -> str:
    """Why a kept candidate judged again fails, in words: every held-out check that fails
    (:func:`~.trials.failing_checks`) or, where all three pass, the pre-screen."""
    return "; ".join(failing_checks(h, level, min_units)) or \
        "its fitted improvement no longer pays for its parameters (the pre-screen)"


def drop_unsupported_artefacts(s: Search, rep) -> None:
    """After the backward elimination: a kept artefact whose size the final fit does not determine, or a slack
    every file shares, goes (:mod:`.artefacts`), latest first, one at a time, the model refitted without it.
    Offsets read at rest are measured, not fitted: of a sensor offset that holds them only an undetermined
    drift goes.

    At the end, not when a candidate enters: the fit's standard errors are
    inflated for the residual's serial correlation, and before the other
    effects are in, their misfit inflates them too (a true slack fitted in
    round 1 beside a relaxation not yet found is not determined then).
    """
    while True:
        for name in reversed([n for n in s.kept if s.candidates[n].kind == "artefact"]):
            why = artefact_reason(s.current, name)
            if not why:
                continue
            c = s.candidates[name]
            measured = name == "sensor_offset" and s.current.spec.sensor_offset == 2 and \
                any(v is not None for v in s.current.problem.forward.pinned)
            spec = s.current.spec.with_(name, 1 if measured else 0)
            try:
                reduced = fit_spec(spec, s.current, init_from=s.warm.get(spec))
            except FitError:
                continue
            if measured and _still_passes(s, name, reduced):  # the offsets read at rest stay, the drift goes
                s.current = reduced
                c.variant = spec.variant_text(name)
                c.reason += f"; its drift then removed from the final model: {why}"
                rep.step(f"removed the drift of {name}: {why}")
                break
            if measured:
                try:
                    reduced = fit_spec(s.current.spec.with_(name, 0), s.current)
                except FitError:
                    continue
                why += "; without the drift, the offsets read at rest do not pass the held-out test"
            s.current = reduced
            c.kept = False
            c.reason = f"kept in round {c.round}, then removed from the final model: {why}"
            rep.step(f"removed {name}: {why}")
            s.kept.remove(name)
            sync_kept(s, c.round)
            break
        else:
            return


def _judged_without(s: Search, name: str, f: Fitted):
    """*name* in *f* judged again against *f* refitted without it, at the level it was kept at:
    (passes, the fit without it, the held-out test, the level), or None when that fit fails.

    Where the fit without *name* fits the data better than *f* (a model nested
    in *f*), *f* sits in a poorer optimum than it could: it is fitted again from
    the nested fit (the search's own start for an added candidate), the better of
    the two taken, and when *f* is the search's current model that fit replaces it.
    """
    spec = f.spec.with_(name, 0)
    try:
        without = fit_spec(spec, f, init_from=s.warm.get(spec))
    except FitError:
        return None
    kept_objective = f.problem.objective(f.z)
    if without.problem.objective(without.z) < kept_objective:
        try:
            again = fit_spec(f.spec, without)
        except FitError:
            again = None
        if again is not None and again.problem.objective(again.z) < kept_objective:
            if f is s.current:
                s.current = again
            f = again
    t = compared(name, f, without)
    h = check_heldout(t, without, judged_on(name, s.material, s.artefact))
    level = s.candidates[name].heldout_level or s.levels[max(s.kept_round.get(name, 1), 1) - 1].single
    return t.screened and passes(h, level, s.crit.min_resolution_units), without, h, level


def _still_passes(s: Search, name: str, f: Fitted) -> bool:
    """Does *name* in *f* still pass its held-out test against *f* without it (True when that fit fails)?"""
    judged = _judged_without(s, name, f)
    return judged is None or judged[0]


def run_search(start: Fitted, material: FoldSet, artefact: FoldSet, records: list[Record],
               candidates: Sequence[str], criteria: Criteria, rep, *, warm: dict | None = None) -> Search:
    """The rounds and the backward elimination from the model *start* (:mod:`.rounds`).

    *warm*: fits to start from, by spec, read but not added to (an inner selection's, :mod:`.nested`).
    """
    search = start_search(start, material, artefact, records, candidates, criteria)
    if warm is not None:
        search.warm, search.record = warm, False
    rnd = 1
    while run_round(search, rnd, rep):
        rnd += 1
    backward(search, rep)
    drop_unsupported_artefacts(search, rep)
    cached_heldout(search.current, material)
    return search
