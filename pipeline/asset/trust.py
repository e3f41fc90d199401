"""How far to trust an asset, in plain words: :class:`Accuracy` (``Asset.accuracy``, ``esmm info``).

The figures come from :mod:`.accuracy`: the fit's error (``/accuracy/fit``), the
compensation's (the ``/tables`` metadata) and the validation's (``/accuracy/validation``).
Every number is said with its unit; a figure the asset does not have is said to be
missing, with what would measure it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

#: Load cases in the order they are said (organ cases first: what a simulation does).
CASE_ORDER = ("lift", "gravity", "tension", "compression", "shear")


def _pct(v) -> str:
    return "?" if v is None else f"{100 * v:.3g} %"


@dataclass(frozen=True)
class Accuracy:
    """The errors an asset states about itself (:mod:`.accuracy`).

    Attributes
    ----------
    fit : dict or None
        The material fit's record (``rmse_pa``, ``nrmse``, ``r2``, ``verdict``, ``reasons``,
        ``files``, ``source``); None when the material is not a calibrate fit (a preset).
    compensation : dict or None
        :func:`~.accuracy.compensation_summary` of the tables; None: not compensated.
    validation : dict or None
        The validation record (``cases``: name -> figures and settings); None: never validated.
    material : str
        The material's name (for the words when there is no fit record).
    law : str
        The tables' default force law (the validation cases run with it are the asset's own).
    volume_term : bool
        Whether the asset has a volume term (likewise).
    """

    fit: dict | None = None
    compensation: dict | None = None
    validation: dict | None = None
    material: str = ""
    law: str = ""
    volume_term: bool = False

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable: the three records and the words (``esmm info --json``)."""
        return {"fit": self.fit, "compensation": self.compensation, "validation": self.validation,
                "headline": self.headline(), "lines": self.lines()}

    # -- the parts, in words ------------------------------------------------------------------
    def fit_words(self) -> str:
        f = self.fit
        if not f:
            return (f"the material {self.material or '(none)'} carries no fit error (a preset, or a file "
                    "calibrate did not write)")
        verdict = f"; calibrate's verdict: {f['verdict']}" if f.get("verdict") else ""
        reasons = f" ({'; '.join(f['reasons'])})" if f.get("reasons") else ""
        data = f" on {', '.join(f['files'])}" if f.get("files") else ""
        return (f"the material follows its tensile data{data} with a normalised RMS error of {_pct(f.get('nrmse'))} "
                f"(RMSE {f.get('rmse_pa', float('nan')):.4g} Pa, R² {f.get('r2', float('nan')):.3f}){verdict}{reasons}")

    def compensation_words(self) -> str:
        c = self.compensation
        if not c:
            return "the network is not compensated: it is several times softer than the material"
        lo, hi = (c.get("stretch_range") or [None, None])[:2]
        where = f" over stretches {lo:.2f}-{hi:.2f}" if lo is not None and hi is not None else ""
        parts = [f"{_pct(c.get('uniaxial_max'))} in tension and compression"]
        parts += [f"{_pct(v)} in {k} shear" for k, v in sorted(c.get("shear_max", {}).items())]
        within = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
        return (f"the network follows the material within {within}{where} (the compensation's virtual tests, "
                f"{c.get('law')} law)")

    def own_cases(self) -> dict[str, dict]:
        """The validated cases run as the asset is simulated (its law, its volume term), solved."""
        cases = (self.validation or {}).get("cases", {})
        term = "on" if self.volume_term else "off"
        return {k: c for k, c in cases.items()
                if c.get("failed") is None and c.get("law") in (None, self.law) and c.get("volume_term") == term}

    def validation_words(self) -> str:
        cases = (self.validation or {}).get("cases", {})
        if not cases:
            return ("not yet compared with a finite-element continuum of this organ: 'esmm validate ASSET' "
                    "measures it (minutes) and records it here")
        parts = []
        for name in sorted(cases, key=lambda k: (CASE_ORDER.index(k) if k in CASE_ORDER else 99, k)):
            c = cases[name]
            if c.get("failed"):
                parts.append(f"{name}: no equilibrium found ({c['failed']})")
                continue
            how = (f"{c.get('element') or 'continuum'}, volume term {c.get('volume_term')}, {c.get('law')} law"
                   + (f", scene {c['scene']}" if c.get("scene") not in (None, "", "default") else ""))
            parts.append(f"{name}: {_pct(c.get('l2_error'))} in displacement (L2), {_pct(c.get('force_error'))} "
                         f"in force ({how}; {str(c.get('utc_time', ''))[:10]})")
        return "against a finite-element continuum of this organ (esmm validate): " + "; ".join(parts)

    def headline(self) -> str:
        """One sentence: the largest error a simulation of the asset carries, as far as it is known."""
        own = self.own_cases()
        if own:
            worst_u = max((c["l2_error"] for c in own.values() if c.get("l2_error") is not None), default=None)
            worst_f = max((c["force_error"] for c in own.values() if c.get("force_error") is not None), default=None)
            net = (f"the network is within {_pct(worst_u)} of a finite-element continuum in displacement and "
                   f"{_pct(worst_f)} in force ({', '.join(sorted(own))})")
        elif self.compensation:
            net = (f"the network follows the material within {_pct(self.compensation.get('uniaxial_max'))} in the "
                   "virtual tests, but was not compared with a continuum of this organ (esmm validate)")
        else:
            net = "the network is not compensated and not validated: several times too soft"
        fit = (f"the material fits its data within {_pct(self.fit.get('nrmse'))} (normalised RMS)"
               + (f", verdict {self.fit['verdict']}" if self.fit.get("verdict") else "")) if self.fit else \
            "the material's own error is not recorded"
        return f"{net}; {fit}"

    def lines(self) -> list[str]:
        """The headline and one line per part (what ``esmm info`` prints under "trust")."""
        return [f"how far to trust this asset: {self.headline()}",
                f"fit: {self.fit_words()}", f"network: {self.compensation_words()}",
                f"continuum: {self.validation_words()}"]


