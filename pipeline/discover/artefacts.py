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
   Slacks are tested with their joint covariance (:func:`joint_wald`, the
   directions the fit does not see left out), for the reason of point 2.
2. **A slack differs between mountings.** Each specimen is clamped with its
   own slack; slacks that agree across every file describe the curve of every
   specimen starting to carry load the same distance above its reference
   length — the material's (fibres recruited only above the reference length,
   a toe the elastic law lacks), which a correction of each mounting would
   hide. The Wald statistic of the m − 1 contrasts :math:`C s` (each slack less
   the first) with the fit's joint covariance Σ of the slacks,
   :math:`W = (Cs)^T (C \\Sigma C^T)^{+} (Cs)`, over :math:`\\chi^2` of the
   contrasts' rank, p at most :data:`LEVEL`. With independent estimates it is
   Cochran's heterogeneity statistic :math:`Q = \\sum_i w_i (s_i - \\bar s)^2`,
   :math:`w_i = 1/\\mathrm{SE}_i^2`; but the slacks share an error where the
   elastic law has an onset of its own (a toe, or any law stiffening from zero):
   a common slack trades with the onset, so each slack's own interval is wide
   while their differences are sharp, and Q on the marginal errors reads slacks
   of 0.55 and 1.35 times one mounting's as agreeing (p 0.63 where the joint
   test gives p below 10⁻¹⁰). And they must differ by what the records resolve
   (:func:`slack_spread` at least 1: every slack set to their mean moves the
   predicted stress on some record by its resolution, the history test's size
   requirement): on tens of thousands of samples a test of differences alone is
   passed by any misfit the slacks can take, and clean toe-law replicates and
   multirate sets gave slacks 0.5-2 % apart at p below 0.05.

