"""Is a per-file artefact what the fit says it is? (docs/design/discovery.md, "What an artefact must show").

An artefact (slack, grip slips, a load-cell offset or drift, per-specimen
scales) is a correction of the data, one value per file or specimen. Beside
the held-out test every candidate passes, an artefact must show two things
in the final model (after the backward elimination,
:func:`~esmm.pipeline.discover.rounds.drop_unsupported_artefacts`: earlier,
the misfit of effects not yet found would inflate its standard errors):

1. **Its size is determined.** Its per-file parameters, jointly, differ from
   their neutral values (no slack, no slip, no offset or drift, scale 1): the
   Wald statistic :math:`W = \\sum_i ((v_i - v_{0,i})/\\mathrm{SE}_i)^2` over
   the m estimates, referred to :math:`\\chi^2_m`, p at most :data:`LEVEL`. The
   standard errors are the fit's covariance (:mod:`.estimates`: inflated for
   the residual's serial correlation; a scale's on the log scale). A drift
   whose every file's interval holds zero is the noise's slow wander (1/f
   amplifier noise), which a fold of consecutive blocks can still reward.
   Offsets read at rest are measured, not fitted, and are not tested here.
2. **A slack differs between mountings.** Each specimen is clamped with its
   own slack; slacks that agree across every file describe the curve of every
   specimen starting to carry load the same distance above its reference
   length — the material's (fibres recruited only above the reference length,
   a toe the elastic law lacks), which a correction of each mounting would
   hide. Cochran's heterogeneity statistic
   :math:`Q = \\sum_i w_i (s_i - \\bar s)^2`, :math:`w_i = 1/\\mathrm{SE}_i^2`,
   over :math:`\\chi^2_{m-1}`, p at most :data:`LEVEL`.

Both are necessary conditions added to the held-out test, so they can only
lower the rate at which artefacts are added to clean records; their cost is
a true artefact the fit cannot size, or a true slack that happens to be the
same in every mounting (measured on the population with the rest,
docs/guide/discover.md).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .estimates import Estimate, estimates
from .fitted import Fitted

#: the level of both checks (as the held-out test's replication check)
LEVEL = 0.05
#: estimate keys of each artefact's per-file parameters, and their neutral value
_NEUTRAL = {"slack": (("slack.slack[", 0.0),), "grip_slip": (("grip_slip.slip", 0.0),),
            "sensor_offset": (("sensor_offset.force[", 0.0), ("sensor_offset.stress[", 0.0),
                              ("sensor_offset.drift[", 0.0)),
            "specimen_scale": (("specimen_scale.scale[", 1.0),)}
_Z95 = float(stats.norm.ppf(0.975))


def _z(e: Estimate, neutral: float) -> tuple[float, float] | None:
    """(value, standard error) of *e* on the scale its interval is symmetric on; None when not finite."""
    if neutral == 1.0:  # a positive quantity: log-normal interval
        if not (e.value > 0 and e.lower > 0 and math.isfinite(e.upper)):
            return None
        return math.log(e.value), math.log(e.upper / e.lower) / (2.0 * _Z95)
    se = (e.upper - e.lower) / (2.0 * _Z95)
    return (e.value - neutral, se) if math.isfinite(se) else None


def _rows(est: list[Estimate], name: str) -> list[tuple[float, float]]:
    out = []
    for prefix, neutral in _NEUTRAL.get(name, ()):
        for e in est:
            if e.key.startswith(prefix):
                z = _z(e, neutral)
                if z is not None and z[1] > 0:
                    out.append(z)
    return out


def _estimates(f: Fitted) -> list[Estimate]:
    prob = f.problem
    saved = (prob.z_full, prob.active)
    try:
        return estimates(prob, f.z)
    finally:
        prob.z_full, prob.active = saved


def determined(rows: list[tuple[float, float]]) -> float:
    """Wald p-value that the per-file deviations *rows* ((deviation, SE), ...) are all zero."""
    w = sum((d / se) ** 2 for d, se in rows)
    return float(stats.chi2.sf(w, len(rows)))


def heterogeneity(rows: list[tuple[float, float]]) -> float:
    """Cochran's p-value that the per-file values *rows* ((value, SE), ...) are one common value."""
    v = np.array([r[0] for r in rows])
    w = 1.0 / np.array([r[1] for r in rows]) ** 2
    mean = float(np.sum(w * v) / np.sum(w))
    return float(stats.chi2.sf(float(np.sum(w * (v - mean) ** 2)), len(rows) - 1))


def shared_slack_reason(f: Fitted, est: list[Estimate] | None = None) -> str | None:
    """Why the per-file slack of *f* is not an artefact (its files' slacks agree), or None (*est*: the estimates
    of *f*, when already computed)."""
    rows = _rows(_estimates(f) if est is None else est, "slack")
    if len(rows) < 2:
        return None
    ph = heterogeneity(rows)
    if ph <= LEVEL:
        return None
    return (f"the {len(rows)} files' slacks agree within their errors (Cochran's heterogeneity p {ph:.2g} > "
            f"{LEVEL:g}); a slack every specimen shares is the material's curve starting above its reference "
            "length (a toe the elastic law lacks), not an artefact of each mounting")


def artefact_reason(f: Fitted, name: str) -> str | None:
    """Why the artefact *name* of *f* does not belong in the final model (module docstring), or None."""
    if name not in _NEUTRAL:
        return None
    est = _estimates(f)
    rows = _rows(est, name)
    if rows:
        p = determined(rows)
        if p > LEVEL:
            return (f"the fit does not determine its size: its {len(rows)} per-file value(s) do not differ "
                    f"from none jointly (Wald p {p:.2g} > {LEVEL:g}); what it fits is the noise's slow wander or "
                    "the fold design's luck")
    return shared_slack_reason(f, est) if name == "slack" else None


__all__ = ["LEVEL", "artefact_reason", "determined", "heterogeneity", "shared_slack_reason"]
