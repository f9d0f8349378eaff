"""The effect vocabulary: what a scene may declare, and how a missing declaration is reported.

A scene lists its effects (``effects: [area_light, {indirect: 3}, camera_motion]``); the
simulator builds only what is declared. Each effect has a small set of parameters:

=================  ===========================================================================
effect             meaning (parameters)
=================  ===========================================================================
``indirect``       global illumination with ``bounces`` extra bounces (default 3)
``glossy``         glossy/specular reflection (rough conductors, plastics, mirrors)
``transmission``   refraction through dielectrics (glass)
``textures``       spatially varying albedo (checkerboards, procedural bitmaps)
``area_light``     emitting shapes
``env_light``      environment emitter (procedural sky bitmap or constant)
``dof``            thin-lens camera (aperture, focus distance)
``motion_blur``    open shutter: radiance integrated over sub-frame times
``camera_motion``  the camera moves between frames
``object_motion``  objects move between frames
=================  ===========================================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from denoiser.errors import ConfigError

#: Effect name -> default parameters.
EFFECTS: dict[str, dict[str, Any]] = {
    "indirect": {"bounces": 3},
    "glossy": {},
    "transmission": {},
    "textures": {},
    "area_light": {},
    "env_light": {},
    "dof": {},
    "motion_blur": {},
    "camera_motion": {},
    "object_motion": {},
}

#: Path-depth increments (see :func:`path_depth`).
DIRECT_DEPTH = 2          # camera ray + one light connection = direct illumination only
GLOSSY_EXTRA_DEPTH = 2    # see the lit scene in (inter-)reflections of glossy surfaces
TRANSMISSION_EXTRA_DEPTH = 4  # enter and leave a glass object, twice


@dataclass(frozen=True)
class Effects:
    """Declared effects of one scene: ``{name: params}``, with the scene name for messages."""

    scene: str
    declared: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def __contains__(self, name: str) -> bool:
        return name in self.declared

    def names(self) -> list[str]:
        return list(self.declared)

    def param(self, effect: str, key: str):
        return self.declared[effect][key]

    def require(self, effect: str, what: str) -> None:
        """Raise a one-line :class:`ConfigError` if ``effect`` is not declared (``what`` needs it)."""
        if effect not in self.declared:
            raise ConfigError(f"scene '{self.scene}': {what} needs effect '{effect}', which the scene does not "
                              f"declare (effects: [{', '.join(self.declared) or ''}])")


def parse_effects(scene: str, entries) -> Effects:
    """Parse a config ``effects`` list: names, or one-key mappings ``{name: value-or-params}``.

    ``{indirect: 5}`` is shorthand for ``{indirect: {bounces: 5}}``.
    """
    if entries is None:
        entries = []
    if isinstance(entries, (str, Mapping)):
        raise ConfigError(f"scene '{scene}': key 'effects' must be a list, got {type(entries).__name__}")
    declared: dict[str, dict[str, Any]] = {}
    for entry in entries:
        if isinstance(entry, str):
            name, params = entry, {}
        elif isinstance(entry, Mapping) and len(entry) == 1:
            name, value = next(iter(entry.items()))
            if isinstance(value, Mapping):
                params = dict(value)
            else:
                defaults = EFFECTS.get(name, {})
                if len(defaults) != 1:
                    raise ConfigError(f"scene '{scene}': effect '{name}' takes no shorthand value")
                params = {next(iter(defaults)): value}
        else:
            raise ConfigError(f"scene '{scene}': effects entry {entry!r} must be a name or {{name: params}}")
        if name not in EFFECTS:
            raise ConfigError(f"scene '{scene}': unknown effect '{name}'; known: {', '.join(EFFECTS)}")
        unknown = set(params) - set(EFFECTS[name])
        if unknown:
            raise ConfigError(f"scene '{scene}': effect '{name}' has unknown parameter(s) "
                              f"{', '.join(sorted(unknown))}")
        declared[name] = {**EFFECTS[name], **params}
    if "indirect" in declared:
        b = declared["indirect"]["bounces"]
        if isinstance(b, bool) or not isinstance(b, int) or b < 1:
            raise ConfigError(f"scene '{scene}': effect 'indirect' bounces must be an integer >= 1, got {b!r}")
    return Effects(scene, declared)


def path_depth(effects: Effects) -> int:
    """Mitsuba ``max_depth`` for the declared light transport.

    2 (direct light only) + ``bounces`` with ``indirect`` + 2 with ``glossy`` + 4 with
    ``transmission``.
    """
    depth = DIRECT_DEPTH
    if "indirect" in effects:
        depth += int(effects.param("indirect", "bounces"))
    if "glossy" in effects:
        depth += GLOSSY_EXTRA_DEPTH
    if "transmission" in effects:
        depth += TRANSMISSION_EXTRA_DEPTH
    return depth
