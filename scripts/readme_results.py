#!/usr/bin/env python3
"""Copy a generated table (and pictures) into ``README.md``: ``make readme`` (the demo's
``reports/demo/summary.md``) and ``make readme`` (``reports/pareto/pareto.md`` and its plot).

The table is the block between ``<!-- <marker>:begin -->`` and ``<!-- <marker>:end -->`` in both
files; the README's block is replaced, with a line naming the source file and the run id and
commit it states (``scripts/readme_check.py`` reads that commit: ``make readme-check``). Where
the README has no block yet, the paragraph holding ``<!-- <marker>:pending -->`` is replaced by it.
``--image SRC:DST`` copies a picture (e.g. to ``docs/images/``) and shows it in the block. Figures
in the README are therefore never typed by hand.

    python scripts/readme_results.py [--summary reports/demo/summary.md] [--readme README.md]
    python scripts/readme_results.py --summary reports/pareto/pareto.md --marker pareto \\
        --image reports/pareto/accuracy_vs_time.png:docs/images/pareto.png
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sys
from pathlib import Path


def block(text: str, where: str, marker: str) -> tuple[int, int]:
    begin, end_mark = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    start, end = text.find(begin), text.find(end_mark)
    if start < 0 or end < start:
        sys.exit(f"error: {where}: no {begin} ... {end_mark} block")
    return start, end + len(end_mark)


def readme_span(text: str, where: str, marker: str) -> tuple[int, int]:
    """The README's block for ``marker``, else the paragraph holding ``<!-- <marker>:pending -->``."""
    pending = f"<!-- {marker}:pending -->"
    if f"<!-- {marker}:begin -->" not in text and pending in text:
        at = text.index(pending)
        start, end = text.rfind("\n\n", 0, at), text.find("\n\n", at)
        return (0 if start < 0 else start + 2), (len(text) if end < 0 else end)
    return block(text, where, marker)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--summary", default="reports/demo/summary.md")
    parser.add_argument("--readme", default="README.md")
    parser.add_argument("--marker", default="results", help="the block's name: <!-- NAME:begin --> ... end")
    parser.add_argument("--image", action="append", default=[], metavar="SRC:DST", help="also copy a picture")
    args = parser.parse_args()
    summary_path, readme_path = Path(args.summary), Path(args.readme)
    if not summary_path.exists():
        sys.exit(f"error: {summary_path}: not found (run the make target that writes it first)")
    images = [tuple(Path(p) for p in spec.split(":", 1)) for spec in args.image]
    for spec, pair in zip(args.image, images):
        if len(pair) != 2:
            sys.exit(f"error: --image {spec}: expected SRC:DST")
        if not pair[0].is_file():
            sys.exit(f"error: {pair[0]}: not found (run the make target that writes it first)")
    begin, end = f"<!-- {args.marker}:begin -->", f"<!-- {args.marker}:end -->"
    summary = summary_path.read_text()
    s0, s1 = block(summary, str(summary_path), args.marker)
    facts = {k: m[1] for k in ("run id", "commit") if (m := re.search(rf"^- {k}: (.+)$", summary, re.MULTILINE))}
    stated = "".join(f", {k} {v}" for k, v in facts.items())
    source = f"<!-- copied by scripts/readme_results.py from {summary_path}{stated} -->\n"
    table = summary[s0 + len(begin): s1 - len(end)].strip("\n")
    if "commit" not in facts:
        sys.exit(f"error: {summary_path}: states no '- commit: ...' line (the README block must name its commit)")
    pictures = "".join(f"\n\n![{args.marker}: {src.name}]({os.path.relpath(dst, readme_path.resolve().parent)})"
                       for src, dst in ((s, d.resolve()) for s, d in images))
    readme = readme_path.read_text()
    r0, r1 = readme_span(readme, str(readme_path), args.marker)
    new = readme[:r0] + begin + "\n" + source + table + pictures + "\n" + end + readme[r1:]
    for src, dst in images:
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst.with_suffix(".tmp"))
        dst.with_suffix(".tmp").replace(dst)
    tmp = readme_path.with_suffix(".tmp")
    tmp.write_text(new)
    tmp.replace(readme_path)
    print(f"{readme_path}: {args.marker} block from {summary_path}{stated}"
          + "".join(f"; {src} -> {dst}" for src, dst in images))


if __name__ == "__main__":
    main()
