#!/usr/bin/env python
"""Robustness study: the diffusion schema trained on noisy and mismatched recorded data, scored on the true model.

    python tools/robustness.py --out-dir runs/robustness          # noise 0/0.5/1/2 %, mismatch 0/5/10/20 %
    python tools/robustness.py --epochs 300 --noise 0 2 --mismatch 20 --out-dir runs/robustness-quick

Writes robustness.md (tables), robustness.png (E_tau, E_q, E_q_phys against noise and mismatch) and
robustness.json, with the datasets and checkpoints of every level, into --out-dir.
"""
from lightning_bodyschema.apps.robustness import robustness_main

if __name__ == "__main__":
    robustness_main()