Both are necessary conditions added to the held-out test, so they can only
lower the rate at which artefacts are added to clean records; their cost is
a true artefact the fit cannot size, or a true slack that happens to be the
same in every mounting (measured on the population with the rest,
docs/guide/discover.md).
"""

from __future__ import annotations

import math
from contextlib import contextmanager

import numpy as np
from scipy import stats

from ..tensile.noise import resolution
from .estimates import Estimate, estimates, slot_covariance
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


@contextmanager
def _state_kept(f: Fitted):
    """The problem of *f* with its optimiser state (``z_full``, ``active``) put back afterwards."""
    prob = f.problem
    saved = (prob.z_full, prob.active)
    try:
        yield prob
    finally:
        prob.z_full, prob.active = saved


def _estimates(f: Fitted) -> list[Estimate]:
    with _state_kept(f) as prob:
        return estimates(prob, f.z)


def determined(rows: list[tuple[float, float]]) -> float:
    """Wald p-value that the per-file deviations *rows* ((deviation, SE), ...) are all zero."""
    w = sum((d / se) ** 2 for d, se in rows)
    return float(stats.chi2.sf(w, len(rows)))


def heterogeneity(rows: list[tuple[float, float]]) -> float:
    """Cochran's p-value that the per-file values *rows* ((value, SE), ...) are one common value (independent
    estimates: :func:`equal_values` with a diagonal covariance)."""
    v = np.array([r[0] for r in rows])
    w = 1.0 / np.array([r[1] for r in rows]) ** 2
    mean = float(np.sum(w * v) / np.sum(w))
    return float(stats.chi2.sf(float(np.sum(w * (v - mean) ** 2)), len(rows) - 1))


def joint_wald(values: np.ndarray, cov: np.ndarray, *, contrasts: np.ndarray | None = None,
               null: np.ndarray | None = None) -> float:
    """Wald p-value that ``C values = 0`` (C: *contrasts*, rows; default the identity) with the values' joint
    covariance *cov* (m, m).

    The statistic is :math:`(Cv)^T (C \\Sigma C^T)^{+} (Cv)` on :math:`\\chi^2` of
    :math:`C \\Sigma C^T`'s rank. *null* (rows, shape (q, m)): directions of the values the data do not see
    (the fit's unidentified directions restricted to these values); the part of every contrast along them is
    left out. 1 where nothing is left to test.
    """
    v = np.asarray(values, float)
    m = v.size
    C = np.eye(m) if contrasts is None else np.asarray(contrasts, float)
    if null is not None and np.size(null):
        n = np.asarray(null, float)
        C = C @ (np.eye(m) - np.linalg.pinv(n) @ n)  # the contrasts' parts the data see
    V = C @ np.asarray(cov, float) @ C.T
    scale = float(np.max(np.abs(V))) if V.size else 0.0
    if not scale > 0:
        return 1.0
    rank = int(np.linalg.matrix_rank(V / scale, tol=1e-10, hermitian=True))
    if rank == 0:
        return 1.0
    d = C @ v
    w = float(d @ np.linalg.pinv(V, rcond=1e-10, hermitian=True) @ d)
    return float(stats.chi2.sf(w, rank))


def equal_values(values: np.ndarray, cov: np.ndarray, null: np.ndarray | None = None) -> float:
    """Wald p-value that *values* (m,) with joint covariance *cov* are one common value: the m − 1 contrasts
    (each value less the first) together (:func:`joint_wald`); Cochran's Q where *cov* is diagonal."""
    m = np.asarray(values).size
    return joint_wald(values, cov, contrasts=np.eye(m)[1:] - np.eye(m)[0], null=null)


def _slack_slots(f: Fitted) -> list[int]:
    return [i for i, s in enumerate(f.problem.slots) if s.effect == "slack" and s.file is not None]


def _slack_covariance(f: Fitted) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(per-file slacks, their joint covariance, the unidentified directions among them or None) of *f*."""
    idx = _slack_slots(f)
    with _state_kept(f) as prob:
        cov, null = slot_covariance(prob, f.z)
    return np.asarray(f.z)[idx], cov[np.ix_(idx, idx)], (null[:, idx] if null.size else None)


def slack_spread(f: Fitted) -> float:
    """How far apart the files' slacks of *f* are in what the records resolve: the largest change of the
    predicted stress on any record when every slack is set to their mean (the rest of the fit as it is), in
    resolutions of that record (:func:`~esmm.pipeline.tensile.noise.resolution`)."""
    prob, idx = f.problem, _slack_slots(f)
    z = np.asarray(f.z, float)
    common = z.copy()
    common[idx] = float(np.mean(z[idx]))
    coefs = prob.offsets(z)
    worst = 0.0
    for k in sorted({prob.slots[i].file for i in idx}):
        r = prob.records[k]
        change = prob.full_prediction(k, common, coefs[k]) - prob.full_prediction(k, z, coefs[k])
        if np.any(np.isfinite(change)):
            worst = max(worst, float(np.nanmax(np.abs(change))) / max(resolution(r.y, r.sigma), 1e-300))
    return worst


def shared_slack_reason(f: Fitted, covariance: tuple | None = None) -> str | None:
    """Why the per-file slack of *f* is not an artefact (its files' slacks agree), or None (*covariance*:
    :func:`_slack_covariance` of *f*, when already computed)."""
    if len(_slack_slots(f)) < 2:
        return None
    p = equal_values(*(covariance or _slack_covariance(f)))
    if p > LEVEL:
        return (f"the files' slacks agree within their errors (joint Wald test of their differences, p {p:.2g} > "
                f"{LEVEL:g}); a slack every specimen shares is the material's curve starting above its reference "
                "length (a toe the elastic law lacks), not an artefact of each mounting")
    spread = slack_spread(f)
    if spread < 1.0:
        return (f"the files' slacks differ by less than the records resolve (every slack set to their mean moves "
                f"the predicted stress by at most {spread:.2g} of a record's resolution); a slack every specimen "
                "shares is the material's curve starting above its reference length (a toe the elastic law "
                "lacks), not an artefact of each mounting")
    return None


def artefact_reason(f: Fitted, name: str) -> str | None:
    """Why the artefact *name* of *f* does not belong in the final model (module docstring), or None."""
    if name not in _NEUTRAL:
        return None
    covariance = None
    if name == "slack":  # jointly: the slacks' common part trades with an elastic onset (the module's docstring)
        covariance = vals, cov, null = _slack_covariance(f)
        p, m = (joint_wald(vals, cov, null=null), vals.size) if vals.size else (None, 0)
    else:
        rows = _rows(_estimates(f), name)
        p, m = (determined(rows), len(rows)) if rows else (None, 0)
    if p is not None and p > LEVEL:
        return (f"the fit does not determine its size: its {m} per-file value(s) do not differ "
                f"from none jointly (Wald p {p:.2g} > {LEVEL:g}); what it fits is the noise's slow wander or "
                "the fold design's luck")
    return shared_slack_reason(f, covariance) if name == "slack" else None


__all__ = ["LEVEL", "artefact_reason", "determined", "equal_values", "heterogeneity", "joint_wald",
           "shared_slack_reason", "slack_spread"]
