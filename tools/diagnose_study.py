#!/usr/bin/env python
"""How well a checkpoint's diagnosis names random faults in logs simulated in MuJoCo (RESULTS.md tables).

    python tools/diagnose_study.py --ckpt CKPT --out runs/diagnose_study.json [--n 200] [--seed 0] \
        [--conditions healthy,single,double] [--no-load-cells] [--end-to-end]

Each log holds 1-5 held postures of the checkpoint's held-out split with its healthy command, the faults drawn to
bind (lightning_bodyschema/diagnosis/trials.py); figures over the identifiable logs (the true body's own diagnosis
of the noise-free log names the true faults), the others counted beside them.
"""
from lightning_bodyschema.apps.diagnose_study import diagnose_study_main

if __name__ == "__main__":
    diagnose_study_main()
