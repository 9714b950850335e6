"""Remembering that tensors passed a check, so that unchanged tensors are not scanned again."""

from __future__ import annotations

from collections.abc import Iterable

import torch


def tensors_state(tensors: Iterable[torch.Tensor]) -> tuple | None:
    """Identity of the tensors' current values: each one's storage, torch's in-place version
    counter and layout. A tensor replaced or changed in place through torch changes it; writes
    through ``.data`` or a NumPy view do not. None when a tensor is an inference-mode tensor,
    which has no version counter (such tensors are checked every time)."""
    tensors = tuple(tensors)
    if any(t.is_inference() for t in tensors):
        return None
    return tuple((t.data_ptr(), t._version, t.shape, t.stride(), t.dtype, t.device) for t in tensors)
