"""Tables of results: Markdown (:func:`markdown_table`, :func:`format_value`) and CSV
(:func:`write_csv` / :func:`read_csv`: NaN as an empty cell, numbers parsed back), written atomically.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

from denoiser.atomic import atomic_write_text
from denoiser.errors import UserError


def _cell(value) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return "" if value is None else str(value)


def write_csv(path: str | os.PathLike, rows: Sequence[Mapping], columns: Sequence[str] | None = None) -> Path:
    """Write ``rows`` (dicts) as CSV with ``columns`` (default: keys in first-seen order); NaN -> empty."""
    if columns is None:
        columns = []
        for r in rows:
            columns.extend(k for k in r if k not in columns)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for r in rows:
        writer.writerow([_cell(r.get(c)) for c in columns])
    return atomic_write_text(path, buf.getvalue())


def _parse(value: str):
    if value == "":
        return float("nan")
    try:
        return int(value)
    except ValueError:
        pass
    try:
        return float(value)
    except ValueError:
        return value


#: columns that name things, read back as written: a user's sequence ``0001`` or a commit ``0496959``
#: is not the number 1 or 496959 (nor ``12e4567`` infinity)
IDENTIFIERS = ("commit", "sequence", "scene", "method", "split")


def read_csv(path: str | os.PathLike, text: Collection[str] = IDENTIFIERS) -> list[dict]:
    """Rows of a CSV written by :func:`write_csv` (numbers parsed, empty cells -> NaN); the
    columns in ``text`` are kept as written, never parsed (default :data:`IDENTIFIERS`)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: CSV file does not exist")
    with open(path, newline="") as fh:
        return [{k: v if k in text else _parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def format_value(value, fmt: str | None = None) -> str:
    """One table cell: floats with ``fmt`` (default 4 significant digits), NaN as an en dash."""
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        return format(value, fmt or ".4g")
    return "" if value is None else str(value)


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str], formats: Mapping[str, str] | None = None,
                   headers: Mapping[str, str] | None = None, align: bool = False) -> str:
    """A Markdown table of ``rows`` (dicts) with ``columns``: the first column left-aligned, the
    others right-aligned. ``formats``: column -> format spec for floats (:func:`format_value`;
    strings are written as they are); ``headers``: column -> title; ``align``: pad every column
    to its widest cell, so the table also reads well as plain text (console output)."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    lines = [[headers.get(c, c) for c in columns]]
    lines += [[format_value(r.get(c), formats.get(c)) for c in columns] for r in rows]
    widths = [max(3, *(len(line[i]) for line in lines)) if align else 0 for i in range(len(columns))]
    rule = ["-" * max(3, w + 2) if i == 0 else "-" * max(3, w + 1) + ":" for i, w in enumerate(widths)]
    cells = [[c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(line, widths))] for line in lines]
    text = ["| " + " | ".join(cells[0]) + " |", "|" + "|".join(rule) + "|"]
    text += ["| " + " | ".join(line) + " |" for line in cells[1:]]
    return "\n".join(text) + "\n"
