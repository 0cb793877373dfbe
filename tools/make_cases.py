#!/usr/bin/env python
"""Draw fault cases from a checkpoint's test split.

    python tools/make_cases.py --ckpt CKPT --seed 0 --out cases.npz [--n-per-condition 40]       # the paper's
    python tools/make_cases.py --ckpt CKPT --protocol binding --n 100 --seed 0 --out b.npz        # binding faults

``paper`` (default): CUT / FIX / BOTH, 40 each; writes ``q_ref (B,N)``, ``cut (B,M)``, ``fix (B,M)``,
``l_fixed (B,M)`` [m, NaN where not jammed], ``cond (B,)``. ``binding``: CUT / FIX / BOTH / WEAK / BAND, ``--n``
each (default 100), every case feasible and every fault broken by the healthy command; adds ``f_max (B,M)`` [N]
and ``l_band (B,M,2)`` [m]; prints how many draws it rejected and why.
"""
from lightning_bodyschema.apps.case_tools import make_cases_main

if __name__ == "__main__":
    make_cases_main()
