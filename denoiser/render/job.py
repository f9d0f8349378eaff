"""Render one sequence into the native layout (docs/design.md §3.1), resumably.

``<out_dir>/frame_0000.exr ...`` (written atomically by :func:`denoiser.data.exr.write_frame`)
and ``<out_dir>/sequence.json`` (:func:`denoiser.data.sequence.write_sequence_json`, rewritten
after every frame). A frame whose file exists with every expected channel is skipped, so an
interrupted render continues where it stopped; its timings come from the previous
``sequence.json``. Settings that differ from an existing ``sequence.json`` are an error
unless ``overwrite`` is set (then stale frames are replaced).

A labeled sequence may take its references from a *donor*: the same sequence directory under
another root (``denoiser-render reference_from=<root>``) rendered with the same scene, sequence
seed, reference spp, size, precision and renderer (:func:`reference_donor`): its frames'
``reference`` buffers are copied instead of rendered again, which is most of a labeled frame's
time (``render_set=demo_compare`` re-renders data/demo's test split with per-sample radiance; its
references are data/demo's). The reference pass has a seed of its own, so a donor's reference
is the one this sequence would render; ``sequence.json`` names the donor (``reference_from``).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from denoiser.buffers import SEQUENCE_BUFFERS, native_channels, sample_channels
from denoiser.data.exr import list_channels, read_channels, write_frame
from denoiser.data.sequence import SEQUENCE_JSON, load_sequence_json, write_sequence_json
from denoiser.errors import ExrError, UserError
from denoiser.render import seeds as sd
from denoiser.render.motion import backward_motion
from denoiser.render.passes import AUX_MODES, NO_HIT_DEPTH, FrameRenderer
from denoiser.render.spec import SceneSpec
from denoiser.render.variant import active_variant

CONVENTIONS = {
    "color": "mean radiance of the frame's samples, linear HDR, box pixel filter",
    "albedo": "first-hit albedo at the pixel centre, clamped to [0, 1]; 0 = no hit",
    "normal": "first-hit shading normal at the pixel centre, camera space (x right, y up, z into the scene), "
              "unit length; 0 = no hit",
    "depth": f"planar depth along the camera's viewing axis at the pixel centre; no hit = {NO_HIT_DEPTH:g}",
    "motion": "backward motion in pixels: the surface seen at pixel centre p in frame t was at p + motion in "
              "frame t-1; x right, y down",
    "camera": "to_world: Mitsuba camera-to-world matrix (row-major; columns left, up, forward, position; "
              "the camera looks along local +z); fov: horizontal, degrees",
    "time": "frame t is the instant tau = t; with motion blur the shutter spans tau in [t - s/2, t + s/2]",
    "aux": "center: albedo and normal through the pixel centre (at tau = t; averaged over lens and shutter "
           "samples with dof or motion blur); samples: the means over the noisy colour's own samples, as "
           "Cycles' denoising passes",
    "seeds": "noisy/reference: Mitsuba sampler seed per frame; samples: seed of each single-sample pass, "
             "frame-major (frame * sample_count + k)",
}


@dataclass(frozen=True)
class RenderSettings:
    """What to render for one sequence."""

    frames: int
    spp: int
    ref_spp: int
    width: int
    height: int
    labeled: bool = True
    save_samples: bool = False
    half: bool = False
    aux: str = "center"      # center | samples (denoiser.render.passes, module docstring)

    def __post_init__(self):
        if self.aux not in AUX_MODES:
            raise UserError(f"render aux: unknown {self.aux!r}; use {' or '.join(AUX_MODES)}")

    def identity(self) -> dict:
        """The settings a resumed render must match (``aux`` only when not the default, so
        sequences rendered before the option existed resume)."""
        out = asdict(self)
        if self.aux == "center":
            del out["aux"]
        return out

    def buffers(self) -> list[str]:
        return [b for b in SEQUENCE_BUFFERS
                if (b != "samples" or self.save_samples) and (b != "reference" or self.labeled)]

    def channels(self) -> list[str]:
        names: list[str] = []
        sizes = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2, "reference": 3}
        for b in self.buffers():
            if b == "samples":
                names += [c for k in range(self.spp) for c in sample_channels(k)]
            else:
                names += list(native_channels(b, sizes[b]))
        return names


def frame_path(out_dir: Path, t: int) -> Path:
    return out_dir / f"frame_{t:04d}.exr"


def frame_complete(path: Path, channels: list[str]) -> bool:
    """True when ``path`` is a readable EXR holding every channel in ``channels``."""
    if not path.exists():
        return False
    try:
        present = set(list_channels(path))
    except ExrError:
        return False
    return all(c in present for c in channels)


#: the render settings a donor's references must share with the sequence that copies them
REFERENCE_KEYS = ("scene", "sequence_seed", "ref_spp", "width", "height", "half")


def reference_donor(donor_dir: Path, identity: Mapping[str, Any], renderer: Mapping[str, str]
                    ) -> tuple[Callable[[int], np.ndarray | None] | None, str]:
    """``(reference_of, why)``: ``reference_of(t)`` is the reference ``[H, W, 3]`` of frame ``t``
    of the donor sequence ``donor_dir`` (None where that frame is not finished there), when the
    donor was rendered with this sequence's :data:`REFERENCE_KEYS` ``identity`` values and the
    same ``renderer`` (Mitsuba version and variant); else ``(None, the reason)``."""
    path = donor_dir / SEQUENCE_JSON
    if not path.exists():
        return None, f"{path}: no such donor sequence"
    meta = load_sequence_json(path)
    theirs = dict(meta.extra.get("render_settings", {}))
    differ = [k for k in REFERENCE_KEYS if theirs.get(k) != identity.get(k)]
    if not theirs.get("labeled", False):
        differ.insert(0, "labeled")
    for key in ("version", "variant"):
        if str(meta.renderer.get(key, "")) != str(renderer.get(key, "")):
            differ.append(f"renderer {key}")
    if differ:
        return None, f"{path}: rendered with other {', '.join(differ)}"
    channels = list(native_channels("reference", 3))

    def reference_of(t: int) -> np.ndarray | None:
        frame = frame_path(donor_dir, t)
        if t >= meta.frames or not frame_complete(frame, channels):
            return None
        arrays = read_channels(frame, channels)
        return np.stack([arrays[c] for c in channels], axis=-1)

    return reference_of, ""


def render_frame(renderer: FrameRenderer, spec: SceneSpec, t: int, settings: RenderSettings,
                 seeds: Mapping[str, Any], reference: np.ndarray | None = None
                 ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """All buffers of frame ``t`` (``{name: [H,W,C]}``, samples ``[S,H,W,3]``) and seconds per buffer;
    ``reference``: the frame's reference from a donor (:func:`reference_donor`), not rendered again."""
    seconds: dict[str, float] = {}
    out: dict[str, np.ndarray] = {}
    tic = time.perf_counter()
    sample_aux = None
    if settings.save_samples and settings.aux == "samples":
        out["samples"], *sample_aux = renderer.samples_aux(t, seeds["samples"])
        out["color"] = out["samples"].mean(axis=0)
    elif settings.save_samples:
        out["samples"] = renderer.samples(t, seeds["samples"])
        out["color"] = out["samples"].mean(axis=0)
    elif settings.aux == "samples":
        out["color"], *sample_aux = renderer.radiance_aux(t, settings.spp, seeds["noisy"])
    else:
        out["color"] = renderer.radiance(t, settings.spp, seeds["noisy"])
    seconds["color"] = time.perf_counter() - tic
    tic = time.perf_counter()
    # depth, position and objects (motion) stay pixel-centre values
    aux = renderer.aux(t, blur=sample_aux is None)
    out.update(albedo=aux.albedo, normal=aux.normal, depth=aux.depth)
    if sample_aux is not None:
        out["albedo"], out["normal"] = sample_aux
    seconds["aux"] = time.perf_counter() - tic
    tic = time.perf_counter()
    out["motion"] = backward_motion(spec, aux, t, settings.width, settings.height)
    seconds["motion"] = time.perf_counter() - tic
    if settings.labeled and reference is not None:
        out["reference"] = reference
    elif settings.labeled:
        tic = time.perf_counter()
        out["reference"] = renderer.reference(t, settings.ref_spp, seeds["reference"])
        seconds["reference"] = time.perf_counter() - tic
    return out, seconds


