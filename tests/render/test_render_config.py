"""Scene configs, effect checks and effect-driven scene building (no rendering beyond tiny loads)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from denoiser.commands.tools.effect_cost import LADDER, bench_scene
from denoiser.conf import CONF_DIR
from denoiser.errors import ConfigError, UserError
from denoiser.render import build
from denoiser.render.catalog import available_scenes, load_scene_config
from denoiser.render.effects import parse_effects, path_depth
from denoiser.render.spec import build_scene


@pytest.fixture(scope="module")
def mi():
    from denoiser.render.variant import activate

    return activate("auto", quiet=True)


def _scene(**changes) -> dict:
    cfg = bench_scene(["area_light"])
    cfg.update(changes)
    return cfg


def _load(mi, cfg, seed=0):
    spec = build_scene(cfg, seed)
    return spec, mi.load_dict(build.scene_dict(mi, spec, 0.0, 8, 8))


def test_unknown_effect_is_one_line_config_error():
    with pytest.raises(ConfigError, match=r"scene 'bench': unknown effect 'caustics'") as exc:
        build_scene(_scene(effects=["area_light", "caustics"]), 0)
    assert "\n" not in str(exc.value)


def test_unknown_material_and_shape_are_errors(mi):
    cfg = _scene()
    cfg["objects"][1]["material"] = {"type": "velvet"}
    with pytest.raises(ConfigError, match=r"scene 'bench'.*unknown material type 'velvet'"):
        _load(mi, cfg)
    cfg = _scene()
    cfg["objects"][1]["shape"] = "teapot"
    with pytest.raises(ConfigError, match=r"unknown shape 'teapot'"):
        _load(mi, cfg)


@pytest.mark.parametrize("mutate, missing", [
    (lambda c: c["objects"][1].update(material={"type": "glass"}), "transmission"),
    (lambda c: c["objects"][1].update(material={"type": "conductor"}), "glossy"),
    (lambda c: c["objects"][1].update(velocity=[0.1, 0, 0]), "object_motion"),
    (lambda c: c["objects"][1].update(spin={"degrees": 3}), "object_motion"),
    (lambda c: c["camera"].update(orbit=1.0), "camera_motion"),
    (lambda c: c["camera"].update(aperture=0.1), "dof"),
    (lambda c: c["camera"].update(shutter=0.5), "motion_blur"),
    (lambda c: c["objects"][0]["params"].update(floor={"type": "diffuse", "color": {"texture": "checker"}}),
     "textures"),
    (lambda c: c["lights"].append({"type": "sky"}), "env_light"),
])
def test_undeclared_effect_is_an_error_naming_scene_and_effect(mi, mutate, missing):
    cfg = copy.deepcopy(_scene())
    mutate(cfg)
    with pytest.raises(ConfigError) as exc:
        _load(mi, cfg)
    msg = str(exc.value)
    assert "scene 'bench'" in msg and f"effect '{missing}'" in msg and "\n" not in msg


def test_area_light_needs_its_effect(mi):
    with pytest.raises(ConfigError, match="effect 'area_light'"):
        _load(mi, _scene(effects=["env_light"]))


def test_integrator_depth_follows_declared_transport():
    def depth(effects):
        return build.integrator(build_scene(bench_scene(effects), 0))["max_depth"]

    assert depth(["area_light"]) == 2  # direct light only
    assert depth(["area_light", "indirect"]) == 5
    assert depth(["area_light", "indirect", "textures"]) == 5  # textures cost no depth
    assert depth(["area_light", "indirect", "textures", "glossy"]) == 7
    assert depth(["area_light", "indirect", "textures", "glossy", "transmission"]) == 11
    assert path_depth(parse_effects("x", ["area_light", {"indirect": 1}])) == 3


def test_pinhole_without_dof_thin_lens_with_dof(mi):
    _, scene = _load(mi, bench_scene(["area_light"]))
    main = next(s for s in scene.sensors() if s.id() == build.MAIN_SENSOR)
    assert main.class_name() == "PerspectiveCamera"
    _, scene = _load(mi, bench_scene(["area_light", "dof"]))
    main = next(s for s in scene.sensors() if s.id() == build.MAIN_SENSOR)
    aux = next(s for s in scene.sensors() if s.id() == build.AUX_SENSOR)
    assert main.class_name() == "ThinLensCamera"
    assert aux.class_name() == "PerspectiveCamera"  # auxiliary buffers stay sharp pixel-centre samples


def test_every_ladder_step_builds_and_loads(mi):
    """Each step of the effect-cost ladder (denoiser/commands/tools/effect_cost.py) builds a spec that
    declares exactly the effects up to it, and the scene loads in Mitsuba with its shapes."""
    for i in range(len(LADDER)):
        spec, scene = _load(mi, bench_scene(LADDER[: i + 1]))
        assert set(spec.effects.names()) == set(LADDER[: i + 1]), LADDER[i]
        assert len(scene.shapes()) >= 2, LADDER[i]


def test_randomization_is_seeded():
    cfg = load_scene_config("cornell")
    a, b, c = build_scene(cfg, 1), build_scene(cfg, 1), build_scene(cfg, 2)
    assert a.params == b.params
    assert a.params != c.params
    assert np.allclose(a.camera.to_world(3), b.camera.to_world(3))


def test_repository_scenes_build_for_several_seeds(mi):
    names = available_scenes()
    assert len(names) >= 6
    for name in names:
        cfg = load_scene_config(name)
        for seed in (0, 1):
            spec, scene = _load(mi, cfg, seed)
            assert len(scene.shapes()) >= 2
            assert set(spec.effects.names()) <= set(LADDER)
    test_only = [n for n in names if load_scene_config(n).get("test_only")]
    assert len(test_only) >= 2


def _compose(overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="render", overrides=overrides)


def test_demo_preset_keeps_test_only_scenes_out_of_training():
    from denoiser.commands.render import plan

    cfg = _compose(["render_set=demo"])
    assert cfg.name == "demo" and cfg.root.endswith("data/demo")
    jobs = plan(cfg)
    splits = {j.split for j in jobs}
    assert splits == {"train", "val", "test", "unlabeled"}
    for j in jobs:
        assert bool(j.scene_config.get("test_only")) == (j.split == "test"), j.directory
        assert (j.settings.width, j.settings.height) == (128, 128)
        assert j.settings.labeled == (j.split != "unlabeled")
    assert len({j.directory for j in jobs}) == len(jobs)


def test_demo_motion_preset_is_the_demo_settings_with_the_motion_families():
    """render_set=demo_motion (data/demo_motion, joined to data/demo by the demo experiments'
    data.extra_roots): demo's size, spp, aux, references and seed; fast_objects and vivid_objects
    for train and unlabeled, fast_spin for val, 6 frames each, no test split; and a sequence's seed
    does not depend on the preset's name: the same sequences as a by-hand render into another root."""
    from denoiser.commands.render import plan
    from denoiser.render.seeds import sequence_seed

    demo, motion = _compose(["render_set=demo"]), _compose(["render_set=demo_motion"])
    assert motion.name == "demo_motion" and motion.root.endswith("data/demo_motion")
    keys = ("width", "height", "spp", "ref_spp", "aux", "seed")
    assert {k: motion[k] for k in keys} == {k: demo[k] for k in keys}
    jobs = plan(motion)
    expected = sorted([*(("train", f"{scene}_{i:03d}", 6) for scene in ("fast_objects", "vivid_objects") for i in range(6)),
                       *(("val", f"fast_spin_{i:03d}", 6) for i in range(3)),
                       *(("unlabeled", f"fast_objects_{i:03d}", 6) for i in range(3)),
                       *(("unlabeled", f"vivid_objects_{i:03d}", 6) for i in range(2))])
    assert sorted((j.split, Path(j.directory).name, j.settings.frames) for j in jobs) == expected
    by_hand = plan(_compose(["scene=fast_objects", "split=train", "sequences=6", "frames=6", "spp=4",
                             "ref_spp=256", "aux=samples", "name=demo_fast"]))

    def seeds(cfg, js):
        return [(j.directory, sequence_seed(cfg.seed, j.scene_name, j.split, j.index), j.settings) for j in js]

    assert seeds(demo, by_hand) == seeds(motion, [j for j in jobs if j.split == "train" and j.scene_name == "fast_objects"])


