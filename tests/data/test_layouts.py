"""Blender Cycles layout on multilayer EXRs written with Blender's channel names.

The frames are built from a physical statement, not from our converter: the content moves
2 px right and 1 px down per frame, so Blender's Vector pass (position in t-1 minus position
in t, +Y up) is (-2, +1) everywhere, and our motion must come out as (-2, -1).
"""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from denoiser.buffers import FRAME_INPUTS
from denoiser.conf import CONF_DIR
from denoiser.data import exr
from denoiser.data.dataset import WindowDataset, index_split
from denoiser.data.layouts import BlenderLayout, NativeLayout
from denoiser.data.synthetic import normal_from_depth
from denoiser.errors import UserError

H, W, FRAMES = 20, 24, 3
DX, DY = 2, 1  # content motion per frame, image axes (x right, y down)


@pytest.fixture(scope="module")
def layouts():
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        blender = instantiate(compose(overrides=["+layout=blender"]).data.layout)
        native = instantiate(compose(overrides=["+layout=native"]).data.layout)
    assert isinstance(blender, BlenderLayout) and isinstance(native, NativeLayout)
    return blender, native


def texture(t: int, seed: int = 0) -> np.ndarray:
    """[H, W, 3] content of frame t: a fixed random texture shifted by (DX, DY) * t."""
    big = np.random.default_rng(seed).uniform(0.1, 5.0, (H + 20, W + 20, 3)).astype(np.float32)
    y0, x0 = 10 - DY * t, 10 - DX * t
    return big[y0:y0 + H, x0:x0 + W]


def blender_frame(t: int, layer: str = "ViewLayer.", denoised: bool = False, reference: bool = False) -> dict:
    """Channels of one Cycles frame, named as Blender names them."""
    ref = texture(t)
    rng = np.random.default_rng(100 + t)
    noisy = ref * rng.uniform(0.5, 1.5, ref.shape).astype(np.float32)
    ch: dict[str, np.ndarray] = {}

    def put(pass_name, suffixes, arr):
        for i, s in enumerate(suffixes):
            ch[f"{layer}{pass_name}.{s}"] = arr[..., i]

    if reference:
        put("Combined", "RGBA", np.dstack([ref, np.ones((H, W))]))
        return ch
    if denoised:  # Cycles' denoiser ran: Combined is denoised, Noisy Image is the raw render
        put("Combined", "RGBA", np.dstack([ref * 0 + 7.0, np.ones((H, W))]))
        put("Noisy Image", "RGBA", np.dstack([noisy, np.ones((H, W))]))
    else:
        put("Combined", "RGBA", np.dstack([noisy, np.ones((H, W))]))
    depth = 3.0 + texture(t)[..., 0]
    put("Depth", "Z", depth[..., None])
    put("Denoising Depth", "Z", depth[..., None])
    put("Normal", "XYZ", np.dstack([np.ones((H, W)), np.zeros((H, W)), np.zeros((H, W))]))  # world space: unused
    put("Denoising Normal", "XYZ", normal_from_depth(depth))
    put("Denoising Albedo", "RGB", texture(t, seed=1))
    # Vector: (X, Y) = pos(t-1) - pos(t) with +Y up; (Z, W) = pos(t) - pos(t+1)
    vec = np.zeros((H, W, 4), np.float32)
    if t > 0:
        vec[..., 0], vec[..., 1] = -DX, +DY
    vec[..., 2], vec[..., 3] = -DX, +DY
    put("Vector", "XYZW", vec)
    return ch


def write_blender_sequence(seq_dir, layer="ViewLayer.", denoised=False, with_reference=True):
    for t in range(FRAMES):
        exr.write_channels(seq_dir / "noisy" / f"{t + 1:04d}.exr", blender_frame(t, layer, denoised))
        if with_reference:
            exr.write_channels(seq_dir / "reference" / f"{t + 1:04d}.exr", blender_frame(t, layer, reference=True))


def test_blender_channels_and_vector_conversion(tmp_path, layouts):
    blender, _ = layouts
    write_blender_sequence(tmp_path / "train" / "shot")
    [src] = index_split(blender, tmp_path, "train")
    assert src.frames == FRAMES and (src.width, src.height) == (W, H) and src.cuts == ()
    assert set(src.buffers) == {"color", "albedo", "normal", "depth", "motion", "reference"}
    frame, counts = blender.read_frame(src, 1, [*FRAME_INPUTS, "reference"])
    assert set(counts.values()) == {0}
    assert frame["motion"].shape == (H, W, 2)
    np.testing.assert_array_equal(frame["motion"][..., 0], -DX)
    np.testing.assert_array_equal(frame["motion"][..., 1], -DY)
    np.testing.assert_array_equal(frame["reference"], texture(1))
    np.testing.assert_array_equal(frame["albedo"], texture(1, seed=1))
    np.testing.assert_array_equal(frame["depth"][..., 0], 3.0 + texture(1)[..., 0])
    np.testing.assert_array_equal(frame["normal"], normal_from_depth(3.0 + texture(1)[..., 0]))
    # warping frame t-1 by the converted motion lands on frame t (where the source is inside)
    prev, _ = blender.read_frame(src, 0, ["reference"])
    ys, xs = np.mgrid[0:H, 0:W]
    qx, qy = xs + frame["motion"][..., 0].astype(int), ys + frame["motion"][..., 1].astype(int)
    ok = (qx >= 0) & (qy >= 0) & (qx < W) & (qy < H)
    np.testing.assert_array_equal(prev["reference"][qy[ok], qx[ok]], frame["reference"][ok])
    assert ok.sum() > H * W / 2


