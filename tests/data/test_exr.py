"""EXR I/O (denoiser.data.exr) on real files written by the tests."""

from __future__ import annotations

import numpy as np
import pytest

from denoiser.buffers import native_channels
from denoiser.data import exr
from denoiser.errors import ExrError, UserError

H, W = 24, 32
#: Compressions that do not reproduce values exactly (for some pixel types).
LOSSY = {"b44", "b44a", "dwaa", "dwab", "pxr24", "lj2k"}


def all_buffers(rng) -> dict[str, np.ndarray]:
    """One of every native buffer, HDR values included (``samples`` ``[S, H, W, 3]``)."""
    return {
        "color": rng.uniform(0, 2000, (H, W, 3)).astype(np.float32),
        "albedo": rng.uniform(0, 1.3, (H, W, 3)).astype(np.float32),
        "normal": rng.normal(size=(H, W, 3)).astype(np.float32),
        "depth": rng.uniform(0.1, 1000, (H, W, 1)).astype(np.float32),
        "motion": rng.uniform(-20, 20, (H, W, 2)).astype(np.float32),
        "reference": rng.uniform(0, 50000, (H, W, 3)).astype(np.float32),
        "samples": rng.uniform(0, 10, (3, H, W, 3)).astype(np.float32),
    }


def native_spec(bufs) -> dict[str, tuple[str, ...]]:
    return {k: native_channels(k, v.shape[-1]) for k, v in bufs.items() if k != "samples"}


@pytest.mark.parametrize("half", [False, True])
def test_roundtrip_every_buffer(tmp_path, half):
    bufs = all_buffers(np.random.default_rng(0))
    path = tmp_path / "f.exr"
    exr.write_frame(path, bufs, half=half)
    got, bad = exr.read_frame(path, native_spec(bufs))
    assert bad == 0
    for k, v in bufs.items():
        if k == "samples":
            continue
        expect = v.astype(np.float16).astype(np.float32) if half else v
        assert got[k].dtype == np.float32 and got[k].shape == v.shape
        np.testing.assert_array_equal(got[k], expect, err_msg=k)
    samples = exr.read_samples(path)
    expect = bufs["samples"].astype(np.float16).astype(np.float32) if half else bufs["samples"]
    np.testing.assert_array_equal(samples, expect)
    assert "color.R" in exr.list_channels(path) and "sample.2.B" in exr.list_channels(path)


def test_half_for_some_buffers_only(tmp_path):
    bufs = all_buffers(np.random.default_rng(1))
    exr.write_frame(tmp_path / "f.exr", bufs, half=["color"])
    got, _ = exr.read_frame(tmp_path / "f.exr", native_spec(bufs))
    np.testing.assert_array_equal(got["color"], bufs["color"].astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(got["depth"], bufs["depth"])  # kept float32: not rounded


def smooth_image() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([1 + 0.5 * np.sin(xx / 5 + c) * np.cos(yy / 7) for c in range(3)], -1).astype(np.float32) * 10


@pytest.mark.parametrize("compression", sorted(exr.COMPRESSIONS))
@pytest.mark.parametrize("half", [False, True])
def test_every_compression(tmp_path, compression, half):
    img = smooth_image()
    path = tmp_path / f"{compression}.exr"
    exr.write_frame(path, {"color": img}, half=half, compression=compression)
    assert exr.read_header(path)["compression"] == exr.COMPRESSIONS[compression]
    got, _ = exr.read_frame(path, {"color": ("color.R", "color.G", "color.B")})
    expect = img.astype(np.float16).astype(np.float32) if half else img
    if compression in LOSSY:
        rel = np.abs(got["color"] - expect) / np.abs(expect)
        assert rel.mean() < 0.01 and rel.max() < 0.1, (rel.mean(), rel.max())
    else:
        np.testing.assert_array_equal(got["color"], expect)


def test_unknown_compression_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="unknown compression 'lzw'"):
        exr.write_frame(tmp_path / "f.exr", {"color": smooth_image()}, compression="lzw")


