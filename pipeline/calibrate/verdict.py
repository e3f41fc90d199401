"""A verdict on every fit: good, poor or unusable, with its reasons in plain words.

The rules and their reasons (docs/design/calibration.md, "The verdict"; for a reader,
docs/guide/trust.md):

* **Misfit against what the record resolves.** The resolution r is the larger of
  the record's noise σ (:func:`esmm.pipeline.tensile.events.noise_sd`, from the
  record alone) and a class 0.5 testing machine's accuracy, 0.5 % of the RMS stress
  (:func:`esmm.pipeline.tensile.noise.resolution`, the same measure the discovery
  uses): a smoothed, averaged or digitised curve has almost no sample-to-sample
  noise, yet its stresses are no more accurate than the machine that measured them.
  A model whose RMSE is within :data:`NOISE_RATIO` r reproduces the file as closely
  as the measurement lets anyone tell (its systematic part is then at most √3 r);
  beyond that the residual is the model's.
* **Unusable: R² < R2_USABLE** with a misfit beyond the noise. Below one half the model
  leaves more of the data's variation unexplained than it explains: a stress predicted
  from it is wrong by more than the variation it reproduces. (When the misfit is within
  the noise, a low R² says the record is mostly noise: poor, not the model's fault.)
* **Poor: NRMSE > NRMSE_GOOD** with a misfit beyond the noise. The stress of a soft
  tissue specimen is itself uncertain by about 5 % (its cross-section, measured on a
  compliant specimen with a caliper or a laser, sets the scale of every stress); a
  model error below that is smaller than what the lab can know of the stress, above it
  the model's shape is wrong by more than the data's own scale uncertainty.
* **Poor: parameters the data do not determine**, or pushed to a bound of their
  range while the data do determine them (the optimum lies outside the allowed range),
  or an optimiser that stopped early: the curve may be fine, but those values are not
  measurements (never report or average them).
* **Unusable: a rupture left in the fitted samples** (the fit describes a broken
  specimen) and **a material that is not Drucker-stable** over the data's range
  (the stiffness tables of ``esmm prepare`` refuse it and a simulation would go
  unstable).

The verdict of a fit is the worst of its reasons; each file gets its own from the
rules that concern one file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..htmlreport import quantity_text
from ..tensile import events
from ..tensile.data import TensileTest
from ..tensile.noise import resolution
from .failure import FailureTest
from .fit import FitResult

GOOD, POOR, UNUSABLE = "good", "poor", "unusable"
#: the order of severity
LEVELS = (GOOD, POOR, UNUSABLE)
#: below this R² (with a misfit beyond the noise) the model explains less of the data than it leaves
R2_USABLE = 0.5
#: above this NRMSE (with a misfit beyond the noise) the model's error exceeds a tissue stress's own uncertainty
NRMSE_GOOD = 0.05
#: an RMSE within this many noise standard deviations is the record's noise, not the model's error
NOISE_RATIO = 2.0

HEADLINES = {
    GOOD: "Good: the model reproduces the data within their noise or their own uncertainty, and the data "
          "determine every fitted parameter.",
    POOR: "Poor: usable with care, for the reasons below.",
    UNUSABLE: "Unusable: do not use these parameters, for the reasons below.",
}


@dataclass(frozen=True)
class Reason:
    """One reason of a verdict: its rule (``code``), level, plain sentence and what to do."""

    code: str
    level: str
    text: str
    advice: str = ""
    file: str | None = None


@dataclass(frozen=True)
class Verdict:
    """The verdict of a fit: its level, its reasons (worst first), and the level of each file."""

    level: str
    reasons: tuple[Reason, ...] = ()
    files: dict[str, str] = field(default_factory=dict)
    noise: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def headline(self) -> str:
        return HEADLINES[self.level]

    @property
    def usable(self) -> bool:
        return self.level != UNUSABLE

    def short(self) -> str:
        """One line: the level and the reasons' sentences (for a console, a CSV cell)."""
        why = "; ".join(r.text for r in self.reasons)
        return f"{self.level}" + (f": {why}" if why else "")

    def advice(self) -> list[str]:
        out: list[str] = []
        for r in self.reasons:
            if r.advice and r.advice not in out:
                out.append(r.advice)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"level": self.level, "headline": self.headline,
                "reasons": [vars(r) for r in self.reasons], "files": dict(self.files), "noise": self.noise,
                "rules": {"r2_usable": R2_USABLE, "nrmse_good": NRMSE_GOOD, "noise_ratio": NOISE_RATIO}}


def worst(levels: Sequence[str]) -> str:
    return max(levels, key=LEVELS.index, default=GOOD)


