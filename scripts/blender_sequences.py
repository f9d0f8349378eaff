"""Render small Blender Cycles test sequences in the layout ``layout=blender`` reads.

Runs with Blender's Python module (``pip install bpy``, in its own venv: ``make blender`` makes
one) and needs only ``bpy``, ``numpy`` and the standard library, so it also runs inside Blender::

    /work/blender-venv/bin/python scripts/blender_sequences.py --root data/blender
    blender -b -P scripts/blender_sequences.py -- --root data/blender --frames 4

Writes, for each sequence, multilayer float32 EXRs named as Blender names them::

    <root>/test/<sequence>/noisy/0001.exr ...       # --spp samples, seed A
    <root>/test/<sequence>/reference/0001.exr ...   # --ref-spp samples, seed B
    <root>/test/<sequence>/render.json              # settings and render seconds (not read by the loader)

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


def area_light(location, rotation, size=2.0, energy=300.0, color=(1.0, 0.95, 0.9)):
    data = bpy.data.lights.new("Area", type="AREA")
    data.size = size
    data.energy = energy
    data.color = color
    obj = bpy.data.objects.new("Area", data)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
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


#: camera of the fast-motion sequences: static, looking along +Y (the image plane is parallel to
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


def build(name: str, frames: int, width: int) -> dict:
    """Build sequence ``name`` into the (reset) scene; returns what a seeded builder drew."""
    seed = fast_seed(name)
    if seed is not None:
        return build_fast(frames, width, seed)
    BUILDERS[name](frames)
    return {}


def sequence_name(name: str) -> str:
    """argparse type of ``--sequences``: a builder's name or ``fast_<seed>``."""
    if name in BUILDERS or fast_seed(name) is not None:
        return name
    raise argparse.ArgumentTypeError(f"unknown sequence {name!r}; use {', '.join(BUILDERS)} or fast_<seed>")


# ----------------------------------------------------------------------------- rendering


def render_pass(scene, out_dir: Path, frames: int, spp: int, seed: int, label: str) -> list[float]:
    """Frames 1..frames to ``out_dir/<frame:04d>.exr``; the seconds of each (blender_cycles.render_frames)."""
    return list(render_frames(scene, out_dir, range(1, frames + 1), spp, seed, label,
                              prefix="blender_sequences").values())


def parse_args(argv):
    if "--" in argv:                               # blender -b -P script.py -- args
        argv = argv[argv.index("--") + 1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, default=Path("data/blender"), help="dataset root (default data/blender)")
    p.add_argument("--split", default="test", help="split folder (default test)")
    p.add_argument("--sequences", nargs="+", type=sequence_name, default=None,
                   help="sequences to render: orbit, slide, probe (a 32x32 Vector/normal check), fast_<seed> "
                        "(default: the split's, " + "; ".join(f"{k}: {' '.join(v)}" for k, v in
                                                                SPLIT_SEQUENCES.items()) + ")")
    p.add_argument("--size", type=int, nargs="+", default=[128], help="W [H] in pixels (default 128)")
    p.add_argument("--frames", type=int, default=8, help="frames per sequence (default 8)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of the noisy render (default 4)")
    p.add_argument("--ref-spp", type=int, default=1024,
                   help="samples per pixel of the reference (default 1024)")
    p.add_argument("--seed", type=int, default=1, help="noisy seed; the reference uses seed + 1000")
    p.add_argument("--threads", type=int, default=2, help="Cycles CPU threads (default 2)")
    p.add_argument("--no-reference", action="store_true", help="render only the noisy frames")
    p.add_argument("--force", action="store_true", help="re-render sequences that are already complete")
    return p.parse_args(argv)


#: version of the ``fast_<seed>`` builder, recorded in render.json: a change re-renders them
MOVING_VERSION = 1


def settings(args, name: str, width: int, height: int) -> dict:
    """What a finished sequence's render.json must record for it to be skipped."""
    out = {"blender": bpy.app.version_string, "width": width, "height": height, "frames": args.frames,
           "noisy": {"spp": args.spp, "seed": args.seed}}
    if fast_seed(name) is not None:
        out["builder"] = f"fast v{MOVING_VERSION}"
    if not args.no_reference:
        out["reference"] = {"spp": args.ref_spp, "seed": args.seed + 1000}
    return out


def complete(seq_dir: Path, frames: int, wanted: dict) -> bool:
    """Every frame on disk and render.json recording the same settings."""
    dirs = ["noisy"] + (["reference"] if "reference" in wanted else [])
    if not all((seq_dir / d / f"{f:04d}.exr").exists() for d in dirs for f in range(1, frames + 1)):
        return False
    try:
        info = json.loads((seq_dir / "render.json").read_text())
    except (OSError, ValueError):
        return False
    return all(info.get(k) == v for k, v in wanted.items())


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.sequences is None:
        if args.split not in SPLIT_SEQUENCES:
            raise SystemExit(f"blender_sequences: split {args.split!r} has no default sequences "
                             f"({', '.join(SPLIT_SEQUENCES)} have); name them with --sequences")
        args.sequences = list(SPLIT_SEQUENCES[args.split])
        stale = sorted(d.name for d in (args.root / args.split).glob("*") if d.is_dir() and d.name not in args.sequences)
        if stale:   # evaluated with the split (make demo, make blender): earlier rounds' looked-at sequences
            raise SystemExit(f"blender_sequences: {args.root / args.split / stale[0]} is not one of the split's "
                             f"sequences ({', '.join(args.sequences)}); move it aside (it was a test sequence of an "
                             "earlier round) and run again")
    width = args.size[0]
    height = args.size[1] if len(args.size) > 1 else width
    print(f"blender_sequences: Blender {bpy.app.version_string}, {width}x{height}, {args.frames} frames, "
          f"{args.spp} spp noisy, {args.ref_spp} spp reference -> {args.root / args.split}", flush=True)
    for name in args.sequences:
        seq_dir = args.root / args.split / name
        wanted = settings(args, name, width, height)
        if not args.force and complete(seq_dir, args.frames, wanted):
            print(f"{name}: complete with these settings, skipped (--force re-renders)", flush=True)
            continue
        print(f"{name}: building scene", flush=True)
        scene = reset_scene(width, height, args.threads)
        scene.frame_start, scene.frame_end = 1, args.frames
        drawn = build(name, args.frames, width)
        info = {**wanted, "engine": "CYCLES", "device": "CPU", "threads": args.threads,
                "pixel_filter": "BOX 1.0", "denoiser": False, **({"scene": drawn} if drawn else {}),
                "seconds": {}}
        t0 = time.perf_counter()
        info["seconds"]["noisy"] = render_pass(scene, seq_dir / "noisy", args.frames, args.spp, args.seed,
                                               f"{name} noisy")
        if not args.no_reference:
            info["seconds"]["reference"] = render_pass(scene, seq_dir / "reference", args.frames, args.ref_spp,
                                                       args.seed + 1000, f"{name} reference")
        (seq_dir / "render.json").write_text(json.dumps(info, indent=2) + "\n")
        print(f"{name}: done in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
