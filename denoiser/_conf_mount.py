"""``denoiser.conf`` in a source checkout: the configs live at the checkout's top level (``conf/``,
as docs/design.md places them), and a wheel ships them inside the package (``pyproject.toml`` maps
the package ``denoiser.conf`` to ``conf/``). When the package directory holds no ``conf/`` of its
own and ``<checkout>/conf/__init__.py`` exists beside it, :func:`mount` imports that file as
``denoiser.conf`` (so ``python train.py``, a ``PYTHONPATH`` checkout and an editable install all
read the checkout's configs); otherwise nothing is done and the normal import finds the wheel's copy.
Called once by ``denoiser/__init__.py``; no import hook stays installed.

Private: not a root module of the package (tests/core/test_house.py counts the others).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def mount() -> None:
    """Import ``<checkout>/conf/__init__.py`` as ``denoiser.conf`` where the package has no
    ``conf/`` of its own (module docstring); a no-op when it is imported already or no checkout is beside it."""
    package = Path(__file__).resolve().parent
    init = package.parent / "conf" / "__init__.py"
    if "denoiser.conf" in sys.modules or (package / "conf" / "__init__.py").is_file() or not init.is_file():
        return
    spec = importlib.util.spec_from_file_location("denoiser.conf", init, submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["denoiser.conf"] = module
    spec.loader.exec_module(module)
    sys.modules["denoiser"].conf = module
