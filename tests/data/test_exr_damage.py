"""EXR reader on files it must refuse: deep images, damaged multi-part files, and the library's own chatter.

Every file is real: written with the OpenEXR Python API (deep scanline and deep tiled parts
included), then damaged byte by byte where needed. The damage helpers follow the OpenEXR file
layout (https://openexr.com/en/latest/OpenEXRFileLayout.html):

* magic ``76 2f 31 01`` (4 bytes), version and flags (4 bytes, little endian; bit ``0x1000``
  = multi-part);
* the headers: each a list of attributes ``name\\0 type\\0 size(int32) value[size]`` ended by a
  null byte; a multi-part file ends the list of headers with one more null byte (an empty
  header);
* the offset tables: for each part in order, ``chunkCount`` uint64 file offsets of its chunks;
* the chunks: in a multi-part file each starts with its part number (int32), then for a tiled
  part the tile x, y, level x, level y (int32 each) and the packed size (int32), then the data.
"""

from __future__ import annotations

import struct
import threading
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from denoiser.data import exr
from denoiser.errors import ExrError

H, W = 16, 24
MULTI_PART = 0x1000


def tile_description(size: int = 8) -> OpenEXR.TileDescription:
    td = OpenEXR.TileDescription()
    td.xSize = td.ySize = size
    return td


def deep_pixels(h: int = 3, w: int = 4) -> np.ndarray:
    """A deep channel: ``[h, w]`` object array of float32 sample arrays (1 to 3 samples per pixel)."""
    px = np.empty((h, w), dtype=object)
    for y, x in np.ndindex(h, w):
        px[y, x] = np.arange((y * w + x) % 3 + 1, dtype=np.float32)
    return px


def write_deep(path: Path, storage) -> Path:
    header = {"type": storage, "compression": OpenEXR.ZIPS_COMPRESSION}
    if storage == OpenEXR.deeptile:
        header["tiles"] = tile_description(2)
    with OpenEXR.File(header, {c: deep_pixels() for c in ("color.R", "color.G", "color.B")}) as f:
        f.write(str(path))
    return path


def write_tiled_multipart(path: Path, seed: int = 0) -> dict[str, np.ndarray]:
    """Two tiled parts (``color.R/G/B`` then ``depth.Z``, 8x8 tiles: 6 chunks each); returns the channels."""
    rng = np.random.default_rng(seed)
    display = (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))
    channels = [{c: rng.random((H, W), dtype=np.float32) for c in names}
                for names in (("color.R", "color.G", "color.B"), ("depth.Z",))]
    parts = [OpenEXR.Part({"type": OpenEXR.tiledimage, "tiles": tile_description(), "name": f"part{i}",
                           "compression": OpenEXR.ZIP_COMPRESSION, "displayWindow": display}, dict(chans))
             for i, chans in enumerate(channels)]  # (a copy: OpenEXR.Part turns the arrays into Channels in place)
    with OpenEXR.File(parts) as f:
        f.write(str(path))
    return {k: v for chans in channels for k, v in chans.items()}


def offset_tables(data: bytes) -> tuple[int, list[list[int]]]:
    """``(start of the offset tables, [chunk offsets of each part])`` of an EXR file (layout above)."""
    multi = bool(struct.unpack_from("<I", data, 4)[0] & MULTI_PART)
    pos, counts = 8, []
    while True:
        count = None
        while data[pos] != 0:  # the attributes of one header
            name_end = data.index(b"\0", pos)
            type_end = data.index(b"\0", name_end + 1)
            size = struct.unpack_from("<i", data, type_end + 1)[0]
            if data[pos:name_end] == b"chunkCount":
                count = struct.unpack_from("<i", data, type_end + 5)[0]
            pos = type_end + 5 + size
        pos += 1
        counts.append(count)
        if not multi or data[pos] == 0:
            break
    start = pos + 1 if multi else pos
    offsets, at = [], start
    for count in counts:
        offsets.append(list(struct.unpack_from(f"<{count}Q", data, at)))
        at += 8 * count
    return start, offsets


# ----------------------------------------------------------------------------- deep images


@pytest.mark.parametrize("storage", [OpenEXR.deepscanline, OpenEXR.deeptile], ids=["scanline", "tiled"])
def test_deep_images_are_refused(tmp_path, storage, capfd):
    path = write_deep(tmp_path / "deep.exr", storage)
    assert OpenEXR.File(str(path), header_only=True).parts[0].type() == storage  # really a deep file
    expected = f"{path}: deep EXR images are not supported (part 0 is {storage.name})"
    for read in (exr.read_channels, exr.list_channels, exr.read_header,
                 lambda p: exr.read_frame(p, {"color": ("color.R", "color.G", "color.B")})):
        with pytest.raises(ExrError) as info:
            read(path)
        assert str(info.value) == expected
    assert capfd.readouterr() == ("", "")


def test_deep_part_in_a_multipart_file_is_refused(tmp_path):
    display = (np.array([0, 0], np.int32), np.array([3, 2], np.int32))
    flat = OpenEXR.Part({"type": OpenEXR.scanlineimage, "name": "flat", "displayWindow": display},
                        {"color.R": np.ones((3, 4), np.float32)})
    deep = OpenEXR.Part({"type": OpenEXR.deepscanline, "name": "deep", "compression": OpenEXR.ZIPS_COMPRESSION,
                         "displayWindow": display}, {"depth.Z": deep_pixels()})
    path = tmp_path / "mixed.exr"
    with OpenEXR.File([flat, deep]) as f:
        f.write(str(path))
    with pytest.raises(ExrError) as info:
        exr.read_channels(path, ["color.R"])  # even when the channels asked for are in the flat part
    assert str(info.value) == f"{path}: deep EXR images are not supported (part 1 is deepscanline)"


