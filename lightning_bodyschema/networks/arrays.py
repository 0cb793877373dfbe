"""The few operations whose spelling differs between numpy and torch, for code written once for both (the body's
snapshots, ``networks.snapshot``), and ``Frozen``: an object of arrays that ``on_host()`` copies to numpy. No
Lightning."""
from __future__ import annotations

import copy

import numpy as np
import torch


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


def product(a, b):
    """``a @ b``; numpy's by torch (its BLAS follows ``torch.set_num_threads``, numpy's OpenBLAS starts threads)."""
    if isinstance(a, np.ndarray):
        return torch.matmul(torch.from_numpy(a), torch.from_numpy(b)).cpu().numpy()
    return a @ b


def rows_product(m, w):
    """``(B, J, C)``: ``m (J, F)`` times each posture's ``w (B, F, C)`` (numpy's broadcast product; torch's one
    ``(J, F) x (F, B C)`` product by einsum, several times faster at thousands of postures)."""
    if isinstance(w, np.ndarray):
        return m @ w
    return torch.einsum("jf,bfc->bjc", m, w.contiguous())


def as_index(a):
    """Whole numbers as int64 indices."""
    return a.astype(np.int64) if isinstance(a, np.ndarray) else a.long()


def as_dtype(a, dtype):
    """``a`` in ``dtype`` (the snapshot's: numpy's or torch's spelling of it)."""
    return a.astype(dtype) if isinstance(a, np.ndarray) else a.to(dtype)


def scatter_sum(index, values, size: int):
    """``(size,)``: the sum of ``values`` at each ``index``, added in their order (numpy's weighted bincount,
    torch's ``scatter_add``: the same bits; the latter also under ``torch.vmap``)."""
    if isinstance(values, np.ndarray):
        return np.bincount(index, values, size)
    return values.new_zeros(size).scatter_add_(0, index, values)


def pick(candidates, choice):
    """``(B, M, K)``: row ``choice[b, m]`` of ``candidates (B, R, K)`` for every posture and muscle."""
    if isinstance(candidates, np.ndarray):
        return candidates[np.arange(len(choice))[:, None], choice]
    return candidates.gather(1, choice[..., None].expand(-1, -1, candidates.shape[-1]))


def offsets(x, step: int):
    """``(B, 1, 1)``: ``step`` times each row's number of ``x (B, ...)``, an integer array on x's device."""
    rows = np.arange(len(x)) if isinstance(x, np.ndarray) else torch.arange(x.shape[0], device=x.device)
    return (step * rows)[:, None, None]


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
