#!/usr/bin/env python
"""Adaptation variants side by side (binding or paper protocol), physical reading, medians and paired intervals.

    python tools/guidance_study.py --ckpt CKPT --protocol binding --seeds 0,1,2 \
        --variants guided default 's20=default:{"n_steps": 20}' inpaint_box strong recurrent projected
"""
from lightning_bodyschema.apps.guidance_study import main

if __name__ == "__main__":
    main()
