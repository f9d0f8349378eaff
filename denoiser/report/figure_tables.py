"""Figure tables of a summary: declared method lists with their metrics, time and ranking lines.

A figure table is declared in YAML (``tables`` of ``conf/compare_summary.yaml``), never in code::

    - title: "Fig. A.2: ..."
      rows:                          # in row order; method: a seed group of the evaluation
        - {method: nppd, label: NPPD}    # (the label of denoiser-eval without _s<k>)
        - {method: student, label: student (ours)}
      rank: student                  # -> "student (ours) ranks above ...; below ..."
      order: {name: baselines, methods: [nppd, ONND, ws]}   # -> "baselines: NPPD > ONND > WS: yes|no"

Each row gives the metrics of ``metrics`` (mean ± std over seeds for a group of several seeds,
:func:`denoiser.report.seed_groups.format_mean_std`) and the group's time at the bench size
(:func:`denoiser.report.seed_groups.group_timing`). The two sentences are computed from the means of
``rank_metric`` (PSNR by default; the direction, higher or lower is better, from
:data:`denoiser.metrics.COLUMNS`). A declared method missing from the evaluation keeps its row,
empty, and is named under the table: a comparison run without ONND still reads as the figure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import pairwise

from denoiser.errors import ConfigError
from denoiser.metrics import COLUMNS
from denoiser.report.seed_groups import format_mean_std, group_timing
from denoiser.tables import markdown_table


def _rows(spec: Mapping) -> list[tuple[str, str]]:
    """``[(method, label)]`` of a table spec, checked."""
    title = spec.get("title")
    if not title or not spec.get("rows"):
        raise ConfigError(f"tables: every table needs a title and rows, got {dict(spec)!r}")
    out = []
    for row in spec["rows"]:
        if not isinstance(row, Mapping) or not row.get("method"):
            raise ConfigError(f"tables '{title}': every row needs a method, got {row!r}")
        out.append((str(row["method"]), str(row.get("label") or row["method"])))
    return out


def _check_metric(metric: str) -> None:
    if metric not in COLUMNS:
        raise ConfigError(f"tables: unknown metric {metric!r} (one of {', '.join(COLUMNS)})")


def figure_table(spec: Mapping, groups: Mapping[str, Mapping], bench: Mapping[str, Mapping],
                 size: tuple[int, int], metrics: Sequence[str]) -> str:
    """The Markdown table of one figure: a row per declared method, in the declared order.

    groups: ``{method: seed group}`` (:func:`denoiser.report.seed_groups.seed_groups` rows by method);
    bench: ``{method: fastest bench row at size (H, W)}``.
    """
    for m in metrics:
        _check_metric(m)
    rows = []
    for method, label in _rows(spec):
        row: dict = {"method": label}
        group = groups.get(method)
        if group is not None:
            row["seeds"] = len(group["seeds"]) or ""
            row.update({m: format_mean_std(group, m, COLUMNS[m].digits) for m in metrics})
            timed = group_timing(group, bench)
            if timed:
                row["ms"] = f"{float(timed['ms_median']):.0f}"
        rows.append(row)
    h, w = size
    return markdown_table(rows, ["method", "seeds", *metrics, "ms"],
                          headers={**{m: COLUMNS[m].header for m in metrics}, "ms": f"ms/frame {w}x{h}"})


def _better(a: float, b: float, metric: str) -> bool:
    return a < b if COLUMNS[metric].lower_is_better else a > b


def rank_line(spec: Mapping, groups: Mapping[str, Mapping], metric: str) -> str | None:
    """``"<label> ranks above A, B; below C (PSNR dB ↑, mean over seeds)"`` for ``spec['rank']``
    against the table's other evaluated methods; None without ``rank``."""
    _check_metric(metric)
    target = spec.get("rank")
    if not target:
        return None
    labels = dict(_rows(spec))
    if target not in labels:
        raise ConfigError(f"tables '{spec['title']}': rank {target!r} is not one of its rows ({', '.join(labels)})")
    how = f"({COLUMNS[metric].header}, mean over seeds)"
    if metric not in groups.get(target, {}):
        return f"{labels[target]}: not evaluated {how}"
    mine = groups[target][metric]
    others = [(labels[m], groups[m][metric]) for m in labels if m != target and metric in groups.get(m, {})]
    above = [label for label, v in others if _better(mine, v, metric)]
    below = [label for label, v in others if _better(v, mine, metric)]
    level = [label for label, v in others if v == mine]
    text = f"{labels[target]} ranks above {', '.join(above) or 'none'}; below {', '.join(below) or 'none'}"
    return text + (f"; level with {', '.join(level)}" if level else "") + f" {how}"


def order_line(spec: Mapping, groups: Mapping[str, Mapping], metric: str) -> str | None:
    """``"baselines: NPPD > ONND > WS: yes"`` (or ``no (measured: ...)``, or ``n/a (not evaluated:
    ...)``) for ``spec['order']``: whether the means of ``metric`` follow the declared order,
    best first; None without ``order``."""
    _check_metric(metric)
    order = spec.get("order")
    if not order:
        return None
    labels = dict(_rows(spec))
    methods = [str(m) for m in order.get("methods", [])]
    unknown = [m for m in methods if m not in labels]
    if len(methods) < 2 or unknown:
        raise ConfigError(f"tables '{spec['title']}': order.methods needs 2+ of its rows ({', '.join(labels)}), "
                          f"got {methods}")
    claim = f"{order.get('name') or 'order'}: {' > '.join(labels[m] for m in methods)}"
    missing = [labels[m] for m in methods if metric not in groups.get(m, {})]
    if missing:
        return f"{claim}: n/a (not evaluated: {', '.join(missing)})"
    values = [groups[m][metric] for m in methods]
    if all(_better(a, b, metric) for a, b in pairwise(values)):
        return f"{claim}: yes ({COLUMNS[metric].header})"
    measured = sorted(methods, key=lambda m: groups[m][metric], reverse=not COLUMNS[metric].lower_is_better)
    return f"{claim}: no (measured: {' > '.join(labels[m] for m in measured)}; {COLUMNS[metric].header})"


def figure_sections(tables: Sequence[Mapping], groups: Sequence[Mapping], bench: Mapping[str, Mapping],
                    size: tuple[int, int], metrics: Sequence[str], rank_metric: str) -> list[str]:
    """Markdown lines of every declared table: a ``##`` title, the table, its missing methods
    and its ranking lines. groups: :func:`denoiser.report.seed_groups.seed_groups`' rows."""
    by_method = {g["method"]: g for g in groups}
    lines: list[str] = []
    for spec in tables:
        rows = _rows(spec)
        lines += [f"## {spec['title']}", "", figure_table(spec, by_method, bench, size, metrics).rstrip(), ""]
        missing = [label for method, label in rows if method not in by_method]
        notes = [f"not evaluated: {', '.join(missing)}" if missing else None,
                 rank_line(spec, by_method, rank_metric), order_line(spec, by_method, rank_metric)]
        notes = [f"- {n}" for n in notes if n]
        lines += [*notes, ""] if notes else []
    return lines
