"""Fitting a candidate against the current model, and the two tests it must pass.

A :class:`Trial` is a candidate model (current model + one candidate, every
parameter refitted) with its fitted improvement in units of the measurement
noise (:func:`~esmm.pipeline.discover.statistics.noise_test`) and, once
checked, its held-out improvement
(:func:`~esmm.pipeline.discover.statistics.paired_heldout`). AICc and BIC on
effective sample sizes are computed for the report (they do not decide).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import FitError
from .fitted import Fitted, fit_spec
from .heldout import Fold, heldout
from .statistics import information, n_effective, noise_test, paired_heldout

#: a candidate must predict held-out data better by this many standard errors (one-sided p = 0.05)
HELDOUT_Z = 1.645
#: ... and by at least this many noise variances per held-out sample
MIN_NOISE_UNITS = 1.0
#: ... and, when the sign test establishes it, better on average by at least one standard error too
MEAN_AT_LEAST = 1.0


@dataclass
class Trial:
    """A candidate model of one round and how it compares with the current model."""

    name: str
    fit: Fitted
    noise: dict[str, float]  # noise_test against the current model
    info: dict[str, float]
    ref: dict[str, float]  # the current model's AICc/BIC, on the candidate's effective sample sizes
    heldout: dict[str, float] = field(default_factory=dict)  # paired_heldout, once checked

    @property
    def dbic(self) -> float:
        """Noise-referenced BIC difference (negative: the fitted improvement pays for the parameters)."""
        return self.noise["dbic"]

    @property
    def d_aicc(self) -> float:
        return self.info["aicc"] - self.ref["aicc"]

    @property
    def d_bic(self) -> float:
        return self.info["bic"] - self.ref["bic"]

    def summary(self) -> dict[str, Any]:
        return {"dchi2": self.noise["dchi2"], "penalty": self.noise["penalty"], "dbic_noise": self.dbic,
                "delta_aicc": self.d_aicc, "delta_bic": self.d_bic, **{f"heldout_{k}": v for k, v in
                                                                        self.heldout.items()}}


def sigmas(f: Fitted) -> list[float]:
    return [r.sigma for r in f.problem.records]


def compared(name: str, f: Fitted, current: Fitted) -> Trial:
    """*f* against *current*: noise test, and AICc/BIC on *f*'s effective sample sizes (for the report)."""
    res1 = f.problem.fit_residuals(f.z)
    res0 = current.problem.fit_residuals(current.z)
    dk = f.problem.n_params() - current.problem.n_params()
    nu = n_effective(res1)
    return Trial(name, f, noise_test(res0, res1, sigmas(f), dk), information(res1, nu, f.problem.n_params()),
                 information(res0, nu, current.problem.n_params()))


def best_variant(name: str, variants, current: Fitted, *, upgrade: bool = False) -> Trial | None:
    """Fit the variants of *name* in order; a richer variant must pay for its parameters against the simpler.

    Returns the best variant by the noise test (None if no fit succeeded).
    """
    best: Trial | None = None
    prev: Trial | None = None
    for v in variants:
        try:
            f = fit_spec(current.spec.with_(name, v), current, init_from=prev.fit if prev is not None else None)
        except FitError:
            break
        t = compared(name, f, current)
        if prev is not None and compared(name, f, prev.fit).dbic >= 0:
            break
        if best is None or t.dbic < best.dbic:
            best = t
        if not upgrade and t.dbic > 0 and name not in ("viscoelastic", "sensor_offset"):
            break  # the simplest variant does not pay: the richer ones will not either
        prev = t
    return best


def check_heldout(t: Trial, current: Fitted, folds: list[Fold], *, z: float = HELDOUT_Z,
                  noise_units: float = MIN_NOISE_UNITS) -> bool:
    """Run the held-out check of *t* against *current*; True when it passes (``t.heldout`` filled)."""
    f = t.fit
    if f.heldout is None or f.heldout.samples is None:
        f.heldout = heldout(f, folds)
    t.heldout = paired_heldout(_pairs(current, f))
    h = t.heldout
    return max(h["z"], h["z_mean"]) >= z and h["z_mean"] >= MEAN_AT_LEAST and h["noise_units"] >= noise_units


def _pairs(current: Fitted, f: Fitted):
    """Per record: (held-out data, current prediction, candidate prediction, range, noise), aligned by sample."""
    out = []
    a, b = current.heldout.samples or {}, f.heldout.samples or {}
    for k, (idx0, y0, p0) in a.items():
        if k not in b:
            continue
        idx1, _, p1 = b[k]
        common, i0, i1 = np.intersect1d(idx0, idx1, return_indices=True)
        r = f.problem.records[k]
        out.append((y0[i0], p0[i0], p1[i1], r.range, r.sigma))
    return out


def finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None
