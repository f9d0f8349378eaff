"""Render small Blender Cycles test sequences in the layout ``layout=blender`` reads.

Runs with Blender's Python module (``pip install bpy``, in its own venv: ``make blender`` makes
one) and needs only ``bpy``, ``numpy`` and the standard library, so it also runs inside Blender::

    /work/blender-venv/bin/python scripts/blender_sequences.py --root data/blender
    blender -b -P scripts/blender_sequences.py -- --root data/blender --frames 4

Writes, for each sequence, multilayer float32 EXRs named as Blender names them::

    <root>/test/<sequence>/noisy/0001.exr ...       # --spp samples, seed A
    <root>/test/<sequence>/reference/0001.exr ...   # --ref-spp samples, seed B
    <root>/test/<sequence>/render.json              # settings and render seconds (not read by the loader)
    <root>/test/<sequence>/reference_check/0001.exr # --ref-check: a second reference, seed + 2000
                                                    # (render.json's noise_floor: PSNR of one against the other)

Render settings: CPU Cycles, no adaptive sampling, Cycles' denoiser off, box pixel filter one
pixel wide (the samples of a pixel stay in the pixel, so the noise is not spatially
correlated), Denoising Data, Depth and Vector passes, motion blur off, animated seed (fresh noise
every frame), fixed thread count. Everything is built from primitives and procedural textures:

* ``orbit``: the camera orbits a checker floor with a diffuse/noise cube, a glossy metal sphere,
  a glass ico-sphere, a rough plastic torus, an area light and a small bright emitter;
* ``slide``: a static camera looks at a brick wall over a checker floor while a sphere and a
  cube move across it (disocclusions every frame);
* ``fast_<seed>``: fast object motion (issue 33): a static camera looks at a textured back wall
  over a textured floor; one or two textured objects (shape, textures, colours, depth, direction
  drawn from the seed) cross the view at 8-15 px/frame (at the image width rendered) and turn
  5-15 degrees per frame, uncovering the background behind them every frame. Their paths are
  laid out on screen and converted to metres at each object's depth, so the speed in pixels
  holds for any ``--size``. Seeds ``MOVING_SEEDS`` are disjoint between splits: ``--split val``
  renders ``fast_101``-``fast_103``, ``--split test`` ``fast_301``-``fast_306`` (``SPLIT_SEQUENCES``;
  issue 49: ``fast_201``-``fast_206`` judged two recipes and ``orbit`` and ``slide`` several, so the
  test split holds fresh seeds only; the retired ones stay renderable by name, ``--sequences``).
* ``<kind>_<seed>`` (issue 62, the release training set): every choice (objects, materials,
  colours, lights, camera path, motion speeds) drawn from the seed; kinds ``RELEASE_KINDS``:
  ``interior`` (a room lit through windows or a door by a sun and sky outside), ``glossy``
  (glossy and metal objects), ``glass``, ``lamps`` (small bright lamps in a dim scene), ``dof``
  (a wide aperture on a long lens), ``motion`` (fast camera and object motion), ``textures``
  (procedural textures with bump); ``RESERVED_KINDS``, never in the release training (issue 67's
  adaptation study): ``foliage`` (thin geometry: grass blades, stems, leaves), ``pool`` (caustics
  under a moving water surface), ``signage`` (emissive letters and neon at night).
  ``--set release --split S`` renders ``RELEASE_SPLITS[S]``: train (42), val (8), test (14; rendered
  once, after the release recipe is frozen), unlabeled (12, noisy only, for distillation), timing
  (one of each kind), reserved (9); seeds 1001-1042, 2001-2008, 3001-3014, 4001-4012, 5001-5010,
  6001-6009, disjoint from each other and from the ``fast_<seed>`` ones. Sizes: 128x128, 256x256
  for ``RELEASE_LARGE`` (one of each kind in train, one in val).

Objects and the camera are keyframed on every frame from 0 to frames+1, so the ``Vector`` pass
has a previous and next position also at the first and last rendered frame.

Seeds are fixed (noisy ``--seed``, reference ``--seed + 1000``, animated per frame), so a re-run
gives the same images up to float noise: on Blender 5.0.1 a few percent of the pixels of
``Combined`` (and a handful of normals) differ slightly between two runs, even with one thread;
every other pass is bit-identical.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import math
import random
import sys
import tempfile
import time
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).resolve().parent))   # blender -b -P does not add the script's folder
from blender_cycles import apply_settings, enable_passes, render_frames, set_exr_output

#: seeds of the fast-object-motion sequences ``fast_<seed>`` per split (disjoint)
MOVING_SEEDS = {"val": (101, 102, 103), "test": (301, 302, 303, 304, 305, 306)}
#: what ``--split`` renders by default
SPLIT_SEQUENCES = {"test": tuple(f"fast_{s}" for s in MOVING_SEEDS["test"]),
                   "val": tuple(f"fast_{s}" for s in MOVING_SEEDS["val"])}


# ----------------------------------------------------------------------------- scene set-up


def reset_scene(width: int, height: int, threads: int):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    scene.render.use_motion_blur = False          # the Vector pass needs motion blur off
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads
    scene.render.film_transparent = False
    apply_settings(scene)                         # blender_cycles.RENDER_SETTINGS: no adaptive sampling, ...
    cyc = scene.cycles
    cyc.device = "CPU"
    cyc.max_bounces = 8
    cyc.caustics_reflective = True
    cyc.caustics_refractive = True
    cyc.sample_clamp_indirect = 0.0
    cyc.sample_clamp_direct = 0.0

    layer = scene.view_layers[0]
    layer.name = "ViewLayer"
    enable_passes(layer)                          # Combined, Z, Vector, Denoising Data
    set_exr_output(scene)                         # multilayer float32 EXR, ZIP

    world = bpy.data.worlds.new("World")
    scene.world = world
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    bg = world.node_tree.nodes.get("Background") or world.node_tree.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.05, 0.07, 0.1, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    out = world.node_tree.nodes.get("World Output") or world.node_tree.nodes.new("ShaderNodeOutputWorld")
    world.node_tree.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return scene


def material(name: str, kind: str, color=(0.8, 0.8, 0.8), roughness=0.5, metallic=0.0,
             texture: str | None = None, color2=(0.1, 0.1, 0.1), scale=8.0, strength=0.0):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    if kind == "emission":
        shader = nodes.new("ShaderNodeEmission")
        shader.inputs["Color"].default_value = (*color, 1.0)
        shader.inputs["Strength"].default_value = strength
        links.new(shader.outputs[0], out.inputs["Surface"])
        return mat
    if kind == "glass":
        shader = nodes.new("ShaderNodeBsdfGlass")
        shader.inputs["Color"].default_value = (*color, 1.0)
        shader.inputs["Roughness"].default_value = roughness
        shader.inputs["IOR"].default_value = 1.45
        links.new(shader.outputs[0], out.inputs["Surface"])
        return mat
    shader = nodes.new("ShaderNodeBsdfPrincipled")
    shader.inputs["Base Color"].default_value = (*color, 1.0)
    shader.inputs["Roughness"].default_value = roughness
    shader.inputs["Metallic"].default_value = metallic
    if texture is not None:
        coord = nodes.new("ShaderNodeTexCoord")
        if texture == "checker":
            tex = nodes.new("ShaderNodeTexChecker")
            tex.inputs["Color1"].default_value = (*color, 1.0)
            tex.inputs["Color2"].default_value = (*color2, 1.0)
        elif texture == "brick":
            tex = nodes.new("ShaderNodeTexBrick")
            tex.inputs["Color1"].default_value = (*color, 1.0)
            tex.inputs["Color2"].default_value = (*color2, 1.0)
        else:
            tex = nodes.new("ShaderNodeTexNoise")
            ramp = nodes.new("ShaderNodeValToRGB")
            ramp.color_ramp.elements[0].color = (*color2, 1.0)
            ramp.color_ramp.elements[1].color = (*color, 1.0)
        tex.inputs["Scale"].default_value = scale
        links.new(coord.outputs["Object"], tex.inputs["Vector"])
        if texture == "noise":
            links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
            links.new(ramp.outputs["Color"], shader.inputs["Base Color"])
        else:
            links.new(tex.outputs["Color"], shader.inputs["Base Color"])
    links.new(shader.outputs[0], out.inputs["Surface"])
    return mat


def add(kind: str, mat, location=(0, 0, 0), scale=(1, 1, 1), rotation=(0, 0, 0), **kw):
    getattr(bpy.ops.mesh, f"primitive_{kind}_add")(location=location, rotation=rotation, **kw)
    obj = bpy.context.active_object
    obj.scale = scale
    if kind in ("uv_sphere", "ico_sphere", "torus"):
        bpy.ops.object.shade_smooth()
    obj.data.materials.append(mat)
    return obj


def _light(kind: str, name: str, location, energy: float, color, **settings):
    """A light object of ``kind`` (AREA, POINT, ...) linked into the scene; ``settings``: its data's own
    attributes (``size``, ``shadow_soft_size``)."""
    data = bpy.data.lights.new(name, type=kind)
    for key, value in settings.items():
        setattr(data, key, value)
    data.energy = energy
    data.color = color
    obj = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
    return obj


def area_light(location, rotation, size=2.0, energy=300.0, color=(1.0, 0.95, 0.9)):
    obj = _light("AREA", "Area", location, energy, color, size=size)
    obj.rotation_euler = rotation
    return obj


def camera(lens=35.0):
    data = bpy.data.cameras.new("Camera")
    data.lens = lens
    data.sensor_fit = "HORIZONTAL"
    obj = bpy.data.objects.new("Camera", data)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj
    return obj


def look_at(obj, target):
    import mathutils
    direction = mathutils.Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def keyframe(obj, frames: int, fn):
    """``fn(f)`` sets the object's transform for frame f; keys on frames 0..frames+1, linear."""
    for f in range(frames + 2):
        fn(f)
        obj.keyframe_insert("location", frame=f)
        obj.keyframe_insert("rotation_euler", frame=f)
    _linear(obj)


