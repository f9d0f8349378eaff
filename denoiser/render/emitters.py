"""Lights -> Mitsuba emitter dicts, each checking the effect it needs.

``lights:`` entries, by ``type``:

* ``area`` (needs ``area_light``): an emitting rectangle at ``position`` facing ``target``
  with ``size: [w, h]`` and ``radiance: [r, g, b]``; or ``shape: sphere`` with ``radius``;
* ``sky`` (needs ``env_light``): a procedural lat-long environment map (y up): ``zenith``,
  ``horizon`` and ``ground`` colours, a sun disc (``sun_direction``, ``sun_radiance``,
  ``sun_size`` in degrees) and ``strength``;
* ``constant`` (needs ``env_light``): uniform ``radiance`` from all directions.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np

from denoiser.errors import ConfigError
from denoiser.render import transforms as tf
from denoiser.render.effects import Effects
from denoiser.render.spec import LightSpec

SKY_WIDTH = 256


def _rgb(value, where: str) -> list[float]:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,):
        raise ConfigError(f"{where}: expected [r, g, b], got {value!r}")
    return arr.tolist()


AREA_KEYS = {"position", "target", "size", "radiance", "shape", "radius"}


def area(mi, light: LightSpec, effects: Effects) -> dict:
    where = f"scene '{effects.scene}': light '{light.name}'"
    effects.require("area_light", f"light '{light.name}' (area)")
    p = light.params
    unknown = set(p) - AREA_KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; allowed: "
                          f"{', '.join(sorted(AREA_KEYS))}")
    emitter = {"type": "area", "radiance": {"type": "rgb", "value": _rgb(p.get("radiance", [10, 10, 10]),
                                                                           f"{where}.radiance")}}
    pos = np.asarray(p.get("position", [0, 1.98, 0]), dtype=float)
    if p.get("shape", "rectangle") == "sphere":
        m = tf.translate(pos) @ tf.scale(float(p.get("radius", 0.1)))
        kind = "sphere"
    else:
        target = np.asarray(p.get("target", pos - np.array([0, 1, 0])), dtype=float)
        w, h = (np.asarray(p.get("size", [0.5, 0.5]), dtype=float) * 0.5).tolist()
        forward = target - pos
        up = [0, 0, 1] if abs(forward[1]) > 0.99 * np.linalg.norm(forward) else [0, 1, 0]
        m = tf.look_at(pos, target, up) @ tf.scale([w, h, 1])  # rectangle normal +z faces the target
        kind = "rectangle"
    return {f"light__{light.name}": {"type": kind, "to_world": mi.ScalarTransform4f(m.tolist()),
                                          "emitter": emitter}}


@lru_cache(maxsize=16)
def sky_array(zenith=(0.2, 0.4, 0.9), horizon=(0.8, 0.85, 0.9), ground=(0.25, 0.22, 0.2),
              sun_direction=(0.4, 0.7, 0.3), sun_radiance=(300.0, 280.0, 250.0), sun_size=3.0,
              strength=1.0) -> np.ndarray:
    """Lat-long environment ``[W/2, W, 3]`` in Mitsuba's envmap parametrization (row 0 = +y)."""
    h, w = SKY_WIDTH // 2, SKY_WIDTH
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    y = d[..., 1:2]
    up = np.clip(y, 0, 1) ** 0.5
    sky = np.asarray(horizon) * (1 - up) + np.asarray(zenith) * up
    img = np.where(y >= 0, sky, np.asarray(ground) * (1 - 0.5 * np.clip(-y, 0, 1)))
    s = np.asarray(sun_direction, dtype=float)
    s = s / np.linalg.norm(s)
    cosang = d @ s
    img = img + np.asarray(sun_radiance) * (cosang > np.cos(np.radians(sun_size)))[..., None]
    return (img * strength).astype(np.float32)


def sky(mi, light: LightSpec, effects: Effects) -> dict:
    effects.require("env_light", f"light '{light.name}' (sky)")
    params = {k: (tuple(v) if isinstance(v, list) else v) for k, v in light.params.items()}
    try:
        arr = sky_array(**params)
    except TypeError as exc:
        raise ConfigError(f"scene '{effects.scene}': light '{light.name}': bad sky params ({exc})") from None
    return {f"light__{light.name}": {"type": "envmap", "bitmap": mi.Bitmap(arr)}}


def constant(mi, light: LightSpec, effects: Effects) -> dict:
    effects.require("env_light", f"light '{light.name}' (constant)")
    where = f"scene '{effects.scene}': light '{light.name}'.radiance"
    if set(light.params) - {"radiance"}:
        raise ConfigError(f"scene '{effects.scene}': light '{light.name}': a constant light takes only 'radiance'")
    return {f"light__{light.name}": {"type": "constant", "radiance": {
        "type": "rgb", "value": _rgb(light.params.get("radiance", 1.0), where)}}}


EMITTERS: dict[str, Callable[..., dict]] = {"area": area, "sky": sky, "constant": constant}


def build_emitter(mi, light: LightSpec, effects: Effects) -> dict:
    if light.type not in EMITTERS:
        raise ConfigError(f"scene '{effects.scene}': light '{light.name}': unknown type {light.type!r}; known: "
                          f"{', '.join(EMITTERS)}")
    return EMITTERS[light.type](mi, light, effects)
