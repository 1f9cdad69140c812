"""Markdown tables from rows of values, e.g. one row per query sequence or ablation variant.

Example:
    >>> rows = [{"seq": "V101", "recall": 0.935, "mATE_m": 0.0491},
    ...         {"seq": "V103", "recall": 0.715, "mATE_m": None}]
    >>> print(markdown_table(rows, [Column("seq", align="left"),
    ...                             Column("recall", "Recall [%]", ".1f", scale=100),
    ...                             Column("mATE_m", "mATE [cm]", ".2f", scale=100)]))
    | seq  | Recall [%] | mATE [cm] |
    | :--- | ---------: | --------: |
    | V101 |       93.5 |      4.91 |
    | V103 |       71.5 |         - |
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

__all__ = ["Column", "markdown_table"]

_RULES = {"left": ":---", "right": "---:", "center": ":---:"}


@dataclass(frozen=True)
class Column:
    """How one column is shown.

    Attributes:
        key: the row key holding the values.
        header: the column title (default: ``key``).
        fmt: a format spec applied to numbers (e.g. ``".1f"``, ``"d"``, ``".2e"``), or a
            callable turning a value into its text. Non-numbers are shown with ``str``.
        scale: numbers are multiplied by this first (e.g. 100 for percent or m -> cm).
        align: ``"left"``, ``"right"`` or ``"center"``.

    Raises:
        ValueError: an unknown alignment or a non-finite scale.
    """

    key: str
    header: str | None = None
    fmt: str | Callable[[object], str] = ""
    scale: float = 1.0
    align: Literal["left", "right", "center"] = "right"

    def __post_init__(self) -> None:
        if self.align not in _RULES:
            raise ValueError(f"align must be one of {sorted(_RULES)}, got {self.align!r}")
        if not math.isfinite(self.scale):
            raise ValueError(f"scale must be finite, got {self.scale}")

    def render(self, value: object, missing: str) -> str:
        """The cell text of ``value`` (``missing`` for None and NaN)."""
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return missing
        if callable(self.fmt):
            return str(self.fmt(value))
        if isinstance(value, numbers.Number) and not isinstance(value, bool):
            if self.scale != 1.0:
                value = value * self.scale
            return format(value, self.fmt)
        return str(value)


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def markdown_table(
    rows: Sequence[Mapping[str, object]],
    columns: Sequence[Column | str] | None = None,
    missing: str = "-",
) -> str:
    """A GitHub-flavoured Markdown table, columns padded to equal width.

    Args:
        rows: one mapping per table row (e.g. ``LocalizationMetrics.to_dict()`` plus a name).
        columns: the columns in order, as :class:`Column` or plain keys; ``None`` takes the
            keys of all rows in first-seen order.
        missing: text of absent keys, ``None`` and NaN values.

    Returns:
        The table text (no trailing newline).

    Raises:
        ValueError: no columns (no ``columns`` and no keys in ``rows``), or a format spec that
            does not apply to a value (the message names the column).

    Example:
        >>> print(markdown_table([{"a": 1, "b": "x"}]))
        |    a |    b |
        | ---: | ---: |
        |    1 |    x |
    """
    if columns is None:
        columns = list(dict.fromkeys(key for row in rows for key in row))
    cols = [Column(c) if isinstance(c, str) else c for c in columns]
    if not cols:
        raise ValueError("markdown_table needs at least one column")
    header = [_escape(c.header if c.header is not None else c.key) for c in cols]
    body = []
    for row in rows:
        cells = []
        for c in cols:
            try:
                cells.append(_escape(c.render(row.get(c.key), missing)))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"column {c.key!r}: cannot format {row.get(c.key)!r}") from exc
        body.append(cells)
    widths = [
        max(len(_RULES[c.align]), len(h), *(len(r[i]) for r in body))
        for i, (c, h) in enumerate(zip(cols, header, strict=True))
    ]

    def line(cells: Sequence[str]) -> str:
        padded = [
            cell.ljust(w)
            if c.align == "left"
            else cell.center(w)
            if c.align == "center"
            else cell.rjust(w)
            for cell, w, c in zip(cells, widths, cols, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rules = []
    for c, w in zip(cols, widths, strict=True):
        rule = _RULES[c.align]
        rules.append(rule[0] + "-" * (w - len(rule)) + rule[1:])
    return "\n".join([line(header), line(rules), *(line(r) for r in body)])
