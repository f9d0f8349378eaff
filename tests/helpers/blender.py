"""The ``bpy`` venv for the tests that run Blender (``make blender-venv`` builds ``.venv-blender``).

Where it is absent the test skips, naming why; under ``$DENOISER_REQUIRE_BPY=1`` (set by ``.ci/run``
where the venv builds) the absence is a failure instead, as ``$DENOISER_REQUIRE_OVEXT`` is for the
OpenVINO extension (tests/conftest.py).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

CHECKOUT = Path(__file__).resolve().parents[2]
REQUIRE_BPY = "DENOISER_REQUIRE_BPY"


def blender_python_or_skip() -> Path:
    """The bpy venv's Python (``$DENOISER_BLENDER_PYTHON``, else the checkout's ``.venv-blender``);
    skips the test when it is missing or cannot import bpy (fails it under ``$DENOISER_REQUIRE_BPY=1``)."""
    python = Path(os.environ.get("DENOISER_BLENDER_PYTHON", CHECKOUT / ".venv-blender" / "bin" / "python"))
    reason = None
    if not python.is_file():
        reason = f"no bpy venv at {python} (make blender-venv builds it)"
    elif subprocess.run([str(python), "-c", "import bpy"], capture_output=True, check=False).returncode != 0:
        reason = f"{python} cannot import bpy (make blender-venv builds the venv)"
    if reason is None:
        return python
    if os.environ.get(REQUIRE_BPY) == "1":
        pytest.fail(f"{reason} (and {REQUIRE_BPY}=1: this test must run here)", pytrace=False)
    pytest.skip(reason)


#: a bpy script: ``<python> -c BUILD_SCENE out.blend <motion blur 0|1> <camera 0|1> <size> <frames>`` saves
#: a scene of ``size`` x ``size`` pixels and frames 1..frames (a cube moving +X 0.5 m per frame, a point
#: light, a camera) with Blender's factory render settings
BUILD_SCENE = """
import sys
import bpy
out, blur, cam, size, frames = sys.argv[1], sys.argv[2] == "1", sys.argv[3] == "1", int(sys.argv[4]), int(sys.argv[5])
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.render.resolution_x = scene.render.resolution_y = size
scene.frame_start, scene.frame_end = 1, frames
scene.render.use_motion_blur = blur
bpy.ops.mesh.primitive_cube_add(location=(0, 0, 0))
cube = bpy.context.active_object
for f, x in ((0, -1.0), (frames + 1, 0.5 * frames - 0.5)):
    cube.location.x = x
    cube.keyframe_insert("location", frame=f)
light = bpy.data.objects.new("Light", bpy.data.lights.new("Light", type="POINT"))
light.data.energy = 1000.0
light.location = (3, -3, 4)
scene.collection.objects.link(light)
if cam:
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0, -6, 2)
    camera.rotation_euler = (1.29, 0, 0)
    scene.collection.objects.link(camera)
    scene.camera = camera
bpy.ops.wm.save_as_mainfile(filepath=out)
"""


def build_scene(python: Path, out: Path, motion_blur: bool = False, camera: bool = True, size: int = 32,
                frames: int = 3) -> Path:
    """Save :data:`BUILD_SCENE`'s scene to ``out`` with the bpy venv's ``python``; returns ``out``."""
    subprocess.run([str(python), "-c", BUILD_SCENE, str(out), str(int(motion_blur)), str(int(camera)), str(size),
                    str(frames)], check=True, capture_output=True)
    return out
