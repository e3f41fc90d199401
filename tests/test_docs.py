"""The documentation's rules (DEVELOPERS.md, "Documentation").

* README.md is at most 150 lines; no page under docs/ is over 600 lines;
* no date and no commit hash in README.md, DEVELOPERS.md and docs/: history lives
  in CHANGELOG.md, measurements with their dates in the generated benchmarks/RESULTS.md;
* every relative link in those pages points to a file that exists;
* every ``docs/....md`` path cited in the source of cli/, pipeline/ and configs/ exists;
* benchmarks/RESULTS.md and the README's table are exactly what
  benchmarks/results_md.py renders from the committed JSON (a hand edit fails).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
DOCS = REPO / "docs"
#: The pages written by hand that the rules cover (CHANGELOG.md and RESULTS.md are outside them).
PAGES = [README, REPO / "DEVELOPERS.md", *sorted(DOCS.rglob("*.md"))]
README_MAX_LINES = 150
PAGE_MAX_LINES = 600

_MONTH = r"(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec)[a-z]*\.?"
#: 2026-11-25; 25 Nov 2026; Nov 2026; November 25, 2026.
DATE = re.compile(rf"\b(?:19|20)\d\d-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12]\d|3[01])\b"
                  rf"|\b(?:\d{{1,2}} )?{_MONTH} (?:\d{{1,2}},? )?(?:19|20)\d\d\b")
#: An abbreviated or full commit hash: 7 to 40 hexadecimal digits with a digit and a letter among them.
HASH = re.compile(r"(?<![\w.\-/])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w\-])")
#: [text](target) outside code; images too.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CITED = re.compile(r"\bdocs/[\w./-]+?\.md\b")


def rel(p: Path) -> str:
    return str(p.relative_to(REPO))


def prose(text: str) -> str:
    """*text* without fenced code blocks and inline code spans (their contents are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def results_md():
    """benchmarks/results_md.py as a module (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("esmm_results_md", REPO / "benchmarks" / "results_md.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines; at most {README_MAX_LINES}: move detail to docs/guide/"


@pytest.mark.parametrize("page", sorted(DOCS.rglob("*.md")), ids=rel)
def test_no_page_is_long(page):
    n = len(page.read_text(encoding="utf-8").splitlines())
    assert n <= PAGE_MAX_LINES, f"{rel(page)} has {n} lines; at most {PAGE_MAX_LINES}: split it"


@pytest.mark.parametrize("page", PAGES, ids=rel)
def test_no_history_in_the_pages(page):
    bad = []
    for k, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        bad += [f"line {k}: date {m.group(0)!r}" for m in DATE.finditer(line)]
        bad += [f"line {k}: commit hash {m.group(0)!r}" for m in HASH.finditer(line)]
    assert not bad, (f"{rel(page)}: history belongs in CHANGELOG.md, dated measurements in "
                     f"benchmarks/RESULTS.md (generated): " + "; ".join(bad[:10]))


@pytest.mark.parametrize("page", PAGES, ids=rel)
def test_relative_links_resolve(page):
    missing = []
    for target in LINK.findall(prose(page.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL or an anchor in the same page
        path = target.split("#", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{rel(page)}: links to files that do not exist: {', '.join(missing)}"


SOURCES = sorted(p for top in ("cli", "pipeline", "configs") for p in (REPO / top).rglob("*")
                 if p.suffix in (".py", ".toml"))


def test_doc_paths_cited_in_the_source_exist():
    missing: dict[str, list[str]] = {}
    for src in SOURCES:
        for cited in sorted(set(CITED.findall(src.read_text(encoding="utf-8")))):
            if not (REPO / cited).is_file():
                missing.setdefault(cited, []).append(rel(src))
    assert not missing, "pages cited in the source that do not exist: " + "; ".join(
        f"{cited} (in {', '.join(srcs)})" for cited, srcs in sorted(missing.items()))


def test_generated_results_match_their_json():
    mod = results_md()
    try:
        expected = mod.rendered(REPO)
    except SystemExit as exc:  # the README has lost its markers
        pytest.fail(str(exc))
    stale = [rel(path) for path, text in expected.items()
             if not path.is_file() or path.read_text(encoding="utf-8") != text]
    assert not stale, (f"{', '.join(stale)} differ from what benchmarks/results_md.py renders from "
                       f"benchmarks/results.json and docs/figures/*.json; run `make results` (never edit them by hand)")


def test_results_cite_every_figure_file():
    """The benchmarks and every docs/figures JSON file have their section in RESULTS.md, titled by the stem."""
    text = (REPO / "benchmarks" / "RESULTS.md").read_text(encoding="utf-8")
    titles = set(re.findall(r"^##+ (\S+)$", text, flags=re.M))
    missing = [p.stem for p in [REPO / "benchmarks" / "results.json", *sorted((DOCS / "figures").glob("*.json"))]
               if p.stem not in titles]
    assert not missing, f"benchmarks/RESULTS.md has no section for {', '.join(missing)}"


def test_date_and_hash_patterns_find_what_they_should():
    """The patterns catch the forms the pages used to carry, and leave numbers and names alone."""
    for s in ("measured 2026-11-25", "(2026-11-28, one run)", "Nov 2026", "on 25 November 2026"):
        assert DATE.search(s), s
    for s in ("commit aa87edb", "(main at b206cc2)", "commits before 2e0745a", "dda5b64;"):
        assert HASH.search(s), s
    for s in ("lu_0d05_2d0.csv", "1 024 points", "stretch 1.3612", "sha256=<64 hex digits>", "decade",
              "12000 tets", "esmm.calibrate/1", "0.99996", "fast-simplification", "feedbac"):
        assert not DATE.search(s) and not HASH.search(s), s
