#!/usr/bin/env python3
"""Fail when a results block is older than the code it measures: ``make readme-check``.

The blocks live in ``README.md`` and ``docs/results.md`` (:data:`FILES`, both checked unless
``--readme`` names the files). Every block ``<!-- NAME:begin --> ... <!-- NAME:end -->`` that
``scripts/readme_results.py`` copied names, in its ``copied by`` line, the commit of the evaluation
that wrote it. A block is stale when what the numbers depend on (:data:`MEASURED`: the package, every
config, the scripts that make a block's inputs; less :data:`UNMEASURED`) differs between that commit
and ``HEAD``: ``git diff -M --name-status <commit> HEAD -- <paths>`` lists a file added or deleted,
or a file whose meaning changed. Meaning, not bytes: a Python file is compared as its syntax tree
without docstrings (comments are not in the tree), a YAML file as the data it parses to (comments
dropped), anything else byte for byte; so a comment, a docstring or a file that only moved (a
rename, e.g. the configs from ``denoiser/conf/`` to ``conf/``, both locations measured) leaves a
block current, and a changed value, default or line of code (a recipe's config in ``conf/base``,
``conf/experiment`` or ``conf/pipeline``, a line of ``denoiser/lit``) does not. An added YAML file
is a new option of its group (a new experiment, render preset or net), which nothing composes unless a
changed file selects it: it leaves a block current too. Also stale: a block that names no commit, or
a commit git does not know. A ``-dirty`` commit counts as its base commit. One line per stale block
on stderr, naming its file, then exit 1 (``--report-only``: exit 0, the lines all the same); exit 0
when every block is current (a ``<!-- NAME:pending -->`` line is not a block).

Code of the networks (:data:`BEHAVIOUR`, ``denoiser/nn``) is judged by what it computes when
nothing else measured changed: :mod:`denoiser.commands.tools.nn_fingerprint` (this checkout's file, by
path, with ``denoiser`` imported from the tree) runs on both trees (``git archive`` of the block's
commit and of ``HEAD``) and hashes, per network config, the training
pass's outputs and gradients and the exported ONNX graphs, bit for bit. Equal fingerprints (a
refactor: code moved between modules, renamed, restructured) leave the block current, with a
line on stdout saying so; different ones, or a tree the fingerprint cannot run on, make it stale.

    python scripts/readme_check.py                        # README.md and docs/results.md of this checkout
    python scripts/readme_check.py --readme README.md [--readme docs/results.md] [--repo DIR] [--report-only]

It also checks the shipped release (``denoiser/models``): a weight file whose size or SHA-256 is not
its manifest's, or a model card that is not what the manifest renders to, fails the check (also with
``--report-only``).
"""

from __future__ import annotations

import argparse
import ast
import functools
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

#: the files that hold results blocks, relative to the checkout (those that exist are checked by default)
FILES = ("README.md", "docs/results.md")
#: where the configs live: conf/ at the top level, denoiser/conf/ before (both measured: a block may be older)
CONF_ROOTS = ("conf/", "denoiser/conf/")
#: what a block's numbers depend on: a change under one of these (less UNMEASURED) makes every block
#: stale. The package: training (denoiser/lit), data and rendering, the networks, evaluation and
#: metrics, the benchmark and its backends (a block's time columns), the pipelines' runner and the
#: summaries that write the blocks; every config (the recipes: conf/base, conf/experiment,
#: conf/pipeline, ...); the scripts that make a block's inputs (the Cycles sequences, make gpu-check's run)
MEASURED = ("denoiser/", "conf/", "scripts/blender_sequences.py", "scripts/blender_cycles.py", "scripts/gpu_check.sh")  # denoiser/conf/ in denoiser/
#: tools that no pipeline (conf/pipeline), summary or gpu-check runs and that no measured module imports
#: (tests/report/test_claims.py checks both), with their configs: benchmarks of what no block shows (data
#: loading, long sequences, network variants, the renderer), the parameter and FLOP count, export and
#: denoise (a trained network applied to a user's frames), the val table, render_blender (a user's .blend file)
TOOLS = ("data_throughput", "memory_longseq", "bench_networks", "effect_cost", "netstats", "export", "denoise", "val_table",
         "render_blender")
