"""scripts/toe_forms.py: the Weibull toe follows Weibull-recruited fibre curves that the compact toe misses."""

from __future__ import annotations

import json

from scriptkit import load_script


def test_weibull_toe_fits_weibull_recruitment_the_compact_toe_does_not(tmp_path):
    mod = load_script("toe_forms")
    out = tmp_path / "rows.json"
    assert mod.main(["--draws", "2", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert {r["family"] for r in rows} == {"tendon", "soft tissue"}
    for r in rows:  # the population's law, written apart from esmm: one form follows it to rounding
        assert r["toeweibull"] < 0.01 < r["toe"], r