def _frame_seeds(seq_seed: int, t: int, settings: RenderSettings) -> dict[str, Any]:
    s: dict[str, Any] = {"noisy": sd.pass_seed(seq_seed, t, sd.NOISY)}
    if settings.labeled:
        s["reference"] = sd.pass_seed(seq_seed, t, sd.REFERENCE)
    if settings.save_samples:
        s["samples"] = [sd.pass_seed(seq_seed, t, sd.FIRST_SAMPLE + k) for k in range(settings.spp)]
    return s


def _previous(out_dir: Path, settings: RenderSettings, identity: dict, overwrite: bool) -> list[dict] | None:
    """Per-frame timings of a previous run with the same settings (None if there is none)."""
    path = out_dir / SEQUENCE_JSON
    if not path.exists():
        return None
    meta = load_sequence_json(path)
    previous = dict(meta.extra.get("render_settings", {}))
    if previous != identity:
        if overwrite:
            return None
        changed = sorted(k for k in set(previous) | set(identity) if previous.get(k) != identity.get(k))
        raise UserError(f"{path}: rendered with different settings ({', '.join(changed)}); "
                        f"pass overwrite=true to re-render or choose another root")
    return list(meta.extra.get("frame_seconds", []))


def render_sequence(mi, spec: SceneSpec, out_dir: str | Path, settings: RenderSettings, seq_seed: int,
                    overwrite: bool = False, on_frame: Callable[[int, bool], None] | None = None,
                    reference_from: str | Path | None = None) -> dict:
    """Render (or resume) one sequence; returns the written ``sequence.json`` content.

    ``on_frame(t, skipped)`` is called after each frame (progress bars). ``reference_from``: the
    donor sequence directory whose references are copied (:func:`reference_donor`; a donor that
    does not match is said on stderr, and the references are rendered).
    """
    out_dir = Path(out_dir)
    identity = {**settings.identity(), "scene": spec.name, "sequence_seed": seq_seed}
    previous = _previous(out_dir, settings, identity, overwrite) or []
    renderer = FrameRenderer(mi, spec, settings.width, settings.height)
    donor = None
    if reference_from is not None and settings.labeled:
        donor, why = reference_donor(Path(reference_from), identity,
                                     {"version": mi.__version__, "variant": active_variant() or mi.variant()})
        if donor is None:
            print(f"note: {out_dir}: references rendered, not copied ({why})", file=sys.stderr)
    channels = settings.channels()
    frame_seconds: list[dict[str, float]] = []
    seeds = [_frame_seeds(seq_seed, t, settings) for t in range(settings.frames)]
    meta = None
    for t in range(settings.frames):
        path = frame_path(out_dir, t)
        done = not overwrite and t < len(previous) and frame_complete(path, channels)
        if done:
            frame_seconds.append(previous[t])
        else:
            reference = donor(t) if donor is not None else None
            buffers, seconds = render_frame(renderer, spec, t, settings, seeds[t], reference)
            write_frame(path, buffers, half=settings.half, attributes={"frameIndex": t})
            frame_seconds.append({k: round(v, 4) for k, v in seconds.items()})
        meta = _metadata(mi, spec, settings, seq_seed, seeds, frame_seconds, identity)
        if donor is not None:
            meta["reference_from"] = str(reference_from)
        write_sequence_json(out_dir / SEQUENCE_JSON, meta)
        if on_frame is not None:
            on_frame(t, done)
    return meta


