"""Every table of measurements in the README, the benchmarks' README and the docs names
the commit it was measured at; a table that is no measurement says so."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STAMP = re.compile(r"Measured at commit [0-9a-f]{7,40} on \d{4}-\d{2}-\d{2}")
EXEMPT = "<!-- not a measurement -->"


def documents():
    yield ROOT / "README.md"
    yield ROOT / "benchmarks" / "README.md"
    for suffix in ("*.md", "*.rst"):
        for path in sorted((ROOT / "docs").rglob(suffix)):
            if "_build" not in path.parts and "generated" not in path.parts[-2]:
                yield path


def unstamped(text):
    """Line numbers (1-based) of tables without a stamp or the exemption among the six
    non-blank lines above them."""
    lines = text.splitlines()
    out = []
    for i, line in enumerate(lines):
        starts = (line.startswith("|") and i + 1 < len(lines)
                  and lines[i + 1].startswith("|---") and (i == 0 or not lines[i - 1]
                                                           .startswith("|")))
        if not starts:
            continue
        above = [s for s in lines[:i] if s.strip()][-6:]
        if not any(STAMP.search(s) or EXEMPT in s for s in above):
            out.append(i + 1)
    return out


@pytest.mark.parametrize("path", list(documents()), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_table_names_its_commit(path):
    missing = unstamped(path.read_text())
    assert not missing, (f"{path.relative_to(ROOT)}: tables at lines {missing} name no commit; "
                         "put 'Measured at commit <hash> on <date>, <machine>.' above each, "
                         f"or '{EXEMPT}' above a table that is no measurement")


def test_the_check_finds_an_unstamped_table():
    table = "| a | b |\n|---|---|\n| 1 | 2 |\n"
    assert unstamped("Some text.\n\n" + table) == [3]
    assert unstamped("Measured at commit abc1234 on 2026-11-28, a laptop.\n\n" + table) == []
    assert unstamped(EXEMPT + "\n\n" + table) == []
    assert unstamped("Measured at commit abc1234 on 2026-11-28.\n" + "x\n" * 7 + table) == [9]


def test_every_public_name_has_an_api_page():
    """docs/api.rst lists every name that a public namespace exports (autosummary makes
    a page of each)."""
    import importlib

    text = (ROOT / "docs" / "api.rst").read_text()
    listed = {}
    module = None
    for line in text.splitlines():
        if line.startswith(".. currentmodule::"):
            module = line.split("::")[1].strip()
        elif line.startswith("   ") and line.strip().isidentifier() and module:
            listed.setdefault(module, set()).add(line.strip())
    names = {}
    for name in ("latentsindy", "latentsindy.results", "latentsindy.options",
                 "latentsindy.systems", "latentsindy.generators", "latentsindy.celegans",
                 "latentsindy.baselines"):
        public = set(importlib.import_module(name).__all__) - {"__version__"}
        namespaces = {n for n in public if n in {"results", "options", "systems",
                                                  "generators", "celegans", "baselines"}}
        documented = listed.get(name, set())
        if name == "latentsindy.generators":  # its options are documented under options
            documented |= listed.get("latentsindy.options", set())
        if name == "latentsindy.results":  # the main result types under the top level
            documented |= listed.get("latentsindy", set())
        names[name] = sorted(public - namespaces - documented)
    assert all(not missing for missing in names.values()), names