#: the console scripts among them (denoiser/commands/<name>.py); the others are python -m tools
#: (denoiser/commands/tools/<name>.py)
CONSOLE_SCRIPTS = ("export", "denoise", "render_blender")
#: the unmeasured tools and diagnoses (:data:`UNMEASURED` below): the fingerprint, the diagnoses written
#: to files of their own, never into a block (run by hand), and the tools of TOOLS
UNMEASURED_TOOLS = ("nn_fingerprint", "albedo_bound", "diagnose_history", "noise_response",
                    *(t for t in TOOLS if t not in CONSOLE_SCRIPTS))
#: under MEASURED but unable to change a trained network or a block's numbers
UNMEASURED = (
    *(f"{root}hydra/help/" for root in CONF_ROOTS),           # the --help text
    *(f"denoiser/commands/tools/{tool}.py" for tool in UNMEASURED_TOOLS),
    *(f"denoiser/commands/{tool}.py" for tool in CONSOLE_SCRIPTS),
    *(f"{root}{tool}.yaml" for root in CONF_ROOTS for tool in TOOLS),
    "denoiser/report/history_diagnosis.py", "denoiser/report/noise_response.py", "denoiser/report/cpu_speed.py",
)
#: the unmeasured tools where they were before denoiser/commands/tools/ (issue 63): left out of the
#: diff as well, so that a block older than the move does not see them deleted
FORMER_UNMEASURED = tuple(f"denoiser/commands/{tool}.py" for tool in UNMEASURED_TOOLS)
#: a file deleted at the first location and added at the second is the same file moved (paired
#: even when git's rename detection, which goes by similarity, does not pair a small edited file)
MOVED = (("denoiser/conf/", "conf/"), ("denoiser/commands/", "denoiser/commands/tools/"))
#: an added file of these kinds is a new option of its config group (``conf/render_set/demo_motion.yaml``): a
#: config composes it only when selected by name, and a changed file that selects it is in the diff
NEW_OPTION = (".yaml", ".yml")
#: Python code judged by what the networks compute (denoiser.commands.tools.nn_fingerprint), not by its text
BEHAVIOUR = ("denoiser/nn/",)
#: the fingerprint module: the one of the package this script's Python imports (this checkout's, in
#: its venv). Found, not imported (nothing of the package runs here), and run in a child by path,
#: never by ``-m``: the child imports ``denoiser`` from the archived tree (an older commit's lacks the
#: module), and both trees must be hashed by the same code.
FINGERPRINT_MODULE = "denoiser.commands.tools.nn_fingerprint"
#: the child's program: run the file at argv[1] as ``__main__`` without putting its directory on
#: sys.path (as ``python FILE`` would: a module of the package's folder would shadow a top-level one)
RUN_FILE = "import runpy, sys; sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')"

BLOCK = re.compile(r"<!-- (?P<name>[\w.-]+):begin -->(?P<body>.*?)<!-- (?P=name):end -->", re.DOTALL)
COPIED_COMMIT = re.compile(r"<!-- copied by scripts/readme_results\.py from [^\n]*?, commit (?P<commit>[0-9a-f]{7,40})"
                           r"(?:-dirty)?\b")


def git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)


def _without_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree


def meaning(path: str, text: str) -> object:
    """What a measured file means: a Python file's syntax tree less docstrings, a YAML file's
    data, else its text (unparsable files fall back to their text)."""
    try:
        if path.endswith(".py"):
            return ast.dump(_without_docstrings(ast.parse(text)))
        if path.endswith((".yaml", ".yml")):
            import yaml

            return yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - a syntax or YAML error: compare the text itself
        return ("unparsable", type(exc).__name__, text)
    return text


def _blob(repo: Path, commit: str, path: str) -> str:
    shown = git(repo, "show", f"{commit}:{path}")
    if shown.returncode != 0:
        raise SystemExit(f"error: {repo}: git show {commit}:{path} failed: {shown.stderr.strip()}")
    return shown.stdout


