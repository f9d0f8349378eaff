"""The Hydra configs, shipped inside the package (``pip install`` is enough to run every command).

``CONF_DIR`` is this directory: every command composes from it, and so do the library helpers
that compose configs by name (net configs, scene configs). Groups and entry configs are listed
in the README (Layout) and docs/design.md §4.
"""

from pathlib import Path

CONF_DIR = str(Path(__file__).resolve().parent)
