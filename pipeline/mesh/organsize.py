"""Is the organ's size plausible for what its file name says it is? (a wrong length unit, caught early)

The reader refuses an organ whose largest extent is not 10-400 mm
(:func:`~esmm.pipeline.mesh.readers.check_unit_sanity`). That band cannot catch a
liver written in centimetres and read as millimetres: 19.5 mm across is a
plausible size for *some* organ. Its volume, 1.04 mL for a liver, is not: the
organ named in the file name gives the size to expect, and a volume far from it
gets a warning that names the ``unit`` option (never a rescale: the file may hold
a part of an organ, a child's or an animal's).

The reference volumes are ICRP Publication 89 (2002), "Basic anatomical and
physiological data for use in radiological protection: reference values", Table
2.8: the reference adult female and male organ masses, divided by a soft-tissue
density of 1.05 g/mL. Only solid organs are listed, whose segmented volume is
their tissue: a segmented heart, lung, stomach, gallbladder or bladder holds blood,
air or contents, whose volume varies far more than the tissue's (they get the
generic band).

**The rule.** A volume below a tenth of the smaller reference or above ten times
the larger one is implausible. Adult organs vary about twofold around the reference
(body size, sex, disease: hepatomegaly, splenomegaly), a child's or a pig's organ is
of the same order, a partial scan is a fraction of it; a length unit error changes a
volume a thousandfold (cm read as mm) or more. A factor of ten on either side flags
every unit error with a margin of a hundred and none of those variations (a
newborn's or a small animal's organ may be flagged; the warning says so). An organ
the file name does not name gets the generic band: from a tenth of the smallest
reference to ten times the largest.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ..units import factor, normalise_unit

#: Soft-tissue density used to turn ICRP reference masses into volumes [g/mL].
TISSUE_DENSITY_G_ML = 1.05

#: Organ -> (reference adult female mass, reference adult male mass) [g] for one organ, ICRP
#: Publication 89, Table 2.8 (the kidneys' pair masses 275 and 310 g halved).
REFERENCE_MASS_G: dict[str, tuple[float, float]] = {
    "liver": (1400.0, 1800.0),
    "brain": (1300.0, 1450.0),
    "kidney": (137.5, 155.0),
    "spleen": (130.0, 150.0),
    "pancreas": (120.0, 140.0),
    "thyroid": (17.0, 20.0),
    "prostate": (17.0, 17.0),
    "uterus": (80.0, 80.0),
}

#: Words of a file name that name an organ of :data:`REFERENCE_MASS_G` (lower case).
SYNONYMS = {"hepar": "liver", "kidneys": "kidney", "renal": "kidney", "cerebrum": "brain", "lien": "spleen"}

#: Factor on either side of the reference volumes inside which a volume is plausible (module docstring).
MARGIN = 10.0

#: A file name word that marks a part of an organ: no organ band applies (the generic one does).
PART_WORDS = {"lobe", "segment", "part", "partial", "half", "section", "slice", "tumor", "tumour", "lesion",
              "vessel", "vessels", "duct", "cortex", "medulla", "capsule"}


@dataclass(frozen=True)
class SizeCheck:
    """The outcome of :func:`check_organ_size`.

    Attributes
    ----------
    organ : str
        The organ the file name names, or "" (the generic band).
    volume_ml : float
        The organ's volume [mL].
    band_ml : (float, float)
        The plausible volumes [mL].
    reference_ml : (float, float) or None
        The adult reference volumes (female, male) of *organ* [mL].
    message : str
        The warning ("" when the size is plausible).
    """

    organ: str
    volume_ml: float
    band_ml: tuple[float, float]
    reference_ml: tuple[float, float] | None
    message: str = ""

    @property
    def plausible(self) -> bool:
        return not self.message


def reference_ml(organ: str) -> tuple[float, float]:
    """The adult reference volumes (female, male) of *organ* [mL]."""
    lo, hi = REFERENCE_MASS_G[organ]
    return lo / TISSUE_DENSITY_G_ML, hi / TISSUE_DENSITY_G_ML


def generic_band_ml() -> tuple[float, float]:
    """The plausible volumes of an organ the file name does not name [mL] (module docstring)."""
    refs = [reference_ml(o) for o in REFERENCE_MASS_G]
    return min(r[0] for r in refs) / MARGIN, max(r[1] for r in refs) * MARGIN


def organ_of(name: str) -> str:
    """The organ a file name names (``"ts_liver_3mm_closed.stl"`` -> ``"liver"``), or "" if none or a part."""
    words = [w.lower() for w in re.split(r"[^A-Za-z]+", name) if w]
    if any(w in PART_WORDS for w in words):
        return ""
    for w in words:
        w = SYNONYMS.get(w, w)
        if w in REFERENCE_MASS_G:
            return w
    return ""


def check_organ_size(volume_m3: float, extent_m: float, *, name: str, unit: str) -> SizeCheck:
    """Whether an organ of *volume_m3* read in *unit* is plausible for what its file *name* says.

    Parameters
    ----------
    volume_m3 : float
        The surface's enclosed volume [m3] (its magnitude is used).
    extent_m : float
        Its largest extent [m] (for the message).
    name : str
        The file name, read for an organ's name (:func:`organ_of`).
    unit : str
        The length unit the file was read in.

    Returns
    -------
    SizeCheck
        ``message`` begins with ``unit:`` and says which unit would make the organ plausible.
    """
    organ = organ_of(name)
    ref = reference_ml(organ) if organ else None
    band = (ref[0] / MARGIN, ref[1] * MARGIN) if ref else generic_band_ml()
    v = abs(float(volume_m3)) * 1e6
    if band[0] <= v <= band[1]:
        return SizeCheck(organ, v, band, ref)
    what = f"a {organ}" if organ else "an organ"
    small = v < band[0]
    expect = (f"an adult {organ} is {_ml(ref[0])}-{_ml(ref[1])} mL (ICRP Publication 89)" if ref else
              f"organs are {_ml(band[0])}-{_ml(band[1])} mL")
    hint = _unit_hint(v, unit, band)
    return SizeCheck(organ, v, band, ref, (
        f"unit: {what} of {_ml(v)} mL ({extent_m * 1e3:.3g} mm across, read in {unit}) is implausibly "
        f"{'small' if small else 'large'}: {expect}; {hint}; ignore this for a part of an organ"
        + (", a newborn's or a small animal's" if small else "")))


def _unit_hint(v_ml: float, unit: str, band: tuple[float, float]) -> str:
    """Which unit would make *v_ml* (read in *unit*) plausible, in words."""
    given = factor(unit, "length")
    for u in ("cm", "mm", "m", "in", "um"):
        if normalise_unit(u) == normalise_unit(unit):
            continue
        scaled = v_ml * (factor(u, "length") / given) ** 3
        if band[0] <= scaled <= band[1]:
            return f"if the file is in {u}, read it with unit {u} (the organ is then {_ml(scaled)} mL)"
    return "check the file's length unit"


def _ml(v: float) -> str:
    """A volume in mL for a message: 3 significant digits, thousands grouped."""
    return f"{v:,.0f}".replace(",", " ") if v >= 100 else f"{v:.3g}"
