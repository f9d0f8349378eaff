"""A non-editable install runs the commands: the wheel ships the configs (``denoiser/conf``) and
the OpenVINO extension's C++ source (package data), and the console scripts compose the configs
from any directory.

The wheel is built from this checkout and installed with ``--no-deps`` into a fresh virtual
environment in a temporary directory. That environment sees the project's dependencies (torch,
Hydra, Mitsuba, ...) through a plain path line in a ``.pth`` file naming this interpreter's
site-packages: a path line adds the directory without running the ``.pth`` files inside it, so
the editable install's finder (``__editable___denoiser_*_finder``) is not loaded there, and
``denoiser`` is imported from the installed wheel only (checked). The commands then run from a
temporary working directory with no ``conf/`` anywhere near and no ``PYTHONPATH``.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from denoiser.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[2]


def run(argv: list, cwd: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, check=False)


@pytest.mark.slow
def test_wheel_install_runs_the_commands_outside_the_checkout(tmp_path):
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "DENOISER_DEBUG", "DENOISER_DATA", "DENOISER_CACHE", "VIRTUAL_ENV")}
    env["PYTHONNOUSERSITE"] = "1"
    # 1. a wheel of the working tree (copied: an in-tree build would leave build/ and *.egg-info behind)
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for name in ("denoiser", "conf", "hydra_plugins"):  # conf/ ships as the package denoiser.conf
        shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    built = run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
                 "-w", tmp_path / "dist", src], tmp_path, env)
    assert built.returncode == 0, built.stderr[-3000:]
    [wheel] = (tmp_path / "dist").glob("denoiser-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    shipped = {n for n in names if n.startswith("denoiser/conf/") and n.endswith(".yaml")}
    configs = {f"denoiser/conf/{p.relative_to(CONF_DIR).as_posix()}" for p in Path(CONF_DIR).rglob("*.yaml")}
    assert configs and shipped == configs, sorted(configs ^ shipped)
    assert "denoiser/conf/__init__.py" in names and not any(n.startswith("conf/") for n in names)
    # the OpenVINO extension's C++ source (package data of denoiser.inference.ovext, built on first use)
    sources = {p.relative_to(REPO).as_posix() for p in (REPO / "denoiser").rglob("*.[ch]pp")}
    assert {"denoiser/inference/ovext/extension.cpp", "denoiser/inference/ovext/kernel_apply.hpp"} <= sources
    assert sources <= names, sorted(sources - names)

    # 2. a fresh environment that sees the dependencies but not the editable install
    venv = tmp_path / "venv"
    made = run([sys.executable, "-m", "venv", "--without-pip", venv], tmp_path, env)
    assert made.returncode == 0, made.stderr[-3000:]
    python = venv / "bin" / "python"
    purelib = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path, env)
    deps = [p for p in site.getsitepackages() if Path(p).is_dir()]
    Path(purelib.stdout.strip(), "_denoiser_test_deps.pth").write_text("\n".join(deps) + "\n")
    installed = run([python, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", "--no-compile",
                     "-q", wheel], tmp_path, env)
    assert installed.returncode == 0, installed.stderr[-3000:]

    # 3. the commands, from a directory outside the checkout
    work = tmp_path / "work"
    work.mkdir()
    where = run([python, "-c", "import denoiser, denoiser.conf; print(denoiser.__file__); print(denoiser.conf.CONF_DIR)"],
                work, env)
    assert where.returncode == 0, where.stderr[-3000:]
    module, conf = map(Path, where.stdout.split())
    assert module.is_relative_to(venv) and conf.is_relative_to(venv), where.stdout
    assert not any((d / "conf").exists() for d in (work, *work.parents))

    helped = run([venv / "bin" / "denoiser-denoise", "--help"], work, env)
    assert helped.returncode == 0, helped.stderr[-3000:]
    assert helped.stdout.startswith("denoiser-denoise: ") and "layout=native|blender" in helped.stdout

    root = tmp_path / "data"
    rendered = run([venv / "bin" / "denoiser-render", "scene=cornell", "split=train", "sequences=1", "frames=1",
                    "spp=1", "ref_spp=1", "width=8", "height=8", "variant=scalar_rgb", f"root={root}"], work, env)
    assert rendered.returncode == 0, rendered.stderr[-3000:]
    sequence = root / "train" / "cornell_000"
    assert (sequence / "frame_0000.exr").is_file() and (sequence / "sequence.json").is_file()
    assert not list(work.iterdir())  # nothing written into the working directory (render's run dir is `.`)
