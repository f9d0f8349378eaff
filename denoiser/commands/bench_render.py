"""Cost of each simulated effect: ``python -m denoiser.commands.bench_render``.

One Cornell-room scene; effects are switched on one at a time, cumulatively, in the order of
``LADDER``. For every step frame 0 is rendered first and reported as ``frame 0``; then
seconds per frame of the noisy pass (``spp``) and of the auxiliary buffers + motion vectors
(each the fastest of frames 1-3, scene loading included), and of the reference pass
(``ref_spp``, frame 3); ``frame 0``
is the whole first frame including kernel compilation (Dr.Jit caches kernels, so only a
process's first frame of a scene structure pays it). Seconds are wall
time; CPU seconds (all threads) are given too, since wall time on a shared machine depends on
the load (on an idle machine, wall ~= CPU / cores for the parallel passes). The reference's
own noise is measured too: two references with different seeds give ``PSNR(ref_a, ref_b)``
on tonemapped values ``x / (1 + x)``; each one's PSNR to the converged image is about 3 dB
higher (independent errors add), reported as ``ref PSNR``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from denoiser.render.motion import backward_motion
from denoiser.render.passes import FrameRenderer
from denoiser.render.spec import build_scene

LADDER = ["area_light", "indirect", "textures", "glossy", "transmission", "env_light", "camera_motion",
          "object_motion", "dof", "motion_blur"]


def bench_scene(effects: list[str]) -> dict:
    """The benchmark scene with exactly ``effects`` declared (and used)."""
    on = set(effects)
    tex = {"texture": "checker", "tiles": 8, "color0": [0.8, 0.8, 0.8], "color1": [0.2, 0.2, 0.25]}
    floor = {"type": "diffuse", "color": tex if "textures" in on else [0.7, 0.7, 0.7]}
    ball = ({"type": "conductor", "metal": "Au", "roughness": 0.15} if "glossy" in on
            else {"type": "diffuse", "color": [0.7, 0.5, 0.2]})
    camera = {"origin": [0, 1, 3.6], "target": [0, 0.8, 0], "fov": 40}
    if "camera_motion" in on:
        camera["orbit"] = 2.0
    if "dof" in on:
        camera.update(aperture=0.08, focus_distance=3.2)
    if "motion_blur" in on:
        camera["shutter"] = 0.5
    objects = [
        {"name": "room", "shape": "room", "params": {"floor": floor}},
        {"name": "ball", "shape": "sphere", "position": [-0.4, 0.35, -0.2], "scale": 0.35, "material": ball,
         **({"velocity": [0.05, 0, 0], "spin": {"degrees": 5}} if "object_motion" in on else {})},
        {"name": "box", "shape": "cube", "position": [0.45, 0.3, -0.3], "rotation": [0, 25, 0], "scale": 0.3},
    ]
    if "transmission" in on:
        objects.append({"name": "glass", "shape": "sphere", "position": [0.2, 0.25, 0.45], "scale": 0.25,
                        "material": {"type": "glass"}})
    lights = [{"type": "area", "position": [0, 1.99, 0], "target": [0, 0, 0], "size": [0.5, 0.5],
               "radiance": [15, 13, 10]}]
    if "env_light" in on:
        objects[0]["params"]["ceiling"] = None  # keep the room closed; the sky shows through the open front
        objects[0]["params"].pop("ceiling")
        lights.append({"type": "sky", "strength": 0.5})
    return {"name": "bench", "effects": list(effects), "camera": camera, "objects": objects, "lights": lights}


def _tonemap(x: np.ndarray) -> np.ndarray:
    x = np.maximum(x, 0)
    return x / (1 + x)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((_tonemap(a) - _tonemap(b)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


class _Clock:
    """Wall and CPU seconds (all threads of this process) of a block."""

    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def measure(mi, effects: list[str], width: int, height: int, spp: int, ref_spp: int) -> dict:
    """Timings and reference noise of the bench scene with ``effects``."""
    from denoiser.render.effects import path_depth

    spec = build_scene(bench_scene(effects), seed=0)
    fr = FrameRenderer(mi, spec, width, height)
    with _Clock() as warm:
        fr.radiance(0, spp, 1)
        fr.aux(0)
        fr.reference(0, ref_spp, 2)
    noisy_runs, aux_runs = [], []
    for t in (1, 2, 3):  # cheap passes: the fastest of 3 frames (a shared CPU adds spikes)
        with _Clock() as t_noisy:
            noisy = fr.radiance(t, spp, 3 + t)
        with _Clock() as t_aux:
            aux = fr.aux(t)
            backward_motion(spec, aux, t, width, height)
        noisy_runs.append(t_noisy)
        aux_runs.append(t_aux)
    t_noisy = min(noisy_runs, key=lambda c: c.wall)
    t_aux = min(aux_runs, key=lambda c: c.wall)
    with _Clock() as t_ref:
        ref_a = fr.reference(3, ref_spp, 10)
    ref_b = fr.reference(3, ref_spp, 11)
    return {"effect": f"+{effects[-1]}", "depth": path_depth(spec.effects), "warm": warm.wall,
            "noisy": t_noisy.wall, "noisy_cpu": t_noisy.cpu, "aux": t_aux.wall, "ref": t_ref.wall,
            "ref_cpu": t_ref.cpu, "ref_psnr": psnr(ref_a, ref_b) + 10 * np.log10(2),
            "noisy_psnr": psnr(noisy, ref_a)}


def table(rows: list[dict], args) -> str:
    head = (f"| effect added | max_depth | noisy s ({args.spp} spp) | noisy CPU s | aux+motion s | "
            f"reference s ({args.ref_spp} spp) | reference CPU s | ref CPU x base | ref PSNR dB | noisy PSNR dB "
            f"| frame 0 s |")
    lines = [head, "|" + "---|" * 11]
    base = rows[0]["ref_cpu"]
    for r in rows:
        lines.append(f"| {r['effect']} | {r['depth']} | {r['noisy']:.3f} | {r['noisy_cpu']:.3f} | {r['aux']:.3f} | "
                     f"{r['ref']:.2f} | {r['ref_cpu']:.2f} | {r['ref_cpu'] / base:.2f} | {r['ref_psnr']:.1f} | "
                     f"{r['noisy_psnr']:.1f} | {r['warm']:.2f} |")
    return "\n".join(lines)


def scene_noise(mi, names: list[str], width: int, height: int, spp: int, ref_spp: int) -> str:
    """Table: per repository scene, reference noise (two seeds) and the noisy input's PSNR."""
    from denoiser.render.catalog import load_scene_config

    lines = [f"| scene | reference s | reference CPU s | ref PSNR dB ({ref_spp} spp) | noisy PSNR dB ({spp} spp) |",
             "|---|---|---|---|---|"]
    for name in names:
        fr = FrameRenderer(mi, build_scene(load_scene_config(name), seed=0), width, height)
        noisy = fr.radiance(1, spp, 1)
        with _Clock() as c:
            ref_a = fr.reference(1, ref_spp, 2)
        ref_b = fr.reference(1, ref_spp, 3)
        lines.append(f"| {name} | {c.wall:.2f} | {c.cpu:.2f} | {psnr(ref_a, ref_b) + 10 * np.log10(2):.1f} | "
                     f"{psnr(noisy, ref_a):.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=128)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--variant", default="auto", help="auto | llvm_ad_rgb | scalar_rgb")
    ap.add_argument("--effects", default=",".join(LADDER), help="comma-separated ladder (first must be a light)")
    ap.add_argument("--scenes", default="", help="also measure reference noise of these repository scenes "
                    "(comma-separated, or 'all')")
    args = ap.parse_args(argv)
    from tqdm import tqdm

    from denoiser.render.variant import activate

    mi = activate(args.variant)
    ladder = [e for e in args.effects.split(",") if e]
    rows = [measure(mi, ladder[: i + 1], args.width, args.height, args.spp, args.ref_spp)
            for i in tqdm(range(len(ladder)), desc="bench", unit="step")]
    from denoiser.render.variant import active_variant

    print(f"Mitsuba {mi.__version__} variant {active_variant()}, {args.width}x{args.height}, effects added "
          f"cumulatively (frame 0 includes JIT compilation)")
    print(table(rows, args))
    if args.scenes:
        from denoiser.render.catalog import available_scenes

        names = available_scenes() if args.scenes == "all" else args.scenes.split(",")
        print(f"\nReference noise of the repository scenes (seed 0, frame 1, {args.width}x{args.height}):")
        print(scene_noise(mi, names, args.width, args.height, args.spp, args.ref_spp))


if __name__ == "__main__":
    main()
