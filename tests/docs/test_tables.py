"""Every Markdown table of the documentation and the README has body rows, each with its header's cell count.

A ``|`` inside a cell (``w_{k|k}``, even in a code span) ends the cell in GitHub-flavoured Markdown and in
MyST unless escaped as ``\\|``; a row with the wrong count renders shifted or cut, and a table whose rows
were replaced by another table's (three cells under a five-cell header) shows the wrong numbers under the
right header.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]
_DELIMITER = re.compile(r"^\|(\s*:?-+:?\s*\|)+\s*$")


def cells(row: str) -> int:
    """Cells of a table row ``| a | b |``, escaped pipes ``\\|`` not counted as separators."""
    return row.strip().replace("\\|", "").count("|") - 1


def table_rows(text: str) -> list[tuple[int, int, int]]:
    """``(line, cells, header cells)`` of every body row of every table (a header line followed by a
    delimiter line ``| --- | --- |``), lines counted from 1."""
    lines = text.splitlines()
    rows = []
    for i in range(len(lines) - 1):
        if lines[i].startswith("|") and _DELIMITER.match(lines[i + 1].strip()):
            header = cells(lines[i])
            j = i + 2
            while j < len(lines) and lines[j].startswith("|"):
                rows.append((j + 1, cells(lines[j]), header))
                j += 1
    return rows


def test_cells_counts_escaped_pipes_as_text():
    assert cells("| a | w_{k\\|k} | b |") == 3
    assert cells("| a | w_{k|k} | b |") == 4


def test_table_rows_finds_a_short_row():
    text = "| a | b | c |\n| --- | --- | --- |\n| 1 | 2 | 3 |\n| 1 | 2 |\n\nprose | with a pipe\n"
    assert table_rows(text) == [(3, 3, 3), (4, 2, 3)]


def headers_without_rows(text: str) -> list[int]:
    """Lines (from 1) of the tables that have a header and a delimiter but no body row."""
    lines = text.splitlines() + [""]
    return [
        i + 1
        for i in range(len(lines) - 2)
        if lines[i].startswith("|") and _DELIMITER.match(lines[i + 1].strip()) and not lines[i + 2].startswith("|")
    ]


def test_headers_without_rows_finds_an_empty_table():
    assert headers_without_rows("| a | b |\n| --- | --- |\n\ntext\n| c |\n| --- |\n| 1 |\n") == [1]


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_table_has_rows(path):
    empty = headers_without_rows(path.read_text())
    assert not empty, f"{path.relative_to(ROOT)}: tables without rows at lines {empty}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_row_has_the_header_cell_count(path):
    wrong = [f"line {line}: {n} cells, header {h}" for line, n, h in table_rows(path.read_text()) if n != h]
    assert not wrong, f"{path.relative_to(ROOT)}: " + "; ".join(wrong)
