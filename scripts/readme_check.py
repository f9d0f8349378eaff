#!/usr/bin/env python3
"""Fail when a results block of ``README.md`` is older than the code it measures: ``make readme-check``.

Every block ``<!-- NAME:begin --> ... <!-- NAME:end -->`` that ``scripts/readme_results.py``
copied names, in its ``copied by`` line, the commit of the run that wrote it. A block is stale
when that commit does not contain the last commit that changed what the numbers measure
(:data:`MEASURED`: the networks, their configs and the dataset; ``git log -1 -- <paths>`` and
``git merge-base --is-ancestor``), when it names no commit, or a commit git does not know. A
``-dirty`` commit counts as its base commit. One line per stale block on stderr, then exit 1;
exit 0 when every block is current (a ``<!-- NAME:pending -->`` line is not a block).

    python scripts/readme_check.py [--readme README.md] [--repo DIR]   # DIR: the README's directory
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

#: what the README's numbers measure: a change under one of these makes every block stale
MEASURED = ("denoiser/nn/", "denoiser/conf/net/", "denoiser/conf/kernel/", "denoiser/conf/experiment/",
            "denoiser/conf/dataset/")

BLOCK = re.compile(r"<!-- (?P<name>[\w.-]+):begin -->(?P<body>.*?)<!-- (?P=name):end -->", re.DOTALL)
COPIED_COMMIT = re.compile(r"<!-- copied by scripts/readme_results\.py from [^\n]*?, commit (?P<commit>[0-9a-f]{7,40})"
                           r"(?:-dirty)?\b")


def git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)


def stale_blocks(readme: Path, repo: Path, measured: tuple[str, ...] = MEASURED) -> list[str]:
    """One line per stale block of ``readme`` (empty when all are current); ``repo``: the git checkout."""
    last = git(repo, "log", "-1", "--format=%H", "--", *measured)
    if last.returncode != 0:
        raise SystemExit(f"error: {repo}: git log failed there (not a git checkout?)")
    last_sha = last.stdout.strip()
    paths = ", ".join(measured)
    lines = []
    for block in BLOCK.finditer(readme.read_text()):
        name, found = block["name"], COPIED_COMMIT.search(block["body"])
        where = f"{readme}: block '{name}'"
        if not found:
            lines.append(f"{where} names no commit (regenerate it: its make target, then make readme-results/-pareto)")
            continue
        commit = found["commit"]
        if git(repo, "rev-parse", "--verify", "--quiet", f"{commit}^{{commit}}").returncode != 0:
            lines.append(f"{where} names commit {commit}, which this checkout does not have")
        elif last_sha and git(repo, "merge-base", "--is-ancestor", last_sha, commit).returncode != 0:
            lines.append(f"{where} (commit {commit}) is older than {last_sha[:10]}, the last change to {paths}: "
                         "rerun what wrote it")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--readme", type=Path, default=Path("README.md"))
    parser.add_argument("--repo", type=Path, help="the git checkout (default: the README's directory)")
    args = parser.parse_args()
    if not args.readme.is_file():
        sys.exit(f"error: {args.readme}: not found")
    stale = stale_blocks(args.readme, args.repo or args.readme.resolve().parent)
    for line in stale:
        print(line, file=sys.stderr)
    if stale:
        sys.exit(1)
    print(f"{args.readme}: every results block is at or after the last change to what it measures")


if __name__ == "__main__":
    main()
