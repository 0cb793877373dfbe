#!/usr/bin/env python
"""Static optimization with faults over a file of postures: tensions, motor lengths and MuJoCo activations per muscle.

    python tools/static_opt.py --config configs/myoarm.yaml --postures reach.csv --cut BIClong_tendon --out out.csv
"""
from lightning_bodyschema.apps.static_opt import static_opt_main

if __name__ == "__main__":
    static_opt_main()
