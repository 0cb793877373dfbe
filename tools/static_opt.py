#!/usr/bin/env python
"""Static optimization with faults over a file of postures: tensions, motor lengths and MuJoCo activations per muscle;
with --motion, inverse dynamics over a motion: activations, MuJoCo excitations and tensions per frame (--track:
simulated in MuJoCo).

    python tools/static_opt.py --config configs/myoarm.yaml --postures reach.csv --cut BIClong_tendon --out out.csv
    python tools/static_opt.py --config configs/myoarm.yaml --motion reach.csv --out motion.csv --plot act.png --track
"""
from lightning_bodyschema.apps.static_opt import static_opt_main

if __name__ == "__main__":
    static_opt_main()
