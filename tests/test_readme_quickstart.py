"""The README's quick start runs as written and prints what the README says it prints.

The code block under "## Quick start" is run in a temporary folder; the summary that
``print(result)`` writes is held, line by line, to the commented lines after it (the
text exactly, every number to 2%, or to its order of magnitude below 1e-4; a
commented ``...`` stands for lines the README leaves out). The quick start guide in
the docs shows the same summary.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
RTOL = 0.02
TINY = 1e-4  # below this, a number is held to its order of magnitude


def _quick_start(path):
    text = path.read_text()
    section = text.split("## Quick start", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def _expected(code):
    """The commented summary lines right after ``print(result)``."""
    lines = code.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("print(result)"))
    out = []
    for line in lines[at + 1:]:
        if not line.startswith("# ") or line.startswith("# the truth"):
            break
        out.append(line[2:])
    return out


def _matches(expected, printed):
    """``(True, None, None)`` where the printed lines match the expected ones (``...``
    skips any lines up to the next expected one), else ``(False, expected line,
    printed line)`` at the first mismatch (None: none left)."""
    i, skipping = 0, False
    for want in expected:
        if want.strip() == "...":
            skipping = True
            continue
        while skipping and i < len(printed) and not _same(want, printed[i]):
            i += 1
        if i == len(printed) or not _same(want, printed[i]):
            return False, want, printed[i] if i < len(printed) else None
        i, skipping = i + 1, False
    if i < len(printed) and not skipping:
        return False, None, printed[i]
    return True, None, None


def _same(want, got):
    if _NUMBER.sub("#", want) != _NUMBER.sub("#", got):
        return False
    a = np.array([float(x) for x in _NUMBER.findall(want)])
    b = np.array([float(x) for x in _NUMBER.findall(got)])
    # numbers at the noise-free data's numerical floor (a standard error of 1e-8, a
    # misfit of 3e-6) move with the BLAS and the build: held to their order of magnitude
    tiny = np.maximum(np.abs(a), np.abs(b)) < TINY
    close = np.isclose(a, b, rtol=RTOL, atol=0.0)
    order = (np.sign(a) == np.sign(b)) & (np.abs(np.log10(np.abs(a) + 1e-300)
                                                - np.log10(np.abs(b) + 1e-300)) < 1.0)
    return bool(np.all(np.where(tiny, order, close)))


def test_the_quick_start_prints_what_the_readme_shows(tmp_path, monkeypatch):
    code = _quick_start(ROOT / "README.md")
    expected = _expected(code)
    assert len(expected) >= 8, "the README's quick start shows no summary after print(result)"
    monkeypatch.chdir(tmp_path)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        exec(compile(code, "README.md quick start", "exec"), {})
    printed = stdout.getvalue().splitlines()
    ok, want, got = _matches(expected, printed)
    assert ok, f"README quick start: expected a line like {want!r}, printed {got!r}"
    assert (tmp_path / "lv.npz").exists()


def test_the_quickstart_guide_shows_the_readme_summary():
    readme = _expected(_quick_start(ROOT / "README.md"))
    guide_text = (ROOT / "docs" / "guide" / "quickstart.md").read_text()
    guide = _expected(guide_text.split("```python\n", 1)[1].split("```", 1)[0])
    assert guide == readme


def test_the_comparison_tells_numbers_and_text_apart():
    assert _same("misfit 0.001518 -> 3.181e-06", "misfit 0.00152 -> 3.18e-06")
    assert not _same("misfit 0.001518 -> 3.181e-06", "misfit 0.001094 -> 3.183e-06")
    assert _same("score 2.653e-05 +- 6.7e-06", "score 4.1e-05 +- 5.2e-06")  # numerical floor
    assert not _same("score 2.653e-05 +- 6.7e-06", "score 2.653e-04 +- 6.7e-06")
    assert not _same("x: -0.0750004 +- 1.3e-08", "x: 0.0750004 +- 1.3e-08")
    assert not _same("dx/dt = 1.0*h*x", "dx/dt = 1.0*h*y")
    assert _matches(["a 1", "...", "c 3"], ["a 1", "b 2", "c 3"])[0]
    assert not _matches(["a 1", "c 3"], ["a 1", "b 2", "c 3"])[0]
    assert not _matches(["a 1", "c 3"], ["a 1", "c 3", "d 4"])[0]
