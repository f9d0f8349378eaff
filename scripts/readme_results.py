#!/usr/bin/env python3
"""Copy the results table of ``reports/demo/summary.md`` into ``README.md`` (``make readme-results``).

The table is the block between ``<!-- results:begin -->`` and ``<!-- results:end -->`` in both
files; the README's block is replaced, with a line naming the summary's run id, commit and
test-split hash. Figures in the README are therefore never typed by hand.

    python scripts/readme_results.py [--summary reports/demo/summary.md] [--readme README.md]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"


def block(text: str, where: str) -> tuple[int, int]:
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        sys.exit(f"error: {where}: no {BEGIN} ... {END} block")
    return start, end + len(END)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--summary", default="reports/demo/summary.md")
    parser.add_argument("--readme", default="README.md")
    args = parser.parse_args()
    summary_path, readme_path = Path(args.summary), Path(args.readme)
    if not summary_path.exists():
        sys.exit(f"error: {summary_path}: not found (run make demo first)")
    summary = summary_path.read_text()
    s0, s1 = block(summary, str(summary_path))
    facts = {k: (re.search(rf"^- {k}: (.+)$", summary, re.M) or [None, "?"])[1]
             for k in ("run id", "commit", "seeds \\(students\\)", "test split")}
    source = (f"<!-- copied by scripts/readme_results.py from {summary_path}: run {facts['run id']}, "
              f"commit {facts['commit']} -->\n")
    table = summary[s0 + len(BEGIN): s1 - len(END)].strip("\n")
    readme = readme_path.read_text()
    r0, r1 = block(readme, str(readme_path))
    new = readme[:r0] + BEGIN + "\n" + source + table + "\n" + END + readme[r1:]
    tmp = readme_path.with_suffix(".tmp")
    tmp.write_text(new)
    tmp.replace(readme_path)
    print(f"{readme_path}: results table from {summary_path} (run {facts['run id']}, commit {facts['commit']})")


if __name__ == "__main__":
    main()