def test_test_only_scene_refused_for_training():
    from denoiser.commands.render import plan

    with pytest.raises(UserError, match="test_only"):
        plan(_compose(["scene=gallery", "split=train"]))
    assert plan(_compose(["scene=gallery", "split=test"]))
    assert plan(_compose(["scene=gallery", "split=train", "allow_test_only=true"]))


def test_unknown_light_keys_and_shape_params_are_errors(mi):
    cfg = _scene()
    cfg["lights"][0]["radiunce"] = [1, 1, 1]
    with pytest.raises(ConfigError, match=r"light 'light0': unknown key\(s\) radiunce"):
        _load(mi, cfg)
    cfg = _scene()
    cfg["objects"][1]["params"] = {"radius": 2}
    with pytest.raises(ConfigError, match="object 'ball': a sphere takes no params"):
        _load(mi, cfg)
    cfg = _scene()
    cfg["camera"]["fob"] = 30
    with pytest.raises(ConfigError, match=r"camera: unknown key\(s\) fob"):
        _load(mi, cfg)


@pytest.mark.slow
def test_bench_prints_one_row_per_effect(mi, capsys):
    from hydra import compose, initialize_config_dir

    from denoiser.commands.tools.effect_cost import run
    from denoiser.conf import CONF_DIR

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("effect_cost", overrides=["width=16", "height=16", "spp=1", "ref_spp=4",
                                                 "effects=[area_light,indirect,glossy]"])
    run(cfg)
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| +")]
    assert [r.split("|")[1].strip() for r in rows] == ["+area_light", "+indirect", "+glossy"]
    assert [int(r.split("|")[2]) for r in rows] == [2, 5, 7]


