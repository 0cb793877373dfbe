"""The one way a tensor leaves torch for numpy: ``to_numpy``.

A tensor may live on any device (CUDA, in a schema moved with ``.to("cuda")``) and may require grad; numpy sees
only host memory. Every numpy boundary of the package goes through ``to_numpy`` (or moves the tensor to the host
with ``.cpu()`` right before converting it): ``tests/training/test_numpy_boundary.py`` checks both, in the source
and with a tensor that refuses the conversion unless it was moved to the host first.
"""
from __future__ import annotations

import numpy as np
import torch


def to_numpy(value, dtype=None) -> np.ndarray:
    """``value`` as a numpy array on the host: a tensor is detached and copied from its device; anything else goes
    through ``np.asarray``. ``dtype``: the array's dtype (None: keep the value's; bfloat16, which numpy lacks,
    becomes float32)."""
    if torch.is_tensor(value):
        value = value.detach()
        value = value.float() if value.dtype == torch.bfloat16 else value
        value = value.cpu().numpy()
    return np.asarray(value, dtype=dtype)