def _linear(obj):
    anim = obj.animation_data
    if anim is None or anim.action is None:
        return
    curves = getattr(anim.action, "fcurves", None)
    if curves is None or len(curves) == 0:        # Blender 4.4+/5.0 layered actions
        curves = [c for layer in anim.action.layers for strip in layer.strips
                  for bag in strip.channelbags for c in bag.fcurves]
    for curve in curves:
        for key in curve.keyframe_points:
            key.interpolation = "LINEAR"


# ----------------------------------------------------------------------------- sequences


def build_orbit(frames: int):
    floor = material("Floor", "principled", (0.75, 0.75, 0.7), 0.6, texture="checker",
                     color2=(0.08, 0.08, 0.1), scale=2.5)
    add("plane", floor, size=12.0)
    add("cube", material("Stone", "principled", (0.8, 0.45, 0.2), 0.8, texture="noise",
                         color2=(0.2, 0.1, 0.05), scale=5.0),
        location=(-1.2, 0.6, 0.6), scale=(0.6, 0.6, 0.6), rotation=(0, 0, 0.5))
    add("uv_sphere", material("Metal", "principled", (0.9, 0.85, 0.8), 0.15, metallic=1.0),
        location=(1.0, 0.4, 0.7), radius=0.7, segments=48, ring_count=24)
    add("ico_sphere", material("Glass", "glass", (0.95, 0.98, 1.0), 0.02),
        location=(0.1, -1.0, 0.5), radius=0.5, subdivisions=3)
    add("torus", material("Plastic", "principled", (0.1, 0.35, 0.8), 0.35),
        location=(-0.4, 1.8, 0.3), major_radius=0.6, minor_radius=0.22, rotation=(0.3, 0.0, 0.0))
    add("uv_sphere", material("Emitter", "emission", (1.0, 0.6, 0.25), strength=60.0),
        location=(1.9, -1.3, 0.25), radius=0.12)
    area_light((-2.5, -2.0, 4.0), (math.radians(35), 0.0, math.radians(-50)), size=2.0, energy=400.0)
    cam = camera(lens=32.0)

    def at(f):
        angle = math.radians(-60.0 + 5.0 * f)     # 5 degrees per frame around the scene
        cam.location = (6.0 * math.sin(angle), -6.0 * math.cos(angle), 3.2)
        look_at(cam, (0.0, 0.2, 0.4))

    keyframe(cam, frames, at)


def build_slide(frames: int):
    floor = material("Floor", "principled", (0.7, 0.7, 0.7), 0.7, texture="checker",
                     color2=(0.15, 0.12, 0.1), scale=2.0)
    add("plane", floor, size=14.0)
    wall = material("Wall", "principled", (0.65, 0.25, 0.15), 0.8, texture="brick",
                    color2=(0.75, 0.72, 0.65), scale=1.0)
    add("plane", wall, location=(0.0, 2.5, 2.0), rotation=(math.radians(90), 0.0, 0.0), size=10.0)
    ball = add("uv_sphere", material("Ball", "principled", (0.9, 0.9, 0.2), 0.25, texture="checker",
                                     color2=(0.1, 0.3, 0.8), scale=4.0),
               location=(0, 0, 0.6), radius=0.6, segments=48, ring_count=24)
    box = add("cube", material("Box", "principled", (0.2, 0.7, 0.3), 0.4, texture="noise",
                               color2=(0.02, 0.15, 0.05), scale=6.0),
              location=(0, 1.2, 0.5), scale=(0.5, 0.5, 0.5))
    add("uv_sphere", material("Emitter", "emission", (0.6, 0.8, 1.0), strength=40.0),
        location=(2.2, 1.8, 1.6), radius=0.1)
    area_light((1.5, -3.0, 4.5), (math.radians(40), 0.0, math.radians(20)), size=3.0, energy=500.0)
    cam = camera(lens=35.0)
    cam.location = (0.0, -6.5, 1.8)
    look_at(cam, (0.0, 0.5, 1.0))

    def ball_at(f):                               # rolls left to right, 0.35 m per frame
        ball.location = (-1.6 + 0.35 * f, -0.5, 0.6)
        ball.rotation_euler = (0.0, 0.35 * f / 0.6, 0.0)

    def box_at(f):                                # slides right to left and turns
        box.location = (1.8 - 0.3 * f, 1.0, 0.5)
        box.rotation_euler = (0.0, 0.0, 0.15 * f)

    keyframe(ball, frames, ball_at)
    keyframe(box, frames, box_at)


def build_probe(frames: int):
    """Known motion for checking the Vector pass: a camera 10 m above a checker plane looking
    down -Z (90 mm lens, 36 mm sensor: 4 m across, 8 px per metre at 32x32). The camera moves +X
    0.25 m (2 px) per frame, so the static plane slides 2 px *left* on screen; a flat cube moves
    with the camera in X and +Y 0.125 m per frame, so on screen it goes 1 px *up* per frame. A
    sphere shows the normal axes (its right half faces +X, its top half +Y on screen).
    (An orthographic camera is not used: Blender 5.0.1's Vector pass is wrong for it, a zoom-like
    field instead of a uniform shift.)"""
    add("plane", material("Floor", "principled", (0.8, 0.8, 0.8), 0.8, texture="checker",
                          color2=(0.1, 0.1, 0.1), scale=4.0), size=40.0)
    cube = add("cube", material("Cube", "principled", (0.2, 0.8, 0.2), 0.5), location=(0, 0, 0.05),
               scale=(0.3, 0.3, 0.02))
    add("uv_sphere", material("Ball", "principled", (0.8, 0.2, 0.2), 0.5), location=(0.8, 0.8, 0.5),
        radius=0.5, segments=48, ring_count=24)
    area_light((0.0, 0.0, 6.0), (0.0, 0.0, 0.0), size=6.0, energy=800.0)
    cam = camera(lens=90.0)
    cam.data.sensor_width = 36.0
    cam.data.clip_end = 100.0

    def cam_at(f):
        cam.location = (0.25 * f, 0.0, 10.0)
        cam.rotation_euler = (0.0, 0.0, 0.0)

    def cube_at(f):
        cube.location = (0.25 * f - 0.6, 0.125 * f - 0.6, 0.05)
        cube.rotation_euler = (0.0, 0.0, 0.0)

    keyframe(cam, frames, cam_at)
    keyframe(cube, frames, cube_at)


BUILDERS = {"orbit": build_orbit, "slide": build_slide, "probe": build_probe}


#: camera of the fast motion sequences: static, looking along +Y (the image plane is parallel to
#: the XZ plane, so a motion in X/Z at a fixed depth is the same number of pixels everywhere)
MOVING_CAMERA = {"location": (0.0, -6.0, 1.4), "lens": 35.0, "sensor": 36.0}
MOVING_SPEED = (8.0, 15.0)      # px per frame, at the rendered width
MOVING_SPIN = (5.0, 15.0)       # degrees per frame
MOVING_SHAPES = ("cube", "uv_sphere", "ico_sphere", "cylinder", "cone", "torus")
MOVING_TEXTURES = ("checker", "noise", "brick")


def fast_seed(name: str) -> int | None:
    """The seed of a ``fast_<seed>`` sequence name, None for other names."""
    head, _, tail = name.partition("_")
    return int(tail) if head == "fast" and tail.isdigit() else None


def _hue_color(rng: random.Random, sat=(0.5, 0.9), val=(0.55, 0.9)):
    return colorsys.hsv_to_rgb(rng.random(), rng.uniform(*sat), rng.uniform(*val))


def _fast_material(rng: random.Random, name: str, scale: tuple[float, float], textures=MOVING_TEXTURES):
    texture = rng.choice(textures)
    mat = material(name, "principled", _hue_color(rng), rng.uniform(0.35, 0.8), texture=texture,
                   color2=_hue_color(rng, (0.1, 0.6), (0.05, 0.25)), scale=rng.uniform(*scale))
    ramp = mat.node_tree.nodes.get("Color Ramp")
    if ramp is not None:      # noise: its Fac stays near 0.5; a narrower ramp gives a visible texture
        ramp.color_ramp.elements[0].position = 0.4
        ramp.color_ramp.elements[1].position = 0.6
    return mat


def _fast_object(rng: random.Random, index: int, radius: float):
    shape = rng.choice(MOVING_SHAPES)
    mat = _fast_material(rng, f"Object{index}", (3.0, 7.0))
    if shape == "cube":
        return add("cube", mat, size=1.6 * radius)
    if shape == "cylinder":
        return add("cylinder", mat, radius=0.8 * radius, depth=1.6 * radius, vertices=48)
    if shape == "cone":
        return add("cone", mat, radius1=radius, depth=1.8 * radius, vertices=48)
    if shape == "torus":
        return add("torus", mat, major_radius=0.75 * radius, minor_radius=0.3 * radius)
    if shape == "ico_sphere":
        return add("ico_sphere", mat, radius=radius, subdivisions=2)   # facets: normals change per face
    return add("uv_sphere", mat, radius=radius, segments=48, ring_count=24)