def test_multipart_read(tmp_path):
    rng = np.random.default_rng(2)
    a = {c: rng.random((H, W), dtype=np.float32) for c in ("color.R", "color.G", "color.B")}
    b = {"depth.Z": rng.random((H, W), dtype=np.float32) * 100}
    path = tmp_path / "multi.exr"
    exr.write_multipart(path, [a, b], names=["rgb", "aux"])
    assert set(exr.list_channels(path)) == {"color.R", "color.G", "color.B", "depth.Z"}
    got, bad = exr.read_frame(path, {"color": ("color.R", "color.G", "color.B"), "depth": ("depth.Z",)})
    assert bad == 0
    np.testing.assert_array_equal(got["depth"][..., 0], b["depth.Z"])
    np.testing.assert_array_equal(got["color"][..., 1], a["color.G"])


def test_missing_file(tmp_path):
    with pytest.raises(ExrError, match=r"nope\.exr: file does not exist"):
        exr.read_channels(tmp_path / "nope.exr")


def test_png_bytes_renamed_exr(tmp_path):
    path = tmp_path / "image.exr"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 64)
    with pytest.raises(ExrError, match=r"image\.exr: not an EXR file"):
        exr.read_frame(path, {"color": ("color.R",)})


def test_truncated_file(tmp_path):
    path = tmp_path / "cut.exr"
    exr.write_frame(path, all_buffers(np.random.default_rng(3)), compression="no")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ExrError, match=r"cut\.exr: truncated or corrupt"):
        exr.read_channels(path)
    path.write_bytes(data[:40])  # not even a whole header
    with pytest.raises(ExrError, match=r"cut\.exr: truncated or corrupt"):
        exr.list_channels(path)


def test_missing_channel_lists_present_ones(tmp_path):
    path = tmp_path / "f.exr"
    exr.write_frame(path, {"color": smooth_image(), "depth": smooth_image()[..., 0]})
    with pytest.raises(ExrError, match=r"f\.exr: missing channel\(s\) albedo\.R.*present: color\.B, color\.G, "
                                       r"color\.R, depth\.Z"):
        exr.read_frame(path, {"color": ("color.R", "color.G", "color.B"), "albedo": ("albedo.R", "albedo.G",
                                                                                   "albedo.B")})
    got, _ = exr.read_frame(path, {"color": ("color.R", "color.G", "color.B"), "albedo": ("albedo.R",)},
                            optional=["albedo"])
    assert set(got) == {"color"}


def test_buffers_of_different_sizes(tmp_path):
    with pytest.raises(ExrError, match=r"channel depth\.Z is 8x8 but others are 32x24"):
        exr.write_frame(tmp_path / "f.exr", {"color": smooth_image(), "depth": np.ones((8, 8), np.float32)})
    assert not list(tmp_path.iterdir())  # nothing, not even a temporary file, is left behind
    path = tmp_path / "multi.exr"
    exr.write_multipart(path, [{"color.R": np.ones((H, W))}, {"depth.Z": np.ones((8, 8))}])
    with pytest.raises(ExrError, match=r"multi\.exr: channel depth\.Z is 8x8 but others are 32x24"):
        exr.read_frame(path, {"color": ("color.R",), "depth": ("depth.Z",)})


def test_nonfinite_replaced_and_counted(tmp_path):
    img = smooth_image()
    img[0, 0, 0] = np.nan
    img[1, 2, 1] = np.inf
    img[3, 4, 2] = -np.inf
    img[5, 5, 0] = 1e30  # huge but finite HDR: never clamped
    path = tmp_path / "bad.exr"
    exr.write_frame(path, {"color": img})
    got, bad = exr.read_frame(path, {"color": ("color.R", "color.G", "color.B")})
    assert bad == 3
    c = got["color"]
    assert np.isfinite(c).all()
    assert c[0, 0, 0] == 0 and c[1, 2, 1] == exr.POS_INF_REPLACEMENT and c[3, 4, 2] == 0
    assert c[5, 5, 0] == np.float32(1e30)
    np.testing.assert_array_equal(c[10:, 10:], img[10:, 10:])


def test_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "f.exr"
    exr.write_frame(path, {"color": smooth_image()})
    before = path.read_bytes()

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(exr.OpenEXR, "File", boom)
    with pytest.raises(RuntimeError):
        exr.write_frame(path, {"color": smooth_image() * 2})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["f.exr"]