def judge(result: FitResult, tests: Sequence[TensileTest], failures: Sequence[FailureTest] = ()) -> Verdict:
    """The verdict on *result*, fitted to *tests* (the intact parts); *failures*: their failure analyses."""
    noise = {t.name: _noise(t, fe.rmse) for t, fe in zip(tests, result.files)}
    reasons: list[Reason] = []
    for t, fe in zip(tests, result.files):
        reasons += _file_reasons(t.name, fe, noise[t.name])
    reasons += _rupture_reasons(tests, failures)
    reasons += _parameter_reasons(result)
    if not result.drucker.get("stable", True):
        reasons.append(Reason("unstable", UNUSABLE, "the fitted material is not Drucker-stable over the data's "
                              f"stretch range ({result.drucker.get('detail', '')}): esmm prepare refuses it",
                              "fix or bound the parameter that makes the stress fall, or fit another model"))
    reasons.sort(key=lambda r: -LEVELS.index(r.level))
    files = {t.name: worst([r.level for r in reasons if r.file in (None, t.name)
                            and r.code in ("misfit", "noisy", "no_fit", "rupture_left")]) for t in tests}
    return Verdict(worst([r.level for r in reasons]), tuple(reasons), files, noise)


def _noise(t: TensileTest, rmse: float) -> dict[str, float]:
    y = np.asarray(t.stress, float)
    sd = float(events.noise_sd(y))
    res = resolution(y, sd)
    return {"sd_Pa": sd, "resolution_Pa": res, "ratio": rmse / res if res > 0 else math.inf}


def _file_reasons(name: str, fe, noise: dict[str, float]) -> list[Reason]:
    """The rules on one file's errors: R², NRMSE, both against the file's own noise."""
    within_noise = noise["ratio"] <= NOISE_RATIO
    by_noise = noise["resolution_Pa"] <= noise["sd_Pa"]
    ratio = (f"{noise['ratio']:.3g} times its {'noise' if by_noise else 'resolution'} "
             f"({quantity_text(noise['resolution_Pa'], 'Pa', digits=3)}{'' if by_noise else ', 0.5 % of its RMS stress'})")
    if fe.r2 < R2_USABLE and not within_noise:
        return [Reason("no_fit", UNUSABLE,
                       f"{name}: R² {fe.r2:.3f} (below {R2_USABLE}): the model explains less of the data than it "
                       f"leaves; RMSE {quantity_text(fe.rmse, 'Pa', digits=3)}, {ratio}",
                       "look at the plot: a loading mode, units or effect the model does not have (try --discover)",
                       name)]
    if fe.r2 < R2_USABLE:
        return [Reason("noisy", POOR, f"{name}: R² {fe.r2:.3f} with a misfit within the noise: the record is "
                       "mostly noise", "test to a larger stress, or with a load cell of a smaller range", name)]
    if fe.nrmse > NRMSE_GOOD and not within_noise:
        return [Reason("misfit", POOR,
                       f"{name}: NRMSE {fe.nrmse:.1%} (above {NRMSE_GOOD:.0%} of the stress range) and {ratio}: "
                       "the model misses the data's shape",
                       "look at the residual plot; try --discover for rate or history effects, or another model",
                       name)]
    return []


def _rupture_reasons(tests: Sequence[TensileTest], failures: Sequence[FailureTest]) -> list[Reason]:
    out = []
    for t, f in zip(tests, failures):
        if f.rupture_early or (f.failed and t.n > f.ultimate_index + 1):
            where = f"stretch {f.rupture_stretch:.4g}" if f.rupture_stretch is not None else \
                f"stretch {f.ultimate_stretch:.4g} (its ultimate stress)"
            what = "a rupture" if f.kind == "rupture" else "a failure"
            out.append(Reason("rupture_left", UNUSABLE, f"{t.name}: {what} at {where} is left in the fitted "
                              "samples: the fit describes a broken specimen",
                              "cut the record before the rupture, or check that the file is one test", t.name))
    return out


def _parameter_reasons(result: FitResult) -> list[Reason]:
    out = []
    unident = [e for e in result.estimates if not e.identifiable]
    if unident:
        keys = ", ".join(e.key for e in unident)
        out.append(Reason("not_identifiable", POOR,
                          f"the data do not determine {keys}: their values are not measurements",
                          "use the material as a whole within the tested range; do not report or average those "
                          "values; fit fewer parameters (--fix, a simpler --model) or add tests in other modes"))
    pushed = [e for e in result.estimates if e.at_bound and e.identifiable]
    if pushed:
        out.append(Reason("at_bound", POOR, "at a bound of its allowed range: " + ", ".join(
            f"{e.key} = {quantity_text(e.value, 'Pa' if e.kind == 'stress' else '1')}" for e in pushed)
            + " (the best value lies outside it)", "check the data's units and mode; another model may fit"))
    stopped = [w for w in result.warnings if w.startswith("the optimiser stopped early")]
    if stopped:
        out.append(Reason("not_converged", POOR, stopped[0], "run again with more --starts"))
    return out
