"""Coverage-guided fuzz target of the EXR reader (:mod:`denoiser.data.exr`) with atheris (libFuzzer).

The property: every input either reads or raises :class:`~denoiser.errors.ExrError`; nothing
else (another exception, a crash, a hang, an allocation past the memory limit). Each input is
written to a file and given to ``list_channels``, ``read_header`` and ``read_channels`` (which
returns float32 ``[H, W]`` arrays), and nothing may reach the terminal. The reader's Python code is instrumented for coverage; the
OpenEXR C++ library is not (its wheel is not built with ``-fsanitize=fuzzer``), so the guidance
comes from the reader's branches (magic, deep parts, dropped parts, channels) and the mutations
reach the library blind.

Usage (see docs/fuzzing.md; ``tests/data/test_exr_fuzz.py`` runs a short bounded session):

    python tests/data/fuzz_exr.py --seeds CORPUS_DIR           # write the seed files
    python tests/data/fuzz_exr.py CORPUS_DIR -max_total_time=600 -artifact_prefix=findings/
    python tests/data/fuzz_exr.py --replay findings/crash-...  # run one input without capturing output

Seeds are small real EXR files written through :mod:`denoiser.data.exr` and the OpenEXR API:
scanline in every compression, half and float channels, tiled,
multi-part (scanline and tiled), a deep scanline file, a file with NaN/Inf pixels.
"""

from __future__ import annotations

import atexit
import contextlib
import faulthandler
import io
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import OpenEXR

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

H, W = 6, 10


def _tiles(size: int, mode=OpenEXR.ONE_LEVEL) -> OpenEXR.TileDescription:
    td = OpenEXR.TileDescription()
    td.xSize = td.ySize = size
    td.mode = mode
    return td


def write_seeds(directory: Path) -> list[Path]:
    """Write the seed corpus (a few hundred bytes to a few KB each) into ``directory``."""
    from denoiser.data import exr

    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    smooth = np.stack([1 + np.sin(xx / 3 + c) * np.cos(yy / 2) for c in range(3)], -1).astype(np.float32) * 4
    frame = {"color": smooth, "depth": (yy + xx)[..., None] + 1.0, "motion": rng.uniform(-2, 2, (H, W, 2))}
    written = []

    def add(name: str, write) -> None:
        path = directory / f"seed_{name}.exr"
        write(path)
        written.append(path)

    for name in sorted(exr.COMPRESSIONS):
        if name in ("htj2k256", "htj2k32", "lj2k"):  # slow codecs: one seed is enough (below)
            continue
        add(f"scanline_{name}", lambda p, c=name: exr.write_frame(p, frame, compression=c))
    add("scanline_half_piz", lambda p: exr.write_frame(p, frame, half=True, compression="piz"))
    add("scanline_half_dwaa", lambda p: exr.write_frame(p, {"color": smooth}, half=True, compression="dwaa"))
    add("scanline_samples", lambda p: exr.write_frame(p, {"color": smooth, "samples": smooth[None].repeat(2, 0)},
                                                      compression="rle"))
    bad = smooth.copy()
    bad[0, 0, 0], bad[1, 1, 1], bad[2, 2, 2] = np.nan, np.inf, -np.inf
    add("scanline_nonfinite", lambda p: exr.write_frame(p, {"color": bad}, compression="no"))
    add("scanline_htj2k", lambda p: exr.write_frame(p, {"color": smooth}, half=True, compression="htj2k32"))
    add("multipart_scanline", lambda p: exr.write_multipart(
        p, [{"color.R": smooth[..., 0], "color.G": smooth[..., 1]}, {"depth.Z": smooth[..., 2]}], compression="zips"))

    def tiled(path: Path, parts: int, mode, compression, half: bool) -> None:
        display = (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))
        dtype = np.float16 if half else np.float32
        items = [OpenEXR.Part({"type": OpenEXR.tiledimage, "tiles": _tiles(4, mode), "name": f"part{i}",
                               "compression": compression, "displayWindow": display},
                              {f"c{i}.{s}": np.ascontiguousarray(smooth[..., k], dtype) for k, s in enumerate("RGB")})
                 for i in range(parts)]
        with OpenEXR.File(items) as f:
            f.write(str(path))

    add("tiled_zip", lambda p: tiled(p, 1, OpenEXR.ONE_LEVEL, OpenEXR.ZIP_COMPRESSION, False))
    add("tiled_half_piz", lambda p: tiled(p, 1, OpenEXR.ONE_LEVEL, OpenEXR.PIZ_COMPRESSION, True))
    add("tiled_multipart_rle", lambda p: tiled(p, 2, OpenEXR.ONE_LEVEL, OpenEXR.RLE_COMPRESSION, False))
    add("tiled_multipart_half_b44", lambda p: tiled(p, 2, OpenEXR.ONE_LEVEL, OpenEXR.B44_COMPRESSION, True))

    def deep(path: Path) -> None:
        px = np.empty((3, 4), dtype=object)
        for y, x in np.ndindex(3, 4):
            px[y, x] = np.arange(1 + (x + y) % 2, dtype=np.float32)
        with OpenEXR.File({"type": OpenEXR.deepscanline, "compression": OpenEXR.ZIPS_COMPRESSION},
                          {"Z": px, "A": px.copy()}) as f:
            f.write(str(path))

    add("deep_scanline", deep)
    return written


