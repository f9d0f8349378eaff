"""Object shapes -> Mitsuba shape dicts (one or several per object), placed at time ``tau``.

Kinds (``shape:``), all in object space before position/rotation/scale:

* ``sphere`` (radius 1), ``cube`` ([-1, 1]^3), ``rectangle`` ([-1, 1]^2 in the xy plane,
  normal +z), ``disk`` (radius 1, normal +z), ``cylinder`` (radius 1, z in [0, 1]);
* procedural meshes built in numpy: ``torus`` (``params: {major: 1, minor: 0.35}``) and
  ``wave`` (a rippled square in the xz plane, ``params: {amplitude, frequency, segments}``);
* ``room``: an open-front Cornell room (x, z in [-1, 1], y in [0, 2]) made of five walls
  with materials ``params: {walls, left, right, floor, ceiling, back}`` (each a material;
  ``floor``/``ceiling``/``back`` default to ``walls``, which defaults to the object's
  ``material`` or light grey).

Shape ids in the Mitsuba scene are ``<object>`` or ``<object>__<part>``, so every hit can be
traced back to its object (for motion vectors).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np

from denoiser.errors import ConfigError
from denoiser.render import transforms as tf
from denoiser.render.effects import Effects
from denoiser.render.materials import build_bsdf
from denoiser.render.spec import ObjectSpec

SEP = "__"


def _xf(mi, m: np.ndarray):
    return mi.ScalarTransform4f(np.asarray(m, dtype=np.float64).tolist())


def _primitive(kind: str):
    def build(mi, obj: ObjectSpec, m: np.ndarray, effects: Effects) -> dict:
        if obj.params:
            raise ConfigError(f"scene '{effects.scene}': object '{obj.name}': a {kind} takes no params "
                              f"(got {', '.join(sorted(obj.params))})")
        return {obj.name: {"type": kind, "to_world": _xf(mi, m),
                           "bsdf": build_bsdf(mi, obj.material, effects, f"object '{obj.name}'")}}
    return build


def _sphere(mi, obj: ObjectSpec, m: np.ndarray, effects: Effects) -> dict:
    if not np.allclose(obj.scale, obj.scale[0]):
        raise ConfigError(f"scene '{effects.scene}': object '{obj.name}': a sphere needs a uniform scale")
    return _primitive("sphere")(mi, obj, m, effects)


ROOM_WALLS = {  # part -> (object-space placement of the [-1,1]^2 rectangle, material key)
    "floor": (tf.rotate([1, 0, 0], -90), "floor"),
    "ceiling": (tf.translate([0, 2, 0]) @ tf.rotate([1, 0, 0], 90), "ceiling"),
    "back": (tf.translate([0, 1, -1]), "back"),
    "left": (tf.translate([-1, 1, 0]) @ tf.rotate([0, 1, 0], 90), "left"),
    "right": (tf.translate([1, 1, 0]) @ tf.rotate([0, 1, 0], -90), "right"),
}
ROOM_DEFAULTS = {"walls": {"type": "diffuse", "color": [0.73, 0.73, 0.73]},
                 "left": {"type": "diffuse", "color": [0.63, 0.065, 0.05]},
                 "right": {"type": "diffuse", "color": [0.14, 0.45, 0.091]}}


def _room(mi, obj: ObjectSpec, m: np.ndarray, effects: Effects) -> dict:
    p = {**ROOM_DEFAULTS, **({"walls": obj.material} if obj.material else {}), **obj.params}
    unknown = set(p) - {"walls", "left", "right", "floor", "ceiling", "back"}
    if unknown:
        raise ConfigError(f"scene '{effects.scene}': object '{obj.name}': unknown room params "
                          f"{', '.join(sorted(unknown))}")
    out = {}
    for part, (place, key) in ROOM_WALLS.items():
        material = p.get(key, p["walls"])
        out[f"{obj.name}{SEP}{part}"] = {
            "type": "rectangle", "to_world": _xf(mi, m @ place),
            "bsdf": build_bsdf(mi, material, effects, f"object '{obj.name}' {part}")}
    return out


@lru_cache(maxsize=32)
def torus_mesh(major: float = 1.0, minor: float = 0.35, segments: int = 48, rings: int = 24):
    """(positions [N,3], faces [M,3] uint32, uv [N,2]) of a torus around the y axis."""
    u = np.linspace(0, 2 * np.pi, segments + 1)
    v = np.linspace(0, 2 * np.pi, rings + 1)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    x = (major + minor * np.cos(vv)) * np.cos(uu)
    z = (major + minor * np.cos(vv)) * np.sin(uu)
    y = minor * np.sin(vv)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    uv = np.stack([uu / (2 * np.pi), vv / (2 * np.pi)], -1).reshape(-1, 2)
    return pos, _grid_faces(segments, rings, flip=True), uv


@lru_cache(maxsize=32)
def wave_mesh(amplitude: float = 0.1, frequency: float = 2.0, segments: int = 64):
    """(positions, faces, uv) of a rippled square in the xz plane (x, z in [-1, 1]), normal +y."""
    s = np.linspace(-1, 1, segments + 1)
    xx, zz = np.meshgrid(s, s, indexing="ij")
    yy = amplitude * np.sin(np.pi * frequency * xx) * np.cos(np.pi * frequency * zz)
    pos = np.stack([xx, yy, zz], -1).reshape(-1, 3)
    uv = np.stack([(xx + 1) / 2, (zz + 1) / 2], -1).reshape(-1, 2)
    return pos, _grid_faces(segments, segments, flip=False), uv


def _grid_faces(nu: int, nv: int, flip: bool) -> np.ndarray:
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = (i * (nv + 1) + j).ravel()
    b, c, d = a + nv + 1, a + 1, a + nv + 2
    f = np.concatenate([np.stack([a, c, b], -1), np.stack([c, d, b], -1)])
    return (f[:, ::-1] if flip else f).astype(np.uint32)


def _mesh(name: str, generator: Callable):
    def build(mi, obj: ObjectSpec, m: np.ndarray, effects: Effects) -> dict:
        try:
            pos, faces, uv = generator(**{k: obj.params[k] for k in obj.params})
        except TypeError as exc:
            raise ConfigError(f"scene '{effects.scene}': object '{obj.name}': bad {name} params ({exc})") from None
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(build_bsdf(mi, obj.material, effects, f"object '{obj.name}'"))
        mesh = mi.Mesh(obj.name, len(pos), len(faces), props=props, has_vertex_normals=True,
                       has_vertex_texcoords=True)
        params = mi.traverse(mesh)
        world = tf.apply(m, pos).astype(np.float32)
        for key, arr in (("vertex_positions", world), ("faces", faces), ("vertex_texcoords", uv.astype(np.float32))):
            params[key] = type(params[key])(np.ascontiguousarray(arr).ravel())
        params.update()
        mesh.recompute_vertex_normals()
        return {obj.name: mesh}
    return build


SHAPES: dict[str, Callable[..., dict]] = {
    "sphere": _sphere,
    "cube": _primitive("cube"),
    "rectangle": _primitive("rectangle"),
    "disk": _primitive("disk"),
    "cylinder": _primitive("cylinder"),
    "torus": _mesh("torus", torus_mesh),
    "wave": _mesh("wave", wave_mesh),
    "room": _room,
}


def build_shapes(mi, obj: ObjectSpec, tau: float, effects: Effects) -> dict:
    """Mitsuba shape entries ``{id: dict-or-Mesh}`` of one object at time ``tau``."""
    if obj.shape not in SHAPES:
        raise ConfigError(f"scene '{effects.scene}': object '{obj.name}': unknown shape {obj.shape!r}; known: "
                          f"{', '.join(SHAPES)}")
    return SHAPES[obj.shape](mi, obj, obj.to_world(tau), effects)


def object_of(shape_id: str) -> str:
    """Object name of a Mitsuba shape id."""
    return shape_id.split(SEP, 1)[0]