def measured_changes(repo: Path, commit: str, measured: tuple[str, ...] = MEASURED,
                     unmeasured: tuple[str, ...] = UNMEASURED) -> list[str]:
    """``git diff -M --name-status`` lines between ``commit`` and ``HEAD`` under ``measured`` but not
    ``unmeasured`` whose file was added, deleted, or changed in :func:`meaning` (pure moves,
    comments and docstrings drop out)."""
    diff = git(repo, "diff", "-M", "--name-status", commit, "HEAD", "--", *measured,
               *(f":(exclude){path}" for path in (*unmeasured, *FORMER_UNMEASURED)))
    if diff.returncode != 0:
        raise SystemExit(f"error: {repo}: git diff {commit} HEAD failed: {diff.stderr.strip()}")
    entries = [line.split("\t") for line in diff.stdout.splitlines() if line]
    added = {e[1] for e in entries if e[0] == "A"}
    moved = {}  # deleted old path -> added new path
    for e in entries:
        if e[0] == "D":
            for before, after in MOVED:
                if e[1].startswith(before) and after + e[1][len(before):] in added:
                    moved[e[1]] = after + e[1][len(before):]
    changed = []
    for status, *paths in entries:
        if status[0] in "RM" or (status == "D" and paths[0] in moved):
            # renamed (maybe edited), modified, or moved between the locations: compare meanings
            old, new = paths[0], moved.get(paths[0], paths[-1])
            if meaning(old, _blob(repo, commit, old)) == meaning(new, _blob(repo, "HEAD", new)):
                continue
        elif status == "A" and paths[0] in moved.values():
            continue  # judged with its deleted twin
        elif status == "A" and paths[0].endswith(NEW_OPTION):
            continue  # a new option of a config group: no composition selects it unless a changed file does
        changed.append("\t".join([status, *paths]))
    return changed


@functools.cache
def fingerprint_file() -> Path:
    """Where :data:`FINGERPRINT_MODULE` is (its spec's origin; the module itself is not run here)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec(FINGERPRINT_MODULE)
    except ImportError as exc:
        raise SystemExit(f"error: {FINGERPRINT_MODULE}: {exc} (run with the project's venv: make readme-check)") from None
    if spec is None or not spec.origin:
        raise SystemExit(f"error: {FINGERPRINT_MODULE}: not found (run with the project's venv: make readme-check)")
    return Path(spec.origin)


@functools.cache
def fingerprints(repo: Path, commit: str, nets: str | None = None) -> dict[str, str] | str:
    """:data:`FINGERPRINT_MODULE` over ``git archive <commit>`` of ``repo``: ``{net: sha256}``,
    or a one-line reason why it could not run. ``nets``: comma-separated conf/net names (all)."""
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(f"git -C '{repo}' archive '{commit}' | tar -x -C '{tmp}'", shell=True,
                                 capture_output=True, text=True, check=False)
        if archive.returncode != 0:
            return f"git archive {commit} failed: {archive.stderr.strip()[:200]}"
        cmd = [sys.executable, "-c", RUN_FILE, str(fingerprint_file()), "--tree", tmp,
               *(["--nets", nets] if nets else [])]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=tmp,
                              env={**os.environ, "PYTHONPATH": tmp, "OMP_NUM_THREADS": "1"})
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        return f"the fingerprint did not run on {commit}: {lines[-1][:200] if lines else proc.returncode}"
    return json.loads(proc.stdout)


def same_behaviour(repo: Path, commit: str, changed: list[str]) -> tuple[bool, str]:
    """Whether ``changed`` (:func:`measured_changes` lines) is code of :data:`BEHAVIOUR` only and
    the networks of ``commit`` and ``HEAD`` compute the same (``$README_CHECK_NETS``: the configs
    compared, default all); with the reason when not."""
    if not all(line.split("\t")[-1].startswith(BEHAVIOUR) and line.split("\t")[-1].endswith(".py")
               and all(p.startswith(BEHAVIOUR) for p in line.split("\t")[1:]) for line in changed):
        return False, ""
    nets = os.environ.get("README_CHECK_NETS") or None
    before, after = fingerprints(repo, commit, nets), fingerprints(repo, "HEAD", nets)
    for side in (before, after):
        if isinstance(side, str):
            return False, side
    common = sorted(set(before) & set(after))
    if not common:
        return False, "no network config in both trees"
    differ = [n for n in common if before[n] != after[n]]
    if differ:
        return False, f"the networks compute differently ({', '.join(differ[:3])}{' ...' if len(differ) > 3 else ''})"
    return True, f"{len(common)} network configs compute the same, bit for bit ({FINGERPRINT_MODULE})"


def stale_blocks(readme: Path, repo: Path, measured: tuple[str, ...] = MEASURED) -> list[str]:
    """One line per stale block of ``readme`` (empty when all are current), each starting with the
    file's name (:func:`shown`); ``repo``: the git checkout."""
    if git(repo, "rev-parse", "--verify", "--quiet", "HEAD").returncode != 0:
        raise SystemExit(f"error: {repo}: not a git checkout with a commit")
    lines = []
    for block in BLOCK.finditer(readme.read_text()):
        name, found = block["name"], COPIED_COMMIT.search(block["body"])
        where = f"{shown(readme)}: block '{name}'"
        if not found:
            lines.append(f"{where} names no commit (regenerate it: its make target, then make readme)")
            continue
        commit = found["commit"]
        if git(repo, "rev-parse", "--verify", "--quiet", f"{commit}^{{commit}}").returncode != 0:
            lines.append(f"{where} names commit {commit}, which this checkout does not have")
            continue
        changed = measured_changes(repo, commit, measured)
        if changed:
            files = ", ".join(line.split("\t")[-1] for line in changed[:3]) + (" ..." if len(changed) > 3 else "")
            same, why = same_behaviour(repo, commit, changed)
            if same:
                print(f"{where} (commit {commit}): {files} changed in form only: {why}")
                continue
            lines.append(f"{where} (commit {commit}): what it measures changed since ({len(changed)} file(s): "
                         f"{files}{'; ' + why if why else ''}): rerun what wrote it")
    return lines


