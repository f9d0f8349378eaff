"""Tiny procedural sequences written as real native-layout EXR files, for the command tests.

The content is analytic (so it is cheap and deterministic) but everything else is real: EXR
frames with every buffer of docs/design.md §3.1 and a validated ``sequence.json``, read back through
the data layer. The camera pans ``shift`` pixels per frame to the left, so the backward motion
is ``(+shift, 0)`` everywhere; the noisy color is the reference times a Gamma(spp)/spp factor
per pixel (the statistics of a mean of ``spp`` exponential samples), plus rare fireflies.
"""

from __future__ import annotations

from helpers.eval_data import write_dataset


def test_written_dataset_reads_back_through_the_data_layer(tmp_path):
    from denoiser.data.dataset import SequenceDataset, index_split
    from denoiser.data.layouts import NativeLayout

    root = write_dataset(tmp_path, sequences=1, frames=3, size=(16, 24), cuts=(2,))
    layout = NativeLayout({"color": ["color.R", "color.G", "color.B"], "reference": ["reference.R", "reference.G",
                                                                                     "reference.B"],
                           "motion": ["motion.X", "motion.Y"]})
    sources = index_split(layout, root, "test")
    assert [s.name for s in sources] == ["test/seq_000"] and sources[0].cuts == (2,)
    item = SequenceDataset(sources, layout, ["color", "motion"])[0]
    assert item["color"].shape == (3, 3, 16, 24) and item["reset"].tolist() == [True, False, True]
    assert float(item["motion"][1, 0].mean()) == 1.0 and float(item["reference"].min()) > 0
