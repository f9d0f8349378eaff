"""The split's id in the test ledger (:func:`denoiser.report.ledger.split_id`): the last bits of a
metadata float (numpy's camera matrix on another CPU) do not make another split; a changed value
does; rows holding the exact-float id of before 2026-12-02 still count."""

from __future__ import annotations

import json

from denoiser.report import ledger


def _split(root, value: float, seed: int = 7):
    """A split of one sequence whose sequence.json holds one float (a camera entry) and a seed."""
    seq = root / "test" / "s0"
    seq.mkdir(parents=True)
    (seq / "sequence.json").write_text(json.dumps({"cameras": [{"to_world": [[value, 0.0], [0.0, 1.0]]}],
                                                   "seeds": {"sequence": seed}, "render_seconds": {"color": 1.5}}))
    (seq / "color_0000.exr").write_bytes(b"frame")
    return root / "test"


def test_the_last_bits_of_a_float_keep_the_split(tmp_path):
    a = _split(tmp_path / "a", -0.0006964234096077559)
    b = _split(tmp_path / "b", -0.0006964234096077556)  # the same entry as another CPU computed it
    c = _split(tmp_path / "c", -0.00069642)             # another value
    d = _split(tmp_path / "d", -0.0006964234096077559, seed=8)
    assert ledger.split_id(a) == ledger.split_id(b)
    assert ledger.split_id(a, digits=None) != ledger.split_id(b, digits=None)  # the ids before the rounding
    assert len({ledger.split_id(a), ledger.split_id(c), ledger.split_id(d)}) == 3


def test_rows_of_the_exact_id_still_count(tmp_path):
    split = _split(tmp_path / "a", 0.1 + 0.2)  # 0.30000000000000004: rounding changes the id
    ids = ledger.split_ids(split)
    assert len(ids) == 2 and ids[1] == ledger.split_id(split, digits=None)
    book = tmp_path / "ledger.csv"
    for i, split_id in enumerate([ids[1], ids[0]]):  # a row from before the rounding, then one after
        look = ledger.record("data", "test", f"sha{i}", 1, ["a.ckpt"], [], "abc1234", "report", book,
                             split_id=ids if i else split_id)
    assert look == 2 and ledger.looks("sha9", book, ids) == 2
    assert [r["split_id"] for r in ledger.read(book)] == [ids[1], ids[0]]
    told = ledger.provenance("abc1234", "2026-12-02T00:00:00Z", "data", "test", "sha1", 1, look, book, ids)
    assert told["split_id"] == ids[0] and told["split_ids"] == ids
    assert "has been evaluated 2 times" in ledger.looks_line(told, book)
    assert ledger.looks("sha9", book, ids[0]) == 1  # the rounded id alone: the later row only
