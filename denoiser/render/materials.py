"""Materials -> Mitsuba BSDF dicts, each checking the effects it needs.

``material: {type: <kind>, ...}``; kinds and the effect each needs:

============  ==========================  =========================================================
type          needs                       parameters
============  ==========================  =========================================================
diffuse       (textures if textured)      ``color``
plastic       glossy                      ``color``, ``roughness`` (GGX alpha, default 0.1)
conductor     glossy                      ``metal`` (Mitsuba name: Al, Au, Cu, Ag...), ``roughness``
                                          (default 0.2; 0 = mirror), ``tint``
glass         transmission                ``ior`` (1.5), ``tint`` (transmittance colour)
rough_glass   transmission, glossy        ``ior``, ``roughness`` (0.15), ``tint``
============  ==========================  =========================================================

A colour is ``[r, g, b]`` (linear) or a texture spec (:mod:`denoiser.render.textures`).
Opaque materials are two-sided, so walls and cards look the same from both sides.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from denoiser.errors import ConfigError
from denoiser.render.effects import Effects
from denoiser.render.textures import SHARP, texture_array

DEFAULT = {"type": "diffuse", "color": [0.7, 0.7, 0.7]}


def _color(mi, value, effects: Effects, where: str) -> dict:
    if isinstance(value, Mapping):
        effects.require("textures", f"{where} (texture '{value.get('texture')}')")
        arr = texture_array(value, where)
        return {"type": "bitmap", "bitmap": mi.Bitmap(arr), "raw": True,
                "filter_type": "nearest" if value.get("texture") in SHARP else "bilinear"}
    try:
        rgb = [float(c) for c in value]
    except TypeError:
        raise ConfigError(f"{where}: colour must be [r, g, b] or a texture, got {value!r}") from None
    if len(rgb) != 3:
        raise ConfigError(f"{where}: colour must have 3 components, got {value!r}")
    return {"type": "rgb", "value": rgb}


def _twosided(bsdf: dict) -> dict:
    return {"type": "twosided", "bsdf": bsdf}


def diffuse(mi, p, effects, where) -> dict:
    return _twosided({"type": "diffuse", "reflectance": _color(mi, p.get("color", DEFAULT["color"]), effects,
                                                                 f"{where}.color")})


def plastic(mi, p, effects, where) -> dict:
    effects.require("glossy", f"{where} (plastic)")
    return _twosided({"type": "roughplastic", "distribution": "ggx", "alpha": float(p.get("roughness", 0.1)),
                      "diffuse_reflectance": _color(mi, p.get("color", [0.5, 0.5, 0.5]), effects,
                                                    f"{where}.color")})


def conductor(mi, p, effects, where) -> dict:
    effects.require("glossy", f"{where} (conductor)")
    alpha = float(p.get("roughness", 0.2))
    bsdf: dict[str, Any] = {"type": "roughconductor" if alpha > 0 else "conductor",
                            "material": str(p.get("metal", "Al"))}
    if alpha > 0:
        bsdf.update(distribution="ggx", alpha=alpha)
    if "tint" in p:
        bsdf["specular_reflectance"] = _color(mi, p["tint"], effects, f"{where}.tint")
    return _twosided(bsdf)


def glass(mi, p, effects, where) -> dict:
    effects.require("transmission", f"{where} (glass)")
    bsdf: dict[str, Any] = {"type": "dielectric", "int_ior": float(p.get("ior", 1.5)), "ext_ior": 1.0}
    if "tint" in p:
        bsdf["specular_transmittance"] = _color(mi, p["tint"], effects, f"{where}.tint")
    return bsdf


def rough_glass(mi, p, effects, where) -> dict:
    effects.require("transmission", f"{where} (rough_glass)")
    effects.require("glossy", f"{where} (rough_glass)")
    bsdf: dict[str, Any] = {"type": "roughdielectric", "distribution": "ggx", "alpha": float(p.get("roughness", 0.15)),
                            "int_ior": float(p.get("ior", 1.5)), "ext_ior": 1.0}
    if "tint" in p:
        bsdf["specular_transmittance"] = _color(mi, p["tint"], effects, f"{where}.tint")
    return bsdf


MATERIALS: dict[str, Callable[..., dict]] = {"diffuse": diffuse, "plastic": plastic, "conductor": conductor,
                                             "glass": glass, "rough_glass": rough_glass}


def build_bsdf(mi, material: Mapping[str, Any] | None, effects: Effects, where: str) -> dict:
    """Mitsuba BSDF dict of a material spec (``None`` = light grey diffuse)."""
    material = dict(material or DEFAULT)
    kind = material.get("type", "diffuse")
    if kind not in MATERIALS:
        raise ConfigError(f"scene '{effects.scene}': {where}: unknown material type {kind!r}; known: "
                          f"{', '.join(MATERIALS)}")
    return MATERIALS[kind](mi, material, effects, f"{where}.material")