def test_noisy_image_preferred_when_cycles_denoiser_ran(tmp_path, layouts):
    blender, _ = layouts
    write_blender_sequence(tmp_path / "d", denoised=True, with_reference=False)
    write_blender_sequence(tmp_path / "n", denoised=False, with_reference=False)
    d = blender.open_sequence(tmp_path / "d")
    n = blender.open_sequence(tmp_path / "n")
    got_d, _ = blender.read_frame(d, 2, ["color"])
    got_n, _ = blender.read_frame(n, 2, ["color"])
    np.testing.assert_array_equal(got_d["color"], got_n["color"])  # the raw render in both cases
    assert not np.any(got_d["color"] == 7.0)
    assert not d.labeled and "reference" not in d.buffers


@pytest.mark.parametrize("layer", ["", "RenderLayer."])
def test_other_view_layer_prefixes(tmp_path, layouts, layer):
    blender, _ = layouts
    write_blender_sequence(tmp_path / "s", layer=layer)
    src = blender.open_sequence(tmp_path / "s")
    frame, _ = blender.read_frame(src, 2, ["color", "motion", "reference"])
    np.testing.assert_array_equal(frame["motion"][..., 1], -DY)
    np.testing.assert_array_equal(frame["reference"], texture(2))


def test_two_view_layers_are_ambiguous(tmp_path, layouts):
    blender, _ = layouts
    chans = {**blender_frame(0, "Fg."), **blender_frame(0, "Bg.")}
    exr.write_channels(tmp_path / "s" / "0001.exr", chans)
    with pytest.raises(UserError, match=r"0001.exr: buffer color: several view layers hold Noisy Image|"
                                        r"0001.exr: buffer color: several view layers hold Combined \(Bg, Fg\)"):
        blender.open_sequence(tmp_path / "s")


def test_folder_of_frames_and_pairing_errors(tmp_path, layouts):
    blender, _ = layouts
    for t in range(2):  # frames directly in the folder: an unlabeled sequence (denoise a render)
        exr.write_channels(tmp_path / "render" / f"frame{t + 9}.exr", blender_frame(t))
    src = blender.open_sequence(tmp_path / "render")
    assert [p.name for p in src.files["noisy"]] == ["frame9.exr", "frame10.exr"]  # numeric order
    assert not src.labeled
    seq = tmp_path / "seq"
    write_blender_sequence(seq)
    (seq / "reference" / "0002.exr").unlink()
    with pytest.raises(UserError, match=r"reference: no reference frame for noisy frame\(s\) 0002.exr"):
        blender.open_sequence(seq)
    exr.write_channels(seq / "reference" / "0002.exr", {"ViewLayer.Combined.R": np.ones((4, 4))})
    with pytest.raises(UserError, match=r"0002.exr: is 4x4 but"):
        blender.open_sequence(seq)
    exr.write_channels(tmp_path / "empty" / "0001.exr", {"ViewLayer.Depth.Z": np.ones((4, 4))})
    with pytest.raises(UserError, match=r"0001.exr: no noisy color \(Noisy Image.R or Combined.R"):
        blender.open_sequence(tmp_path / "empty")



def test_blender_sequence_json_is_optional_unless_required(tmp_path, layouts):
    """``require_meta`` as in the native layout: off by default for Blender renders (the config
    leaves it so), on it makes a directory without sequence.json an error naming the file."""
    blender, _ = layouts
    seq = tmp_path / "seq"
    write_blender_sequence(seq, with_reference=False)
    assert not blender.require_meta and blender.open_sequence(seq).frames == FRAMES
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        strict = instantiate(compose(overrides=["+layout=blender"]).data.layout, require_meta=True)
    with pytest.raises(UserError, match=r"seq/sequence.json: file does not exist"):
        strict.open_sequence(seq)


