"""The state of a discovery's search: the verdict on each candidate, the criteria, the current model.

Shared by the rounds (:mod:`.rounds`), the nested held-out errors (:mod:`.nested`) and the entry
point (:mod:`.search`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ..materials.effects import ARTEFACTS
from ..materials.terms import TERMS
from .diagnose import Diagnosis
from .fitted import Fitted
from .heldout import FoldSet
from .identify import identifiability
from .levels import ALPHA, Levels
from .model import CANDIDATES
from .records import Record
from .trials import MIN_RESOLUTION_UNITS


def kind_of(name: str) -> str:
    """``material`` (travels with the material), ``artefact`` (corrected per test) or ``elastic`` (a term)."""
    if name in TERMS:
        return "elastic"
    return "artefact" if name in ARTEFACTS else "material"


@dataclass
class Candidate:
    """The verdict on one candidate (last round it was tried in)."""

    name: str
    kind: str  # "material", "artefact" or "elastic"
    round: int = 0
    variant: str = ""
    delta_aicc: float | None = None
    delta_bic: float | None = None
    dbic_noise: float | None = None
    dchi2: float | None = None
    heldout_nrmse: float | None = None
    heldout_gain: float | None = None
    heldout_z: float | None = None  # the held-out statistic t
    heldout_p: float | None = None  # its one-sided p-value
    heldout_level: float | None = None  # the level it was judged at (search-wide control)
    heldout_p_replication: float | None = None  # the replication check's p-value
    heldout_noise_units: float | None = None
    history_p: float | None = None  # the path-dependent part's one-sided p-value (:mod:`.history`)
    history_share: float | None = None  # the share of the candidate's change that depends on the path
    kept: bool = False
    identifiable: bool = True
    applicable: bool = True
    reason: str = ""
    score: float = 0.0
    gain_chi2: float = 0.0
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "kind": self.kind, "round": self.round, "variant": self.variant,
            "delta_aicc": self.delta_aicc, "delta_bic": self.delta_bic, "dbic_noise": self.dbic_noise,
            "dchi2": self.dchi2, "heldout_nrmse": self.heldout_nrmse, "heldout_gain": self.heldout_gain,
            "heldout_z": self.heldout_z, "heldout_p": self.heldout_p, "heldout_level": self.heldout_level,
            "heldout_p_replication": self.heldout_p_replication,
            "heldout_noise_units": self.heldout_noise_units,
            "history_p": self.history_p, "history_share": self.history_share,
            "kept": self.kept, "identifiable": self.identifiable, "applicable": self.applicable,
            "first_order_share": self.score, "first_order_chi2": self.gain_chi2, "reason": self.reason,
            "params": self.params,
        }


@dataclass(frozen=True)
class Criteria:
    """When a candidate is kept, and when the search stops (see :func:`discover`)."""

    alpha: float = ALPHA
    min_resolution_units: float = MIN_RESOLUTION_UNITS
    max_effects: int = 6


@dataclass
class Search:
    """The state of the greedy search: the current model, the verdicts so far, what was kept."""

    base: Fitted
    current: Fitted
    material: FoldSet  # the folds material effects and terms are judged on
    artefact: FoldSet  # the folds per-file artefacts are judged on
    candidates: dict[str, Candidate]
    testable: list[str]
    crit: Criteria
    kept: list[str] = field(default_factory=list)
    kept_round: dict[str, int] = field(default_factory=dict)
    diagnoses: list[Diagnosis] = field(default_factory=list)
    upgrades: list[str] = field(default_factory=list)
    levels: list[Levels] = field(default_factory=list)  # per round
    #: fits to start from, by spec (the full search's own; an inner selection of :mod:`.nested` reads the
    #: full search's and records nothing)
    warm: dict = field(default_factory=dict)
    record: bool = True

    def remember(self, f: Fitted) -> None:
        """Keep *f* as the warm start of its spec."""
        if self.record:
            self.warm[f.spec] = f


def start_search(start: Fitted, material: FoldSet, artefact: FoldSet, records: list[Record],
                  considered: Sequence[str], crit: Criteria) -> Search:
    """Every candidate, with the reason it is not tried where the data cannot show it."""
    ident = identifiability(records)
    cands: dict[str, Candidate] = {}
    for n in CANDIDATES:
        applicable, ok, why = ident[n]
        c = Candidate(n, kind_of(n), identifiable=ok, applicable=applicable)
        if n not in considered:
            c.reason = "not considered (excluded by the caller)"
        elif not applicable or not ok:
            c.reason = why
        cands[n] = c
    testable = [n for n in considered if ident[n][0] and ident[n][1]]
    return Search(start, start, material, artefact, cands, testable, crit)


