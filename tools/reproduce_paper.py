#!/usr/bin/env python
"""Train (or reuse) the paper's 7 schemas, run the fault benchmark, write docs/*.png, RESULTS.md and results.json.

    python tools/reproduce_paper.py                # the paper's 10000 epochs per schema
    python tools/reproduce_paper.py --epochs 1000  # a short run
"""
from lightning_bodyschema.apps.reproduce import main

if __name__ == "__main__":
    main()
