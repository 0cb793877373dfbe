"""LeanFusedAdam takes the same steps as torch's fused Adam, to the bit, and keeps its state layout."""
import copy

import torch

from lightning_bodyschema.networks.mlp import MLP
from lightning_bodyschema.optim import LeanFusedAdam


def _train(opt_cls, steps=60, **kwargs):
    torch.manual_seed(0)
    net = MLP(8, 32, 8, 2, "tanh")
    opt = opt_cls(net.parameters(), lr=1e-2, **kwargs)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=1e-4)
    x = torch.randn(64, 8)
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        net(x).pow(2).mean().backward()
        opt.step()
        sched.step()
    return net, opt


def test_lean_adam_matches_fused_adam_to_the_bit():
    lean, lean_opt = _train(LeanFusedAdam)
    ref, ref_opt = _train(torch.optim.Adam, fused=True)
    for a, b in zip(lean.parameters(), ref.parameters()):
        assert torch.equal(a, b)
    for a, b in zip(lean_opt.state.values(), ref_opt.state.values()):
        assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def test_lean_adam_resumes_from_a_state_dict_like_adam():
    net, opt = _train(LeanFusedAdam, steps=10)
    twin = copy.deepcopy(net)
    twin_opt = LeanFusedAdam(twin.parameters(), lr=1e-2)
    twin_opt.load_state_dict(copy.deepcopy(opt.state_dict()))  # Adam shares the tensors otherwise
    x = torch.randn(16, 8)
    for model, optimizer in ((net, opt), (twin, twin_opt)):
        optimizer.zero_grad(set_to_none=True)
        model(x).sum().backward()
        optimizer.step()
    for a, b in zip(net.parameters(), twin.parameters()):
        assert torch.equal(a, b)
