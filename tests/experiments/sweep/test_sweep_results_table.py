"""The sweep's results table (``results.md``): every row, its parameters and main metrics."""

from __future__ import annotations

import pytest

from agsf_torch.experiments.sweep import results_table


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


ROWS = [
    {
        "digest": "aaaa",
        "params": {"reg": 0.1, "filters": ["GSF", "AGSF"]},
        "metrics": {
            "GSF/mean_rms_between_frames_deg": 0.0123456,
            "GSF/time_averaged_nees": 3.14159,
            "AGSF/mean_rms_between_frames_deg": 0.0111,
            "AGSF/time_averaged_nees": 2.9,
            "agsf_minus_gsf_deg": -1.23456e-4,
        },
    },
    {"digest": "bbbb", "params": {"reg": 10}, "metrics": {"GSF/time_averaged_nees": 3.0}},
]


def _table_lines(rows) -> list[str]:
    """The table's lines, without the sentence under it."""
    text = results_table(rows)
    table, note = text.split("\n\n")
    assert note.startswith(
        "RMS: the mean over runs of each run's RMS in the window between frames: every step after the first star frame"
    )
    return table.splitlines()


def test_one_line_per_row_with_params_and_main_metrics():
    lines = _table_lines(ROWS)
    assert len(lines) == 2 + len(ROWS)
    assert _cells(lines[0]) == [
        "config",
        "reg",
        "filters",
        "GSF RMS (deg)",
        "GSF NEES",
        "AGSF RMS (deg)",
        "AGSF NEES",
        "AGSF − GSF (deg)",
    ]
    assert set(lines[1]) <= {"|", "-", " "}
    assert _cells(lines[2]) == ["aaaa", "0.1", '["GSF", "AGSF"]', "0.01235", "3.142", "0.0111", "2.9", "-0.0001235"]
    assert _cells(lines[3]) == ["bbbb", "10", "—", "—", "3", "—", "—", "—"]  # missing values shown as —


def test_columns_are_aligned():
    lines = _table_lines(ROWS)
    assert len({len(line) for line in lines}) == 1
    assert len({tuple(i for i, ch in enumerate(line) if ch == "|") for line in lines}) == 1


def test_no_difference_column_without_the_difference():
    rows = [{"digest": "c", "params": {"seed": 1}, "metrics": {"EKF/time_averaged_nees": 2.5}}]
    header = _cells(_table_lines(rows)[0])
    assert header == ["config", "seed", "EKF RMS (deg)", "EKF NEES"]


def test_pipes_in_values_are_escaped():
    rows = [{"digest": "d", "params": {"name": "a|b"}, "metrics": {}}]
    assert "a\\|b" in results_table(rows)


def test_no_rows():
    assert results_table([]) == "no finished configurations"


@pytest.mark.parametrize("row", [{"digest": "x"}, {"params": {}, "metrics": None}, "text"])
def test_a_malformed_row_is_named(row):
    with pytest.raises(ValueError, match="sweep row 1"):
        results_table([ROWS[0], row])
