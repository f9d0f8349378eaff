#!/usr/bin/env python3
"""Fail when a results block of ``README.md`` is older than the code it measures: ``make readme-check``.

Every block ``<!-- NAME:begin --> ... <!-- NAME:end -->`` that ``scripts/readme_results.py``
copied names, in its ``copied by`` line, the commit of the run that wrote it. A block is stale
when what the numbers measure (:data:`MEASURED`: the networks, their configs and the dataset)
differs between that commit and ``HEAD``: ``git diff -M --name-status <commit> HEAD -- <paths>``
lists a file added, deleted or changed. A file that only moved (a rename with identical content,
``R100``, e.g. the configs moving from ``denoiser/conf/`` to ``conf/``) changes nothing measured,
so both locations are listed. Also stale: a block that names no commit, or a commit git does not
know. A ``-dirty`` commit counts as its base commit. One line per stale block on stderr, then
exit 1; exit 0 when every block is current (a ``<!-- NAME:pending -->`` line is not a block).

    python scripts/readme_check.py [--readme README.md] [--repo DIR]   # DIR: the README's directory
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

#: what the README's numbers measure: a change under one of these makes every block stale (the
#: config groups at both of their locations: conf/ at the top level, denoiser/conf/ before)
MEASURED = ("denoiser/nn/", *(f"{root}{group}/" for root in ("conf/", "denoiser/conf/")
                              for group in ("net", "kernel", "experiment", "dataset")))

BLOCK = re.compile(r"<!-- (?P<name>[\w.-]+):begin -->(?P<body>.*?)<!-- (?P=name):end -->", re.DOTALL)
COPIED_COMMIT = re.compile(r"<!-- copied by scripts/readme_results\.py from [^\n]*?, commit (?P<commit>[0-9a-f]{7,40})"
                           r"(?:-dirty)?\b")


def git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)


def measured_changes(repo: Path, commit: str, measured: tuple[str, ...] = MEASURED) -> list[str]:
    """``git diff -M --name-status`` lines between ``commit`` and ``HEAD`` under ``measured``,
    less pure moves (``R100``): the files whose content differs."""
    diff = git(repo, "diff", "-M", "--name-status", commit, "HEAD", "--", *measured)
    if diff.returncode != 0:
        raise SystemExit(f"error: {repo}: git diff {commit} HEAD failed: {diff.stderr.strip()}")
    return [line for line in diff.stdout.splitlines() if line and not line.startswith("R100\t")]


def stale_blocks(readme: Path, repo: Path, measured: tuple[str, ...] = MEASURED) -> list[str]:
    """One line per stale block of ``readme`` (empty when all are current); ``repo``: the git checkout."""
    if git(repo, "rev-parse", "--verify", "--quiet", "HEAD").returncode != 0:
        raise SystemExit(f"error: {repo}: not a git checkout with a commit")
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
            continue
        changed = measured_changes(repo, commit, measured)
        if changed:
            files = ", ".join(line.split("\t")[-1] for line in changed[:3]) + (" ..." if len(changed) > 3 else "")
            lines.append(f"{where} (commit {commit}): what it measures changed since ({len(changed)} file(s): "
                         f"{files}): rerun what wrote it")
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
    print(f"{args.readme}: what every results block measures is unchanged since its commit")


if __name__ == "__main__":
    main()
