"""Checkpoint writes that are atomic on every filesystem (a killed job never leaves a broken .ckpt).

Lightning's default ``TorchCheckpointIO`` writes a local checkpoint through an fsspec transaction:
the bytes go to a temporary file in the *system* temp directory (``TMPDIR``, usually ``/tmp``)
and are then ``shutil.move``d onto the target. When ``TMPDIR`` and the run directory are on
different filesystems (node-local ``/tmp`` and a shared cluster filesystem, the usual case on
SLURM) that move is a copy, and a job killed during the copy leaves a truncated ``last.ckpt``
under its final name. :class:`AtomicCheckpointIO` writes the temporary file next to the target
(same directory, hence same filesystem), fsyncs it and renames it into place with
``os.replace``. Remote paths (``s3://`` etc.) keep Lightning's behaviour.

Used by every trainer preset (``conf/trainer/cpu.yaml`` ``plugins``; ``gpu`` and ``ddp``
inherit it).
"""

from __future__ import annotations

from typing import Any

import torch
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol
from lightning.pytorch.plugins.io import TorchCheckpointIO

from denoiser.atomic import atomic_path


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose local saves go to ``.<name>.*.tmp`` beside the target, then ``os.replace``."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or not _is_local_file_protocol(path):
            return super().save_checkpoint(checkpoint, path, storage_options)
        with atomic_path(path, fsync=True) as tmp:
            torch.save(checkpoint, tmp)
        return None
