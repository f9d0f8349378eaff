"""Every option of every config group of train.py composes (Hydra compose API) and means what it says."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from denoiser.conf import CONF_DIR

GROUPS = ["data", "layout", "net", "kernel", "model", "lever", "ablation", "trainer", "logger", "callbacks",
          "experiment", "debug"]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


def compose_train(*overrides: str, hydra_cfg: bool = False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("train", overrides=["output_dir=/tmp/denoiser-test-configs", *overrides],
                       return_hydra_config=hydra_cfg)


def resolved(cfg) -> dict:
    cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)


def test_every_group_has_options():
    for group in GROUPS + ["hydra/launcher"]:
        assert options(group), group


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in options(g)])
def test_every_option_composes_and_resolves(group, option):
    cfg = compose_train(f"{group}={option}")
    plain = resolved(cfg)
    assert plain["model"]["_target_"].startswith("denoiser.lit.")
    assert plain["net"]["_target_"] == "denoiser.nn.denoiser.Denoiser"
    # the kernel group drives the pyramid filters; WS has its own kernel set (docs/baselines.md)
    own_kernels = plain["net"]["filter"]["_target_"].endswith("WeightSharingFilter")
    assert plain["net"]["filter"]["kernel_sizes"] == plain["kernel"]["sizes"] or group == "ablation" or own_kernels


@pytest.mark.parametrize("launcher", options("hydra/launcher"))
def test_launcher_presets_compose(launcher):
    cfg = compose_train(f"hydra/launcher={launcher}", hydra_cfg=True)
    assert cfg.hydra.launcher._target_.startswith("hydra_plugins.")
    assert cfg.hydra.launcher.get("n_jobs", 2) == 2  # our preset, not the plugin's default (-1)


@pytest.mark.parametrize("model,encoder,kernels", [("teacher", [128, 256, 512], [5, 7, 9]),
                                                   ("student", [32, 64, 128], [5, 5, 5]),
                                                   ("distill", [32, 64, 128], [5, 5, 5])])
def test_model_selects_its_network_unless_overridden(model, encoder, kernels):
    cfg = compose_train(f"model={model}")
    assert list(cfg.net.unet.encoder) == encoder and list(cfg.net.filter.kernel_sizes) == kernels
    cfg = compose_train(f"model={model}", "net=tiny", "kernel=k3")
    assert list(cfg.net.unet.encoder) == [8, 12, 16] and list(cfg.net.filter.kernel_sizes) == [3, 3, 3]


def test_paper_experiments_hold_the_design_widths():
    teacher = compose_train("experiment=paper_teacher")
    assert teacher.net.embed.hidden == 256 and list(teacher.net.unet.encoder) == [128, 256, 512]
    assert teacher.net.unet.bottleneck == 512 and list(teacher.net.unet.decoder) == [512, 256]
    assert list(teacher.net.filter.kernel_sizes) == [5, 7, 9] and teacher.trainer.accelerator == "gpu"
    for exp in ("paper_student", "paper_distill"):
        student = compose_train(f"experiment={exp}")
        assert student.net.embed.hidden == 32 and list(student.net.unet.encoder) == [32, 64, 128]
        assert student.net.unet.bottleneck == 128 and list(student.net.unet.decoder) == [64, 32]
        assert list(student.net.filter.kernel_sizes) == [5, 5, 5]
    assert compose_train("experiment=paper_distill").model._target_.endswith("DistillationModule")


def test_demo_experiments():
    teacher = compose_train("experiment=demo_teacher")
    assert teacher.model._target_.endswith("SupervisedModule") and teacher.net.embed.hidden == 64
    assert list(teacher.net.filter.kernel_sizes) == [5, 7, 9] and teacher.data.crop == 64
    distill = compose_train("experiment=demo_distill", "model.teacher_ckpt=x.ckpt")
    assert distill.model._target_.endswith("DistillationModule") and distill.net.embed.hidden == 16
    assert distill.data.use_unlabeled is True and distill.trainer.max_time


def test_noise_scale_lever_reaches_the_augmentation():
    off = instantiate(compose_train("experiment=demo_distill").data.augment)
    on = instantiate(compose_train("experiment=demo_distill", "lever=noise_scale").data.augment)
    assert off.noise_scale is None and (on.noise_scale, on.noise_prob) == ((0.2, 1.0), 0.5)
    assert (on.flip, on.transpose, on.exposure) == (off.flip, off.transpose, off.exposure)


def test_each_demo_experiment_joins_the_motion_families_with_a_share():
    """make demo's experiments (demo, and demo_distill and demo_teacher, which inherit it) train on
    data/demo joined by exactly data/demo_motion (conf/render_set/demo_motion.yaml's fast-moving and
    saturated families) through data.extra_roots, with data.extra_share of the labeled windows from
    it (the val's choice: 0 for the students, whose val and unlabeled sequences still hold it; 0.25 for
    the teacher); no noise-level augmentation (lever=noise_scale adds it); the teacher at lr 1e-3."""
    for experiment in ("demo", "demo_distill", "demo_teacher"):
        cfg = resolved(compose_train(f"experiment={experiment}"))["data"]
        root = Path(cfg["root"])
        assert root.name == "demo" and [Path(r) for r in cfg["extra_roots"]] == [root.parent / "demo_motion"]
        assert cfg["extra_share"] == (0.25 if experiment == "demo_teacher" else 0.0)
        assert instantiate(compose_train(f"experiment={experiment}").data.augment).noise_scale is None
    assert compose_train("experiment=demo_teacher").model.optimizer.lr == 1e-3


def test_distillation_ablations_switch_off_their_parts():
    base = compose_train("model=distill")
    assert base.model.loss.adversarial_weight > 0 and base.model.param_transfer is not None
    assert compose_train("model=distill", "ablation=no_adversarial").model.loss.adversarial_weight == 0
    assert compose_train("model=distill", "ablation=no_param_transfer").model.param_transfer is None
    assert compose_train("experiment=demo_distill", "ablation=no_unlabeled").data.use_unlabeled is False
    no_kd = compose_train("experiment=demo_distill", "ablation=no_kd")
    assert (no_kd.model.loss.kd_weight, no_kd.model.loss.feature_weight, no_kd.model.loss.adversarial_weight) == (0, 0, 0)
    assert no_kd.model.param_transfer is None and no_kd.data.use_unlabeled is False and no_kd.model.loss.gt_weight > 0


@pytest.mark.parametrize("group,option", [(g, o) for g in ("ablation", "lever") for o in options(g)])
def test_every_ablation_and_lever_builds_a_network(group, option):
    cfg = compose_train("net=tiny", f"{group}={option}")
    net = instantiate(cfg.net)
    assert net.num_parameters() > 0


def test_a_lever_stored_under_its_old_group_composes_as_the_lever():
    """Run directories from before the levers left conf/ablation/ (issue 63) store ``ablation=<lever>``
    (.hydra/overrides.yaml, metrics.json): read through compose_config it is ``lever=<lever>``, for
    every moved option; the file is gone from ablation/, and no option is in both groups."""
    from denoiser.configs import MOVED_OPTIONS, compose_config, compose_net_config, current_overrides

    assert set(options("ablation")).isdisjoint(options("lever"))
    for (group, name), now in MOVED_OPTIONS.items():
        assert name in options(now) and name not in options(group), name
        old = ["output_dir=/tmp/denoiser-test-configs", "experiment=demo_distill", f"{group}={name}"]
        new = old[:-1] + [f"{now}={name}"]
        assert resolved(compose_config(old, "train")) == resolved(compose_config(new, "train")), name
    assert compose_net_config("tiny", ablation="history_clamp")["temporal"]["history_clamp"] == 1.0
    assert current_overrides(["+ablation=log_filter", "ablation=no_pyramid", "ablation=none,history_clamp", "seed=0"]) \
        == ["+lever=log_filter", "ablation=no_pyramid", "ablation=none,history_clamp", "seed=0"]


@pytest.mark.parametrize("trainer", options("trainer"))
def test_trainer_presets(trainer):
    cfg = compose_train(f"trainer={trainer}")
    assert cfg.trainer._target_ == "lightning.pytorch.Trainer" and cfg.trainer.max_steps > 0
    if trainer == "ddp":  # spawn: never re-executes train.py (safe inside Hydra multiruns)
        assert cfg.trainer.strategy.start_method == "spawn"
    if trainer == "cpu":
        assert instantiate(cfg.trainer, logger=False, enable_checkpointing=False).max_steps == cfg.trainer.max_steps


def test_logger_and_callbacks_instantiate(tmp_path):
    cfg = compose_train(f"output_dir={tmp_path}")
    logger = instantiate(cfg.logger)
    assert Path(logger.log_dir) == tmp_path / "tb"
    callbacks = {name: instantiate(c) for name, c in cfg.callbacks.items()}
    assert callbacks["last"].save_last and callbacks["best"].monitor == "val/psnr"
    assert {"best", "last", "final", "lr_monitor", "progress"} <= set(callbacks)


# ----------------------------------------------------------------------------- composed, not copied

#: what every model shares (conf/base/model.yaml), as the three model files spelled it out before
SHARED_MODEL = {
    "_recursive_": False, "net": "${net}",
    "optimizer": {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 2e-3, "weight_decay": 1e-5},
    "scheduler": {"_target_": "denoiser.lit.schedule.ProgressCosineLR", "_partial_": True,
                  "total_steps": "${trainer.max_steps}", "final_ratio": 0.01, "warmup_steps": 20,
                  "follow_time": True},
    "scheduler_interval": "step", "detach_every": 0, "warmup_frames": 2, "image_interval": 100, "grad_clip": 1.0, "logit_penalty": 1e-4,
    "performance": {"channels_last": False, "fused_optimizer": True, "compile": None},
}
DENOISE_LOSS = {"_target_": "denoiser.lit.losses.DenoiseLoss", "smape_weight": 1.0, "gradient_weight": 0.5,
                "temporal_weight": 0.25}
SUPERVISED_MODEL = {**SHARED_MODEL, "_target_": "denoiser.lit.supervised.SupervisedModule", "loss": DENOISE_LOSS,
                    "init_ckpt": None}
DISTILL_MODEL = {
    **SHARED_MODEL, "_target_": "denoiser.lit.distill.DistillationModule", "teacher_ckpt": None,
    "trust_teacher_ckpt": False, "init_ckpt": None,
    "loss": {"kd_weight": 1.0, "gt_weight": 1.0, "feature_weight": 0.1, "adversarial_weight": 0.01,
             "kd": DENOISE_LOSS, "gt": DENOISE_LOSS},
    "critic": {"_target_": "denoiser.nn.critic.PatchCritic", "in_channels": 3, "widths": [32, 64, 128],
               "spectral_norm": True},
    "adversarial": {"_target_": "denoiser.lit.losses.HingeAdversarial"},
    "critic_optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 2e-4, "betas": [0.5, 0.9]},
    "critic_steps": 1,
    "param_transfer": {"_target_": "denoiser.lit.transfer.L1ChannelTransfer", "probe_size": 32, "outer_tap_logit": None},
}


def merged(base: dict, changes: dict) -> dict:
    out = dict(base)
    for k, v in changes.items():
        out[k] = merged(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


@pytest.mark.parametrize("overrides,expected", [
    (["model=teacher"], SUPERVISED_MODEL),
    (["model=student"], SUPERVISED_MODEL),
    (["model=distill"], DISTILL_MODEL),
    (["model=teacher", "net=tiny", "kernel=k3"], SUPERVISED_MODEL),
    (["model=student", "model.optimizer.lr=1e-4", "trainer=gpu"], merged(SUPERVISED_MODEL, {"optimizer": {"lr": 1e-4}})),
    (["model=distill", "ablation=no_kd"], merged(DISTILL_MODEL, {"loss": {"kd_weight": 0.0, "feature_weight": 0.0,
                                                                         "adversarial_weight": 0.0},
                                                                "param_transfer": None})),
    (["experiment=demo_teacher"], merged(SUPERVISED_MODEL, {"optimizer": {"lr": 1e-3}, "scheduler": {"follow_time": False}})),
    (["experiment=demo"], merged(SUPERVISED_MODEL, {"optimizer": {"lr": 3e-3}, "scheduler": {"follow_time": False}})),
    (["experiment=demo_distill"], merged(DISTILL_MODEL, {"optimizer": {"lr": 3e-3}, "critic": {"widths": [16, 32, 64]},
                                                         "scheduler": {"follow_time": False}})),
    (["experiment=paper_distill"], merged(DISTILL_MODEL, {"optimizer": {"lr": 1e-3}, "detach_every": 4,
                                                          "image_interval": 1000})),
])
def test_models_compose_the_shared_base_into_the_same_values(overrides, expected):
    """teacher/student/distill compose conf/base/{model,supervised}.yaml; the composed `model` node
    holds exactly the values the three files spelled out before they shared a base."""
    cfg = compose_train(*overrides)
    assert OmegaConf.to_container(cfg.model, resolve=False) == expected


def test_teacher_and_student_differ_only_in_their_network():
    teacher, student = compose_train("model=teacher"), compose_train("model=student")
    assert OmegaConf.to_container(teacher.model) == OmegaConf.to_container(student.model)  # net: ${net}
    assert (list(teacher.kernel.sizes), list(student.kernel.sizes)) == ([5, 7, 9], [5, 5, 5])
    assert teacher.net.embed.hidden == 256 and student.net.embed.hidden == 32


def test_the_model_base_is_not_an_option():
    """The shared base lives outside the model group (conf/base/): `model` offers real modules only."""
    assert options("model") == ["distill", "student", "teacher"]
    assert not [p for p in (Path(CONF_DIR) / "model").rglob("*") if p.is_dir()]
    for base in options("base"):
        assert "_global_" not in (Path(CONF_DIR) / "base" / f"{base}.yaml").read_text()


@pytest.mark.parametrize("size", ["k3", "k7"])
def test_kernel_ablations_select_the_kernel_variant(size):
    """ablation=k3|k7 merge conf/kernel/k3|k7.yaml (one home for kernel variants); like every
    ablation they come after experiments and the kernel group, so they win over both."""
    sizes = OmegaConf.to_container(compose_train(f"kernel={size}").kernel)
    assert sizes == {"sizes": [int(size[1])] * 3}
    for extra in ([], ["model=teacher"], ["experiment=demo_teacher"], ["kernel=teacher"]):
        cfg = compose_train(f"ablation={size}", *extra)
        assert OmegaConf.to_container(cfg.kernel) == sizes and list(cfg.net.filter.kernel_sizes) == sizes["sizes"]
    assert "sizes" not in (Path(CONF_DIR) / "ablation" / f"{size}.yaml").read_text()


def compose_entry(name: str, *overrides: str, hydra_cfg: bool = False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(name, overrides=list(overrides), return_hydra_config=hydra_cfg)


def test_one_layout_group_chosen_with_layout_everywhere():
    """conf/layout/ is the only layout group: `layout=native|blender` chooses the data module's
    layout (train, eval, bench; package data.layout) and denoiser-denoise's input layout (at `layout`)."""
    assert options("layout") == ["blender", "native", "oidn"] and not (Path(CONF_DIR) / "data" / "layout").exists()
    for name in ("train", "eval", "bench"):
        native = compose_entry(name, *(["output_dir=x"] if name == "train" else []))
        blender = compose_entry(name, "layout=blender", *(["output_dir=x"] if name == "train" else []))
        assert native.data.layout._target_.endswith("NativeLayout") and native.data.layout.require_meta is True
        assert blender.data.layout._target_.endswith("BlenderLayout") and "layout" not in blender
    demo = compose_train("experiment=demo", "layout=blender")
    assert demo.data.crop == 64 and demo.data.layout._target_.endswith("BlenderLayout")
    for layout, target in (("native", "NativeLayout"), ("blender", "BlenderLayout")):
        cfg = compose_entry("denoise", f"layout={layout}", hydra_cfg=True)
        assert cfg.layout._target_.endswith(target) and "data" not in cfg
        assert cfg.layout.require_meta is False  # a folder of frames needs no sequence.json
        assert cfg.hydra.runtime.choices.layout == layout
    same = {k: v for k, v in compose_entry("denoise", "layout=blender").layout.items() if k != "require_meta"}
    assert same == dict(compose_train("layout=blender").data.layout)


def test_one_baseline_list_for_eval_and_bench():
    """conf/baselines/default.yaml is composed by eval and bench; bench times every baseline but
    the noisy input (its config sets `baselines.noisy: null`, which the benchmark skips)."""
    assert options("baselines") == ["compare", "default"]  # compare = default + ONND (tests/methods/test_onnd.py)
    ev, bench = compose_entry("eval", "threads=3"), compose_entry("bench", "threads=3")
    assert list(ev.baselines) == ["noisy", "oidn_fast", "oidn_balanced", "oidn_high"]
    assert ev.baselines.noisy._target_ == "denoiser.methods.baselines.NoisyInput" and ev.baselines.noisy.label == "noisy input"
    assert bench.baselines.noisy is None
    for key in ("oidn_fast", "oidn_balanced", "oidn_high"):
        assert ev.baselines[key] == bench.baselines[key]
        assert ev.baselines[key].quality == key[5:] and ev.baselines[key].threads == 3 == bench.baselines[key].threads
    for name in ("eval.yaml", "bench.yaml"):
        assert "OidnDenoiser" not in (Path(CONF_DIR) / name).read_text()
