"""The operations whose spelling differs between numpy and torch (for ``networks.snapshot``'s code written once for
both) and ``Frozen``: an object of arrays that ``on_host()`` copies to numpy. No Lightning."""
from __future__ import annotations

import copy

import numpy as np
import torch

from .._arrays import namespace  # noqa: F401  (re-exported: the package's one backend switch)


def encode_q(q, lo, hi):
    """Postures ``q`` [rad] within ``[lo, hi]`` to ``[-1, 1]`` (the schemas' normalized postures; numpy arrays or
    tensors, ``lo``, ``hi`` in q's dtype)."""
    return 2.0 * (q - lo) / (hi - lo) - 1.0


def decode_q(q_n, lo, hi):
    """``encode_q``'s inverse."""
    return lo + (q_n + 1.0) * 0.5 * (hi - lo)


def horner(columns, x):
    """A polynomial per column of ``x`` from the rows of ``columns`` (the highest power first), by Horner's rule as
    numpy's polyval (the same operations); torch tensors (one ``unbind``) or numpy arrays."""
    value, *rest = columns.unbind() if torch.is_tensor(columns) else columns
    for column in rest:
        value = value * x + column
    return value


def take(a, index, axis: int):
    """``a``'s entries ``index`` along ``axis`` (numpy ``take``, torch ``index_select``: one gather each)."""
    return a.take(index, axis) if isinstance(a, np.ndarray) else a.index_select(axis, index)


def unbind(a, axis: int) -> tuple:
    """The slices of ``a`` along ``axis`` (torch's one ``unbind``; numpy's views)."""
    return a.unbind(axis) if torch.is_tensor(a) else tuple(a.swapaxes(0, axis))


def take_columns(a, index):
    """``a (B, K)``'s columns ``index``: numpy's ``take``, torch's ``gather`` (faster than ``index_select``)."""
    return a.take(index, 1) if isinstance(a, np.ndarray) else a.gather(1, index.expand(a.shape[0], -1))


def product(a, b):
    """``a @ b``; numpy's by torch (its BLAS follows ``torch.set_num_threads``, numpy's OpenBLAS starts threads)."""
    if isinstance(a, np.ndarray):
        return torch.matmul(torch.from_numpy(a), torch.from_numpy(b)).cpu().numpy()
    return a @ b


def rows_product(m, w):
    """``(B, J, C)``: ``m (J, F)`` times each posture's ``w (B, F, C)`` (numpy's broadcast product; torch's one
    ``(J, F) x (F, B C)`` product by einsum)."""
    if isinstance(w, np.ndarray):
        return m @ w
    return torch.einsum("jf,bfc->bjc", m, w.contiguous())


def clip(a, lo: float, hi: float):
    """``a`` within ``[lo, hi]``, a NaN at ``lo`` (numpy's fmax and fmin; torch's clamp of ``nan_to_num``)."""
    if isinstance(a, np.ndarray):
        return np.fmin(np.fmax(a, lo), hi)
    return torch.nan_to_num(a, nan=lo).clamp(lo, hi)


def as_dtype(a, dtype):
    """``a`` in ``dtype`` (the snapshot's: numpy's or torch's spelling of it)."""
    return a.astype(dtype) if isinstance(a, np.ndarray) else a.to(dtype)


def scatter_columns(values: list, column, flat_index, width: int):
    """``(B, P, width)``: every entry of ``values`` (K arrays ``(B, P)``) added in order onto zeros at its column
    ``column (P, K)`` (torch: one ``scatter_add``; numpy: one weighted bincount over ``flat_index (K, P)``, each
    entry's place in a ``(P, width)`` row; the same bits)."""
    n, p = values[0].shape
    if isinstance(values[0], np.ndarray):
        index = flat_index + (p * width) * np.arange(n)[:, None, None]
        return np.bincount(index.ravel(), np.stack(values, 1).ravel(), n * p * width).reshape(n, p, width)
    return values[0].new_zeros(n, p, width).scatter_add_(2, column.expand(n, -1, -1), torch.stack(values, -1))


def pick(candidates, choice):
    """``(B, M, K)``: row ``choice[b, m]`` of ``candidates (B, R, K)`` for every posture and muscle."""
    if isinstance(candidates, np.ndarray):
        return candidates[np.arange(len(choice))[:, None], choice]
    return candidates.gather(1, choice[..., None].expand(-1, -1, candidates.shape[-1]))


def apply_keeping_dtype(module, names, apply, *args, **kwargs):
    """``apply(*args, **kwargs)`` (the module's ``nn.Module._apply``) with its buffers ``names`` moved to the new device
    but kept in their dtype: a schema cast to float32 keeps its float64 coefficients and tables."""
    kept = {name: module._buffers[name] for name in names if module._buffers.get(name) is not None}
    out = apply(*args, **kwargs)
    for name, value in kept.items():
        module._buffers[name] = value.to(module._buffers[name].device)
    return out


class Frozen:
    """Arrays (torch tensors, or numpy arrays after ``on_host()``) and plain values held as attributes; ``xp`` is the
    array library they belong to (``on_host()``: numpy)."""

    xp = torch

    def on_host(self):
        """A copy in numpy over host copies of every tensor (the parts' too); never a view of a module's memory."""
        out = copy.copy(self)
        for name, value in vars(self).items():
            if torch.is_tensor(value):
                setattr(out, name, value.detach().cpu().numpy().copy())
            elif isinstance(value, Frozen):
                setattr(out, name, value.on_host())
            elif isinstance(value, list) and value and torch.is_tensor(value[0]):
                setattr(out, name, [v.detach().cpu().numpy().copy() for v in value])
            elif isinstance(value, torch.dtype):
                setattr(out, name, torch.empty(0, dtype=value).cpu().numpy().dtype)
        out.xp = np
        return out
