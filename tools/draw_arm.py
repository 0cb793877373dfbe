r"""Draw a model's arm and muscle routing at a few postures, e.g.

    python tools/draw_arm.py --model paper_arm                  # -> runs/arm.png
    python tools/draw_arm.py --model arm3_8 --out runs/arm3_8.png
    python tools/draw_arm.py --model my_robot.xml --q 0,0 --q 0.5,-0.3 --out /tmp/robot.png
    python tools/draw_arm.py --model myo:myoelbow_2dof --site wrist --out docs/myoelbow.png

The README's drawings of the MyoSuite bodies from their configs (standing, stepping and seated for the legs):

    python tools/draw_arm.py --config configs/myolegs.yaml --no-zoom --frame moving --out docs/myolegs.png \
        --q 0,0,0,0,0,0,0,0,0,0,0,0,0,0 --q 0.7,0,0,1.0,0.2,0,0,-0.3,0,0,0.2,-0.2,0,0 --q 1.5,0,0,1.5,0,0,0,1.5,0,0,1.5,0,0,0
    python tools/draw_arm.py --config configs/myolegs_osl.yaml --no-zoom --frame moving --out docs/myolegs_osl.png \
        --q 0,0,0,0,0,0,0,0,0,0 --q 0.7,0,0,-0.3,0,0,0.2,-0.2,0,0 --q 1.5,0,0,1.5,0,0,1.5,0,0,0
    python tools/draw_arm.py --config configs/myohand.yaml --no-zoom --frame moving --view-joint mcp3_flexion_r \
        --out docs/myohand.png

--config draws a config's robot: its data section's model, muscles, gravity, locked joints and fixed base, as
the data module builds it; --model, --lock and --fixed-base given beside it replace or add to those.

The default output is under runs/ (git-ignored): docs/arm.png is the README's tracked figure and is
replaced only when asked for (``--out docs/arm.png``).

Without --q, three postures placed in each joint's own range (mid-range and two bent ones; for the
paper arm's [-1, 1] ranges: 0,0  0.8,0.6  -0.7,-0.9).

Exit status 2 with one line on stderr for bad input (unknown model, posture out of range, ...).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from lightning_bodyschema.errors import BodySchemaInputError

# default postures as fractions of each joint's half range around its midpoint, cycled over the joints
DEFAULT_POSTURES_NORMALIZED = ((0.0,), (0.8, 0.6), (-0.7, -0.9))


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None,
                        help="a packaged model (paper_arm, arm3_8, opensim_like_arm), myo:<name> or a path to an MJCF "
                             "file (default: the config's data.model, else paper_arm)")
    parser.add_argument("--config", default=None, help="a config whose data section gives the robot, e.g. "
                                                       "configs/myolegs.yaml")
    parser.add_argument("--out", default="runs/arm.png", help="output image (png, pdf, svg); default runs/arm.png")
    parser.add_argument("--q", action="append", metavar="Q1,Q2,...",
                        help="a posture [rad], comma separated; repeat for more "
                             "(default: three postures spread over the model's joint ranges)")
    parser.add_argument("--site", default="hand", help="site to mark, e.g. the hand")
    parser.add_argument("--no-zoom", action="store_true", help="no close-up row per joint (for many joints)")
    parser.add_argument("--lock", action="append", metavar="JOINT=RAD", default=[],
                        help="lock a joint, e.g. --lock cmc_flexion=0 (repeat; as data.locked_joints)")
    parser.add_argument("--fixed-base", action="store_true",
                        help="hold a floating base (free joint) at the reference pose (as data.fixed_base)")
    parser.add_argument("--view-joint", default=None, metavar="JOINT",
                        help="draw in the plane perpendicular to this hinge's axis (default: the first hinge's)")
    parser.add_argument("--frame", choices=("all", "moving"), default="all",
                        help="all: show everything drawn; moving: only the bodies the free joints move")
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


def parse_locks(texts) -> dict[str, float]:
    """{joint: value} from '--lock JOINT=RAD' texts."""
    locks = {}
    for text in texts:
        name, _, value = text.partition("=")
        try:
            locks[name] = float(value)
        except ValueError:
            raise BodySchemaInputError(f"--lock {text!r} must be JOINT=RAD, e.g. cmc_flexion=0") from None
    return locks


def default_postures(q_range: np.ndarray) -> list[list[float]]:
    """Mid-range and two bent postures inside the joint ranges ``q_range (N, 2)`` [rad]."""
    mid, half = q_range.mean(axis=1), 0.5 * (q_range[:, 1] - q_range[:, 0])
    return [(mid + half * np.resize(u, len(mid))).round(3).tolist() for u in DEFAULT_POSTURES_NORMALIZED]


def robot_options(args: argparse.Namespace) -> dict:
    """``MusculoskeletalModel`` keyword arguments: the config's data section, then the command-line options."""
    from lightning_bodyschema.apps.common import config_data, robot_options as from_data

    options = from_data(config_data(args.config) if args.config else {})
    options["source"] = args.model or options["source"]
    options["locked_joints"] = {**(options["locked_joints"] or {}), **parse_locks(args.lock)}
    options["fixed_base"] = options["fixed_base"] or args.fixed_base
    return options


def main(argv=None) -> int:
    torch.set_num_threads(1)
    args = parse_args(argv)
    from lightning_bodyschema.plots.arm import draw_arm
    from lightning_bodyschema.sim import MusculoskeletalModel

    try:
        model = MusculoskeletalModel(**robot_options(args))
        qs = parse_postures(args.q) if args.q else default_postures(model.q_range)
        draw_arm(model, qs, path=args.out, site=args.site, zoom=not args.no_zoom, view_joint=args.view_joint,
                 frame=args.frame)
    except BodySchemaInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
