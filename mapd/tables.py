"""Tables and JSON for what the report commands print (``mapd bench ...``, ``mapd demo``).

Rows are dicts; a table's columns are ``(key, title, format spec)`` triples. :func:`table` renders
aligned plain text for the terminal, :func:`md_table` Markdown for report files, and
:func:`dump_json` JSON that any reader takes (inf and nan as strings). :func:`emit` is the one
ending of a report command: JSON with ``--json``, else its text.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from typing import Any

#: ``(key, title, format spec)``: the row key shown, its column title, how its values are formatted.
Column = tuple[str, str, str]


def fmt(v: Any, spec: str = "") -> str:
    """One cell: floats by ``spec`` (default ``.3g``), inf as ``inf``, nan as ``-``, others as str()."""
    if isinstance(v, float):
        if math.isinf(v):
            return "inf"
        if math.isnan(v):
            return "-"
        return format(v, spec or ".3g")
    return str(v)


def table(rows: Sequence[dict[str, Any]], columns: Sequence[Column]) -> str:
    """Rows as an aligned text table: the first column left-aligned, the others right-aligned."""
    cells = [[title for _, title, _ in columns]]
    for r in rows:
        cells.append([fmt(r.get(k, ""), spec) for k, _, spec in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = []
    for n, row in enumerate(cells):
        parts = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        lines.append("  ".join(parts))
        if n == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def md_table(rows: Sequence[dict[str, Any]], columns: Sequence[Column]) -> str:
    """Rows as a Markdown table: numbers right-aligned, text (and yes/no) left-aligned."""
    head = "| " + " | ".join(t for _, t, _ in columns) + " |"
    numeric = [
        all(isinstance(r.get(k), int | float) and not isinstance(r.get(k), bool) for r in rows)
        for k, _, _ in columns
    ]
    align = "|" + "|".join("---:" if n else "---" for n in numeric) + "|"
    body = ["| " + " | ".join(fmt(r.get(k, ""), s) for k, _, s in columns) + " |" for r in rows]
    return "\n".join([head, align, *body])


def dump_json(obj: Any) -> str:
    """JSON with inf/nan written as strings, so any JSON reader takes it."""

    def clean(x: Any) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            return str(x)
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(obj), indent=2)


def emit(doc: Any, as_json: bool, text: Callable[[], str]) -> None:
    """Print ``doc`` as JSON (:func:`dump_json`) when ``as_json``, else what ``text()`` renders.

    ``text`` is called only when needed, so a command builds its tables only for the terminal.
    """
    print(dump_json(doc) if as_json else text())