def build_fast(frames: int, width: int, seed: int) -> dict:
    """Fast object motion over a textured background (module docstring); returns what was drawn
    (written to render.json). Screen paths: object k's centre moves ``speed`` px/frame along a
    direction within 15 degrees of horizontal (the second object the other way, at another depth,
    so the two cross), through a point near the image centre half-way through the sequence."""
    rng = random.Random(seed)
    # planes: Object texture coordinates span their whole size, so the scales are per metre
    add("plane", _fast_material(rng, "Floor", (1.5, 4.0), ("checker", "brick")), size=30.0)
    add("plane", _fast_material(rng, "Wall", (0.8, 2.0), ("checker", "brick")), location=(0.0, 4.0, 5.0),
        rotation=(math.radians(90), 0.0, 0.0), size=16.0)
    area_light((rng.uniform(-2.5, 2.5), -3.5, 4.5), (math.radians(45), 0.0, 0.0), size=3.0,
               energy=rng.uniform(500.0, 800.0))
    cam = camera(lens=MOVING_CAMERA["lens"])
    cam.data.sensor_width = MOVING_CAMERA["sensor"]
    cam.location = MOVING_CAMERA["location"]
    cam.rotation_euler = (math.radians(90), 0.0, 0.0)
    mid = (frames + 1) / 2.0                  # keys run over frames 0..frames+1
    rightwards = rng.random() < 0.5           # the first object's way; a second one goes the other way
    drawn = []
    for k in range(rng.choice((1, 2))):
        depth = rng.uniform(4.5, 5.5) + 1.5 * k
        px_per_m = width * MOVING_CAMERA["lens"] / (MOVING_CAMERA["sensor"] * depth)
        speed = rng.uniform(*MOVING_SPEED)
        heading = math.radians(rng.uniform(-15.0, 15.0)) + (0.0 if rightwards == (k == 0) else math.pi)
        centre = (rng.uniform(-0.12, 0.12) * width, rng.uniform(0.0, 0.15) * width + 0.1 * width * k)
        spin_axis = [rng.gauss(0.0, 1.0) for _ in range(3)]
        norm = math.sqrt(sum(a * a for a in spin_axis)) or 1.0
        spin = rng.uniform(*MOVING_SPIN) * rng.choice((-1.0, 1.0))
        rates = [math.radians(spin) * a / norm for a in spin_axis]
        obj = _fast_object(rng, k, rng.uniform(0.45, 0.6))
        phase = [rng.uniform(0.0, 2 * math.pi) for _ in range(3)]

        def at(f, obj=obj, px_per_m=px_per_m, speed=speed, heading=heading, centre=centre, rates=rates,
               phase=phase, depth=depth):
            u = centre[0] + speed * (f - mid) * math.cos(heading)     # px right of the image centre
            v = centre[1] + speed * (f - mid) * math.sin(heading)     # px above it
            obj.location = (u / px_per_m, MOVING_CAMERA["location"][1] + depth,
                            MOVING_CAMERA["location"][2] + v / px_per_m)
            obj.rotation_euler = tuple(p + r * f for p, r in zip(phase, rates))

        keyframe(obj, frames, at)
        drawn.append({"shape": obj.name, "depth_m": round(depth, 3), "speed_px": round(speed, 2),
                      "heading_deg": round(math.degrees(heading), 1), "spin_deg": round(spin, 2)})
    return {"seed": seed, "objects": drawn}


# ----------------------------------------------------------------------------- release kinds (issue 62)
#
# Seeded scenes for the release training set: ``<kind>_<seed>``, every choice (objects, materials,
# colours, lights, camera path, motion speeds) drawn from ``random.Random(seed)`` (the kind names
# the builder; the release splits give each seed its kind, RELEASE_SPLITS). Primitives, meshes
# made from numbers and procedural textures only.

#: version of the release builders, recorded in render.json: a change re-renders their sequences
RELEASE_VERSION = 1
#: kinds of the release training set (train, val, test and unlabeled hold only these)
RELEASE_KINDS = ("interior", "glossy", "glass", "lamps", "dof", "motion", "textures")
#: kinds the release training never contains (issue 67's adaptation study); renderable by name
RESERVED_KINDS = ("foliage", "pool", "signage")
SEEDED_KINDS = ("fast",) + RELEASE_KINDS + RESERVED_KINDS
PROCEDURAL = ("checker", "brick", "noise", "voronoi", "wave", "magic", "gradient")
SHAPES = ("cube", "uv_sphere", "ico_sphere", "cylinder", "cone", "torus", "monkey")


def seeded(name: str) -> tuple[str, int] | None:
    """``(kind, seed)`` of a seeded sequence name (``fast_101``, ``interior_1001``), else None."""
    kind, _, tail = name.rpartition("_")
    return (kind, int(tail)) if kind in SEEDED_KINDS and tail.isdigit() else None


def procedural_material(rng: random.Random, name: str, texture: str | None = None, color=None, color2=None,
                        scale: float | None = None, roughness: float | None = None, metallic: float = 0.0,
                        bump: float | None = None):
    """Principled BSDF whose base colour (and bump) is a procedural texture on Object coordinates
    through a two-colour ramp; what is not given is drawn from ``rng``."""
    texture = texture or rng.choice(PROCEDURAL)
    color = color or _hue_color(rng)
    color2 = color2 or _hue_color(rng, (0.1, 0.7), (0.05, 0.35))
    mat = material(name, "principled", color, rng.uniform(0.3, 0.8) if roughness is None else roughness,
                   metallic=metallic)
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    coord = nodes.new("ShaderNodeTexCoord")
    tex = nodes.new({"checker": "ShaderNodeTexChecker", "brick": "ShaderNodeTexBrick", "noise": "ShaderNodeTexNoise",
                     "voronoi": "ShaderNodeTexVoronoi", "wave": "ShaderNodeTexWave", "magic": "ShaderNodeTexMagic",
                     "gradient": "ShaderNodeTexGradient"}[texture])
    if "Scale" in tex.inputs:
        tex.inputs["Scale"].default_value = rng.uniform(2.0, 8.0) if scale is None else scale
    if texture == "wave":
        tex.inputs["Distortion"].default_value = rng.uniform(0.0, 6.0)
        tex.wave_type = rng.choice(("BANDS", "RINGS"))
    elif texture == "magic":
        tex.turbulence_depth = rng.randint(1, 4)
    elif texture == "voronoi":
        tex.feature = rng.choice(("F1", "F2", "DISTANCE_TO_EDGE"))
    elif texture == "gradient":
        tex.gradient_type = rng.choice(("LINEAR", "SPHERICAL", "RADIAL", "DIAGONAL"))
    links.new(coord.outputs["Object"], tex.inputs["Vector"])
    fac = tex.outputs[0 if texture in ("noise", "voronoi") else 1]        # Factor / Distance
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*color2, 1.0)
    ramp.color_ramp.elements[1].color = (*color, 1.0)
    if texture in ("noise", "voronoi", "magic", "wave"):   # values bunch near the middle: a narrower ramp
        lo = rng.uniform(0.3, 0.45)
        ramp.color_ramp.elements[0].position = lo
        ramp.color_ramp.elements[1].position = lo + rng.uniform(0.1, 0.3)
    links.new(fac, ramp.inputs[0])
    links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bump = rng.choice((0.0, rng.uniform(0.1, 0.6))) if bump is None else bump
    if bump > 0.0:
        node = nodes.new("ShaderNodeBump")
        node.inputs["Strength"].default_value = bump
        node.inputs["Distance"].default_value = 0.02
        links.new(fac, node.inputs["Height"])
        links.new(node.outputs["Normal"], bsdf.inputs["Normal"])
    mat["drawn"] = f"{texture} bump {bump:.2f}"
    return mat


def surface(rng: random.Random, name: str, family: str):
    """A material of ``family``: diffuse, textured, plastic (glossy dielectric), metal, glass;
    returns ``(material, description)``."""
    if family == "textured":
        mat = procedural_material(rng, name)
        return mat, mat["drawn"]
    if family == "metal":
        hue = rng.choice(((0.95, 0.93, 0.88), (1.0, 0.78, 0.34), (0.95, 0.64, 0.54), (0.91, 0.92, 0.92),
                          _hue_color(rng, (0.2, 0.6), (0.6, 0.95))))
        rough = rng.choice((rng.uniform(0.0, 0.08), rng.uniform(0.1, 0.4)))
        if rng.random() < 0.3:                                   # brushed/scratched: a textured metal
            return procedural_material(rng, name, color=hue, color2=tuple(0.6 * c for c in hue),
                                       roughness=rough, metallic=1.0, bump=rng.uniform(0.05, 0.3)), \
                f"metal rough {rough:.2f} textured"
        return material(name, "principled", hue, rough, metallic=1.0), f"metal rough {rough:.2f}"
    if family == "glass":
        tint = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.0, 0.35), 1.0)
        rough = rng.choice((0.0, rng.uniform(0.0, 0.05), rng.uniform(0.05, 0.25)))
        mat = material(name, "glass", tint, rough)
        ior = rng.uniform(1.33, 1.6)
        mat.node_tree.nodes["Glass BSDF"].inputs["IOR"].default_value = ior
        return mat, f"glass rough {rough:.2f} ior {ior:.2f}"
    if family == "plastic":
        rough = rng.uniform(0.02, 0.3)
        mat = material(name, "principled", _hue_color(rng), rough)
        if rng.random() < 0.5:
            mat.node_tree.nodes["Principled BSDF"].inputs["Coat Weight"].default_value = 1.0
        return mat, f"plastic rough {rough:.2f}"
    rough = rng.uniform(0.5, 1.0)
    return material(name, "principled", _hue_color(rng, (0.1, 0.8), (0.3, 0.9)), rough), "diffuse"


