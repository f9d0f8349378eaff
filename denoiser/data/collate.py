"""Batch assembly: items of ``[T, ...]`` buffers -> the batch dict ``[B, T, ...]`` of the contract.

In DataLoader worker processes this is torch's ``default_collate`` (which builds the batch in
shared memory for the trip to the main process). In the main process (``num_workers: 0``) the
buffers are stacked with numpy: one single-threaded copy that does not compete with the
training step's intra-op threads (torch.stack on a busy 2-core machine was 10x slower).
Items whose keys differ (e.g. some without ``reference``) are a ``UserError`` naming them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import get_worker_info
from torch.utils.data._utils.collate import default_collate

from denoiser.errors import UserError


def collate_items(items: Sequence[dict]) -> dict:
    """``[{buffer: [T, C, H, W], reset: bool[T], labeled, sequence, frame_index}]`` -> batch dict."""
    keys = list(items[0])
    for it in items[1:]:
        if list(it) != keys:
            a, b = set(keys), set(it)
            raise UserError(f"batch mixes items of {items[0].get('sequence')} and {it.get('sequence')} with "
                            f"different buffers ({', '.join(sorted(a ^ b))})")
    if get_worker_info() is not None:
        return default_collate(list(items))
    out = {}
    for k in keys:
        vals = [it[k] for it in items]
        if isinstance(vals[0], torch.Tensor) and vals[0].dtype == torch.float32:
            out[k] = torch.from_numpy(np.stack([v.numpy() for v in vals]))
        else:
            out[k] = default_collate(vals)
    return out