@contextlib.contextmanager
def terminal() -> Iterator[list[bytes]]:
    """What reaches file descriptors 1 and 2 or Python's ``sys.stdout``/``sys.stderr`` in the block."""
    printed: list[bytes] = []
    python = io.StringIO()
    with tempfile.TemporaryFile() as tmp:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            with contextlib.redirect_stdout(python), contextlib.redirect_stderr(python):
                yield printed
        finally:
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
            tmp.seek(0)
            printed.append(tmp.read() + python.getvalue().encode())


def check(data: bytes, path: Path) -> None:
    """The property for one input (raises on a violation: atheris reports it with the input).

    Each reader returns or raises ExrError, ``read_channels`` returns float32 ``[H, W]``
    arrays, and nothing reaches the terminal (the library's messages belong in the error).
    """
    from denoiser.data import exr
    from denoiser.errors import ExrError

    path.write_bytes(data)
    with terminal() as printed:
        for read in (exr.list_channels, exr.read_header):
            try:
                read(path)
            except ExrError:
                pass
        try:
            channels = exr.read_channels(path)
        except ExrError:
            channels = {}
    assert not printed[0], f"library output reached the terminal: {printed[0][:300]!r}"
    for name, arr in channels.items():
        assert isinstance(arr, np.ndarray) and arr.dtype == np.float32 and arr.ndim == 2, (name, type(arr))


def main(argv: list[str]) -> None:
    if len(argv) == 3 and argv[1] == "--seeds":
        for p in write_seeds(Path(argv[2])):
            print(p)
        return
    work = Path(tempfile.mkdtemp(prefix="fuzz_exr_"))
    atexit.register(shutil.rmtree, work, True)
    path = work / "input.exr"
    if len(argv) == 3 and argv[1] == "--replay":  # one input, the library's output not captured
        from denoiser.data import exr

        global terminal
        faulthandler.enable()
        exr.library_output = lambda: contextlib.nullcontext([""])  # the library's messages to the terminal
        terminal = lambda: contextlib.nullcontext([b""])
        check(Path(argv[2]).read_bytes(), path)
        print(f"{argv[2]}: no finding")
        return

    import atheris

    with atheris.instrument_imports(include=["denoiser"]):
        import denoiser.data.exr  # noqa: F401 - imported here to be instrumented for coverage

    def one_input(data: bytes) -> None:
        check(data, path)

    atheris.Setup(argv, one_input)
    atheris.Fuzz()  # does not return: libFuzzer exits the process


if __name__ == "__main__":
    main(sys.argv)
