"""Markdown tables: known output, alignment, formatting, missing values and bad input."""

from __future__ import annotations

import math

import pytest

from diffloc.eval.tables import Column, markdown_table


def test_known_table() -> None:
    rows = [
        {"seq": "V101", "recall": 0.935, "mATE_m": 0.0491, "n": 120},
        {"seq": "V103", "recall": 0.715, "mATE_m": None},
        {"seq": "a|b", "recall": math.nan, "mATE_m": 0.1},
    ]
    text = markdown_table(
        rows,
        [
            Column("seq", align="left"),
            Column("recall", "Recall [%]", ".1f", scale=100),
            Column("mATE_m", "mATE [cm]", ".2f", scale=100, align="center"),
            Column("n", "queries", "d"),
        ],
    )
    assert text == (
        "| seq  | Recall [%] | mATE [cm] | queries |\n"
        "| :--- | ---------: | :-------: | ------: |\n"
        "| V101 |       93.5 |    4.91   |     120 |\n"
        "| V103 |       71.5 |     -     |       - |\n"
        "| a\\|b |          - |   10.00   |       - |"
    )


def test_default_columns_callable_format_and_bools() -> None:
    rows = [{"name": "full", "ok": True}, {"name": "naive", "extra": 1.5}]
    text = markdown_table(rows, missing="n/a")
    lines = text.splitlines()
    assert lines[0] == "|  name |   ok | extra |"
    assert lines[2] == "|  full | True |   n/a |"
    assert lines[3] == "| naive |  n/a |   1.5 |"
    text = markdown_table(rows, [Column("name", fmt=str.upper)])
    assert text.splitlines()[2:] == ["|  FULL |", "| NAIVE |"]
    # Every line has the same length (padded columns).
    assert len({len(line) for line in text.splitlines()}) == 1


def test_no_rows_gives_header_only() -> None:
    assert markdown_table([], ["a"]) == "|    a |\n| ---: |"


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="at least one column"):
        markdown_table([])
    with pytest.raises(ValueError, match="align"):
        Column("a", align="middle")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="scale"):
        Column("a", scale=math.inf)
    with pytest.raises(ValueError, match="column 'a'"):
        markdown_table([{"a": 1.5}], [Column("a", fmt="d")])
