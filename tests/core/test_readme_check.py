"""The README's provenance and staleness (scripts/readme_check.py, scripts/readme_results.py) in a
throwaway git repository: a block older than the measured code, a changed recipe, what the check
leaves unmeasured, network code judged by what it computes, a pending block filled."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


README = """# x

<!-- results:begin -->
<!-- copied by scripts/readme_results.py from reports/demo/summary.md, run id 2026-01-01T00:00:00Z, commit {commit} -->
| a | b |
<!-- results:end -->

<!-- pareto:pending -->
pending
"""


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=True,
                          env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                               "GIT_COMMITTER_EMAIL": "t@t", "PATH": "/usr/bin:/bin"}).stdout.strip()


def readme_check(repo: Path, **env: str) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_check.py"), "--readme",
                           str(repo / "README.md")], capture_output=True, text=True, check=False,
                          env={**os.environ, **env}, timeout=600)


def test_readme_check_fails_on_a_block_older_than_the_measured_code(tmp_path):
    repo = tmp_path / "repo"
    (repo / "denoiser" / "nn").mkdir(parents=True)
    git(repo, "init", "-q")
    (repo / "denoiser" / "nn" / "unet.py").write_text("width = 16\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "first")
    old = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "denoiser" / "nn" / "unet.py").write_text("width = 32\n")  # the measured network changes
    git(repo, "commit", "-qam", "wider")
    new = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "docs.md").write_text("words\n")  # a later commit that measures nothing
    git(repo, "add", "docs.md")
    git(repo, "commit", "-qm", "docs")

    (repo / "README.md").write_text(README.format(commit=old))
    proc = readme_check(repo)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert "block 'results'" in proc.stderr and f"commit {old}" in proc.stderr and "denoiser/nn/unet.py" in proc.stderr
    (repo / "README.md").write_text(README.format(commit=new + "-dirty"))
    assert readme_check(repo).returncode == 0  # at the change (or after it): current
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD")))
    assert readme_check(repo).returncode == 0
    (repo / "README.md").write_text(README.replace(", commit {commit}", ""))
    proc = readme_check(repo)
    assert proc.returncode == 1 and "names no commit" in proc.stderr
    (repo / "README.md").write_text(README.format(commit="abcdef1"))
    assert "does not have" in readme_check(repo).stderr

    # a move with identical content (the configs to the top level) measures the same thing ...
    (repo / "denoiser" / "conf" / "net").mkdir(parents=True)
    (repo / "denoiser" / "conf" / "net" / "student.yaml").write_text("width: 32\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "net config")
    at = git(repo, "rev-parse", "HEAD")
    (repo / "conf").mkdir()
    git(repo, "mv", "denoiser/conf/net", "conf/net")
    git(repo, "commit", "-qm", "conf at the top level")
    (repo / "README.md").write_text(README.format(commit=at))
    assert readme_check(repo).returncode == 0
    # ... and so do a comment, a docstring and a YAML comment ...
    (repo / "denoiser" / "nn" / "unet.py").write_text('"""The U-Net."""\nwidth = 32  # channels\n')
    (repo / "conf" / "net" / "student.yaml").write_text("# the student\nwidth: 32   # channels\n")
    git(repo, "commit", "-qam", "words only")
    assert readme_check(repo).returncode == 0
    # ... and a new option of a config group (composed only when selected by name) ...
    (repo / "conf" / "net" / "wide.yaml").write_text("width: 64\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "another net option")
    assert readme_check(repo).returncode == 0
    # ... but deleting one does not (a composition may have selected it) ...
    git(repo, "rm", "-q", "conf/net/wide.yaml")
    git(repo, "commit", "-qm", "net option removed")
    assert readme_check(repo).returncode == 0  # it was added after the block's commit: nothing measured it
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD~1")))
    proc = readme_check(repo)
    assert proc.returncode == 1 and "conf/net/wide.yaml" in proc.stderr
    (repo / "README.md").write_text(README.format(commit=at))
    # ... a change of a value after the move does not
    (repo / "conf" / "net" / "student.yaml").write_text("width: 48\n")
    git(repo, "commit", "-qam", "wider config")
    proc = readme_check(repo)
    assert proc.returncode == 1 and "conf/net/student.yaml" in proc.stderr


RECIPE_FILES = {
    "denoiser/lit/distill.py": "ALPHA = 0.5\n",
    "denoiser/commands/tools/netstats.py": "WIDTH = 1\n",
    "conf/base/model.yaml": "lr: 0.001\n",
    "conf/experiment/demo_distill.yaml": "trainer:\n  max_steps: 900\n",
    "conf/pipeline/demo.yaml": "alpha: 0.75\n",
    "conf/hydra/help/command.yaml": "header: usage\n",
    "docs/notes.md": "words\n",
}


def test_readme_check_catches_a_changed_recipe_in_every_file_of_blocks(tmp_path):
    """What a result depends on is all of denoiser/ and conf/ (less hydra/help and the tools no
    pipeline runs): a changed value of a recipe config (conf/base, conf/experiment, conf/pipeline)
    or a changed line of denoiser/lit makes a block stale, in README.md and in docs/results.md, one
    line per block naming its file; comments, --help text and a tool's code do not. With no
    --readme, both files are checked; --report-only lists the stale blocks and exits 0."""
    repo = tmp_path / "repo"
    for path, text in RECIPE_FILES.items():
        (repo / path).parent.mkdir(parents=True, exist_ok=True)
        (repo / path).write_text(text)
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "recipe")
    at = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "README.md").write_text(README.format(commit=at))
    (repo / "docs" / "results.md").write_text(README.format(commit=at).replace("results:", "ablations:"))

    def check(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_check.py"), *args], cwd=repo,
                              capture_output=True, text=True, check=False, timeout=600)

    def commit(path: str, text: str) -> None:
        (repo / path).write_text(text)
        git(repo, "commit", "-qam", f"edit {path}")

    # comments, the help text, a tool that no pipeline runs, and the docs: both blocks stay current
    commit("denoiser/lit/distill.py", "ALPHA = 0.5  # the distillation weight\n")
    commit("conf/base/model.yaml", "# the base recipe\nlr: 0.001  # Adam\n")
    commit("conf/hydra/help/command.yaml", "header: usage, longer\n")
    commit("denoiser/commands/tools/netstats.py", "WIDTH = 2\n")
    commit("docs/notes.md", "other words\n")
    proc = check()
    assert proc.returncode == 0, proc.stderr
    assert "README.md" in proc.stdout and "docs/results.md" in proc.stdout
    # each recipe change alone makes both blocks stale, one line each, naming its file
    for path, text in (("conf/experiment/demo_distill.yaml", "trainer:\n  max_steps: 1200\n"),
                       ("conf/base/model.yaml", "lr: 0.002\n"), ("conf/pipeline/demo.yaml", "alpha: 1.0\n"),
                       ("denoiser/lit/distill.py", "ALPHA = 0.7\n")):
        before = (repo / path).read_text()
        commit(path, text)
        proc = check()
        assert proc.returncode == 1, (path, proc.stdout)
        lines = proc.stderr.splitlines()
        assert len(lines) == 2 and all(path in line for line in lines), (path, lines)
        assert lines[0].startswith("README.md: block 'results'") and lines[1].startswith("docs/results.md: block 'ablations'")
        assert check("--readme", "docs/results.md").stderr.splitlines() == lines[1:]  # one file: its blocks only
        report = check("--report-only")
        assert report.returncode == 0 and report.stderr.splitlines() == lines
        commit(path, before)  # back to the block's values: current again
        assert check().returncode == 0, path


def test_what_readme_check_leaves_unmeasured_no_pipeline_runs_and_no_measured_module_imports():
    """scripts/readme_check.py's UNMEASURED modules cannot change a block: no measured Python file
    imports one (at any depth of its syntax tree) or names
    one in a string (``python -m <module>``), no measured config names one (a _target_, a pipeline
    stage's module), and no pipeline stage runs one as its console command."""
    import ast
    import importlib.util

    import tomllib
    import yaml

    spec = importlib.util.spec_from_file_location("readme_check", ROOT / "scripts" / "readme_check.py")
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)

    off = {p.removesuffix(".py").replace("/", ".") for p in check.UNMEASURED if p.endswith(".py")}
    assert "denoiser.commands.tools.netstats" in off and all(importlib.util.find_spec(m) for m in off)

    def measured(path: Path) -> bool:
        rel = path.relative_to(ROOT).as_posix()
        return rel.startswith(check.MEASURED) and not rel.startswith(check.UNMEASURED)

    def strings(data):
        if isinstance(data, dict):
            for key, value in data.items():
                yield from strings(key)
                yield from strings(value)
        elif isinstance(data, list):
            for value in data:
                yield from strings(value)
        elif isinstance(data, str):
            yield data

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for path in [*(ROOT / "denoiser").rglob("*.py"), *(ROOT / "scripts").glob("*.py")]:
        if not measured(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant):
                assert node.value not in off, f"{path}:{node.lineno} names {node.value}"
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or "", *(f"{node.module}.{a.name}" for a in node.names)]
            else:
                continue
            assert not off & set(names), f"{path} imports {off & set(names)}"
    configs = [p for p in (ROOT / "conf").rglob("*.yaml") if measured(p)]
    assert any(p.parent.name == "pipeline" for p in configs)
    for path in configs:
        data = yaml.safe_load(path.read_text())
        named = {s for s in strings(data) if any(s == m or s.startswith(m + ".") for m in off)}
        assert not named, f"{path} names {named}"
        for stage in ((data or {}).get("stages") or {}).values() if path.parent.name == "pipeline" else []:
            if stage.get("command"):
                target = scripts[f"denoiser-{stage['command']}"].split(":")[0]
                assert target not in off, f"{path}: a stage runs {target}"


