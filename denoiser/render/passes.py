"""Render passes of one frame: noisy colour, per-sample radiance, auxiliary buffers, reference.

All arrays are numpy float32, ``[H, W, C]`` (samples ``[S, H, W, 3]``).

* noisy colour: ``spp`` samples through the main sensor (box pixel filter) with one seed;
  with ``save_samples`` ``spp`` passes of 1 sample, each with its own seed;
* motion blur (``camera.shutter > 0``): samples are spread over stratified sub-frame instants
  ``tau in [t - shutter/2, t + shutter/2]`` and averaged (one scene per instant; the scene is
  otherwise rendered at ``tau = t``);
* auxiliary buffers: one ray through each pixel centre at ``tau = t`` (pinhole, also with dof;
  Mitsuba's ``aov`` integrator): albedo (clamped to [0, 1]; Mitsuba's exceeds 1 on rough
  conductors), camera-space shading normal, planar depth (no hit: ``NO_HIT_DEPTH``), the world
  position and the object hit (index into ``spec.objects``, -1 = none or a light). With dof or
  an open shutter, albedo and normal are instead averaged over ``BLURRED_AUX_SPP`` samples
  through the lens and over the shutter, like the colour (as Cycles' denoising passes are), so
  they blur where the image blurs; depth, position and motion stay pixel-centre values;
* reference: ``ref_spp`` samples with its own seed, same sensor as the noisy colour;
* ``aux: samples`` (:meth:`FrameRenderer.radiance_aux`): albedo and normal are instead the means
  over the noisy colour's own samples (Mitsuba's ``aov`` integrator nesting the path tracer, so
  the colour is unchanged), as Cycles' ``Denoising Albedo`` and ``Denoising Normal`` are: at a
  few spp they carry the colour's sub-pixel texture noise, and they blur with dof and motion blur.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from denoiser.render import transforms as tf
from denoiser.render.build import AUX_SENSOR, MAIN_SENSOR, integrator, scene_dict
from denoiser.render.shapes import object_of
from denoiser.render.spec import SceneSpec

NO_HIT_DEPTH = 1e10
MAX_TIME_SAMPLES = 16  # sub-frame instants for a motion-blurred reference
BLURRED_AUX_SPP = 16   # lens/shutter samples of albedo and normal with dof or motion blur
AOVS = "albedo:albedo,nn:sh_normal,pos:position,dd:depth,sid:shape_index"
ALBEDO_NORMAL_AOVS = "albedo:albedo,nn:sh_normal"  # blurred aux; aux=samples nests the path tracer in it
AUX_MODES = ("center", "samples")


@dataclass
class AuxBuffers:
    """Pixel-centre buffers of one frame.

    ``albedo [H,W,3]`` in [0,1]; ``normal [H,W,3]`` camera space unit (0 = no hit);
    ``depth [H,W,1]`` planar (``NO_HIT_DEPTH`` = no hit); ``position [H,W,3]`` world;
    ``hit bool [H,W]``; ``object int32 [H,W]`` (-1 = no object).
    """

    albedo: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    position: np.ndarray
    hit: np.ndarray
    object: np.ndarray


class FrameRenderer:
    """Renders the passes of a :class:`SceneSpec` at ``width x height`` (scenes cached per ``tau``)."""

    def __init__(self, mi, spec: SceneSpec, width: int, height: int):
        self.mi = mi
        self.spec = spec
        self.width = width
        self.height = height
        self._cached: tuple[float, object] | None = None
        self._aov = None
        self._with_aux = None
        self.scene_loads = 0

    # -- scenes
    def scene(self, tau: float):
        """The loaded Mitsuba scene at time ``tau`` (the last one is cached)."""
        if self._cached is None or self._cached[0] != tau:
            self._cached = (tau, self.mi.load_dict(scene_dict(self.mi, self.spec, tau, self.width, self.height)))
            self.scene_loads += 1
        return self._cached[1]

    def _sensor(self, scene, name: str):
        return next(s for s in scene.sensors() if s.id() == name)

    def _render(self, tau: float, spp: int, seed: int) -> np.ndarray:
        scene = self.scene(tau)
        img = self.mi.render(scene, sensor=self._sensor(scene, MAIN_SENSOR), spp=int(spp), seed=int(seed) & 0xFFFFFFFF)
        return np.array(img, dtype=np.float32)[..., :3]

    @property
    def shutter_open(self) -> bool:
        """True when the shutter is open and something moves (a static scene needs no sub-frames)."""
        return self.spec.camera.shutter > 0 and not self.spec.is_static

    def _instants(self, t: int, count: int, seed: int) -> list[float]:
        """``count`` stratified instants over the shutter interval of frame ``t`` (just ``t`` if closed)."""
        shutter = self.spec.camera.shutter
        if not self.shutter_open:
            return [float(t)] * count
        u = np.random.default_rng(seed).random(count)
        return [float(t + shutter * ((k + u[k]) / count - 0.5)) for k in range(count)]

    # -- passes
    def _mean_over_shutter(self, render, t: int, spp: int, seed: int, time_samples: int | None = None
                           ) -> np.ndarray:
        """Mean of ``render(tau, spp, seed) -> [H,W,C]`` over ``spp`` samples, spread over
        sub-frame instants when the shutter is open (one seed per instant)."""
        if not self.shutter_open:
            return render(float(t), spp, seed)
        n = min(spp, time_samples or spp)
        counts = [spp // n + (1 if k < spp % n else 0) for k in range(n)]
        acc = None
        for k, (tau, c) in enumerate(zip(self._instants(t, n, seed), counts)):
            part = c * render(tau, c, seed + 7919 * (k + 1))
            acc = part if acc is None else acc + part
        return acc / spp

    def radiance(self, t: int, spp: int, seed: int, time_samples: int | None = None) -> np.ndarray:
        """Mean radiance ``[H,W,3]`` of ``spp`` samples (spread over sub-frame instants if blurred)."""
        return self._mean_over_shutter(self._render, t, spp, seed, time_samples)

    def samples(self, t: int, seeds: list[int]) -> np.ndarray:
        """Per-sample radiance ``[S,H,W,3]``: one 1-spp pass per seed (and per instant if blurred)."""
        taus = self._instants(t, len(seeds), seeds[0])
        return np.stack([self._render(tau, 1, s) for tau, s in zip(taus, seeds)])

    def samples_aux(self, t: int, seeds: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`samples` with the albedo and normal of the same samples (``aux: samples``):
        ``(samples [S,H,W,3], albedo [H,W,3], normal [H,W,3])``, as :meth:`radiance_aux`."""
        taus = self._instants(t, len(seeds), seeds[0])
        passes = np.stack([self._render_with_aux(tau, 1, s) for tau, s in zip(taus, seeds)])
        _, albedo, normal = self._split_aux(passes.astype(np.float64).mean(axis=0), t)
        return passes[..., 0:3], albedo, normal

    def _split_aux(self, mean: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``[H, W, 9]`` sample means of :meth:`_render_with_aux` -> ``(color, albedo clamped to
        [0, 1], unit camera-space normal)``, each ``[H, W, 3]`` float32."""
        normal = camera_normals(mean[..., 6:9], self.spec.camera.to_world(float(t)))
        return (mean[..., 0:3].astype(np.float32), np.clip(mean[..., 3:6], 0.0, 1.0).astype(np.float32),
                normal.astype(np.float32))

    def _render_with_aux(self, tau: float, spp: int, seed: int) -> np.ndarray:
        """``[H, W, 9]``: mean radiance, albedo and world shading normal of the same ``spp`` samples
        (the radiance equals :meth:`_render`'s for the same seed)."""
        if self._with_aux is None:
            self._with_aux = self.mi.load_dict({"type": "aov", "aovs": ALBEDO_NORMAL_AOVS,
                                                "integrator": integrator(self.spec)})
        scene = self.scene(tau)
        img = self.mi.render(scene, sensor=self._sensor(scene, MAIN_SENSOR), integrator=self._with_aux,
                             spp=int(spp), seed=int(seed) & 0xFFFFFFFF)
        return np.array(img, dtype=np.float32)[..., :9]

    def radiance_aux(self, t: int, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`radiance` with the albedo and normal of the same samples (``aux: samples``).

        Returns ``(color [H,W,3], albedo [H,W,3] in [0, 1], normal [H,W,3])``: the colour is
        :meth:`radiance`'s for the same seed; albedo is the mean of the samples' first-hit albedo
        (0 for misses), clamped; normal the camera-space mean of the samples' shading normals,
        renormalised (0 where no sample hit).
        """
        return self._split_aux(self._mean_over_shutter(self._render_with_aux, t, spp, seed), t)

    def reference(self, t: int, spp: int, seed: int) -> np.ndarray:
        return self.radiance(t, spp, seed, time_samples=MAX_TIME_SAMPLES)

    def aux(self, t: int, blur: bool = True) -> AuxBuffers:
        """Albedo, normal, depth, position and object id through the pixel centres at ``tau = t``.

        blur: with dof or an open shutter, average albedo and normal over lens and shutter
        samples (False: keep the pixel-centre ones, for a caller that replaces them).
        """
        mi = self.mi
        scene = self.scene(float(t))
        if self._aov is None:
            self._aov = mi.load_dict({"type": "aov", "aovs": AOVS})
        img = np.array(mi.render(scene, sensor=self._sensor(scene, AUX_SENSOR), integrator=self._aov, spp=1, seed=0),
                       dtype=np.float32)
        albedo, nn, pos, dist, sid = img[..., 0:3], img[..., 3:6], img[..., 6:9], img[..., 9], img[..., 10]
        hit = dist > 0
        cam = self.spec.camera.to_world(float(t))
        normal = tf.apply_vector(np.linalg.inv(cam), nn.astype(np.float64)) * np.array([-1.0, 1.0, 1.0])
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(hit[..., None] & (length > 0), normal / np.maximum(length, 1e-12), 0.0)
        depth = tf.camera_space(cam, pos.astype(np.float64))[..., 2]
        depth = np.where(hit, depth, NO_HIT_DEPTH)
        albedo = np.where(hit[..., None], albedo, 0.0)
        if blur and self.blurred:
            albedo, normal = self._blurred_albedo_normal(t, cam)
        return AuxBuffers(
            albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32),
            normal=normal.astype(np.float32), depth=depth[..., None].astype(np.float32),
            position=pos.astype(np.float64), hit=hit, object=self._object_ids(scene, sid, hit))

    @property
    def blurred(self) -> bool:
        """True when the camera blurs the image (dof or an open shutter)."""
        cam = self.spec.camera
        return ("dof" in self.spec.effects and cam.aperture > 0) or self.shutter_open

    def _blurred_albedo_normal(self, t: int, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Albedo ``[H,W,3]`` and unit camera-space normal ``[H,W,3]`` averaged over lens and shutter
        samples (misses count as 0; the mean normal is renormalized, 0 where nothing was hit)."""
        mi = self.mi
        integrator = mi.load_dict({"type": "aov", "aovs": ALBEDO_NORMAL_AOVS})
        n = BLURRED_AUX_SPP // 2 if self.shutter_open else 1
        acc = np.zeros((self.height, self.width, 6), np.float64)
        for k, tau in enumerate(self._instants(t, n, seed=t)):
            scene = self.scene(tau)
            img = mi.render(scene, sensor=self._sensor(scene, MAIN_SENSOR), integrator=integrator,
                            spp=BLURRED_AUX_SPP // n, seed=104729 + k)
            acc += np.array(img, dtype=np.float64)[..., :6]
        acc /= n
        return acc[..., 0:3], camera_normals(acc[..., 3:6], cam)

    def _object_ids(self, scene, sid: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """Map Mitsuba's per-pixel shape index to object indices: one probe ray per distinct shape."""
        names = {o.name: i for i, o in enumerate(self.spec.objects)}
        out = np.full(sid.shape, -1, np.int32)
        sensor = self._sensor(scene, AUX_SENSOR)
        for value in np.unique(sid[hit]):
            ys, xs = np.nonzero((sid == value) & hit)
            y, x = int(ys[0]), int(xs[0])
            shape_id = self._probe(scene, sensor, (x + 0.5) / self.width, (y + 0.5) / self.height)
            if shape_id is not None and object_of(shape_id) in names:
                out[(sid == value) & hit] = names[object_of(shape_id)]
        return out

    def _probe(self, scene, sensor, u: float, v: float) -> str | None:
        mi = self.mi
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
        si = scene.ray_intersect(ray)
        shape = si.shape
        if hasattr(shape, "id"):
            return shape.id() if shape is not None else None
        entry = shape[0]
        return entry.id() if entry is not None else None


def camera_normals(world: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """Mean world-space normals ``[H,W,3]`` -> unit camera-space normals (x right, y up, z into
    the scene; 0 where the mean is about 0, i.e. nothing was hit). cam: camera-to-world ``[4, 4]``."""
    normal = tf.apply_vector(np.linalg.inv(cam), world.astype(np.float64)) * np.array([-1.0, 1.0, 1.0])
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.where(length > 1e-6, normal / np.maximum(length, 1e-12), 0.0)