# ----------------------------------------------------------------------------- damaged parts


def test_tiled_multipart_reads_back(tmp_path):
    """The undamaged file of the cases below reads whole (so the failures below are the damage's)."""
    path = tmp_path / "multi.exr"
    channels = write_tiled_multipart(path)
    got = exr.read_channels(path)
    assert set(got) == set(channels)
    for k, v in channels.items():
        np.testing.assert_array_equal(got[k], v)
    _, offsets = offset_tables(path.read_bytes())
    assert [len(o) for o in offsets] == [6, 6]


def _bad_part_number(data: bytearray, offsets: list[list[int]]) -> None:
    for off in offsets[1]:  # every chunk of part 1 claims to belong to part 99
        struct.pack_into("<i", data, off, 99)


def _cut_in_part_1(data: bytearray, offsets: list[list[int]]) -> None:
    del data[offsets[1][2]:]  # the file ends in the middle of part 1's chunks


@pytest.mark.parametrize("damage, library_says", [
    (_bad_part_number, ("(EXR_ERR_BAD_CHUNK_LEADER) Corrupt tile (0, 0), level (0, 0) (chunk 0): bad part number "
                        "(99, expect 1)")),
    (_cut_in_part_1, "corrupt chunk table"),
], ids=["bad_chunk_leader", "truncated_part"])
def test_damaged_second_part_fails_the_whole_read(tmp_path, capfd, damage, library_says):
    path = tmp_path / "multi.exr"
    write_tiled_multipart(path)
    data = bytearray(path.read_bytes())
    damage(data, offset_tables(bytes(data))[1])
    path.write_bytes(bytes(data))
    for names in (None, ["color.R"], ["depth.Z"]):  # the channels of the good part 0 too
        with pytest.raises(ExrError) as info:
            exr.read_channels(path, names)
        message = str(info.value)
        assert message.startswith(f"{path}: truncated or corrupt EXR (part 1 of 2 unreadable: ")
        assert library_says in message and "\n" not in message
    # the library's messages went into the error, none to the terminal
    assert capfd.readouterr() == ("", "")


def test_concurrent_reads_keep_their_own_messages(tmp_path, capfd):
    """Reads in several threads: each error carries its own file's message, good files read whole."""
    good = tmp_path / "good.exr"
    channels = write_tiled_multipart(good)
    bad = []
    for i in range(4):
        path = tmp_path / f"bad{i}.exr"
        data = bytearray(good.read_bytes())
        _, offsets = offset_tables(bytes(data))
        for off in offsets[1]:
            struct.pack_into("<i", data, off, 90 + i)
        path.write_bytes(bytes(data))
        bad.append(path)
    results: dict[str, object] = {}

    def read(path: Path) -> None:
        for _ in range(5):
            try:
                results[f"{path.name}"] = exr.read_channels(path)
            except ExrError as exc:
                results[f"{path.name}"] = str(exc)

    threads = [threading.Thread(target=read, args=(p,)) for p in [good, *bad, good]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    np.testing.assert_array_equal(results["good.exr"]["depth.Z"], channels["depth.Z"])
    for i, path in enumerate(bad):
        assert f"bad part number ({90 + i}, expect 1)" in results[path.name]
        assert all(f"bad part number ({90 + j}," not in results[path.name] for j in range(4) if j != i)
    assert capfd.readouterr() == ("", "")


# ----------------------------------------------------------------------------- fuzzer findings


def test_channel_name_that_is_not_utf8(tmp_path, capfd):
    """Found by tests/data/fuzz_exr.py: the bindings decode channel names lazily and raised UnicodeDecodeError."""
    path = tmp_path / "name.exr"
    exr.write_frame(path, {"color": np.ones((H, W, 3), np.float32)}, compression="no")
    data = path.read_bytes()
    assert data.count(b"color.G\0") == 1
    path.write_bytes(data.replace(b"color.G\0", b"c\x9flor.G\0"))
    for read in (exr.list_channels, exr.read_channels):
        with pytest.raises(ExrError, match=r"name\.exr: truncated or corrupt EXR \(.*utf-8.*can't decode byte 0x9f"):
            read(path)
    assert capfd.readouterr() == ("", "")


def test_absurd_tile_size_is_refused_before_allocating(tmp_path, capfd):
    """Found by tests/data/fuzz_exr.py: a ~1.7 KB file whose header declares 8 x 83886084 tiles made the library
    allocate gigabytes for one tile (an out-of-memory finding). The reader sets OpenEXR's own size limits."""
    import resource

    path = tmp_path / "tiles.exr"
    write_tiled_multipart(path)
    data = bytearray(path.read_bytes())
    at = data.index(b"tiles\0tiledesc\0") + len(b"tiles\0tiledesc\0") + 4  # the value: xSize, ySize (uint32), mode
    assert struct.unpack_from("<II", data, at) == (8, 8)
    struct.pack_into("<I", data, at + 4, 83886084)
    path.write_bytes(bytes(data))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for read in (exr.list_channels, exr.read_channels):
        with pytest.raises(ExrError, match=r"tiles\.exr: truncated or corrupt EXR \(Unable to open '.*' for read\)$"):
            read(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB: no gigabyte buffer
    assert capfd.readouterr() == ("", "")