def shape(rng: random.Random, mat, size: float, kind: str | None = None, location=(0.0, 0.0, 0.0)):
    """A primitive of about ``size`` metres across (the origin at its centre); returns the object."""
    kind = kind or rng.choice(SHAPES)
    r = size / 2.0
    if kind == "cube":
        obj = add("cube", mat, location=location, size=size)
    elif kind == "cylinder":
        obj = add("cylinder", mat, location=location, radius=0.8 * r, depth=size, vertices=48)
    elif kind == "cone":
        obj = add("cone", mat, location=location, radius1=r, depth=size, vertices=48)
    elif kind == "torus":
        obj = add("torus", mat, location=location, major_radius=0.7 * r, minor_radius=0.3 * r)
    elif kind == "ico_sphere":
        obj = add("ico_sphere", mat, location=location, radius=r, subdivisions=rng.choice((1, 2, 4)))
    elif kind == "monkey":
        obj = add("monkey", mat, location=location, size=size)
        bpy.ops.object.shade_smooth()
    else:
        obj = add("uv_sphere", mat, location=location, radius=r, segments=48, ring_count=24)
    return obj


def point_light(location, radius=0.05, energy=50.0, color=(1.0, 1.0, 1.0)):
    return _light("POINT", "Point", location, energy, color, shadow_soft_size=radius)


def sun_light(direction, strength=4.0, angle_deg=1.0, color=(1.0, 0.95, 0.85)):
    """A sun shining along ``direction`` (towards where the light goes)."""
    import mathutils
    data = bpy.data.lights.new("Sun", type="SUN")
    data.energy = strength
    data.angle = math.radians(angle_deg)
    data.color = color
    obj = bpy.data.objects.new("Sun", data)
    bpy.context.scene.collection.objects.link(obj)
    obj.rotation_euler = mathutils.Vector(direction).to_track_quat("-Z", "Y").to_euler()
    return obj


def sky(horizon, zenith, strength: float, ground=None):
    """The world as a sky: ``ground`` below the horizon, ``horizon`` to ``zenith`` above it."""
    tree = bpy.context.scene.world.node_tree
    bg = tree.nodes["Background"]
    bg.inputs["Strength"].default_value = strength
    coord = tree.nodes.new("ShaderNodeTexCoord")
    xyz = tree.nodes.new("ShaderNodeSeparateXYZ")
    ramp = tree.nodes.new("ShaderNodeValToRGB")
    tree.links.new(coord.outputs["Generated"], xyz.inputs["Vector"])     # the ray's direction
    tree.links.new(xyz.outputs["Z"], ramp.inputs[0])
    elements = ramp.color_ramp.elements
    elements[0].position, elements[0].color = 0.0, (*(ground or horizon), 1.0)
    elements[1].position, elements[1].color = 0.7, (*zenith, 1.0)
    elements.new(0.02).color = (*horizon, 1.0)
    tree.links.new(ramp.outputs["Color"], bg.inputs["Color"])


def world_color(color, strength: float):
    bg = bpy.context.scene.world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*color, 1.0)
    bg.inputs["Strength"].default_value = strength


