#!/usr/bin/env python
"""Generate a healthy equilibrium dataset: ``q (N,nq)``, ``l_motor (N,M)``, ``f (N,M)`` in SI units, ``model_xml``.

    python tools/make_dataset.py --model paper_arm --n 800 --seed 0 --out data/paper_arm.npz
"""
from lightning_bodyschema.apps.dataset_tool import make_dataset_main

if __name__ == "__main__":
    make_dataset_main()
