"""The Cycles render settings, passes and output that ``layout=blender`` needs, said once for
``scripts/blender_sequences.py`` (the project's own scenes) and ``scripts/blender_render.py`` (a
user's ``.blend`` file, ``denoiser-render-blender``). Needs only ``bpy`` and the standard library.

The settings the results depend on (:data:`RENDER_SETTINGS`, docs/guide.md "Render settings and
passes"): no adaptive sampling (every pixel gets the same spp, so the noise level is the one the
network was trained for), Cycles' denoiser off (``Combined`` is the raw Monte Carlo estimate), a box
pixel filter one pixel wide (a sample stays in its pixel: the noise is not spatially correlated),
animated seed (fresh noise every frame, as a real-time renderer's), no compositor or sequencer
(they would change ``Combined``). Motion blur must be off (:func:`refusal`): Cycles then writes no
``Vector`` pass. The passes (:func:`enable_passes`): Denoising Data (albedo, normal, depth), Z and
Vector. The output (:func:`set_exr_output`): multilayer float32 EXR, ZIP.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from pathlib import Path

import bpy

#: (attribute path from the scene, value): the render settings the noisy/reference pair depends on
RENDER_SETTINGS = (
    ("render.engine", "CYCLES"),
    ("cycles.use_adaptive_sampling", False),    # the same spp in every pixel
    ("cycles.use_denoising", False),            # Combined is the raw estimate
    ("cycles.use_animated_seed", True),         # fresh noise every frame
    ("cycles.pixel_filter_type", "BOX"),
    ("cycles.filter_width", 1.0),               # a box one pixel wide: no cross-pixel splatting
    ("render.use_compositing", False),          # the compositor would change Combined
    ("render.use_sequencer", False),
)
#: (attribute path from a view layer, value): the passes the blender layout reads
PASSES = (
    ("use_pass_combined", True),
    ("use_pass_z", True),                       # Depth.Z: planar depth
    ("use_pass_vector", True),                  # Vector: screen motion (needs motion blur off)
    ("cycles.denoising_store_passes", True),    # Denoising Normal / Albedo / Depth
)


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, path: str, value) -> str | None:
    """Set ``obj.<path>`` to ``value``; ``"path: old -> new"`` when it changed, else None."""
    head, _, last = path.rpartition(".")
    owner = _get(obj, head) if head else obj
    old = getattr(owner, last)
    if old == value:
        return None
    setattr(owner, last, value)
    return f"{path}: {old!r} -> {value!r}"


def apply_settings(scene) -> list[str]:
    """Set :data:`RENDER_SETTINGS` on ``scene``; returns what changed (``"path: old -> new"``)."""
    return [c for path, value in RENDER_SETTINGS if (c := _set(scene, path, value))]


def enable_passes(layer) -> list[str]:
    """Turn on :data:`PASSES` on view layer ``layer``; returns what changed (named by the layer)."""
    return [f"view layer {layer.name!r} {c}" for path, value in PASSES if (c := _set(layer, path, value))]


def _enum(struct, prop: str) -> set[str]:
    return {item.identifier for item in struct.bl_rna.properties[prop].enum_items}


def set_exr_output(scene) -> list[str]:
    """The output format the blender layout reads: multilayer float32 EXR, ZIP; returns what changed."""
    fmt = scene.render.image_settings
    changed = []
    if hasattr(fmt, "media_type"):                # Blender 5.0: multilayer is a media type
        changed.append(_set(fmt, "media_type", "MULTI_LAYER_IMAGE"))
        changed.append(_set(fmt, "file_format", "OPEN_EXR_MULTILAYER" if "OPEN_EXR_MULTILAYER" in
                            _enum(fmt, "file_format") else "OPEN_EXR"))
    else:
        changed.append(_set(fmt, "file_format", "OPEN_EXR_MULTILAYER"))
    changed += [_set(fmt, "color_depth", "32"), _set(fmt, "exr_codec", "ZIP")]
    return [f"output {c}" for c in changed if c]


def refusal(scene) -> str | None:
    """Why ``scene`` cannot be rendered into the layout as it is (None when it can): motion blur on
    (Cycles writes no Vector pass then), no camera, or not exactly one view layer rendered."""
    if scene.render.use_motion_blur:
        return ("motion blur is on (Render Properties > Motion Blur): Cycles writes no Vector pass with it, "
                "and the layout needs one; turn it off and save the file")
    if scene.camera is None:
        return "the scene has no camera (Scene Properties > Camera)"
    used = [layer.name for layer in scene.view_layers if layer.use]
    if len(used) != 1:
        return (f"{len(used)} view layers are rendered ({', '.join(used) or 'none'}); the layout reads one: "
                "leave one with 'Use for Rendering' on")
    return None


def render_frames(scene, out_dir: Path, frames: Iterable[int], spp: int, seed: int, label: str,
                  keep: bool = False, prefix: str = "blender") -> dict[int, float]:
    """Render ``frames`` of ``scene`` at ``spp`` samples and noise seed ``seed`` to
    ``out_dir/<frame:04d>.exr``; returns ``{frame: seconds}`` of the frames rendered. Each frame is
    written to a ``.partial`` name and renamed when complete, so a killed render leaves no truncated
    frame; ``keep``: frames already on disk are kept (not rendered again)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob("*.exr.partial"):   # left by a killed render
        stale.unlink()
    scene.cycles.samples = spp
    scene.cycles.seed = seed
    scene.render.use_file_extension = False
    frames = list(frames)
    seconds = {}
    for k, f in enumerate(frames, 1):
        path = out_dir / f"{f:04d}.exr"
        if keep and path.exists():
            continue
        partial = path.with_name(path.name + ".partial")
        scene.frame_set(f)
        scene.render.filepath = str(partial)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds[f] = time.perf_counter() - t0
        if not partial.exists():
            raise SystemExit(f"{prefix}: Blender did not write {partial}")
        os.replace(partial, path)
        print(f"  {label} frame {f} ({k}/{len(frames)}, {spp} spp): {seconds[f]:.1f} s", flush=True)
    return seconds