def mesh_object(name: str, verts, faces, mat, location=(0.0, 0.0, 0.0)):
    """An object from vertex and face lists (thin geometry, water surfaces)."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(v) for v in verts], [], [tuple(f) for f in faces])
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
    me.materials.append(mat)
    return obj


def _scatter(rng: random.Random, n: int, radius: float, sizes=(0.4, 1.1), gap=0.15, centre=(0.0, 0.0)):
    """Up to ``n`` ``(x, y, size)`` on the floor within ``radius`` of ``centre``, not overlapping."""
    placed = []
    for _ in range(40 * n):
        if len(placed) == n:
            break
        s = rng.uniform(*sizes)
        x, y = centre[0] + rng.uniform(-radius, radius), centre[1] + rng.uniform(-radius, radius)
        if all(math.hypot(x - px, y - py) > (s + ps) / 2 + gap for px, py, ps in placed):
            placed.append((x, y, s))
    return placed


def _objects(rng: random.Random, n: int, families, weights, radius: float, sizes=(0.4, 1.1), centre=(0.0, 0.0),
             floor_z: float = 0.0):
    """``n`` primitives resting on the floor, materials of ``families`` (drawn with ``weights``);
    returns ``[(object, description)]``."""
    out = []
    for k, (x, y, s) in enumerate(_scatter(rng, n, radius, sizes, centre=centre)):
        family = rng.choices(families, weights)[0]
        mat, desc = surface(rng, f"Obj{k}", family)
        kind = rng.choice(SHAPES)
        obj = shape(rng, mat, s, kind, location=(x, y, floor_z + s / 2.0))
        obj.rotation_euler = (0.0, 0.0, rng.uniform(0.0, 2 * math.pi))
        out.append((obj, {"shape": kind, "size_m": round(s, 2), "material": desc}))
    return out


def _move(rng: random.Random, obj, frames: int, speed: tuple[float, float], spin: tuple[float, float]) -> dict:
    """Keys ``obj`` moving in a straight line on the floor plane at a drawn speed (m/frame) and
    turning about a drawn axis (degrees/frame); returns what was drawn."""
    v = rng.uniform(*speed)
    heading = rng.uniform(0.0, 2 * math.pi)
    rate = rng.uniform(*spin) * rng.choice((-1.0, 1.0))
    axis = [rng.gauss(0.0, 1.0) for _ in range(3)]
    norm = math.sqrt(sum(a * a for a in axis)) or 1.0
    start, rot0 = tuple(obj.location), tuple(obj.rotation_euler)
    mid = (frames + 1) / 2.0

    def at(f):
        obj.location = (start[0] + v * (f - mid) * math.cos(heading), start[1] + v * (f - mid) * math.sin(heading),
                        start[2])
        obj.rotation_euler = tuple(r0 + math.radians(rate) * a / norm * f for r0, a in zip(rot0, axis))

    keyframe(obj, frames, at)
    return {"speed_m": round(v, 3), "heading_deg": round(math.degrees(heading), 1), "spin_deg": round(rate, 2)}


def camera_path(rng: random.Random, cam, frames: int, target, styles=("orbit", "truck", "dolly", "pan", "crane"),
                speed: float = 1.0, distance=(4.0, 7.0), height=(1.0, 3.0), angle=(-1.0, 1.0)) -> dict:
    """Keys ``cam`` on a drawn path around ``target``: orbit (degrees/frame about the target), truck
    (sideways), dolly (towards it), crane (up or down) in metres/frame, or pan (a fixed position,
    the view turning); ``speed`` scales the drawn rates. The camera starts ``angle`` radians (drawn
    in the range) round from -Y of the target (0: looking along +Y, at the back walls). Returns
    what was drawn."""
    style = rng.choice(styles)
    d, h = rng.uniform(*distance), rng.uniform(*height)
    angle0 = rng.uniform(*angle)
    sign = rng.choice((-1.0, 1.0))
    rate = {"orbit": rng.uniform(1.0, 4.0), "truck": rng.uniform(0.03, 0.12), "dolly": rng.uniform(0.03, 0.1),
            "crane": rng.uniform(0.03, 0.1), "pan": rng.uniform(0.6, 2.0)}[style] * speed
    tx, ty, tz = target
    base = (tx + d * math.sin(angle0), ty - d * math.cos(angle0), h)
    side = (math.cos(angle0), math.sin(angle0))                  # perpendicular to the view, on the floor
    mid = (frames + 1) / 2.0

    def at(f):
        t = f - mid
        if style == "orbit":
            a = angle0 + sign * math.radians(rate) * t
            cam.location = (tx + d * math.sin(a), ty - d * math.cos(a), h)
        elif style == "truck":
            cam.location = (base[0] + sign * rate * t * side[0], base[1] + sign * rate * t * side[1], h)
        elif style == "dolly":
            k = sign * rate * t / d
            cam.location = tuple(b + k * (c - b) for b, c in zip(base, (tx, ty, tz)))
        elif style == "crane":
            cam.location = (base[0], base[1], max(0.3, h + sign * rate * t))
        else:
            cam.location = base
        look_at(cam, target)
        if style == "pan":
            cam.rotation_euler[2] += sign * math.radians(rate) * t

    keyframe(cam, frames, at)
    return {"style": style, "rate": round(rate, 3), "unit": "deg/frame" if style in ("orbit", "pan") else "m/frame",
            "distance_m": round(d, 2), "height_m": round(h, 2), "lens_mm": round(cam.data.lens, 1)}


def _stage(rng: random.Random, wall: bool | None = None) -> dict:
    """A floor (textured) and, drawn, a back wall; returns what was drawn."""
    floor = procedural_material(rng, "Floor", rng.choice(("checker", "brick", "noise", "voronoi", "wave")),
                                scale=rng.uniform(0.3, 1.5))
    add("plane", floor, size=40.0)
    wall = rng.random() < 0.6 if wall is None else wall
    if wall:
        mat = procedural_material(rng, "Wall", rng.choice(("brick", "checker", "noise", "wave")),
                                  scale=rng.uniform(0.3, 1.0))
        add("plane", mat, location=(0.0, rng.uniform(3.0, 6.0), 4.0), rotation=(math.radians(90), 0.0, 0.0),
            size=30.0)
    return {"floor": floor["drawn"], "wall": wall}


def _sky_lit(rng: random.Random, strength=(0.3, 1.5)) -> dict:
    s = rng.uniform(*strength)
    sky(_hue_color(rng, (0.0, 0.3), (0.6, 1.0)), _hue_color(rng, (0.2, 0.7), (0.5, 1.0)), s,
        ground=_hue_color(rng, (0.1, 0.5), (0.1, 0.4)))
    return {"sky": round(s, 2)}


def _area_lights(rng: random.Random, n: int, energy=(200.0, 900.0)) -> list:
    out = []
    for _ in range(n):
        a = rng.uniform(-math.pi, math.pi)
        d, h = rng.uniform(3.0, 6.0), rng.uniform(3.0, 6.0)
        e = rng.uniform(*energy)
        light = area_light((d * math.sin(a), -d * math.cos(a), h), (0.0, 0.0, 0.0), size=rng.uniform(0.5, 3.0),
                           energy=e, color=colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.0, 0.3), 1.0))
        look_at(light, (0.0, 0.0, 0.5))
        out.append(round(e))
    return out


def build_interior(rng: random.Random, frames: int) -> dict:
    """A room lit through openings (windows or a door) in its walls by a sun and the sky outside,
    a drawn ceiling lamp sometimes; furniture-sized primitives; the camera inside, panning or dollying."""
    w, d, h, t = rng.uniform(4.0, 7.0), rng.uniform(4.0, 7.0), rng.uniform(2.6, 3.4), 0.15
    wall_mat = surface(rng, "Walls", rng.choice(("diffuse", "diffuse", "textured")))[0]
    floor_mat = procedural_material(rng, "Floor", rng.choice(("checker", "wave", "brick", "noise")),
                                    scale=rng.uniform(0.5, 2.0), roughness=rng.uniform(0.2, 0.7))
    add("cube", floor_mat, location=(0.0, 0.0, -t / 2), scale=(w / 2 + t, d / 2 + t, t / 2))
    add("cube", wall_mat, location=(0.0, 0.0, h + t / 2), scale=(w / 2 + t, d / 2 + t, t / 2))
    openings = []
    walls = {"back": (0.0, d / 2 + t / 2, w, "x"), "front": (0.0, -d / 2 - t / 2, w, "x"),
             "left": (-w / 2 - t / 2, 0.0, d, "y"), "right": (w / 2 + t / 2, 0.0, d, "y")}
    with_hole = rng.sample(["back", "left", "right"], rng.choice((1, 1, 2)))
    for name, (cx, cy, length, axis) in walls.items():
        pieces = [(-length / 2, length / 2, 0.0, h)]            # (u0, u1, z0, z1) along the wall
        if name in with_hole:
            door = rng.random() < 0.3
            ow = rng.uniform(0.9, 1.6) if door else rng.uniform(1.0, min(2.8, length - 1.0))
            z0, z1 = (0.0, rng.uniform(2.0, min(2.3, h - 0.2))) if door else \
                (rng.uniform(0.6, 1.1), rng.uniform(1.9, h - 0.25))
            u = rng.uniform(-length / 2 + ow / 2 + 0.3, length / 2 - ow / 2 - 0.3)
            pieces = [(-length / 2, u - ow / 2, 0.0, h), (u + ow / 2, length / 2, 0.0, h),
                      (u - ow / 2, u + ow / 2, z1, h)] + ([(u - ow / 2, u + ow / 2, 0.0, z0)] if z0 > 0 else [])
            openings.append({"wall": name, "door": door, "width_m": round(ow, 2), "z_m": [round(z0, 2), round(z1, 2)],
                             "centre": (cx + (u if axis == "x" else 0.0), cy + (u if axis == "y" else 0.0),
                                        (z0 + z1) / 2)})
        for u0, u1, z0, z1 in pieces:
            du, dz = (u1 - u0) / 2, (z1 - z0) / 2
            loc_u = (u0 + u1) / 2
            loc = (cx + loc_u, cy, z0 + dz) if axis == "x" else (cx, cy + loc_u, z0 + dz)
            scale = (du, t / 2, dz) if axis == "x" else (t / 2, du, dz)
            add("cube", wall_mat, location=loc, scale=scale)
    drawn = {"room_m": [round(w, 2), round(d, 2), round(h, 2)], "openings": [
        {k: v for k, v in o.items() if k != "centre"} for o in openings]}
    drawn.update(_sky_lit(rng, (0.8, 3.0)))
    if rng.random() < 0.75:                       # the sun shines in through the first opening
        cx, cy, cz = openings[0]["centre"]
        inside = (rng.uniform(-w / 4, w / 4), rng.uniform(-d / 4, d / 4), 0.0)
        direction = (inside[0] - cx, inside[1] - cy, inside[2] - cz - rng.uniform(0.5, 2.5))
        s = rng.uniform(2.0, 6.0)
        sun_light(direction, s, rng.uniform(0.5, 4.0))
        drawn["sun"] = round(s, 2)
    if rng.random() < 0.35:
        e = rng.uniform(20.0, 120.0)
        lamp = area_light((rng.uniform(-w / 4, w / 4), rng.uniform(-d / 4, d / 4), h - 0.02), (0.0, 0.0, 0.0),
                          size=rng.uniform(0.2, 0.6), energy=e, color=(1.0, 0.85, 0.65))
        lamp.rotation_euler = (0.0, 0.0, 0.0)     # an area light shines down -Z
        drawn["ceiling_lamp"] = round(e)
    objects = _objects(rng, rng.randint(3, 6), ("diffuse", "textured", "plastic", "metal", "glass"),
                       (3, 3, 2, 1, 1), min(w, d) / 2 - 0.8, sizes=(0.4, 1.2), centre=(0.0, 0.4))
    drawn["objects"] = [o for _, o in objects]
    if objects and rng.random() < 0.5:
        drawn["objects"][0]["motion"] = _move(rng, objects[0][0], frames, (0.02, 0.08), (0.0, 4.0))
    cam = camera(lens=rng.uniform(18.0, 28.0))
    z = rng.uniform(1.2, 1.7)
    start = (rng.uniform(-w / 2 + 0.7, w / 2 - 0.7), -d / 2 + rng.uniform(0.5, 0.9), z)
    target = (rng.uniform(-w / 4, w / 4), d / 2, rng.uniform(0.8, 1.6))
    style = rng.choice(("pan", "dolly", "truck"))
    rate = {"pan": rng.uniform(0.5, 2.0), "dolly": rng.uniform(0.02, 0.06), "truck": rng.uniform(0.02, 0.06)}[style]
    sign = rng.choice((-1.0, 1.0))
    mid = (frames + 1) / 2.0

    def at(f):
        k = f - mid
        if style == "dolly":
            cam.location = (start[0], start[1] + rate * (f + 0.5), start[2])
        elif style == "truck":
            cam.location = (start[0] + sign * rate * k, start[1], start[2])
        else:
            cam.location = start
        look_at(cam, target)
        if style == "pan":
            cam.rotation_euler[2] += sign * math.radians(rate) * k

    keyframe(cam, frames, at)
    drawn["camera"] = {"style": style, "rate": round(rate, 3), "lens_mm": round(cam.data.lens, 1)}
    return drawn


def _objects_on_stage(rng: random.Random, frames: int, wall, sky, materials, weights, speed, lens) -> dict:
    """3-6 objects of ``materials`` (drawn with ``weights``) on a stage (``wall``: :func:`_stage`)
    under a sky (``sky``: its strength range) and 1-2 area lights, the first moving at ``speed``
    (m/frame) half the time, a camera of ``lens`` (mm) on a drawn path: ``glossy`` and ``textures``."""
    drawn = _stage(rng, wall=wall)
    drawn.update(_sky_lit(rng, sky))
    drawn["area_lights"] = _area_lights(rng, rng.randint(1, 2))
    objects = _objects(rng, rng.randint(3, 6), materials, weights, 1.8)
    drawn["objects"] = [o for _, o in objects]
    if rng.random() < 0.5:
        drawn["objects"][0]["motion"] = _move(rng, objects[0][0], frames, speed, (0.0, 8.0))
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(*lens)), frames, (0.0, 0.0, 0.4))
    return drawn


def build_glossy(rng: random.Random, frames: int) -> dict:
    """Glossy and metal objects (mirror-like to rough) on a textured floor under a sky and area
    lights; the camera orbits, trucks, dollies, cranes or pans."""
    return _objects_on_stage(rng, frames, None, (0.3, 1.5), ("metal", "plastic", "diffuse"), (5, 4, 1),
                             (0.03, 0.15), (28.0, 50.0))


def build_glass(rng: random.Random, frames: int) -> dict:
    """Glass objects (clear to frosted, tinted) in front of textured surfaces, lit by area lights
    and sometimes a small lamp, so refraction and caustics show."""
    drawn = _stage(rng, wall=True)
    drawn.update(_sky_lit(rng, (0.1, 0.8)))
    drawn["area_lights"] = _area_lights(rng, rng.randint(1, 2), (300.0, 1000.0))
    objects = _objects(rng, rng.randint(3, 5), ("glass", "diffuse", "textured"), (6, 1, 2), 1.6)
    drawn["objects"] = [o for _, o in objects]
    if rng.random() < 0.5:
        e = rng.uniform(20.0, 100.0)
        point_light((rng.uniform(-2, 2), rng.uniform(-1, 2), rng.uniform(1.0, 2.5)), rng.uniform(0.02, 0.1), e)
        drawn["point_light"] = round(e)
    if rng.random() < 0.5:
        drawn["objects"][0]["motion"] = _move(rng, objects[0][0], frames, (0.03, 0.12), (0.0, 8.0))
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(30.0, 50.0)), frames, (0.0, 0.0, 0.4))
    return drawn


def build_lamps(rng: random.Random, frames: int) -> dict:
    """A dim scene lit by small bright lamps (emitting spheres and point lights with small radii,
    some moving) over diffuse, glossy and metal objects: high-variance direct light."""
    drawn = _stage(rng)
    s = rng.uniform(0.0, 0.08)
    world_color(_hue_color(rng, (0.2, 0.6), (0.3, 0.8)), s)
    drawn["world"] = round(s, 3)
    objects = _objects(rng, rng.randint(3, 6), ("diffuse", "textured", "plastic", "metal"), (3, 2, 2, 2), 1.8)
    drawn["objects"] = [o for _, o in objects]
    lamps = []
    for k in range(rng.randint(2, 6)):
        color = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.0, 0.8), 1.0)
        loc = (rng.uniform(-2.5, 2.5), rng.uniform(-2.0, 2.5), rng.uniform(0.15, 2.5))
        if rng.random() < 0.5:
            r, e = rng.uniform(0.02, 0.08), rng.uniform(100.0, 1500.0)
            obj = add("uv_sphere", material(f"Lamp{k}", "emission", color, strength=e), location=loc, radius=r,
                      segments=24, ring_count=12)
            lamp = {"emitter_radius_m": round(r, 3), "strength": round(e)}
        else:
            r, e = rng.uniform(0.01, 0.06), rng.uniform(20.0, 200.0)
            obj = point_light(loc, r, e, color)
            lamp = {"point_radius_m": round(r, 3), "watts": round(e)}
        if rng.random() < 0.4:
            lamp["motion"] = _move(rng, obj, frames, (0.03, 0.15), (0.0, 0.0))
        lamps.append(lamp)
    drawn["lamps"] = lamps
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(28.0, 50.0)), frames, (0.0, 0.0, 0.5))
    return drawn


def build_dof(rng: random.Random, frames: int) -> dict:
    """Depth of field: objects spread in depth along the view, a long lens at a wide aperture
    focused on one of them; the camera trucks, dollies or pans slowly."""
    drawn = _stage(rng, wall=rng.random() < 0.5)
    drawn.update(_sky_lit(rng, (0.4, 1.5)))
    drawn["area_lights"] = _area_lights(rng, rng.randint(1, 2))
    objects = []
    n = rng.randint(4, 7)
    for k in range(n):                          # from 1.5 m to 12 m in front of a camera at y = -6
        y = -4.5 + (k + rng.uniform(-0.3, 0.3)) * 10.5 / n
        s = rng.uniform(0.3, 0.9)
        family = rng.choice(("diffuse", "textured", "textured", "plastic", "metal"))
        mat, desc = surface(rng, f"Obj{k}", family)
        kind = rng.choice(SHAPES)
        obj = shape(rng, mat, s, kind, location=(rng.uniform(-1.5, 1.5) * (y + 6) / 6, y, s / 2))
        objects.append((obj, {"shape": kind, "size_m": round(s, 2), "material": desc, "y_m": round(y, 2)}))
    drawn["objects"] = [o for _, o in objects]
    cam = camera(lens=rng.uniform(50.0, 100.0))
    cam.data.dof.use_dof = True
    focus = rng.choice(objects)[0]
    cam.data.dof.focus_object = focus
    cam.data.dof.aperture_fstop = rng.uniform(1.2, 4.0)
    drawn["dof"] = {"fstop": round(cam.data.dof.aperture_fstop, 2), "focus": focus.name}
    drawn["camera"] = camera_path(rng, cam, frames, (0.0, 0.0, 0.4), ("truck", "dolly", "pan"), speed=0.7,
                                  distance=(5.5, 7.0), height=(0.6, 1.8), angle=(-0.1, 0.1))
    return drawn


def build_motion(rng: random.Random, frames: int) -> dict:
    """Camera and object motion together: a fast camera path (two to four times the other kinds'
    rates) and one to three objects crossing at 0.1-0.4 m/frame, turning."""
    drawn = _stage(rng)
    drawn.update(_sky_lit(rng, (0.4, 1.5)))
    drawn["area_lights"] = _area_lights(rng, rng.randint(1, 2))
    objects = _objects(rng, rng.randint(3, 6), ("diffuse", "textured", "plastic", "metal", "glass"),
                       (2, 4, 2, 1, 1), 2.0)
    drawn["objects"] = [o for _, o in objects]
    for obj, desc in objects[:rng.randint(1, 3)]:
        desc["motion"] = _move(rng, obj, frames, (0.1, 0.4), (3.0, 15.0))
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(24.0, 45.0)), frames, (0.0, 0.0, 0.4),
                                  speed=rng.uniform(2.0, 4.0))
    return drawn


def build_textures(rng: random.Random, frames: int) -> dict:
    """Procedural textures everywhere (checker, brick, noise, Voronoi, wave, magic, gradient, with
    bump), high-frequency detail a denoiser must keep; the camera moves slowly."""
    return _objects_on_stage(rng, frames, True, (0.3, 1.2), ("textured",), (1,), (0.03, 0.12), (28.0, 60.0))


def build_foliage(rng: random.Random, frames: int) -> dict:
    """(Reserved) thin geometry: a meadow of grass blades (one mesh of thin tapered quads) and
    plants of thin stems and leaf quads, swaying, under a sun and sky."""
    ground = procedural_material(rng, "Ground", "noise", (0.25, 0.35, 0.1), (0.12, 0.08, 0.04), scale=2.0)
    add("plane", ground, size=40.0)
    drawn = _sky_lit(rng, (0.6, 1.5))
    s = rng.uniform(2.0, 5.0)
    sun_light((rng.uniform(-1, 1), rng.uniform(-1, 1), -rng.uniform(0.5, 1.5)), s, rng.uniform(0.5, 3.0))
    drawn["sun"] = round(s, 2)
    verts, faces = [], []
    n = rng.randint(600, 1200)
    for _ in range(n):                           # blades: 3 m x 3 m patch, 1-4 mm wide, 10-50 cm tall
        x, y = rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0)
        h, wb = rng.uniform(0.1, 0.5), rng.uniform(0.001, 0.004)
        a, lean = rng.uniform(0, math.pi), rng.uniform(-0.3, 0.3)
        dx, dy = wb * math.cos(a), wb * math.sin(a)
        i = len(verts)
        verts += [(x - dx, y - dy, 0.0), (x + dx, y + dy, 0.0),
                  (x + lean * h * math.sin(a) + 0.3 * dx, y - lean * h * math.cos(a) + 0.3 * dy, h),
                  (x + lean * h * math.sin(a) - 0.3 * dx, y - lean * h * math.cos(a) - 0.3 * dy, h)]
        faces.append((i, i + 1, i + 2, i + 3))
    grass = mesh_object("Grass", verts, faces, material("Blades", "principled", _hue_color(rng, (0.5, 0.9),
                                                                                          (0.3, 0.7)), 0.6))
    leaves, stems = [], []
    for p in range(rng.randint(2, 4)):
        px, py, ph = rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(0.6, 1.5)
        stems.append(add("cylinder", material(f"Stem{p}", "principled", (0.2, 0.3, 0.1), 0.7),
                         location=(px, py, ph / 2), radius=rng.uniform(0.004, 0.012), depth=ph, vertices=8))
        for _ in range(rng.randint(15, 40)):
            z, a, ls = rng.uniform(0.2, 1.0) * ph, rng.uniform(0, 2 * math.pi), rng.uniform(0.03, 0.1)
            cx, cy = px + ls * math.cos(a), py + ls * math.sin(a)
            i = len(leaves)
            leaves.append([(px, py, z), (cx - 0.3 * ls * math.sin(a), cy + 0.3 * ls * math.cos(a), z + 0.2 * ls),
                           (px + 2 * ls * math.cos(a), py + 2 * ls * math.sin(a), z + 0.1 * ls),
                           (cx + 0.3 * ls * math.sin(a), cy - 0.3 * ls * math.cos(a), z + 0.2 * ls)])
    leaf_obj = mesh_object("Leaves", [v for q in leaves for v in q], [tuple(range(4 * i, 4 * i + 4))
                                                                      for i in range(len(leaves))],
                           material("Leaf", "principled", _hue_color(rng, (0.5, 0.9), (0.3, 0.8)), 0.5))
    sway = rng.uniform(0.3, 1.2)
    for obj in (grass, leaf_obj):
        keyframe(obj, frames, lambda f, obj=obj: setattr(obj, "rotation_euler",
                                                          (math.radians(sway) * math.sin(0.8 * f), 0.0, 0.0)))
    drawn.update({"blades": n, "leaves": len(leaves), "plants": len(stems), "sway_deg": round(sway, 2)})
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(30.0, 60.0)), frames, (0.0, 0.0, 0.3),
                                  ("orbit", "truck", "dolly"), speed=0.6, distance=(2.5, 4.0), height=(0.4, 1.2),
                                  angle=(-math.pi, math.pi))
    return drawn


def build_pool(rng: random.Random, frames: int) -> dict:
    """(Reserved) caustics: a pool of tiled walls and floor under a moving wavy water surface
    (refractive, IOR 1.33) lit by a small sun: the floor's light is refracted caustics only."""
    tiles = procedural_material(rng, "Tiles", "brick", colorsys.hsv_to_rgb(rng.uniform(0.45, 0.6),
                                                                          rng.uniform(0.1, 0.5), 0.9),
                                (0.9, 0.9, 0.9), scale=rng.uniform(1.0, 3.0), roughness=0.3, bump=0.1)
    w, d, depth = rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0), rng.uniform(0.8, 1.6)
    add("cube", tiles, location=(0.0, 0.0, -depth - 0.05), scale=(w / 2, d / 2, 0.05))
    for sx, sy, lx, ly in ((1, 0, 0.05, d / 2), (-1, 0, 0.05, d / 2), (0, 1, w / 2, 0.05), (0, -1, w / 2, 0.05)):
        add("cube", tiles, location=(sx * (w / 2 + 0.05), sy * (d / 2 + 0.05), -depth / 2), scale=(lx, ly, depth / 2))
    deck = procedural_material(rng, "Deck", "noise", scale=3.0)
    rim = 0.1                                     # the deck: four slabs round the pool, top at z = 0
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        half = (10.0, 10.0 + d / 2 + rim, 0.05) if sx else (w / 2 + rim, 10.0, 0.05)
        add("cube", deck, location=(sx * (w / 2 + rim + 10.0), sy * (d / 2 + rim + 10.0), -0.05), scale=half)
    n, amp = 64, rng.uniform(0.01, 0.04)
    waves = [(rng.uniform(2.0, 6.0), rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)) for _ in range(3)]
    verts = []
    for j in range(n + 1):
        for i in range(n + 1):
            x, y = (i / n - 0.5) * (w + 3.0), (j / n - 0.5) * (d + 3.0)
            verts.append((x, y, sum(amp * math.sin(k * (x * math.cos(a) + y * math.sin(a)) + p)
                                    for k, a, p in waves)))
    faces = [(j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i)
             for j in range(n) for i in range(n)]
    water_mat = material("Water", "glass", (0.9, 0.97, 1.0), 0.0)
    water_mat.node_tree.nodes["Glass BSDF"].inputs["IOR"].default_value = 1.33
    water = mesh_object("Water", verts, faces, water_mat, location=(0.0, 0.0, -0.2))   # under the deck
    for poly in water.data.polygons:
        poly.use_smooth = True
    drawn = {"pool_m": [round(w, 2), round(d, 2), round(depth, 2)], "wave_amp_m": round(amp, 3)}
    drawn["water_motion"] = _move(rng, water, frames, (0.02, 0.08), (0.0, 0.0))
    s = rng.uniform(3.0, 6.0)
    sun_light((rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), -1.0), s, rng.uniform(0.3, 1.5))
    drawn.update(_sky_lit(rng, (0.3, 1.0)))
    drawn["sun"] = round(s, 2)
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(20.0, 35.0)), frames, (0.0, 0.0, -depth),
                                  ("orbit", "truck", "pan"), speed=0.7, distance=(3.0, 5.0), height=(1.5, 3.0),
                                  angle=(-math.pi, math.pi))
    return drawn


