#!/usr/bin/env python
"""Training-step time of the structured schema's two networks for each ``block`` / ``norm`` option.

At myoArm's sizes (7 joints -> 50 lengths, and a scalar potential; width 256, 3 hidden layers, minibatch 256,
float32, one thread): both ``with_jacobian`` passes, a loss on values and Jacobians, backward, an Adam step.
The options run interleaved round by round (fair under a shared, loaded machine); prints per option the median and
the least time per step over the rounds (each round the mean of ``--steps`` steps).

    python tools/bench_structured_step.py --rounds 5 --steps 20
"""
import argparse
import time

import torch

from lightning_bodyschema.networks.structured import BLOCKS, NORMS, JacobianMLP


def make_step(block, norm, x, lengths, torques):
    torch.manual_seed(0)
    nets = torch.nn.ModuleList([JacobianMLP(7, 50, 256, 3, block, norm), JacobianMLP(7, 1, 256, 3, block, norm)])
    optimizer = torch.optim.Adam(nets.parameters(), 1e-4)

    def step():
        l_geo, G = nets[0].with_jacobian(x)
        _, dV = nets[1].with_jacobian(x)
        loss = (l_geo - lengths).pow(2).mean() + 1e-3 * G.pow(2).mean() + (dV[:, 0] - torques).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return step


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(1)
    x, lengths, torques = torch.randn(256, 7), torch.randn(256, 50), torch.randn(256, 7)
    steps = {(b, n): make_step(b, n, x, lengths, torques) for b in BLOCKS for n in NORMS}
    times = {key: [] for key in steps}
    for step in steps.values():
        for _ in range(5):
            step()
    for _ in range(args.rounds):
        for key, step in steps.items():
            start = time.perf_counter()
            for _ in range(args.steps):
                step()
            times[key].append(1e3 * (time.perf_counter() - start) / args.steps)
    for (block, norm), values in times.items():
        values = sorted(values)
        print(f"block={block:8s} norm={norm:5s} median {values[len(values) // 2]:7.1f} ms/step, "
              f"least {values[0]:7.1f} ms/step")


if __name__ == "__main__":
    main()
