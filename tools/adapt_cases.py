#!/usr/bin/env python
"""Adapt a trained schema's commands to every case of a fault-case file, in one batch.

    python tools/adapt_cases.py --ckpt CKPT --cases cases.npz --out adapted.npz \
        [--variant default|literal|guided|strong|recurrent|inpaint_box|inpaint_spring|projected] [--sampler ddpm]

Writes the five case arrays plus ``l_motor (B,M)`` [m], ``f (B,M)`` [N] and ``status (B,)``; only
``ok`` rows hold a command (other rows are NaN).
"""
from lightning_bodyschema.apps.case_tools import adapt_cases_main

if __name__ == "__main__":
    adapt_cases_main()