def test_blender_and_native_give_the_same_windows(tmp_path, layouts):
    """The same frames stored both ways read identically through the dataset."""
    blender, native = layouts
    write_blender_sequence(tmp_path / "blender" / "train" / "s")
    from denoiser.data.sequence import write_sequence_json

    for t in range(FRAMES):
        b, _ = blender.read_frame(blender.open_sequence(tmp_path / "blender" / "train" / "s"), t,
                                  [*FRAME_INPUTS, "reference"])
        exr.write_frame(tmp_path / "native" / "train" / "s" / f"frame_{t:04d}.exr", b)
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    write_sequence_json(tmp_path / "native" / "train" / "s", {
        "width": W, "height": H, "frames": FRAMES, "spp": 1,
        "buffers": [*FRAME_INPUTS, "reference"],
        "cameras": [{"to_world": eye, "fov": 30}] * FRAMES, "cuts": [], "scene": {"name": "t"},
        "renderer": {"name": "blender", "version": "4.2", "variant": "cycles"}, "seeds": {}, "render_seconds": {}})
    inputs = list(FRAME_INPUTS)
    a = WindowDataset(index_split(blender, tmp_path / "blender", "train"), blender, inputs, window=3)[0]
    b = WindowDataset(index_split(native, tmp_path / "native", "train"), native, inputs, window=3)[0]
    for k in (*inputs, "reference", "reset", "frame_index"):
        assert a[k].equal(b[k]), k
    assert a["motion"][1:, 1].eq(-DY).all()


def blender5_parts(t: int, z_pass: bool = True) -> tuple[list[dict], list[str]]:
    """One frame as Blender 5.0.1 writes it by default: one EXR part per pass, named
    ``ViewLayer.<Pass>``, the values of the verified probe render (scripts/blender_sequences.py
    ``--sequences probe``): the camera pans right 2 px per frame, so the static floor has Vector
    (X, Y) = (+2, 0); a square moving 1 px *up* per frame on screen has (0, -1) (+Y is up).
    Misses: Depth 1e10, Denoising Depth 0, normal 0; albedo of an emitter above 1."""
    one, zero = np.ones((H, W), np.float32), np.zeros((H, W), np.float32)
    obj = np.zeros((H, W), bool)
    obj[8:12, 6:10] = True
    miss = np.zeros((H, W), bool)
    miss[:2] = True
    vx, vy = np.where(obj, 0.0, 2.0).astype(np.float32), np.where(obj, -1.0, 0.0).astype(np.float32)
    color = texture(t)
    parts = {
        "Combined": {f"ViewLayer.Combined.{c}": color[..., i] for i, c in enumerate("RGB")}
        | {"ViewLayer.Combined.A": one},
        "Vector": {"ViewLayer.Vector.X": vx, "ViewLayer.Vector.Y": vy, "ViewLayer.Vector.Z": vx,
                   "ViewLayer.Vector.W": vy},
        "Denoising Normal": {"ViewLayer.Denoising Normal.X": zero, "ViewLayer.Denoising Normal.Y": zero,
                             "ViewLayer.Denoising Normal.Z": np.where(miss, 0.0, -1.0).astype(np.float32)},
        "Denoising Albedo": {f"ViewLayer.Denoising Albedo.{c}": np.where(obj, 60.0, 0.5).astype(np.float32)
                             for c in "RGB"},
        "Denoising Depth": {"ViewLayer.Denoising Depth.Z": np.where(miss, 0.0, 10.2).astype(np.float32)},
    }
    if z_pass:
        parts = {"Depth": {"ViewLayer.Depth.Z": np.where(miss, 1e10, 10.0).astype(np.float32)}, **parts}
    return list(parts.values()), [f"ViewLayer.{p}" for p in parts]


@pytest.mark.parametrize("z_pass", [True, False])
def test_blender5_multipart_files_and_verified_signs(tmp_path, layouts, z_pass):
    """Blender 5.0 multi-part files read like 4.x ones; the probe's Vector signs give our motion
    (floor: camera pans right, so what is at p was at p + (2, 0) before; the square moved up, so
    it was at p + (0, 1), y down); misses are far whichever depth pass is there."""
    blender, _ = layouts
    for t in range(2):
        parts, names = blender5_parts(t, z_pass)
        exr.write_multipart(tmp_path / "s" / "noisy" / f"{t + 1:04d}.exr", parts, names=names)
    src = blender.open_sequence(tmp_path / "s")
    assert set(src.buffers) == {"color", "albedo", "normal", "depth", "motion"}
    frame, counts = blender.read_frame(src, 1, list(FRAME_INPUTS))
    assert set(counts.values()) == {0}
    np.testing.assert_array_equal(frame["color"], texture(1))
    motion = frame["motion"]
    np.testing.assert_array_equal(motion[8:12, 6:10], np.broadcast_to([0.0, 1.0], (4, 4, 2)))
    np.testing.assert_array_equal(motion[15:, 12:], np.broadcast_to([2.0, 0.0], (H - 15, W - 12, 2)))
    depth = frame["depth"][..., 0]
    assert np.all(depth[:2] == 1e10) and np.all(depth[2:] == (10.0 if z_pass else np.float32(10.2)))
    assert frame["albedo"].max() == 60.0  # emitters: albedo is the emitted radiance, kept as is
    np.testing.assert_array_equal(frame["normal"][2:, :, 2], -1.0)
