"""Draw a model's arm and muscle routing at a few postures, e.g.

    python tools/draw_arm.py --model paper_arm --out docs/arm.png
    python tools/draw_arm.py --model my_robot.xml --q 0,0 --q 0.5,-0.3 --out /tmp/robot.png

Exit status 2 with one line on stderr for bad input (unknown model, posture out of range, ...).
"""
from __future__ import annotations

import argparse
import sys

import torch

from lightning_bodyschema.errors import BodySchemaInputError

DEFAULT_POSTURES = ("0,0", "0.8,0.6", "-0.7,-0.9")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="paper_arm", help="'paper_arm' or a path to an MJCF file")
    parser.add_argument("--out", default="docs/arm.png", help="output image (png, pdf, svg)")
    parser.add_argument("--q", action="append", metavar="Q1,Q2,...",
                        help="a posture [rad], comma separated; repeat for more "
                             f"(default {' '.join(DEFAULT_POSTURES)})")
    parser.add_argument("--site", default="hand", help="site to mark, e.g. the hand")
    return parser.parse_args(argv)


def parse_postures(texts) -> list[list[float]]:
    """Postures from '--q' texts; all must have the same number of joints."""
    try:
        qs = [[float(v) for v in text.split(",")] for text in texts]
    except ValueError:
        raise BodySchemaInputError(f"--q values {texts} must be comma-separated numbers like 0.8,0.6") from None
    if len({len(q) for q in qs}) > 1:
        raise BodySchemaInputError(f"--q values {texts} have different numbers of joints")
    return qs


def main(argv=None) -> int:
    torch.set_num_threads(1)
    args = parse_args(argv)
    from lightning_bodyschema.plots.arm import draw_arm
    from lightning_bodyschema.sim import MusculoskeletalModel

    try:
        model = MusculoskeletalModel(args.model)
        draw_arm(model, parse_postures(args.q or DEFAULT_POSTURES), path=args.out, site=args.site)
    except BodySchemaInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
