"""Scene configs -> plain scene descriptions (dataclasses), randomized per sequence.

A scene config (``conf/scene/<name>.yaml``) holds ``name``, ``test_only``, ``effects``,
``camera``, ``objects`` and ``lights`` (format in ``docs/simulator.md``), and may hold keys
named ``x-...``: definitions that the others share through YAML anchors, dropped before the
draw (``conf/scene/medley.yaml``). Random specs in it
(:mod:`denoiser.render.randomize`) are drawn with ``numpy.random.default_rng(seed)``, so one
config yields many sequences. Time ``tau`` is measured in frames (frame ``t`` is at
``tau = t``; motion blur integrates over ``tau`` in ``[t - shutter/2, t + shutter/2]``).
Checks that need the declared effects live in :mod:`denoiser.render.effects` and in the
builders; this module checks structure (unknown keys, shapes of vectors).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from denoiser.errors import ConfigError
from denoiser.render import transforms as tf
from denoiser.render.effects import Effects, parse_effects
from denoiser.render.randomize import resolve

CAMERA_KEYS = {"origin", "target", "up", "fov", "orbit", "dolly", "aperture", "focus_distance", "shutter"}
OBJECT_KEYS = {"name", "shape", "params", "position", "rotation", "scale", "material", "velocity", "spin",
               "enabled"}
SCENE_KEYS = {"name", "test_only", "effects", "camera", "objects", "lights", "description"}
SHARED_PREFIX = "x-"  # top-level keys that only hold YAML anchors' definitions
DEFAULT_SHUTTER = 0.5


def _vec(value, where: str, n: int = 3) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise ConfigError(f"{where}: expected {n} finite numbers, got {value!r}")
    return arr


def _check_keys(node: Mapping, allowed: set[str], where: str) -> None:
    unknown = set(node) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; allowed: "
                          f"{', '.join(sorted(allowed))}")


@dataclass(frozen=True)
class CameraSpec:
    """Perspective camera; ``orbit`` (degrees/frame about ``up`` through ``target``) and
    ``dolly`` (world units/frame) animate it; ``aperture`` (lens radius) needs ``dof``;
    ``shutter`` (fraction of a frame interval) needs ``motion_blur``."""

    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float
    orbit: float = 0.0
    dolly: np.ndarray = field(default_factory=lambda: np.zeros(3))
    aperture: float = 0.0
    focus_distance: float | None = None
    shutter: float = 0.0

    @property
    def moves(self) -> bool:
        return self.orbit != 0.0 or bool(np.any(self.dolly != 0.0))

    def to_world(self, tau: float) -> np.ndarray:
        """Camera-to-world 4x4 at time ``tau`` (frames)."""
        rot = tf.rotate(self.up, self.orbit * tau)
        origin = self.target + tf.apply_vector(rot, self.origin - self.target) + self.dolly * tau
        return tf.look_at(origin, self.target + self.dolly * tau, self.up)

    def focus(self) -> float:
        return float(self.focus_distance or np.linalg.norm(self.target - self.origin))


@dataclass(frozen=True)
class ObjectSpec:
    """One object: a shape (``shape`` + ``params``) placed by position/rotation/scale and moved
    per frame by ``velocity`` (units/frame) and ``spin`` (``axis``, ``degrees``/frame)."""

    name: str
    shape: str
    params: Mapping[str, Any]
    material: Mapping[str, Any] | None
    position: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    velocity: np.ndarray
    spin_axis: np.ndarray
    spin_degrees: float

    @property
    def moves(self) -> bool:
        return bool(np.any(self.velocity != 0.0)) or self.spin_degrees != 0.0

    def to_world(self, tau: float) -> np.ndarray:
        """Object-to-world 4x4 at time ``tau``: translate . spin . rotation . scale."""
        return (tf.translate(self.position + self.velocity * tau) @ tf.rotate(self.spin_axis, self.spin_degrees * tau)
                @ tf.euler(self.rotation) @ tf.scale(self.scale))


@dataclass(frozen=True)
class LightSpec:
    """An emitter: ``type`` (area, sky, constant) and its parameters."""

    name: str
    type: str
    params: Mapping[str, Any]


@dataclass(frozen=True)
class SceneSpec:
    """A fully drawn scene: everything the Mitsuba builders need, plus the drawn ``params``."""

    name: str
    effects: Effects
    camera: CameraSpec
    objects: tuple[ObjectSpec, ...]
    lights: tuple[LightSpec, ...]
    test_only: bool = False
    params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def moving_objects(self) -> list[int]:
        return [i for i, o in enumerate(self.objects) if o.moves]

    @property
    def is_static(self) -> bool:
        return not self.camera.moves and not self.moving_objects


def _camera(node: Mapping, effects: Effects, where: str) -> CameraSpec:
    _check_keys(node, CAMERA_KEYS, where)
    for key in ("origin", "target", "fov"):
        if key not in node:
            raise ConfigError(f"{where}: missing key '{key}'")
    fov = float(node["fov"])
    if not 0 < fov < 180:
        raise ConfigError(f"{where}.fov: must be in (0, 180) degrees, got {fov}")
    shutter = node.get("shutter")
    if shutter is None:
        shutter = DEFAULT_SHUTTER if "motion_blur" in effects else 0.0
    cam = CameraSpec(
        origin=_vec(node["origin"], f"{where}.origin"), target=_vec(node["target"], f"{where}.target"),
        up=_vec(node.get("up", [0, 1, 0]), f"{where}.up"), fov=fov, orbit=float(node.get("orbit", 0.0)),
        dolly=_vec(node.get("dolly", 0.0), f"{where}.dolly"), aperture=float(node.get("aperture", 0.0)),
        focus_distance=None if node.get("focus_distance") is None else float(node["focus_distance"]),
        shutter=float(shutter),
    )
    if cam.moves:
        effects.require("camera_motion", "a camera with orbit/dolly")
    if cam.aperture > 0:
        effects.require("dof", f"a camera aperture of {cam.aperture}")
    if cam.shutter > 0:
        effects.require("motion_blur", f"an open shutter ({cam.shutter})")
    if not 0 <= cam.shutter <= 1:
        raise ConfigError(f"{where}.shutter: must be in [0, 1] (fraction of a frame), got {cam.shutter}")
    return cam


def _object(node: Mapping, index: int, effects: Effects, where: str) -> ObjectSpec | None:
    if not isinstance(node, Mapping):
        raise ConfigError(f"{where}: must be a mapping")
    _check_keys(node, OBJECT_KEYS, where)
    if not node.get("enabled", True):
        return None
    if "shape" not in node:
        raise ConfigError(f"{where}: missing key 'shape'")
    spin = node.get("spin") or {}
    obj = ObjectSpec(
        name=str(node.get("name", f"{node['shape']}{index}")), shape=str(node["shape"]),
        params=dict(node.get("params") or {}), material=node.get("material"),
        position=_vec(node.get("position", 0.0), f"{where}.position"),
        rotation=_vec(node.get("rotation", 0.0), f"{where}.rotation"),
        scale=_vec(node.get("scale", 1.0), f"{where}.scale"),
        velocity=_vec(node.get("velocity", 0.0), f"{where}.velocity"),
        spin_axis=_vec(spin.get("axis", [0, 1, 0]), f"{where}.spin.axis"),
        spin_degrees=float(spin.get("degrees", 0.0)),
    )
    if obj.moves:
        effects.require("object_motion", f"object '{obj.name}' with velocity/spin")
    return obj


def build_scene(config: Mapping[str, Any], seed: int) -> SceneSpec:
    """Draw the random parameters of ``config`` with ``seed`` and build a :class:`SceneSpec`.

    Raises :class:`ConfigError` (one line naming the scene and key) on structural mistakes and
    on settings that need an undeclared effect.
    """
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(config, (DictConfig, ListConfig)):
        config = OmegaConf.to_container(config, resolve=True)
    config = {k: v for k, v in config.items() if not str(k).startswith(SHARED_PREFIX)}
    name = str(config.get("name", "")) or "unnamed"
    where = f"scene '{name}'"
    _check_keys(config, SCENE_KEYS, where)
    drawn = resolve(config, np.random.default_rng(seed), where)
    effects = parse_effects(name, drawn.get("effects"))
    if "camera" not in drawn:
        raise ConfigError(f"{where}: missing key 'camera'")
    camera = _camera(drawn["camera"], effects, f"{where}.camera")
    objects = []
    for i, node in enumerate(drawn.get("objects") or []):
        obj = _object(node, i, effects, f"{where}.objects[{i}]")
        if obj is not None:
            objects.append(obj)
    names = [o.name for o in objects]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(f"{where}: duplicate object name(s) {', '.join(sorted(dup))}")
    lights = []
    for i, node in enumerate(drawn.get("lights") or []):
        if not isinstance(node, Mapping) or "type" not in node:
            raise ConfigError(f"{where}.lights[{i}]: must be a mapping with a 'type'")
        params = {k: v for k, v in node.items() if k not in ("type", "name")}
        lights.append(LightSpec(str(node.get("name", f"light{i}")), str(node["type"]), params))
    if not lights:
        raise ConfigError(f"{where}: no lights (add an area light or an environment light)")
    return SceneSpec(name=name, effects=effects, camera=camera, objects=tuple(objects), lights=tuple(lights),
                     test_only=bool(drawn.get("test_only", False)), params=drawn)
