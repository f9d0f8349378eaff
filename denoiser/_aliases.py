"""Old module paths that still import: the modules that moved from the package root into a wing.

A stored checkpoint or an old config may name a module by its old path (a ``_target_`` such as
``denoiser.losses.DenoiseLoss``, a pickled class). :class:`AliasFinder`, installed first on
``sys.meta_path`` by ``denoiser/__init__.py``, answers an import of an old name (and of the
names below it: ``denoiser.ovext.x``) with the module at its new path, imported on first use:
``denoiser.losses`` *is* ``denoiser.lit.losses``, the same module object. New code imports the
new paths; this table only grows (a module that moves again gets its latest path).

It also finds ``denoiser.conf`` in a source checkout: the configs live at the checkout's top
level (``conf/``, as docs/design.md places them), and a wheel ships them inside the package
(``pyproject.toml`` maps the package ``denoiser.conf`` to ``conf/``). When the package directory
holds no ``conf/`` of its own and ``<checkout>/conf/__init__.py`` exists beside it, that is
``denoiser.conf`` (so ``python train.py``, a ``PYTHONPATH`` checkout and an editable install
all read the checkout's configs); otherwise the normal import finds the wheel's copy.

Private: not a root module of the package (tests/test_house.py counts the others).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from importlib.machinery import ModuleSpec
from pathlib import Path

#: old module -> where it lives now
MOVED = {
    "denoiser.backends": "denoiser.inference.backends",
    "denoiser.cuda_backend": "denoiser.inference.cuda_backend",
    "denoiser.triton_filter": "denoiser.inference.triton_filter",
    "denoiser.step_graph": "denoiser.inference.step_graph",
    "denoiser.ovext": "denoiser.inference.ovext",
    "denoiser.baselines": "denoiser.methods.baselines",
    "denoiser.onnd": "denoiser.methods.onnd",
    "denoiser.evaluation": "denoiser.report.evaluation",
    "denoiser.summary": "denoiser.report.summary",
    "denoiser.figure_tables": "denoiser.report.figure_tables",
    "denoiser.plot_crops": "denoiser.report.plot_crops",
    "denoiser.plot_tradeoff": "denoiser.report.plot_tradeoff",
    "denoiser.pareto": "denoiser.report.pareto",
    "denoiser.stats": "denoiser.report.stats",
    "denoiser.history_diagnosis": "denoiser.report.history_diagnosis",
    "denoiser.losses": "denoiser.lit.losses",
    "denoiser.transfer": "denoiser.lit.transfer",
}


def new_name(fullname: str) -> str | None:
    """The current path of the old module ``fullname`` (or of a module inside an old package), or None."""
    for old, new in MOVED.items():
        if fullname == old or fullname.startswith(old + "."):
            return new + fullname[len(old):]
    return None


class _Alias:
    """Loads an old name as the module at its new path (imported, not copied)."""

    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        return importlib.import_module(self.target)

    def exec_module(self, module) -> None:
        """Nothing to run: the module at the new path is already imported."""


class AliasFinder:
    """Finds the old names of :data:`MOVED` (first on ``sys.meta_path``, so no stale copy of an
    old file, e.g. in an editable install of an older checkout, is found instead). A meta path
    finder and its loader by protocol (``importlib.abc`` would make ``import denoiser`` slower)."""

    def find_spec(self, fullname, path=None, target=None):
        if not fullname.startswith("denoiser."):
            return None
        if fullname == "denoiser.conf":
            return checkout_conf_spec()
        new = new_name(fullname)
        return None if new is None else ModuleSpec(fullname, _Alias(new))


def checkout_conf_spec() -> ModuleSpec | None:
    """The spec of ``denoiser.conf`` at a source checkout's top-level ``conf/`` (module
    docstring), or None where the package ships its own ``conf/`` (a wheel) or no checkout is beside it."""
    package = Path(__file__).resolve().parent
    if (package / "conf" / "__init__.py").is_file():
        return None
    init = package.parent / "conf" / "__init__.py"
    if not init.is_file():
        return None
    return importlib.util.spec_from_file_location("denoiser.conf", init, submodule_search_locations=[str(init.parent)])


def install() -> None:
    """Put :class:`AliasFinder` first on ``sys.meta_path`` (once)."""
    if not any(isinstance(finder, AliasFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, AliasFinder())
