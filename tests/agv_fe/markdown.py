"""Checks of the benchmark reports' markdown."""

from __future__ import annotations


def tables(text: str) -> list[list[str]]:
    """Every table of a markdown text: its lines, header and rule first."""
    found: list[list[str]] = []
    previous = ""
    for line in text.splitlines():
        if line.startswith("|"):
            if not previous.startswith("|"):
                found.append([])
            found[-1].append(line)
        previous = line
    return found


def assert_rows_match_headers(text: str, at_least: int, rows_required: bool = False) -> None:
    """At least ``at_least`` tables, each with a rule under its header and every row as many cells as the
    header: a stray '|' in a cell (|a_y|, |estimate|) would shift the columns. ``rows_required``: no empty table."""
    found = tables(text)
    assert len(found) >= at_least, len(found)
    for table in found:
        header, rule, *rows = table
        assert set(rule.replace("|", "")) == {"-"}, table[:2]
        assert rows or not rows_required, header
        for row in rows:
            assert row.count("|") == header.count("|"), (header, row)