#: Largest uniaxial error of the compensation's virtual tests for a usable asset (a fraction): the
#: calibration leaves about 1 % on the bundled liver (docs/guide/prepare.md, "How far to trust it"); five
#: times that is a network whose stress-stretch curve visibly departs from its material's.
COMPENSATION_POOR = 0.05
#: Largest validated displacement (L2) or force error for a "good" asset (a fraction): the paper preset's
#: liver, stiff where the field bends over few elements, is 16.65 % off in force under a 20 mm lift and
#: --split brings it within 2 % (docs/guide/validate.md); above 10 % the advice is that refinement.
VALIDATION_POOR = 0.10


def judge(accuracy: Accuracy, *, quality_passes: bool | None = None) -> tuple[str, list[str], list[str]]:
    """The asset's verdict: (level ``good`` / ``poor`` / ``unusable``, reasons, what to do), each reason
    with its figure and unit. Thresholds: :data:`COMPENSATION_POOR`, :data:`VALIDATION_POOR`; the fit's
    verdict is calibrate's."""
    reasons: list[tuple[str, str, str]] = []
    c = accuracy.compensation
    if not c:
        reasons.append(("unusable", "the network is not compensated: its forces are several times too small",
                        "compensate it: esmm tables ASSET --compensate"))
    elif (c.get("uniaxial_max") or 0) > COMPENSATION_POOR:
        reasons.append(("poor", f"the network departs from its material by {_pct(c['uniaxial_max'])} in the "
                        f"virtual tests (above {_pct(COMPENSATION_POOR)})",
                        "check the material's curve over stretches 0.9-1.3 (a fit far outside its data)"))
    level = (accuracy.fit or {}).get("verdict", "")
    if level in ("poor", "unusable"):
        reasons.append((level, f"calibrate's verdict on the material's fit is {level}",
                        "see the fit's report.html; refit or use another material"))
    for name, case in sorted(accuracy.own_cases().items()):
        worst = max(v for v in (case.get("l2_error"), case.get("force_error"), 0.0) if v is not None)
        if worst > VALIDATION_POOR:
            reasons.append(("poor", f"{name}: {_pct(worst)} from the finite-element continuum (above "
                            f"{_pct(VALIDATION_POOR)})", "a finer network: esmm prepare --split (or --config fine)"))
    if quality_passes is False:
        reasons.append(("poor", "the mesh is below the quality floors (written with --force)",
                        "another mesh size, or repair the surface"))
    if not accuracy.own_cases():
        reasons.append(("good", "not compared with a finite-element continuum of this organ yet",
                        "run esmm validate ASSET (minutes); it records the figures in the asset"))
    order = ("good", "poor", "unusable")
    verdict = max((r[0] for r in reasons), key=order.index, default="good")
    shown = [r for r in reasons if r[0] != "good" or verdict == "good"]
    advice = list(dict.fromkeys(r[2] for r in reasons))
    return verdict, [r[1] for r in shown], advice
