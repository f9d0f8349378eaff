"""Effect-aware assembly of the Mitsuba scene dict of one instant ``tau``.

One small function per concern: :func:`integrator` (path depth from the declared light
transport), :func:`main_sensor` (pinhole unless ``dof``), :func:`aux_sensor` (pinhole through
the pixel centres, one sample, for the auxiliary buffers and motion), :func:`emitters`,
:func:`shapes`. :func:`scene_dict` puts them together.
"""

from __future__ import annotations

from denoiser.errors import ConfigError
from denoiser.render.effects import path_depth
from denoiser.render.emitters import build_emitter
from denoiser.render.shapes import build_shapes
from denoiser.render.spec import SceneSpec

MAIN_SENSOR = "main_sensor"
AUX_SENSOR = "aux_sensor"


def integrator(spec: SceneSpec) -> dict:
    """Unidirectional path tracer; ``max_depth`` from :func:`denoiser.render.effects.path_depth`
    (Russian roulette from depth 5, Mitsuba's default)."""
    depth = path_depth(spec.effects)
    return {"type": "path", "max_depth": depth}


def _film(width: int, height: int) -> dict:
    return {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "rgb", "sample_border": False}


def main_sensor(mi, spec: SceneSpec, tau: float, width: int, height: int) -> dict:
    """Noisy/reference camera: ``thinlens`` only with ``dof``, else ``perspective`` (pinhole).

    The shutter stays closed in Mitsuba (it has no animated shapes); motion blur is made by
    rendering sub-frame instants (see :mod:`denoiser.render.passes`).
    """
    cam = spec.camera
    sensor = {"type": "perspective", "fov": cam.fov, "fov_axis": "x",
              "to_world": mi.ScalarTransform4f(cam.to_world(tau).tolist()),
              "sampler": {"type": "independent", "sample_count": 1}, "film": _film(width, height)}
    if "dof" in spec.effects:
        if cam.aperture <= 0:
            raise ConfigError(f"scene '{spec.name}': effect 'dof' declared but camera.aperture is {cam.aperture}")
        sensor.update(type="thinlens", aperture_radius=cam.aperture, focus_distance=cam.focus())
    return sensor


def aux_sensor(mi, spec: SceneSpec, tau: float, width: int, height: int) -> dict:
    """Pinhole camera sampling exactly the pixel centres (stratified, no jitter, 1 spp)."""
    cam = spec.camera
    return {"type": "perspective", "fov": cam.fov, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(cam.to_world(tau).tolist()),
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
            "film": _film(width, height)}


def emitters(mi, spec: SceneSpec) -> dict:
    out: dict = {}
    for light in spec.lights:
        out.update(build_emitter(mi, light, spec.effects))
    return out


def shapes(mi, spec: SceneSpec, tau: float) -> dict:
    out: dict = {}
    for obj in spec.objects:
        out.update(build_shapes(mi, obj, tau, spec.effects))
    return out


def scene_dict(mi, spec: SceneSpec, tau: float, width: int, height: int) -> dict:
    """The complete Mitsuba scene dict at time ``tau`` (frames)."""
    return {"type": "scene", "integrator": integrator(spec),
            MAIN_SENSOR: main_sensor(mi, spec, tau, width, height),
            AUX_SENSOR: aux_sensor(mi, spec, tau, width, height),
            **emitters(mi, spec), **shapes(mi, spec, tau)}
