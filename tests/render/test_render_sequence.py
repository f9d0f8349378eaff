"""Rendering sequences to disk: buffers, sequence.json, resume, unlabeled split, samples, CLI."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from denoiser.buffers import FRAME_INPUTS
from denoiser.data.exr import list_channels, read_frame, read_samples
from denoiser.data.sequence import load_sequence_json
from denoiser.errors import UserError
from denoiser.render import job as job_module
from denoiser.render.job import RenderSettings, frame_path, render_sequence
from denoiser.render.passes import NO_HIT_DEPTH
from denoiser.render.spec import build_scene

NATIVE = {"color": ("color.R", "color.G", "color.B"), "albedo": ("albedo.R", "albedo.G", "albedo.B"),
          "normal": ("normal.X", "normal.Y", "normal.Z"), "depth": ("depth.Z",), "motion": ("motion.X", "motion.Y"),
          "reference": ("reference.R", "reference.G", "reference.B")}
TINY = RenderSettings(frames=2, spp=2, ref_spp=8, width=32, height=32)


def static_scene() -> dict:
    """A rough gold sphere (albedo AOV > 1 before clamping) and a cube over a constant sky."""
    return {
        "name": "static_probe", "effects": ["env_light", "area_light", "glossy"],
        "camera": {"origin": [0, 0, 4], "target": [0, 0, 0], "fov": 45},
        "objects": [
            {"name": "ball", "shape": "sphere", "position": [-0.5, 0, 0], "scale": 0.6,
             "material": {"type": "conductor", "metal": "Au", "roughness": 0.4}},
            {"name": "box", "shape": "cube", "position": [0.7, 0, -0.5], "rotation": [20, 30, 0], "scale": 0.4},
        ],
        "lights": [{"type": "constant", "radiance": 0.5},
                   {"type": "area", "position": [0, 2, 2], "target": [0, 0, 0], "size": [1, 1], "radiance": 5}],
    }


@pytest.fixture(scope="module")
def mi():
    from denoiser.render.variant import activate

    return activate("auto", quiet=True)


@pytest.fixture(scope="module")
def static_seq(mi, tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "train" / "static_probe_000"
    spec = build_scene(static_scene(), 0)
    meta = render_sequence(mi, spec, out, TINY, seq_seed=1234)
    return out, meta


def test_static_scene_buffers(static_seq):
    out, _ = static_seq
    for t in range(TINY.frames):
        buf, bad = read_frame(frame_path(out, t), NATIVE)
        assert bad == 0
        assert buf["color"].shape == (32, 32, 3)
        assert np.array_equal(buf["motion"], np.zeros((32, 32, 2), np.float32))  # exact zeros
        assert buf["albedo"].min() >= 0 and buf["albedo"].max() <= 1
        hit = buf["depth"][..., 0] < NO_HIT_DEPTH
        assert 0.1 < hit.mean() < 0.9  # objects and sky both visible
        assert np.all(buf["depth"][~hit] == np.float32(NO_HIT_DEPTH))
        n = np.linalg.norm(buf["normal"], axis=-1)
        assert np.allclose(n[hit], 1, atol=1e-3) and np.all(n[~hit] == 0)
        # sphere centre faces the camera: normal ~ (0, 0, -1) in camera space (z into the scene)
        h, w = 32, 32
        cx = round(w / 2 - 0.5 / (4 * np.tan(np.radians(22.5))) * w / 2)
        assert buf["normal"][h // 2, cx, 2] < -0.9
        assert np.all(buf["depth"][hit] > 2.5) and np.all(buf["depth"][hit] < 6)


def test_sequence_json_complete(static_seq, mi):
    out, _ = static_seq
    parsed = load_sequence_json(out)  # validates the schema
    assert (parsed.width, parsed.height, parsed.frames, parsed.spp) == (32, 32, 2, 2)
    assert list(parsed.buffers) == [*FRAME_INPUTS, "reference"]
    assert len(parsed.cameras) == 2 and parsed.cameras[0].fov == 45
    assert np.allclose(np.array(parsed.cameras[0].to_world)[:3, 3], [0, 0, 4])
    assert parsed.cuts == ()
    assert parsed.scene["name"] == "static_probe"
    assert parsed.scene["effects"] == ["env_light", "area_light", "glossy"]
    assert "params" in parsed.scene
    assert parsed.renderer["name"] == "mitsuba" and parsed.renderer["version"] == mi.__version__
    assert parsed.renderer["variant"] in ("llvm_ad_rgb", "scalar_rgb")
    seeds = parsed.seeds
    assert seeds["sequence"] == 1234
    all_seeds = seeds["noisy"] + seeds["reference"]
    assert len(set(all_seeds)) == 4  # distinct per frame and per pass
    assert set(parsed.render_seconds) == {"color", "aux", "motion", "reference"}
    assert all(v >= 0 for v in parsed.render_seconds.values())
    assert parsed.extra["ref_spp"] == 8
    assert {"motion", "normal", "depth", "camera"} <= set(parsed.extra["conventions"])
    assert len(parsed.extra["frame_seconds"]) == 2


def test_resume_skips_finished_frames(static_seq, mi, monkeypatch):
    out, meta = static_seq
    calls = []
    real = job_module.render_frame

    def counting(*args, **kwargs):
        calls.append(args[2])
        return real(*args, **kwargs)

    monkeypatch.setattr(job_module, "render_frame", counting)
    spec = build_scene(static_scene(), 0)
    mtimes = [os.stat(frame_path(out, t)).st_mtime_ns for t in range(2)]
    again = render_sequence(mi, spec, out, TINY, seq_seed=1234)
    assert calls == []
    assert [os.stat(frame_path(out, t)).st_mtime_ns for t in range(2)] == mtimes
    assert again["render_seconds"] == meta["render_seconds"]
    frame_path(out, 1).write_bytes(b"truncated")  # a damaged frame is rendered again
    render_sequence(mi, spec, out, TINY, seq_seed=1234)
    assert calls == [1]
    assert os.stat(frame_path(out, 0)).st_mtime_ns == mtimes[0]


def test_changed_settings_refuse_to_mix(static_seq, mi):
    out, _ = static_seq
    from denoiser.errors import UserError

    spec = build_scene(static_scene(), 0)
    with pytest.raises(UserError, match="different settings"):
        render_sequence(mi, spec, out, RenderSettings(frames=2, spp=4, ref_spp=8, width=32, height=32), 1234)


def test_unlabeled_split_has_no_reference(mi, tmp_path):
    settings = RenderSettings(frames=1, spp=2, ref_spp=8, width=16, height=16, labeled=False)
    render_sequence(mi, build_scene(static_scene(), 0), tmp_path, settings, seq_seed=5)
    chans = list_channels(frame_path(tmp_path, 0))
    assert not any(c.startswith("reference") for c in chans)
    assert "color.R" in chans and "motion.X" in chans
    meta = load_sequence_json(tmp_path)
    assert "reference" not in meta.buffers and "reference" not in meta.seeds
    assert "reference" not in meta.render_seconds


def test_samples_are_written_and_average_to_color(mi, tmp_path):
    settings = RenderSettings(frames=1, spp=3, ref_spp=4, width=16, height=16, save_samples=True)
    render_sequence(mi, build_scene(static_scene(), 0), tmp_path, settings, seq_seed=9)
    path = frame_path(tmp_path, 0)
    samples = read_samples(path)
    assert samples.shape == (3, 16, 16, 3)
    assert not np.allclose(samples[0], samples[1])  # different seeds per sample
    color, _ = read_frame(path, {"color": NATIVE["color"]})
    assert np.allclose(samples.mean(0), color["color"], atol=1e-5)
    meta = load_sequence_json(tmp_path)
    assert meta.sample_count == 3 and len(set(meta.seeds["samples"])) == 3


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-c", "from denoiser.commands.render import main; main()", *args],
                          cwd=cwd, capture_output=True, text=True, timeout=300, check=False)


@pytest.mark.slow
def test_cli_renders_and_reports_user_errors(tmp_path):
    ok = _cli("scene=cornell", "frames=1", "width=16", "height=16", "spp=1", "ref_spp=2", "sequences=2",
              f"root={tmp_path}/ds", cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr
    for k in range(2):
        assert (tmp_path / "ds" / "train" / f"cornell_{k:03d}" / "frame_0000.exr").exists()
    a = load_sequence_json(tmp_path / "ds" / "train" / "cornell_000")
    b = load_sequence_json(tmp_path / "ds" / "train" / "cornell_001")
    assert a.scene["params"] != b.scene["params"]  # one config, different draws
    bad = _cli("split=training", f"root={tmp_path}/ds", cwd=tmp_path)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1].startswith("error: render: key 'split'")
    assert "Traceback" not in bad.stderr


def test_dof_blurs_albedo_but_depth_and_motion_stay_pixel_centre(mi):
    from denoiser.commands.tools.effect_cost import bench_scene
    from denoiser.render.motion import backward_motion
    from denoiser.render.passes import FrameRenderer

    sharp = FrameRenderer(mi, build_scene(bench_scene(["area_light"]), 0), 24, 24).aux(0)
    cfg = bench_scene(["area_light", "dof"])
    cfg["camera"].update(aperture=0.2, focus_distance=1.5)
    spec = build_scene(cfg, 0)
    blurred = FrameRenderer(mi, spec, 24, 24).aux(0)
    assert np.array_equal(sharp.depth, blurred.depth)
    assert np.abs(sharp.albedo - blurred.albedo).max() > 0.1
    n = np.linalg.norm(blurred.normal, axis=-1)
    assert np.allclose(n[n > 0], 1, atol=1e-4)
    assert not backward_motion(spec, blurred, 0, 24, 24).any()


def test_motion_blur_smears_a_moving_object_only_when_declared(mi):
    from denoiser.render.passes import FrameRenderer

    def scene(blur: bool) -> dict:
        cfg = {"name": "smear", "effects": ["env_light", "object_motion"] + (["motion_blur"] if blur else []),
               "camera": {"origin": [0, 0, 4], "target": [0, 0, 0], "fov": 40, "shutter": 1.0 if blur else 0.0},
               "objects": [{"name": "ball", "shape": "sphere", "scale": 0.3, "velocity": [0.8, 0, 0],
                            "material": {"type": "diffuse", "color": [0.05, 0.05, 0.05]}}],
               "lights": [{"type": "constant", "radiance": 1.0}]}
        return cfg

    def partial_pixels(blur: bool) -> int:
        fr = FrameRenderer(mi, build_scene(scene(blur), 0), 24, 24)
        row = fr.reference(1, 64, 7)[12, :, 0]  # background 1, dark ball ~0.05
        return int(((row < 0.9) & (row > 0.15)).sum())

    sharp, blurred = partial_pixels(False), partial_pixels(True)
    assert blurred >= sharp + 4  # the ball sweeps ~0.8 units (several pixels) during the open shutter


def textured_scene() -> dict:
    """A checkered plane seen at a grazing angle (sub-pixel texture detail) and a sphere over a sky."""
    return {
        "name": "aux_probe", "effects": ["env_light", "area_light", "textures"],
        "camera": {"origin": [0, 1.0, 4], "target": [0, 0, 0], "fov": 50},
        "objects": [
            {"name": "floor", "shape": "rectangle", "position": [0, -0.5, 0], "rotation": [-90, 0, 0], "scale": 6,
             "material": {"type": "diffuse", "color": {"texture": "checker", "tiles": 64,
                                                       "color0": [0.05, 0.05, 0.05], "color1": [0.9, 0.9, 0.9]}}},
            {"name": "ball", "shape": "sphere", "position": [0, 0.2, 0], "scale": 0.5},
        ],
        "lights": [{"type": "constant", "radiance": 0.5},
                   {"type": "area", "position": [0, 2, 2], "target": [0, 0, 0], "size": [1, 1], "radiance": 5}],
    }


def test_aux_samples_are_means_of_the_colour_samples(mi, tmp_path):
    """aux=samples: the colour is unchanged (same seeds), albedo and normal are sample means like
    Cycles' denoising passes: noisier than the pixel-centre ones on sub-pixel texture, equal to
    them where the albedo is flat, normals still unit length where something was hit."""
    spec = build_scene(textured_scene(), 0)
    settings = RenderSettings(frames=1, spp=4, ref_spp=4, width=32, height=32, labeled=False)
    center = render_sequence(mi, spec, tmp_path / "center", settings, seq_seed=7)
    samples = render_sequence(mi, spec, tmp_path / "samples",
                              RenderSettings(**{**settings.identity(), "aux": "samples"}), seq_seed=7)
    inputs = {k: v for k, v in NATIVE.items() if k != "reference"}
    a, _ = read_frame(frame_path(tmp_path / "center", 0), inputs)
    b, _ = read_frame(frame_path(tmp_path / "samples", 0), inputs)
    np.testing.assert_array_equal(a["color"], b["color"])
    np.testing.assert_array_equal(a["depth"], b["depth"])
    assert "aux" not in center["render_settings"] and samples["render_settings"]["aux"] == "samples"
    assert "noisy colour's own samples" in samples["conventions"]["albedo"]
    # the floor (rows 20+, below the sphere): a pixel covers several checker cells, so the
    # sample means take in-between values where the pixel-centre albedo is one of the two colours
    floor_a, floor_b = a["albedo"][20:], b["albedo"][20:]
    grey = lambda x: ((x > 0.1) & (x < 0.85)).mean()
    assert grey(floor_a) < 0.05 and grey(floor_b) > 0.5
    assert np.abs(floor_a - floor_b).mean() > 0.05
    length = np.linalg.norm(b["normal"], axis=-1)
    hit = a["depth"][..., 0] < NO_HIT_DEPTH
    assert np.allclose(length[hit], 1.0, atol=1e-4)  # silhouettes: some samples hit where the centre misses
    assert np.all(np.isclose(length, 1.0, atol=1e-4) | (length == 0)) and (length == 0).mean() > 0.2


def test_aux_samples_with_saved_samples_and_resume_identity(mi, tmp_path):
    """With save_samples the aux means come from the saved samples' own passes; a sequence
    rendered before the option existed (no aux key) resumes as aux=center; a changed aux refuses."""
    spec = build_scene(textured_scene(), 0)
    settings = RenderSettings(frames=1, spp=2, ref_spp=2, width=16, height=16, labeled=False,
                              save_samples=True, aux="samples")
    render_sequence(mi, spec, tmp_path / "s", settings, seq_seed=3)
    buf, _ = read_frame(frame_path(tmp_path / "s", 0), {k: v for k, v in NATIVE.items() if k != "reference"})
    assert 0.0 <= buf["albedo"].min() and buf["albedo"].max() <= 1.0
    with pytest.raises(UserError, match="aux"):
        render_sequence(mi, spec, tmp_path / "s", RenderSettings(**{**settings.identity(), "aux": "center"}),
                        seq_seed=3)
    with pytest.raises(UserError, match="render aux"):
        RenderSettings(frames=1, spp=1, ref_spp=1, width=8, height=8, aux="pixel")


def test_aux_samples_under_motion_blur_follow_the_colour_samples(mi):
    """With an open shutter radiance_aux spreads its samples over the same sub-frame instants as
    radiance (same colour); the albedo smears along the motion like the colour does."""
    from denoiser.render.passes import FrameRenderer

    cfg = {"name": "smear_aux", "effects": ["env_light", "object_motion", "motion_blur"],
           "camera": {"origin": [0, 0, 4], "target": [0, 0, 0], "fov": 40, "shutter": 1.0},
           "objects": [{"name": "ball", "shape": "sphere", "scale": 0.3, "velocity": [0.8, 0, 0],
                        "material": {"type": "diffuse", "color": [0.9, 0.9, 0.9]}}],
           "lights": [{"type": "constant", "radiance": 1.0}]}
    fr = FrameRenderer(mi, build_scene(cfg, 0), 24, 24)
    color, albedo, _ = fr.radiance_aux(1, 16, 11)
    np.testing.assert_allclose(color, fr.radiance(1, 16, 11), rtol=1e-6, atol=1e-7)  # one shared helper
    row = albedo[12, :, 0]  # sky 0, ball 0.9; the swept band has fractions in between
    assert ((row > 0.05) & (row < 0.85)).sum() >= 4


def _reference(out, t: int = 0) -> np.ndarray:
    arrays, _ = read_frame(frame_path(out, t), {"reference": NATIVE["reference"]})
    return arrays["reference"]


def test_references_copied_from_a_donor_are_the_ones_rendered(static_seq, mi, tmp_path, capsys):
    """render_set=demo_compare re-renders demo's test split with per-sample radiance: its references
    come from data/demo (reference_from), and they are the references the sequence would render."""
    donor, _ = static_seq
    spec = build_scene(static_scene(), 0)
    with_samples = RenderSettings(frames=2, spp=2, ref_spp=8, width=32, height=32, save_samples=True)
    copied = tmp_path / "copied"
    meta = render_sequence(mi, spec, copied, with_samples, seq_seed=1234, reference_from=donor)
    assert meta["reference_from"] == str(donor)
    assert all("reference" not in seconds for seconds in meta["frame_seconds"])   # nothing rendered for them
    rendered = tmp_path / "rendered"
    render_sequence(mi, spec, rendered, with_samples, seq_seed=1234)
    for t in range(2):
        assert np.array_equal(_reference(copied, t), _reference(donor, t))
        assert np.array_equal(_reference(copied, t), _reference(rendered, t))   # the reference pass's own seed
    # a donor of another reference spp (or seed, size, renderer) is not used: said, and rendered
    other = tmp_path / "other"
    meta = render_sequence(mi, spec, other, RenderSettings(frames=2, spp=2, ref_spp=4, width=32, height=32),
                           seq_seed=1234, reference_from=donor)
    assert "reference_from" not in meta and all("reference" in s for s in meta["frame_seconds"])
    assert f"note: {other}: references rendered, not copied ({donor / 'sequence.json'}: rendered with other ref_spp)" \
        in capsys.readouterr().err