def build_signage(rng: random.Random, frames: int) -> dict:
    """(Reserved) emissive signage at night: glowing letters (Blender's built-in font) and neon
    tubes on a dark wall over a wet, glossy street; the camera trucks past."""
    world_color((0.02, 0.03, 0.06), rng.uniform(0.0, 0.1))
    street = procedural_material(rng, "Street", "noise", (0.06, 0.06, 0.07), (0.02, 0.02, 0.02), scale=4.0,
                                 roughness=rng.uniform(0.03, 0.25), bump=0.05)
    add("plane", street, size=40.0)
    wall = procedural_material(rng, "Wall", "brick", (0.2, 0.12, 0.1), (0.08, 0.08, 0.08), scale=0.6)
    add("plane", wall, location=(0.0, 2.0, 4.0), rotation=(math.radians(90), 0.0, 0.0), size=30.0)
    signs = []
    letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"
    for k in range(rng.randint(2, 4)):
        color = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.6, 1.0), 1.0)
        e = rng.uniform(5.0, 40.0)
        bpy.ops.object.text_add(location=(rng.uniform(-3.0, 2.0), 1.95, rng.uniform(0.6, 3.0)),
                                rotation=(math.radians(90), 0.0, 0.0))
        text = bpy.context.active_object
        text.data.body = "".join(rng.choice(letters) for _ in range(rng.randint(3, 7)))
        text.data.size = rng.uniform(0.3, 0.7)
        text.data.extrude = 0.01
        text.data.materials.append(material(f"Sign{k}", "emission", color, strength=e))
        signs.append({"text": text.data.body, "strength": round(e, 1)})
    for k in range(rng.randint(1, 3)):
        color = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.6, 1.0), 1.0)
        e = rng.uniform(10.0, 60.0)
        tube = add("torus", material(f"Neon{k}", "emission", color, strength=e),
                   location=(rng.uniform(-3.0, 3.0), 1.9, rng.uniform(0.8, 3.0)), rotation=(math.radians(90), 0, 0),
                   major_radius=rng.uniform(0.2, 0.6), minor_radius=rng.uniform(0.01, 0.025))
        signs.append({"neon": tube.name, "strength": round(e, 1)})
    e = rng.uniform(20.0, 80.0)
    point_light((rng.uniform(-3, 3), rng.uniform(-1.0, 1.0), 3.5), 0.05, e, (1.0, 0.75, 0.45))
    drawn = {"signs": signs, "street_lamp": round(e)}
    drawn["camera"] = camera_path(rng, camera(lens=rng.uniform(24.0, 40.0)), frames, (0.0, 2.0, 1.6),
                                  ("truck", "dolly", "pan"), distance=(4.0, 7.0), height=(1.0, 2.0),
                                  angle=(-0.8, 0.8))
    return drawn


