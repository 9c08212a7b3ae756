"""The user documentation stays a front page and a set of pages a user can read: the README
within 200 lines, no page over 60 kB, no project history (stops, issues) in the docs or the
code (it belongs in CHANGELOG.md, docs/decisions/ and the commit log), the seed's concepts
table naming real functions whose docstrings cite the paper, every relative link resolving,
and every documented snippet marked so that tests/integration/test_doc_snippets.py runs it."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

from tests.docs_snippets import snippets

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
HISTORY = re.compile(r"\b(stop|issue)s? [0-9]+", re.I)
CODE_DIRS = ("service", "schemas", "clients", "sim_publisher", "bench", "tests")


def _pages() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]


def test_the_readme_is_a_front_page() -> None:
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 200, len(lines)


def test_no_page_is_over_60_kb() -> None:
    big = {p.relative_to(REPO): p.stat().st_size for p in _pages() if p.stat().st_size > 60_000}
    assert not big, big


def test_no_history_in_the_docs_or_the_code() -> None:
    found = []
    files = [p for p in _pages() if "decisions" not in p.parts]
    files += [p for d in CODE_DIRS for p in (REPO / d).rglob("*.py")]
    for path in files:
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                found.append(f"{path.relative_to(REPO)}:{n}: {line.strip()[:100]}")
    assert not found, "\n".join(found[:40]) + f"\n({len(found)} lines)"


def _seed_table() -> list[tuple[str, str]]:
    text = (DOCS / "architecture.md").read_text()
    section = text.split("### The seed's concepts, one place each", 1)[1].split("\n#", 1)[0]
    return re.findall(r"^\| ([^|]+?) \| `(service\.core\.[\w.]+)` \|$", section, re.M)


def test_the_seed_table_names_real_functions_that_cite_the_paper() -> None:
    rows = _seed_table()
    assert len(rows) >= 12, rows
    for concept, dotted in rows:
        module, name = dotted.rsplit(".", 1)
        fn = getattr(importlib.import_module(module), name)
        doc = fn.__doc__ or ""
        cites = re.findall(r"(§\s?[0-9.]+|eq\.\s?[0-9]+)", concept)
        assert cites, f"the row of {dotted} cites no section or equation"
        for cite in cites:
            number = re.sub(r"[^0-9.]", "", cite).strip(".")
            assert number in doc, f"{dotted}'s docstring does not cite {cite}"


def test_relative_links_resolve() -> None:
    broken = []
    for page in _pages():
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)} -> {target}")
    assert not broken, broken


def test_the_robot_snippets_are_marked_for_the_tests() -> None:
    found = snippets()
    assert {"robot", "client"} <= set(found), sorted(found)
    assert found["robot"][0].name == "README.md"