def _metadata(mi, spec: SceneSpec, settings: RenderSettings, seq_seed: int, seeds: list[dict],
              frame_seconds: list[dict], identity: dict) -> dict:
    totals: dict[str, float] = {}
    for fs in frame_seconds:
        for k, v in fs.items():
            totals[k] = round(totals.get(k, 0.0) + v, 4)
    cameras = [{"to_world": spec.camera.to_world(float(t)).tolist(), "fov": spec.camera.fov, "fov_axis": "x"}
               for t in range(settings.frames)]
    seed_lists: dict[str, Any] = {"sequence": seq_seed, "noisy": [s["noisy"] for s in seeds]}
    if settings.labeled:
        seed_lists["reference"] = [s["reference"] for s in seeds]
    if settings.save_samples:
        seed_lists["samples"] = [x for s in seeds for x in s["samples"]]
    return {
        "width": settings.width, "height": settings.height, "frames": settings.frames, "spp": settings.spp,
        "ref_spp": settings.ref_spp if settings.labeled else 0,
        "buffers": settings.buffers(), "sample_count": settings.spp if settings.save_samples else 0,
        "cameras": cameras, "cuts": [],
        "scene": {"name": spec.name, "effects": spec.effects.names(),
                  "effect_params": {k: dict(v) for k, v in spec.effects.declared.items()},
                  "test_only": spec.test_only, "params": spec.params},
        "renderer": {"name": "mitsuba", "version": mi.__version__, "variant": active_variant() or mi.variant(),
                     "integrator": "path", "max_depth": _depth(spec)},
        "seeds": seed_lists,
        "render_seconds": totals,
        "frame_seconds": frame_seconds,
        "frames_done": len(frame_seconds),
        "render_settings": identity,
        "conventions": _conventions(settings),
    }


def _conventions(settings: RenderSettings) -> dict[str, str]:
    """:data:`CONVENTIONS`, with albedo and normal as ``settings.aux`` renders them."""
    conv = dict(CONVENTIONS)
    if settings.aux == "samples":
        conv["albedo"] = "mean first-hit albedo of the noisy colour's own samples, clamped to [0, 1]; misses count 0"
        conv["normal"] = ("mean first-hit shading normal of the noisy colour's own samples, camera space (x right, "
                          "y up, z into the scene), renormalised; 0 = no sample hit")
    return conv


def _depth(spec: SceneSpec) -> int:
    from denoiser.render.effects import path_depth

    return path_depth(spec.effects)
