#!/usr/bin/env python
"""Commands for a file of requests: target postures or hand targets, each with its own faults.

    python tools/predict.py --ckpt CKPT --requests requests.yaml --out commands.json \
        [--evaluate] [--variant default|literal] [--sampler ddpm] [--site hand] [--reach-tol-mm 0.1]

Requests: YAML / JSON (a list of {q_ref | target, cut, jam, weak, band}) or NPZ (q_ref / target arrays plus
fault arrays; a tools/make_cases.py file works). Output: .npz or .json by extension, written atomically;
only ``ok`` rows hold a command. ``--evaluate`` adds feasible, E_cut, E_fix, E_tau, E_q, E_weak, E_band and
the MuJoCo settle check's E_q_phys. See ``lightning_bodyschema/apps/predict.py`` for the formats.
Bad requests exit with code 2 and one line on stderr, and write nothing.
"""
from lightning_bodyschema.apps.predict import predict_main

if __name__ == "__main__":
    predict_main()