@pytest.mark.slow
def test_readme_check_judges_network_code_by_what_it_computes(tmp_path):
    """A refactor of denoiser/nn (another syntax tree, the same numbers) leaves a block current; a
    change of what a network computes makes it stale (denoiser/commands/tools/nn_fingerprint.py on both trees)."""
    import shutil

    repo = tmp_path / "repo"
    for name in ("denoiser", "conf"):
        shutil.copytree(ROOT / name, repo / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so"))
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "code")
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD")))
    inputs = repo / "denoiser" / "nn" / "inputs.py"
    text = inputs.read_text()
    line = "    return log1p(x.float().clamp_min(0) / scale)\n"
    assert line in text
    inputs.write_text(text.replace(line, "    ratio = x.float().clamp_min(0) / scale\n    return log1p(ratio)\n"))
    git(repo, "commit", "-qam", "refactor")
    proc = readme_check(repo, README_CHECK_NETS="tiny")
    assert proc.returncode == 0, proc.stderr
    assert "denoiser/nn/inputs.py changed in form only: 1 network configs compute the same" in proc.stdout
    inputs.write_text(text.replace(line, "    return log1p(x.float().clamp_min(0) / (2 * scale))\n"))
    git(repo, "commit", "-qam", "another feature scale")
    proc = readme_check(repo, README_CHECK_NETS="tiny")
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert "denoiser/nn/inputs.py; the networks compute differently (tiny)" in proc.stderr


def test_readme_results_fills_a_pending_block_and_names_its_commit(tmp_path):
    summary = tmp_path / "pareto.md"
    summary.write_text("# P\n\n- run id: R1\n- commit: 1234abc\n\n<!-- pareto:begin -->\n| t |\n<!-- pareto:end -->\n")
    (tmp_path / "plot.png").write_bytes(b"png")
    readme = tmp_path / "README.md"
    readme.write_text(README.format(commit="0"))
    cmd = [sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary", str(summary), "--readme",
           str(readme), "--marker", "pareto", "--image", f"{tmp_path / 'plot.png'}:{tmp_path / 'docs' / 'p.png'}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    text = readme.read_text()
    assert "pending" not in text and (tmp_path / "docs" / "p.png").read_bytes() == b"png"
    assert ("<!-- pareto:begin -->\n<!-- copied by scripts/readme_results.py from " in text
            and "run id R1, commit 1234abc -->\n| t |\n\n![pareto: plot.png](docs/p.png)\n<!-- pareto:end -->" in text)
    summary.write_text("<!-- pareto:begin -->\n| t |\n<!-- pareto:end -->\n")  # no commit: no copy
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert proc.returncode == 1 and "states no '- commit" in proc.stderr
