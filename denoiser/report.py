"""Atomic writing of the tables and files produced by evaluation and the benchmark.

* :func:`atomic_write_text` / :func:`atomic_path` - write under a temporary name in the target
  directory, then ``os.replace`` (a crash never leaves a half-written file);
* :func:`write_csv` / :func:`read_csv` - rows as dicts, columns in a given order;
* :func:`markdown_table` - a GitHub Markdown table with per-column number formats.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from denoiser.atomic import atomic_path, atomic_write_text  # noqa: F401  (re-exported)
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


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a CSV written by :func:`write_csv` (numbers parsed, empty cells -> NaN)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: CSV file does not exist")
    with open(path, newline="") as fh:
        return [{k: _parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def format_value(value, fmt: str | None = None) -> str:
    """One table cell: floats with ``fmt`` (default 4 significant digits), NaN as an en dash."""
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        return format(value, fmt or ".4g")
    return "" if value is None else str(value)


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str], formats: Mapping[str, str] | None = None,
                   headers: Mapping[str, str] | None = None) -> str:
    """A Markdown table of ``rows`` with ``columns``; ``formats``: column -> format spec."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    lines = ["| " + " | ".join(headers.get(c, c) for c in columns) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i, _ in enumerate(columns)) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(format_value(r.get(c), formats.get(c)) for c in columns) + " |")
    return "\n".join(lines) + "\n"
