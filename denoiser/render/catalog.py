"""Scene configs by name (``conf/scene/<name>.yaml``), for render presets (``conf/render_set/``) that list scenes."""

from __future__ import annotations

from pathlib import Path

from denoiser.conf import CONF_DIR
from denoiser.errors import ConfigError

SCENE_DIR = Path(CONF_DIR) / "scene"


def available_scenes() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.yaml"))


def load_scene_config(name: str):
    """The scene config ``conf/scene/<name>.yaml`` as an OmegaConf ``DictConfig``."""
    from omegaconf import OmegaConf

    path = SCENE_DIR / f"{name}.yaml"
    if not path.exists():
        raise ConfigError(f"scene '{name}': no such scene config {path}; available: "
                          f"{', '.join(available_scenes())}")
    return OmegaConf.load(path)