def test_preset_refuses_sequences_it_does_not_describe(tmp_path, monkeypatch):
    """After a preset changed (a retired test seed, a removed scene), the old sequence directories
    would still be read by training and evaluation: the render names one and stops before
    rendering anything; sequences of other splits and non-sequence files are left alone."""
    from denoiser.commands import render

    def no_render(*args, **kwargs):
        raise AssertionError("rendered although a stale sequence lies in the split")

    monkeypatch.setattr(render, "render_sequence", no_render)
    monkeypatch.setattr("denoiser.render.variant.activate", lambda variant: pytest.fail("activated the renderer"))
    cfg = _compose(["render_set=demo", f"root={tmp_path}"])
    stale = tmp_path / "test" / "gallery_006"
    stale.mkdir(parents=True)
    (stale / "sequence.json").write_text("{}")
    (tmp_path / "test" / "notes.txt").write_text("not a sequence")
    with pytest.raises(UserError, match=r"test/gallery_006: a sequence that render_set=demo does not describe"):
        render.run(cfg)


def test_shared_definitions_are_dropped_before_the_draw():
    """``x-...`` keys only hold YAML anchors; any other unknown key is still an error."""
    cfg = _scene(**{"x-shared": {"choice": [1, 2]}})
    assert build_scene(cfg, 0).params == build_scene(_scene(), 0).params
    with pytest.raises(ConfigError, match="unknown key"):
        build_scene(_scene(shared={"a": 1}), 0)


def test_medley_draws_a_new_composition_per_sequence(mi):
    """The random-composition family: each seed draws its set, objects, lights and camera."""
    cfg = load_scene_config("medley")
    specs = [build_scene(cfg, seed) for seed in range(40)]
    sets = {s.objects[0].shape for s in specs}
    lights = {tuple(sorted(light.type for light in s.lights)) for s in specs}
    counts = {len(s.objects) - 1 for s in specs}
    materials = {(o.material or {}).get("type") for s in specs for o in s.objects[1:]}
    assert sets == {"room", "rectangle"}
    assert lights == {("area",), ("sky",), ("area", "sky")}
    assert counts == {2, 3, 4, 5}
    assert materials == {"diffuse", "plastic", "conductor", "glass", "rough_glass"}
    assert {s.camera.shutter > 0 for s in specs} == {True, False}
    assert {bool(s.moving_objects) for s in specs} == {True, False}
    for seed in range(8):  # every draw builds and loads with only the effects the family declares
        _, scene = _load(mi, cfg, seed)
        assert len(scene.shapes()) >= 3
