#!/usr/bin/env python
"""Which muscles failed, and how, from a robot's sensor log; the faults as tools/predict.py takes them.

    python tools/diagnose.py --ckpt CKPT --log LOG.csv --out diagnosis.json \
        [--noise-q-rad 1e-3] [--noise-l-m 5e-5] [--noise-f-frac 0.005]

LOG: CSV or NPZ with q_<joint>, l_<muscle>, f_<muscle> (optional per muscle), l_cmd_<muscle>, f_cmd_<muscle>,
optional t and case (README "When you don't know what broke"). Output: a JSON list, one entry per case: case,
status, muscles ({name: {kind, score, observed, and its parameter}}) and faults (cut, jam, weak, band in
tools/predict.py's keys and units). Bad input exits with code 2 and one line on stderr, and writes nothing.
"""
from lightning_bodyschema.apps.diagnose import diagnose_main

if __name__ == "__main__":
    diagnose_main()
