"""Cost of each simulated effect: ``python -m denoiser.commands.tools.effect_cost``.

::

    python -m denoiser.commands.tools.effect_cost
    python -m denoiser.commands.tools.effect_cost width=64 height=64 effects=[area_light,indirect,glossy]
    python -m denoiser.commands.tools.effect_cost effects=[area_light] scenes=all

A Hydra app over ``conf/effect_cost.yaml``. One Cornell-room scene; effects are switched on one at a time, cumulatively, in the order of
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
higher (independent errors add), reported as ``ref PSNR``. ``scenes`` (a list, or ``all``) adds
the reference noise of repository scenes (``conf/scene/``).
"""

from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from denoiser.measure import Clock, fastest
from denoiser.render.motion import backward_motion
from denoiser.render.passes import FrameRenderer
from denoiser.render.spec import build_scene
from denoiser.tables import markdown_table

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


def measure(mi, effects: list[str], width: int, height: int, spp: int, ref_spp: int) -> dict:
    """Timings and reference noise of the bench scene with ``effects``."""
    from denoiser.render.effects import path_depth

    spec = build_scene(bench_scene(effects), seed=0)
    fr = FrameRenderer(mi, spec, width, height)
    with Clock() as warm:
        fr.radiance(0, spp, 1)
        fr.aux(0)
        fr.reference(0, ref_spp, 2)
    noisy_runs, aux_runs = [], []
    for t in (1, 2, 3):  # cheap passes: the fastest of 3 frames (a shared CPU adds spikes)
        with Clock() as t_noisy:
            noisy = fr.radiance(t, spp, 3 + t)
        with Clock() as t_aux:
            aux = fr.aux(t)
            backward_motion(spec, aux, t, width, height)
        noisy_runs.append(t_noisy)
        aux_runs.append(t_aux)
    t_noisy, t_aux = fastest(noisy_runs), fastest(aux_runs)
    with Clock() as t_ref:
        ref_a = fr.reference(3, ref_spp, 10)
    ref_b = fr.reference(3, ref_spp, 11)
    return {"effect": f"+{effects[-1]}", "depth": path_depth(spec.effects), "warm": warm.wall,
            "noisy": t_noisy.wall, "noisy_cpu": t_noisy.cpu, "aux": t_aux.wall, "ref": t_ref.wall,
            "ref_cpu": t_ref.cpu, "ref_psnr": psnr(ref_a, ref_b) + 10 * np.log10(2),
            "noisy_psnr": psnr(noisy, ref_a)}


#: columns of the effect table: key -> (title, format)
COLUMNS = {"effect": ("effect added", None), "depth": ("max_depth", None), "noisy": ("noisy s ({spp} spp)", ".3f"),
           "noisy_cpu": ("noisy CPU s", ".3f"), "aux": ("aux+motion s", ".3f"),
           "ref": ("reference s ({ref_spp} spp)", ".2f"), "ref_cpu": ("reference CPU s", ".2f"),
           "ref_x": ("ref CPU x base", ".2f"), "ref_psnr": ("ref PSNR dB", ".1f"),
           "noisy_psnr": ("noisy PSNR dB", ".1f"), "warm": ("frame 0 s", ".2f")}


def table(rows: list[dict], cfg) -> str:
    """The Markdown table of :func:`measure`'s rows (``cfg``: ``spp``, ``ref_spp``)."""
    base = rows[0]["ref_cpu"]
    shown = [{**r, "ref_x": r["ref_cpu"] / base} for r in rows]
    headers = {k: title.format(spp=cfg.spp, ref_spp=cfg.ref_spp) for k, (title, _) in COLUMNS.items()}
    return markdown_table(shown, list(COLUMNS), {k: f for k, (_, f) in COLUMNS.items() if f}, headers)


def scene_noise(mi, names: list[str], width: int, height: int, spp: int, ref_spp: int) -> str:
    """Table: per repository scene, reference noise (two seeds) and the noisy input's PSNR."""
    from denoiser.render.catalog import load_scene_config

    rows = []
    for name in names:
        fr = FrameRenderer(mi, build_scene(load_scene_config(name), seed=0), width, height)
        noisy = fr.radiance(1, spp, 1)
        with Clock() as c:
            ref_a = fr.reference(1, ref_spp, 2)
        ref_b = fr.reference(1, ref_spp, 3)
        rows.append({"scene": name, "ref": c.wall, "ref_cpu": c.cpu, "ref_psnr": psnr(ref_a, ref_b) + 10 * np.log10(2),
                     "noisy_psnr": psnr(noisy, ref_a)})
    return markdown_table(rows, ["scene", "ref", "ref_cpu", "ref_psnr", "noisy_psnr"],
                          {"ref": ".2f", "ref_cpu": ".2f", "ref_psnr": ".1f", "noisy_psnr": ".1f"},
                          {"ref": "reference s", "ref_cpu": "reference CPU s", "ref_psnr": f"ref PSNR dB ({ref_spp} spp)",
                           "noisy_psnr": f"noisy PSNR dB ({spp} spp)"})


def run(cfg: DictConfig) -> list[dict]:
    """The ``effect_cost`` task: print the effect table (and the scenes' noise); returns its rows."""
    from tqdm import tqdm

    from denoiser.render.variant import activate, active_variant

    mi = activate(cfg.variant)
    ladder = list(cfg.effects) if cfg.get("effects") else LADDER
    w, h = int(cfg.width), int(cfg.height)
    rows = [measure(mi, ladder[: i + 1], w, h, int(cfg.spp), int(cfg.ref_spp))
            for i in tqdm(range(len(ladder)), desc="bench", unit="step")]
    print(f"Mitsuba {mi.__version__} variant {active_variant()}, {w}x{h}, effects added "
          f"cumulatively (frame 0 includes JIT compilation)")
    print(table(rows, cfg), end="")
    if cfg.get("scenes"):
        from denoiser.render.catalog import available_scenes

        names = available_scenes() if cfg.scenes == "all" else [str(n) for n in cfg.scenes]
        print(f"\nReference noise of the repository scenes (seed 0, frame 1, {w}x{h}):")
        print(scene_noise(mi, names, w, h, int(cfg.spp), int(cfg.ref_spp)), end="")
    return rows


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "effect_cost")()


if __name__ == "__main__":
    main()
