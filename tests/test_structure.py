"""The shape of the source, enforced: short functions, small classes, docstrings without history.

Checked from the source text (nothing is imported or run):

* every function fits on a screen (at most :data:`MAX_FUNCTION_LINES` lines, from
  its ``def`` to its last line) and every class does one job (fewer than
  :data:`MAX_CLASS_LINES` lines), in cli/, pipeline/, benchmarks/, scripts/ and tests/;
* the docstrings and comments of cli/ and pipeline/ say what and why, not what
  happened on a day: no date (YYYY-MM-DD) and no commit hash;
* a repository path a docstring cites (docs/..., pipeline/..., tests/..., ...)
  exists, so that a reader who follows it finds the file.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
#: The folders whose functions and classes are measured.
CODE_ROOTS = ("cli", "pipeline", "benchmarks", "scripts", "tests")
#: The folders whose docstrings and comments must carry no date or commit hash.
HISTORY_ROOTS = ("cli", "pipeline")
MAX_FUNCTION_LINES = 80
MAX_CLASS_LINES = 300

#: A calendar date, as a log or a changelog writes it.
DATE = re.compile(r"\b(?:19|20)\d\d-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12]\d|3[01])\b")
#: 7 to 40 hexadecimal digits standing alone, with at least one digit and one letter (a commit hash;
#: a word such as "defaced" has no digit, a number such as 1234567 no letter).
HEX = re.compile(r"(?<![\w.])(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w])")
#: A path inside the repository, as a docstring cites it.
PATH = re.compile(r"(?<![\w./~-])(?:docs|pipeline|tests|benchmarks|scripts|cli|configs|data)/[\w./-]*[\w/]")


def _files(roots) -> list[Path]:
    return sorted(p for r in roots for p in (REPO / r).rglob("*.py") if ".venv" not in p.parts)


def _rel(p: Path) -> str:
    return p.relative_to(REPO).as_posix()


def _tree(p: Path) -> ast.Module:
    return ast.parse(p.read_text(encoding="utf-8"), filename=str(p))


def docstrings(tree: ast.Module) -> Iterator[tuple[int, str]]:
    """(first line, text) of the docstring of the module and of every class and function."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                yield body[0].lineno, body[0].value.value


def comments(text: str) -> Iterator[tuple[int, str]]:
    """(line, text) of every comment."""
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string


def long_definitions(tree: ast.Module) -> Iterator[tuple[str, int, int]]:
    """(kind and name, line, length) of every function longer than allowed and every class as long or longer."""
    for node in ast.walk(tree):
        length = (node.end_lineno or node.lineno) - node.lineno + 1 if hasattr(node, "lineno") else 0
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and length > MAX_FUNCTION_LINES:
            yield f"function {node.name}", node.lineno, length
        elif isinstance(node, ast.ClassDef) and length >= MAX_CLASS_LINES:
            yield f"class {node.name}", node.lineno, length


def history_marks(text: str) -> list[str]:
    """The dates and commit hashes in *text* (a docstring or a comment)."""
    found = DATE.findall(text)
    for token in HEX.findall(text):
        try:
            float(token)          # 1234e56: a number written in exponent form, not a hash
        except ValueError:
            found.append(token)
    return found


def missing_paths(text: str) -> list[str]:
    """The repository paths cited in *text* that do not exist (patterns such as ``test_*.py`` or
    ``docs/....md`` aside)."""
    out = []
    for m in PATH.finditer(text):
        if text[m.end():m.end() + 1] in ("*", "{", "<", "[") or "..." in m.group(0):
            continue
        path = m.group(0).rstrip("./")
        if not (REPO / path).exists():
            out.append(path)
    return out


def test_the_checks_see_what_they_must():
    src = ('def f():\n    """Since 2026-11-27 (commit 689fbfe); see docs/no-such-page.md."""\n'
           + "    x = 1\n" * MAX_FUNCTION_LINES)
    tree = ast.parse(src)
    assert [k for k, _, _ in long_definitions(tree)] == ["function f"]
    (_, doc), = docstrings(tree)
    assert history_marks(doc) == ["2026-11-27", "689fbfe"]
    assert missing_paths(doc) == ["docs/no-such-page.md"]
    assert history_marks("a constant 0.0149231e6, the word 'defaced', the number 12345678, sha256") == []
    assert missing_paths("pipeline/prepare.py, tests/test_simulate*.py, ../shared/data/x.stl, docs/guide/{a,b}.md, "
                         "every docs/....md") == []
    assert list(long_definitions(ast.parse("def g():\n    return 1\n"))) == []


@pytest.mark.parametrize("path", _files(CODE_ROOTS), ids=_rel)
def test_functions_fit_on_a_screen_and_classes_do_one_job(path):
    bad = [f"{_rel(path)}:{line}: {what} is {n} lines" for what, line, n in long_definitions(_tree(path))]
    assert not bad, (f"split into named steps (functions <= {MAX_FUNCTION_LINES} lines, classes < "
                     f"{MAX_CLASS_LINES}):\n" + "\n".join(bad))


@pytest.mark.parametrize("path", _files(HISTORY_ROOTS), ids=_rel)
def test_docstrings_and_comments_carry_no_dates_or_commit_hashes(path):
    text = path.read_text(encoding="utf-8")
    pieces = list(docstrings(_tree(path))) + list(comments(text))
    bad = [f"{_rel(path)}:{line}: {mark}" for line, piece in pieces for mark in history_marks(piece)]
    assert not bad, "say what and why, not when (history goes to CHANGELOG.md):\n" + "\n".join(bad)


@pytest.mark.parametrize("path", _files(CODE_ROOTS), ids=_rel)
def test_docstrings_cite_files_that_exist(path):
    bad = [f"{_rel(path)}:{line}: {p}" for line, doc in docstrings(_tree(path)) for p in missing_paths(doc)]
    assert not bad, "docstrings cite repository files that do not exist:\n" + "\n".join(bad)
