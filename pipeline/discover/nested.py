"""Nested held-out errors (placeholder while the search is reworked)."""

from __future__ import annotations


def nested_heldout(result, search, candidates, criteria, rep):
    return None
