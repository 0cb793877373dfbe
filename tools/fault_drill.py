#!/usr/bin/env python
"""A fault strikes the robot holding a posture in MuJoCo; the monitor finds it from the simulated sensors and the
adapter re-commands.

    python tools/fault_drill.py --ckpt CKPT --fault cut:NAME [--fault jam:NAME=L_M ...] [--at 1.0] [--seconds 4] \
        [--noise Q_RAD,L_M,F_FRAC] [--no-load-cells] [--tensorboard DIR] --out DIR
    python tools/fault_drill.py --ckpt CKPT --n 100 --seed 0 --out DIR     # 100 random drills: the table

Faults: cut:NAME, jam:NAME=L_FIXED_M, weak:NAME=F_MAX_N, band:NAME=LO_M,HI_M. One drill writes DIR/trace.csv (a
sensor log: tools/diagnose.py reads it), DIR/summary.json (detection delay, what was identified, posture errors
before the fault, after it and at rest after adaptation beside the true-fault adapter's) and DIR/drill.png.
"""
from lightning_bodyschema.apps.fault_drill import fault_drill_main

if __name__ == "__main__":
    fault_drill_main()