def shown(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it, else as given."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def toplevel(directory: Path) -> Path:
    """The git checkout holding ``directory`` (git's paths are relative to it); ``directory`` itself
    outside one (:func:`stale_blocks` then says so)."""
    top = git(directory, "rev-parse", "--show-toplevel")
    return Path(top.stdout.strip()) if top.returncode == 0 else directory


def release_problems(repo: Path) -> list[str]:
    """The shipped release (``denoiser/models``): its weight files and its card agree with its
    manifest (:func:`denoiser.report.model_card.check_release`); one line per problem."""
    sys.path.insert(0, str(repo))
    from denoiser.report.model_card import check_release

    folder = repo / "denoiser" / "models"
    problems = check_release(folder)
    if not problems and (folder / "release.json").is_file():
        print(f"{folder.relative_to(repo)}: the shipped weights and their card agree with release.json")
    return problems


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--readme", type=Path, action="append",
                        help=f"a file holding results blocks, repeatable (default: {' and '.join(FILES)} of the checkout)")
    parser.add_argument("--repo", type=Path, help="the git checkout (default: the one holding the first file, "
                                                  "or the working directory)")
    parser.add_argument("--report-only", action="store_true",
                        help="list the stale blocks but exit 0 (make test: a stale block is a result to rerun, not a failure)")
    args = parser.parse_args()
    for path in args.readme or []:
        if not path.is_file():
            sys.exit(f"error: {path}: not found")
    repo = args.repo or toplevel(args.readme[0].resolve().parent if args.readme else Path.cwd())
    files = args.readme or [repo / name for name in FILES if (repo / name).is_file()]
    if not files:
        sys.exit(f"error: {repo}: none of {', '.join(FILES)} found (--readme names the files)")
    release = release_problems(repo)
    for line in release:
        print(line, file=sys.stderr)
    stale = [line for path in files for line in stale_blocks(path, repo)]
    for line in stale:
        print(line, file=sys.stderr)
    if release or (stale and not args.report_only):
        sys.exit(1)  # shipped weights that disagree with their card fail even --report-only: it is no stale figure
    if stale:
        print(f"{len(stale)} stale results block(s) (listed on stderr; --report-only): rerun what wrote them, then make readme")
    for path in files:
        if not any(line.startswith(f"{shown(path)}: ") for line in stale):
            print(f"{shown(path)}: what every results block measures is unchanged since its commit")


if __name__ == "__main__":
    main()
