"""``training.finite.all_finite``: the per-step gradient check, on its fast path (a private torch op) and its public
fallback. If torch changes or drops ``_amp_foreach_non_finite_check_and_unscale_``, the first test fails loudly:
the fallback still gives correct answers (the second test), but each training step then pays ~6x for the check."""
import pytest
import torch

from lightning_bodyschema.training import finite
from lightning_bodyschema.training.finite import all_finite

DTYPES = [torch.float32, torch.float64, torch.bfloat16, torch.float16]


def test_the_fast_path_exists_and_is_used(monkeypatch):
    assert finite._AMP_CHECK is not None, "torch._amp_foreach_non_finite_check_and_unscale_ is gone: see training/finite.py"
    calls = []
    op = torch._amp_foreach_non_finite_check_and_unscale_
    monkeypatch.setattr(finite, "_AMP_CHECK", lambda *args: calls.append(args) or op(*args))
    assert all_finite([torch.ones(3)]) and len(calls) == 1


@pytest.mark.parametrize("fast", [True, False], ids=["fast", "public"])
@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("bad", [None, float("inf"), float("-inf"), float("nan")])
def test_inf_and_nan_are_found_and_finite_values_left_bit_identical(fast, dtype, bad):
    gen = torch.Generator().manual_seed(0)
    grads = [torch.randn(91, 13, generator=gen).to(dtype) * 1e3, torch.randn(91, generator=gen).to(dtype)]
    if bad is not None:
        grads[1][17] = bad
    before = [g.clone() for g in grads]
    assert all_finite(grads, fast=fast) is (bad is None)
    assert torch.equal(grads[0], before[0])  # the check must not change what the optimizer is about to apply


def test_mixed_dtypes_and_empty():
    assert all_finite([])
    assert all_finite([torch.ones(2), torch.ones(2, dtype=torch.float64)])
    assert not all_finite([torch.ones(2), torch.tensor([1.0, float("nan")], dtype=torch.float64)])
