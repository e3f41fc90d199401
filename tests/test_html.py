"""The HTML report framework (esmm.pipeline.htmlreport): one self-contained file, verdict first, units on
every number, and a page a real browser opens without an error."""

from __future__ import annotations

import re

import pytest
from esmm.pipeline.htmlreport import (
    DIMENSIONLESS,
    Column,
    Document,
    Quantity,
    interval_text,
    quantity_text,
    readable_unit,
)
from htmlkit import browser_or_skip, check_page


def _page() -> Document:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    doc = Document("A report <with> markup & quotes \"", producer="esmm test", subtitle="two files")
    doc.section("Numbers")
    doc.table([Column("parameter"), Column("value"), Column("R²", unit=DIMENSIONLESS),
               Column("RMSE", unit="kPa", scale=1e3)],
              [["mu", Quantity(0.6663, "Pa"), 0.93, 1234.0], ["N", Quantity(26.0, DIMENSIONLESS), 0.5, None]])
    doc.text("<script>alert(1)</script> is shown as text")
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([1, 2, 3], [1, 4, 9])
    doc.figure(fig, alt="a parabola", caption="data")
    plt.close(fig)
    svg = ('<svg xmlns="http://www.w3.org/2000/svg" width="40" height="20">'
           '<rect width="40" height="20" fill="teal"/></svg>')
    doc.figure(svg, alt="a teal box")
    doc.section("Details", collapsed=True)
    doc.items(["one", "two"])
    doc.verdict("poor", "Usable with care.", reasons=["a reason"], advice=["do this"])
    return doc


def test_readable_units_per_quantity():
    assert readable_unit([6.66e-7 * 1e6], "Pa") == ("Pa", 1.0)           # the "mu 6.66e-07 MPa"
    assert readable_unit([1.29e8], "Pa") == ("MPa", 1e6)
    assert readable_unit([2.3e-4], "Pa") == ("Pa", 1.0)
    assert readable_unit([2.3e-4], "N") == ("µN", 1e-6)
    assert readable_unit([0.0123], "N") == ("mN", 1e-3)
    assert readable_unit([0.03], "m") == ("mm", 1e-3)
    assert quantity_text(0.6663, "Pa") == "0.6663 Pa"
    assert quantity_text(0.6663, DIMENSIONLESS) == "0.6663 (dimensionless)"
    assert quantity_text(0.125, "%") == "12.5 %"
    assert interval_text(1.2e7, 1.386e9, "Pa") == "[0.012, 1.386] GPa"
    assert interval_text(0.0, float("inf"), "Pa") == "[0, ∞] Pa"
    assert interval_text(None, None, "Pa") == "unbounded"


def test_a_number_without_a_unit_is_refused():
    doc = Document("t")
    doc.verdict("info", "x")
    with pytest.raises(ValueError, match="declares no unit"):
        doc.table([Column("value")], [[1.5]])
    with pytest.raises(ValueError, match="3 cells for 2 columns"):
        doc.table([Column("a"), Column("b", unit="Pa")], [["x", 1.0, 2.0]])


def test_the_verdict_comes_first_and_is_required():
    doc = Document("t")
    doc.text("body")
    with pytest.raises(ValueError, match="verdict first"):
        doc.render()
    with pytest.raises(ValueError, match="use one of"):
        doc.verdict("ok", "x")
    with pytest.raises(ValueError, match="alt text"):
        doc.figure(b"\x89PNG\r\n\x1a\n", alt=" ")
    text = _page().render()
    body = text.split("<body>", 1)[1]
    assert body.index('class="verdict poor"') < body.index("<h2>Numbers</h2>")


def test_one_self_contained_file(tmp_path):
    text = _page().render()
    # nothing outside the page: every src is a data: URI, no href, no script, no stylesheet link
    assert re.findall(r'src="(?!data:)', text) == []
    assert "href=" not in text and "<script" not in text and "<link" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    assert "0.6663 Pa" in text and "26 (dimensionless)" in text and "RMSE [kPa]" in text and "1.234" in text
    path = _page().write(tmp_path / "r.html")
    assert path.read_text(encoding="utf-8") == text


def test_the_browser_checker_sees_errors(tmp_path):
    """The check below would pass on anything if the checker saw nothing: a page with a script error, a
    console error and a missing image must show all three."""
    browser = browser_or_skip()
    bad = tmp_path / "bad.html"
    bad.write_text('<html><body><img src="missing.png" alt="x"><script>console.error("boom");'
                   "undefined_function();</script></body></html>", encoding="utf-8")
    page = check_page(bad, browser=browser)
    assert any("undefined_function" in e for e in page.exceptions)
    assert any("boom" in c for c in page.console)
    assert any("did not load" in p for p in page.problems)


def test_a_report_opens_in_a_browser_without_error(tmp_path):
    browser = browser_or_skip()
    path = _page().write(tmp_path / "report.html")
    page = check_page(path, browser=browser)
    assert page.problems == []
    assert len(page.images) == 2
    assert page.text.index("POOR") < page.text.index("Numbers")