RELEASE_BUILDERS = {"interior": build_interior, "glossy": build_glossy, "glass": build_glass,
                    "lamps": build_lamps, "dof": build_dof, "motion": build_motion, "textures": build_textures,
                    "foliage": build_foliage, "pool": build_pool, "signage": build_signage}


def build_release(kind: str, frames: int, seed: int) -> dict:
    """Build the release kind ``kind`` from ``seed``; returns what was drawn (for render.json)."""
    drawn = RELEASE_BUILDERS[kind](random.Random(f"{kind}:{seed}"), frames)
    return {"kind": kind, "seed": seed, **drawn}


def _round_robin(kinds, seeds) -> tuple[str, ...]:
    return tuple(f"{kinds[i % len(kinds)]}_{s}" for i, s in enumerate(seeds))


#: the release Cycles splits (issue 62) by seed, disjoint from each other and from MOVING_SEEDS
#: (101-103, 201-206, 301-306): seeds are given kinds in turn, so every split holds every kind
#: of its list. ``test`` is rendered once, after the release recipe is frozen; ``unlabeled`` is
#: noisy only (distillation); ``timing`` (one per kind, reserved ones too) measured the seconds per
#: sequence and the reference's noise floor; ``reserved`` holds the kinds training never sees.
RELEASE_SPLITS = {
    "train": _round_robin(RELEASE_KINDS, range(1001, 1043)),       # 42, 6 per kind
    "val": _round_robin(RELEASE_KINDS, range(2001, 2009)),         # 8 (interior twice)
    "test": _round_robin(RELEASE_KINDS, range(3001, 3015)),        # 14, 2 per kind
    "unlabeled": _round_robin(RELEASE_KINDS, range(4001, 4013)),   # 12, noisy only
    "timing": _round_robin(RELEASE_KINDS + RESERVED_KINDS, range(5001, 5011)),
    "reserved": _round_robin(RESERVED_KINDS, range(6001, 6010)),   # 9, 3 per reserved kind
}
#: release splits rendered without references
RELEASE_NOISY_ONLY = ("unlabeled",)
#: sequences of the release set rendered at 256x256 (the rest at 128x128): the last seed of each kind
#: in train (interior_1036 ... textures_1042) and val's interior_2001, the set the release render
#: started at 21:48 (--ref-spp 256) runs with, so that it resumes as it began (issue 62's timing renders,
#: split timing: an 8-frame 128x128 sequence of a training kind is 54-142 s on 2 cores at 256 spp,
#: 106-262 s at 512; train + val + unlabeled about 2.1 h at 256 spp, 2.9 h at 384)
RELEASE_LARGE = frozenset(RELEASE_SPLITS["train"][-len(RELEASE_KINDS):] + RELEASE_SPLITS["val"][:1])


def build(name: str, frames: int, width: int) -> dict:
    """Build sequence ``name`` into the (reset) scene; returns what a seeded builder drew."""
    seed = fast_seed(name)
    if seed is not None:
        return build_fast(frames, width, seed)
    if seeded(name) is not None:
        kind, seed = seeded(name)
        return build_release(kind, frames, seed)
    BUILDERS[name](frames)
    return {}


def sequence_name(name: str) -> str:
    """argparse type of ``--sequences``: a builder's name, ``fast_<seed>`` or ``<kind>_<seed>``."""
    if name in BUILDERS or seeded(name) is not None:
        return name
    raise argparse.ArgumentTypeError(f"unknown sequence {name!r}; use {', '.join(BUILDERS)} or <kind>_<seed> "
                                     f"with a kind of {', '.join(SEEDED_KINDS)}")


# ----------------------------------------------------------------------------- rendering


def render_pass(scene, out_dir: Path, frames: int, spp: int, seed: int, label: str, keep: bool = False) -> list[float]:
    """Frames 1..frames to ``out_dir/<frame:04d>.exr``; the seconds of each frame rendered
    (blender_cycles.render_frames; ``keep``: frames on disk are kept)."""
    return list(render_frames(scene, out_dir, range(1, frames + 1), spp, seed, label, keep=keep,
                              prefix="blender_sequences").values())


