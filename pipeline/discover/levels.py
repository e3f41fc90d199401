r"""Search-wide false-positive control: the level at which each held-out test is judged.

A discovery tries many candidates (every effect, artefact and strain-energy
term the data can identify), their richer variants and pairs, over several
rounds; each is judged by a held-out test with a one-sided p-value
(:func:`~esmm.pipeline.discover.statistics.heldout_test`). Taken each at 5 %,
the search as a whole would add something to a clean record far more often
than 5 %. The levels here bound that probability.

**Round r** (r = 1, 2, ...) spends α_r = α 2^{-r}, so Σ_r α_r ≤ α. Within a
round, every hypothesis that *could* be tested counts, whether or not the
pre-screen lets it through (the pre-screen sees the same data, so the family
is fixed before it): the m_s single candidates still open (and the richer
variants of kept effects), and, when two more effects are allowed, the m_p
pairs of effects and artefacts that could be formed from them and the pairs of
a strain-energy term and one of them. Singles get
α_r/2 and pairs α_r/2 (all of α_r to singles when no pair can be tried), each
split equally (Bonferroni): a single is kept at p ≤ α_r/(2 m_s), a pair at
p ≤ α_r/(2 m_p). By the union bound, on a record where the current model is
right (nothing left to find) the probability that round r adds anything is at
most α_r, and that the search adds anything at most α. On a clean record the
search stops after round 1 unless something is (falsely) kept there, so the
bound there is α_1 = α/2.

The bound needs each p-value to be valid: the held-out statistic's variance
counts the serial correlation of the loss differences (its assumptions:
docs/design/discovery.md, "The held-out test, and its assumptions"). Its
rate on clean records is measured on an independent population
(benchmarks/bench_discover_population.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: the probability that a discovery adds anything (effect, artefact or term) to records it already explains
ALPHA = 0.05


@dataclass(frozen=True)
class Levels:
    """The levels of one round: α_r split between its m_s single candidates and its m_p pairs."""

    alpha: float
    round: int
    singles: int
    pairs: int

    @property
    def round_alpha(self) -> float:
        """α_r = α 2^{-r}."""
        return self.alpha * 2.0 ** (-self.round)

    @property
    def single(self) -> float:
        """The level of one single candidate (or variant upgrade)."""
        share = self.round_alpha / 2.0 if self.pairs else self.round_alpha
        return share / max(self.singles, 1)

    @property
    def pair(self) -> float:
        """The level of one pair (0 when no pair can be tried)."""
        return self.round_alpha / 2.0 / self.pairs if self.pairs else 0.0

    def to_dict(self) -> dict[str, float | int]:
        return {"round": self.round, "alpha_round": self.round_alpha, "singles": self.singles,
                "pairs": self.pairs, "level_single": self.single, "level_pair": self.pair}


def round_levels(alpha: float, rnd: int, singles: int, pair_pool: int, term_pairs: int = 0) -> Levels:
    """The levels of round *rnd* with *singles* hypotheses, the pairs formed from *pair_pool* candidates and
    *term_pairs* pairs of a strain-energy term and an effect or artefact."""
    pairs = (math.comb(pair_pool, 2) if pair_pool >= 2 else 0) + max(term_pairs, 0)
    return Levels(alpha, rnd, singles, pairs)


__all__ = ["ALPHA", "Levels", "round_levels"]
