#!/usr/bin/env python
"""Draw the paper's fault cases (CUT / FIX / BOTH, 40 each) from a checkpoint's test split.

    python tools/make_cases.py --ckpt CKPT --seed 0 --out cases.npz [--n-per-condition 40]

Writes ``q_ref (B,N)``, ``cut (B,M)``, ``fix (B,M)``, ``l_fixed (B,M)`` [m, NaN where not jammed], ``cond (B,)``.
"""
from lightning_bodyschema.apps.case_tools import make_cases_main

if __name__ == "__main__":
    make_cases_main()