def parse_args(argv):
    if "--" in argv:                               # blender -b -P script.py -- args
        argv = argv[argv.index("--") + 1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, default=Path("data/blender"), help="dataset root (default data/blender)")
    p.add_argument("--split", default="test", help="split folder (default test)")
    p.add_argument("--set", choices=("release",), default=None,
                   help="release: the split's sequences are RELEASE_SPLITS[split] (train, val, test, unlabeled "
                        "(noisy only), timing, reserved), at 128x128 but 256x256 for RELEASE_LARGE (issue 62)")
    p.add_argument("--sequences", nargs="+", type=sequence_name, default=None,
                   help="sequences to render: orbit, slide, probe (a 32x32 Vector/normal check), fast_<seed> "
                        "(default: the split's, " + "; ".join(f"{k}: {' '.join(v)}" for k, v in
                                                                SPLIT_SEQUENCES.items()) + ")")
    p.add_argument("--size", type=int, nargs="+", default=None,
                   help="W [H] in pixels of every sequence (default 128; --set release: 128 or 256 per sequence)")
    p.add_argument("--frames", type=int, default=8, help="frames per sequence (default 8)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of the noisy render (default 4)")
    p.add_argument("--ref-spp", type=int, default=1024,
                   help="samples per pixel of the reference (default 1024)")
    p.add_argument("--seed", type=int, default=1, help="noisy seed; the reference uses seed + 1000")
    p.add_argument("--threads", type=int, default=2, help="Cycles CPU threads (default 2)")
    p.add_argument("--no-reference", action="store_true", help="render only the noisy frames")
    p.add_argument("--force", action="store_true", help="re-render sequences that are already complete")
    p.add_argument("--ref-check", action="store_true",
                   help="also render a second reference (seed + 2000, reference_check/, not read by the layout) "
                        "and write the reference's noise floor, its PSNR against the second one, to render.json")
    return p.parse_args(argv)


#: version of the ``fast_<seed>`` builder, recorded in render.json: a change re-renders them
MOVING_VERSION = 1


def settings(args, name: str, width: int, height: int) -> dict:
    """What a finished sequence's render.json must record for it to be skipped."""
    out = {"blender": bpy.app.version_string, "width": width, "height": height, "frames": args.frames,
           "noisy": {"spp": args.spp, "seed": args.seed}}
    if fast_seed(name) is not None:
        out["builder"] = f"fast v{MOVING_VERSION}"
    elif seeded(name) is not None:
        out["builder"] = f"{seeded(name)[0]} v{RELEASE_VERSION}"
    if not args.no_reference:
        out["reference"] = {"spp": args.ref_spp, "seed": args.seed + 1000}
        if args.ref_check:
            out["reference_check"] = {"spp": args.ref_spp, "seed": args.seed + 2000}
    return out


def complete(seq_dir: Path, frames: int, wanted: dict) -> bool:
    """Every frame on disk and render.json recording the same settings."""
    dirs = ["noisy"] + [d for d in ("reference", "reference_check") if d in wanted]
    if not all((seq_dir / d / f"{f:04d}.exr").exists() for d in dirs for f in range(1, frames + 1)):
        return False
    try:
        info = json.loads((seq_dir / "render.json").read_text())
    except (OSError, ValueError):
        return False
    return all(info.get(k) == v for k, v in wanted.items())


def sequence_size(args, name: str) -> tuple[int, int]:
    """``(width, height)`` of sequence ``name``: ``--size``, else 256x256 for the release set's
    RELEASE_LARGE, else 128x128."""
    if args.size is not None:
        return args.size[0], args.size[1] if len(args.size) > 1 else args.size[0]
    side = 256 if args.set == "release" and name in RELEASE_LARGE else 128
    return side, side


def _copy_combined(directory: Path):
    """A ``render_write`` handler saving each written frame's Combined pass as an RGB float32 EXR
    ``directory/<frame:04d>.exr`` (``bpy.data.images.load`` reads those pixels, not a multilayer
    file's; the copy equals the multilayer file's Combined.RGB exactly)."""
    directory.mkdir(parents=True, exist_ok=True)

    def handler(scene, *_):
        fmt = scene.render.image_settings
        saved = [(k, getattr(fmt, k)) for k in ("media_type", "file_format", "color_mode", "color_depth")
                 if hasattr(fmt, k)]
        if hasattr(fmt, "media_type"):
            fmt.media_type = "IMAGE"
        fmt.file_format, fmt.color_mode, fmt.color_depth = "OPEN_EXR", "RGB", "32"
        try:
            bpy.data.images["Render Result"].save_render(str(directory / f"{scene.frame_current:04d}.exr"),
                                                         scene=scene)
        finally:
            for k, v in saved:
                setattr(fmt, k, v)

    return handler


def _rgb(path: Path):
    """``[H*W, 3]`` float32 linear RGB of a single-layer EXR (via ``bpy.data.images``)."""
    import numpy as np
    image = bpy.data.images.load(str(path))
    pixels = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(-1, image.channels)[:, :3]
    bpy.data.images.remove(image)
    return pixels


def tonemapped(x):
    """denoiser.metrics.tonemap in numpy (this script runs without the package): ACES fit
    (Narkowicz: 2.51, 0.03, 2.43, 0.59, 0.14) of the linear values clamped at 0, then the sRGB OETF."""
    import numpy as np
    x = np.clip(x, 0.0, None)
    y = np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.maximum(y, 0.0031308) ** (1.0 / 2.4) - 0.055)


def noise_floor(reference_dir: Path, check_dir: Path) -> dict:
    """PSNR (dB, tonemapped as the project's metric) of each frame of one reference against a
    second one with another seed, over the frames both folders hold, and their mean: what no
    denoiser scored against this reference can be told apart from."""
    import numpy as np
    per_frame = {}
    for path in sorted(reference_dir.glob("*.exr")):
        other = check_dir / path.name
        if other.exists():
            mse = float(np.mean((tonemapped(_rgb(path)) - tonemapped(_rgb(other))) ** 2))
            per_frame[int(path.stem)] = round(10.0 * math.log10(1.0 / max(mse, 1e-12)), 3)
    if not per_frame:
        raise SystemExit(f"blender_sequences: no frame of {reference_dir} has a second reference in {check_dir}")
    return {"psnr_db": round(sum(per_frame.values()) / len(per_frame), 3), "per_frame": per_frame,
            "metric": "PSNR of tonemapped frames (denoiser.metrics.psnr), mean over frames"}


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    lists = RELEASE_SPLITS if args.set == "release" else SPLIT_SEQUENCES
    if args.set == "release" and args.split in RELEASE_NOISY_ONLY:
        args.no_reference = True                  # distillation's unlabeled sequences: noisy only
    if args.sequences is None:
        if args.split not in lists:
            raise SystemExit(f"blender_sequences: split {args.split!r} has no default sequences "
                             f"({', '.join(lists)} have); name them with --sequences")
        args.sequences = list(lists[args.split])
        stale = sorted(d.name for d in (args.root / args.split).glob("*") if d.is_dir() and d.name not in args.sequences)
        if stale:   # evaluated with the split (make demo, make blender): earlier rounds' looked-at sequences
            raise SystemExit(f"blender_sequences: {args.root / args.split / stale[0]} is not one of the split's "
                             f"sequences ({', '.join(args.sequences)}); move it aside (it was a test sequence of an "
                             "earlier round) and run again")
    sizes = {name: sequence_size(args, name) for name in args.sequences}
    print(f"blender_sequences: Blender {bpy.app.version_string}, "
          f"{', '.join(sorted({f'{w}x{h}' for w, h in sizes.values()}))}, {args.frames} frames, {args.spp} spp noisy, "
          f"{'no' if args.no_reference else args.ref_spp} spp reference -> {args.root / args.split}", flush=True)
    for name in args.sequences:
        seq_dir = args.root / args.split / name
        width, height = sizes[name]
        wanted = settings(args, name, width, height)
        if not args.force and complete(seq_dir, args.frames, wanted):
            print(f"{name}: complete with these settings, skipped (--force re-renders)", flush=True)
            continue
        # render.pending.json: the settings of a run under way; a run stopped with the same settings
        # left frames this one keeps (each frame is renamed into place only when complete)
        pending = seq_dir / "render.pending.json"
        try:
            keep = not args.force and json.loads(pending.read_text()) == wanted
        except (OSError, ValueError):
            keep = False
        seq_dir.mkdir(parents=True, exist_ok=True)
        pending.write_text(json.dumps(wanted, indent=2) + "\n")
        print(f"{name}: building scene{' (resuming: frames on disk kept)' if keep else ''}", flush=True)
        scene = reset_scene(width, height, args.threads)
        scene.frame_start, scene.frame_end = 1, args.frames
        drawn = build(name, args.frames, width)
        info = {**wanted, "engine": "CYCLES", "device": "CPU", "threads": args.threads,
                "pixel_filter": "BOX 1.0", "denoiser": False, **({"scene": drawn} if drawn else {}),
                "seconds": {}, **({"resumed": True} if keep else {})}
        info["cpu_seconds"] = {}                  # Cycles' threads together: the figure a busy host keeps
        t0 = time.perf_counter()
        passes = [("noisy", args.spp, args.seed)]
        if not args.no_reference:
            passes.append(("reference", args.ref_spp, args.seed + 1000))
        if args.ref_check and not args.no_reference:
            passes.append(("reference_check", args.ref_spp, args.seed + 2000))
        with tempfile.TemporaryDirectory() as copies:
            for folder, spp, seed in passes:
                handler = _copy_combined(Path(copies) / folder) if "reference_check" in wanted else None
                if handler is not None:
                    bpy.app.handlers.render_write.append(handler)
                c0 = time.process_time()
                try:
                    info["seconds"][folder] = render_pass(scene, seq_dir / folder, args.frames, spp, seed,
                                                          f"{name} {folder}", keep=keep)
                finally:
                    if handler is not None:
                        bpy.app.handlers.render_write.remove(handler)
                info["cpu_seconds"][folder] = round(time.process_time() - c0, 2)
            if "reference_check" in wanted:
                info["noise_floor"] = noise_floor(Path(copies) / "reference", Path(copies) / "reference_check")
                print(f"{name}: reference vs a second reference (seed {args.seed + 2000}): "
                      f"{info['noise_floor']['psnr_db']:.2f} dB", flush=True)
        (seq_dir / "render.json").write_text(json.dumps(info, indent=2) + "\n")
        pending.unlink()
        print(f"{name}: done in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
