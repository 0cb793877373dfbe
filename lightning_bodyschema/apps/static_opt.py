"""``tools/static_opt.py``: static optimization with faults over a file of postures (``statics``), written per muscle.

Postures: a CSV (header of joint names, one row per posture; ``#`` lines are comments) or an NPZ (one 1-D array per
joint), SI units (rad, m). A column is a free joint of the body, named bare (``elbow_flexion_r``) or as the
recorded-data format does (``q_elbow_flexion_r``). Faults from flags or a JSON/YAML file. Output: ``.csv`` (the
posture, ``status``, ``status_code``, then ``<muscle>.tension_n``, ``<muscle>.activation``, ``<muscle>.l_motor_m``
per muscle) or ``.npz`` (arrays ``q``, ``tension_n``, ``activation``, ``l_motor_m``, ``status``, ``status_code``,
``joints``, ``muscles``, ``objective``), written to a temporary name and renamed. ``--motion`` (a motion file instead
of postures): ``apps.motion_opt``.
"""
from __future__ import annotations

import csv
import io
import os

import numpy as np

from ..errors import BodySchemaInputError, did_you_mean
from ..notes import notes_held
from ..status import status_codes, status_names
from .common import argument_parser, config_data, exits_cleanly, robot_options, write_bytes, write_npz
from .posture_files import concatenate, postures_of, read_posture_columns

EXAMPLE = """example:
  python tools/static_opt.py --config configs/myoarm.yaml --postures reach.csv --cut BIClong_tendon \\
      --out reach_tensions.csv
  python tools/static_opt.py --model myo:myolegs --fixed-base --postures squat.npz \\
      --weak soleus_r_tendon=800 --out legs.npz
  python tools/static_opt.py --config configs/myoarm.yaml --motion reach.csv --cut BIClong_tendon \
      --out reach_motion.csv --plot reach_activations.png --track
"""
CHUNK = 256  # postures per solve: the progress bar's step
_EXAMPLES = {"--jam": "BIClong_tendon=0.21", "--weak": "BIClong_tendon=300", "--lock": "elbow_flexion_r=1.2"}


def _name_value(text: str, flag: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = np.nan
    if not sep or not name or not np.isfinite(number):
        raise BodySchemaInputError(f"{flag} {text!r}: expected NAME=NUMBER (SI units), e.g. {flag} {_EXAMPLES[flag]}")
    return name, number


def read_faults(args) -> dict:
    """``{"cut": [...], "jam": {...}, "weak": {...}, "band": {...}}`` from --faults FILE, then the flags."""
    faults = {"cut": [], "jam": {}, "weak": {}, "band": {}}
    if args.faults:
        faults = _faults_file(args.faults, faults)
    faults["cut"] = list(faults["cut"]) + list(args.cut)
    faults["jam"].update(_name_value(t, "--jam") for t in args.jam)
    faults["weak"].update(_name_value(t, "--weak") for t in args.weak)
    return faults


def _faults_file(path: str, faults: dict) -> dict:
    import yaml  # reads JSON too

    if not os.path.isfile(path):
        raise BodySchemaInputError(f"--faults {path!r} does not exist")
    with open(path) as fh:
        try:
            doc = yaml.safe_load(fh) or {}
        except yaml.YAMLError as err:
            raise BodySchemaInputError(f"--faults {path!r} is not JSON/YAML: {str(err).splitlines()[0]}") from None
    unknown = sorted(set(doc) - set(faults)) if isinstance(doc, dict) else ["(not a mapping)"]
    if unknown:
        raise BodySchemaInputError(f"--faults {path!r}: unknown keys {unknown}; allowed: {sorted(faults)}")
    return {key: doc.get(key, default) for key, default in faults.items()}


def read_postures(path: str, model) -> np.ndarray:
    """(B, N) postures of ``model``'s free joints from a CSV or NPZ with one column per joint (module docstring)."""
    return postures_of(read_posture_columns(path), model.joint_names, path)


def check_fault_names(faults: dict, muscles: list, what: str = "the body's muscles") -> None:
    """Every muscle a fault names is one of ``muscles`` (what ``StaticBody.fault_batch`` checks, with a body)."""
    named = list(faults["cut"]) + [name for key in ("jam", "weak", "band") for name in faults[key]]
    for name in named:
        if isinstance(name, str) and name not in muscles:
            raise BodySchemaInputError(f"unknown muscle {name!r}{did_you_mean(name, muscles)}; {what} are "
                                       f"{list(muscles)}")


def _csv_text(result) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    fields = [("tension_n", result.tension_n), ("activation", result.activation), ("l_motor_m", result.l_motor_m)]
    fields = [(label, values) for label, values in fields if values is not None]
    writer.writerow(list(result.joints) + ["status", "status_code"]
                    + [f"{m}.{label}" for m in result.muscles for label, _ in fields])
    per_muscle = np.stack([values for _, values in fields], axis=2).reshape(len(result.q), -1)
    for q, name, code, values in zip(result.q, status_names(result.status), status_codes(result.status), per_muscle):
        writer.writerow([repr(float(v)) for v in q] + [name, int(code)] + [repr(float(v)) for v in values])
    return buffer.getvalue()


def write_result(path: str, result) -> None:
    """The result as ``.csv`` or ``.npz`` (module docstring), atomically."""
    if path.endswith(".csv"):
        return write_bytes(path, _csv_text(result).encode())
    arrays = {"q": result.q, "tension_n": result.tension_n, "l_motor_m": result.l_motor_m,
              "status": status_names(result.status), "status_code": status_codes(result.status),
              "joints": np.array(result.joints, dtype=str), "muscles": np.array(result.muscles, dtype=str),
              "objective": np.array(result.objective)}
    if result.activation is not None:
        arrays["activation"] = result.activation
    write_npz(path, arrays)


def _parser():
    import argparse

    parser = argument_parser("Static optimization with faults: the muscle tensions, motor lengths and MuJoCo muscle "
                             "activations that hold each posture of a file, with a status per posture.")
    parser.formatter_class, parser.epilog = argparse.RawDescriptionHelpFormatter, EXAMPLE
    parser.add_argument("--model", default="paper_arm",
                        help="packaged name, myo:<name> (needs myo-sim) or an MJCF path")
    parser.add_argument("--config", help="take the body from a config's data section (model, muscles, gravity, "
                        "locked_joints, fixed_base, spring constants) instead of --model")
    parser.add_argument("--fixed-base", action="store_true", help="weld a floating base (e.g. myo:myolegs's pelvis)")
    parser.add_argument("--lock", action="append", default=[], metavar="JOINT=VALUE",
                        help="lock a joint at a value [rad or m]; repeatable")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--postures", help="CSV or NPZ, one column per free joint (SI units)")
    source.add_argument("--motion", help="a motion: CSV or NPZ with a t column [s] and one column per free joint "
                        "(optional qvel_<joint>, qacc_<joint> columns), or an OpenSim .mot; inverse dynamics per frame")
    parser.add_argument("--out", required=True, help="output file: .csv, else .npz")
    parser.add_argument("--cut", action="append", default=[], metavar="MUSCLE", help="a ruptured muscle; repeatable")
    parser.add_argument("--jam", action="append", default=[], metavar="MUSCLE=L_FIXED_M",
                        help="a jammed motor: l_motor <= L_FIXED_M [m]; repeatable")
    parser.add_argument("--weak", action="append", default=[], metavar="MUSCLE=F_MAX_N",
                        help="a weakened muscle: tension <= F_MAX_N [N]; repeatable")
    parser.add_argument("--faults", help="JSON/YAML file {cut: [...], jam: {...}, weak: {...}, band: {m: [lo, hi]}}")
    parser.add_argument("--objective", choices=["activation", "tension"], help="min sum a^2 (default with MuJoCo "
                        "muscle actuators) or min sum f^2 (default otherwise)")
    parser.add_argument("--solver", choices=["newton", "proxqp"], default="newton")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    motion = parser.add_argument_group("motions (--motion)")
    motion.add_argument("--residual", action="append", default=[], metavar="JOINT",
                        help="a residual actuator on this free joint (reported per frame); repeatable (a floating root always has its own)")
    motion.add_argument("--residual-weight", type=float, default=1.0,
                        help="objective weight per (N m)^2 of residual torque (default 1: 1 N m costs as much as one "
                             "muscle at full activation)")
    motion.add_argument("--smooth-window", type=float, default=0.05, metavar="SECONDS",
                        help="the Savitzky-Golay differentiator's window for velocities and accelerations the file "
                             "does not give (degree 3)")
    motion.add_argument("--plot", help="write a plot of the activations over time (PNG)")
    motion.add_argument("--track", action="store_true", help="simulate the motion in MuJoCo by computed muscle "
                        "control and open loop; print the tracking error and the per-step solve cost")
    motion.add_argument("--control-step", type=float, metavar="SECONDS",
                        help="--track's control step (default the model's timestep)")
    motion.add_argument("--device", default=None, help="the QP's torch device, e.g. cuda (default the CPU)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="threads for MuJoCo's kinematics (default: every core; the same answers for any count)")
    return parser


def _body(data: dict, locks: dict, args):
    from ..statics import StaticBody

    options = robot_options(data)
    locks = {**dict(options.pop("locked_joints") or {}), **locks}
    # a motion may move a floating root (its columns in the file); statics welds it, the dynamics puts it back
    options["fixed_base"] = options["fixed_base"] or args.fixed_base or bool(args.motion)
    return StaticBody(options.pop("source"), locked_joints=locks, k_n=data.get("k_n"),
                      alpha_per_m=data.get("alpha_per_m", 20.0), f_max_n=data.get("f_max_n"), threads=args.threads,
                      **options)


@exits_cleanly
@notes_held(lambda: os.path.join(_cache_root(), "logs", "static_opt.log"))
def static_opt_main(argv=None):
    args = _parser().parse_args(argv)
    if os.path.isdir(args.out):
        raise BodySchemaInputError(f"--out {args.out!r} is a directory; give a file path such as tensions.csv")
    faults = read_faults(args)
    locks = dict(_name_value(t, "--lock") for t in args.lock)
    _check_motion_options(args)
    columns = read_posture_columns(args.postures) if args.postures else None
    data = config_data(args.config) if args.config else {"model": args.model, "fixed_base": args.fixed_base}
    known = _remembered_names(data, args)  # the names of this body when it was built before: checked at once
    if known is not None:
        if columns is not None:
            postures_of(columns, known["joints"], args.postures)
        check_fault_names(faults, known["muscles"])
    else:  # a first run: every tendon of the parsed MJCF (seconds, no compile) bounds the muscles a fault may name
        check_fault_names(faults, _spec_tendons(data), "the model's tendons")
    print("building the body (MuJoCo model, muscle paths; a MyoSuite body takes ~15-60 s on 2 cores)", flush=True)
    body = _body(data, locks, args)
    _remember_names(data, args, body.model)
    if args.motion:
        return _motion(body, faults, args)
    q = postures_of(columns, body.model.joint_names, args.postures)
    body.model.check_q(q, within_range=True)
    body.fault_batch(faults, 1)  # names checked before any solve
    result = _solve(body, q, faults, args)
    write_result(args.out, result)
    counts = dict(zip(*np.unique(status_names(result.status), return_counts=True)))
    print(f"wrote {args.out}: {len(q)} postures, {len(result.muscles)} muscles, objective {result.objective}; "
          + ", ".join(f"{k} {int(v)}" for k, v in counts.items()))


def _check_motion_options(args) -> None:
    """Motion options need --motion; checked before the body is built."""
    given = [flag for flag, value in (("--residual", args.residual), ("--plot", args.plot), ("--track", args.track),
                                      ("--control-step", args.control_step)) if value]
    if given and not args.motion:
        verb = "needs" if len(given) == 1 else "need"
        raise BodySchemaInputError(f"{', '.join(given)} {verb} --motion (a motion file), not --postures")
    if args.motion and not os.path.isfile(args.motion):
        raise BodySchemaInputError(f"--motion {args.motion!r} does not exist")


def _motion(body, faults, args):
    from .motion_opt import plot_activations, solve_file, track_file, write_motion

    body.fault_batch(faults, 1)  # names checked before any solve
    result = solve_file(body, args, faults)
    write_motion(args.out, result)
    counts = dict(zip(*np.unique(status_names(result.status), return_counts=True)))
    clipped = 0 if result.control_clipped is None else int(result.control_clipped.any(1).sum())
    print(f"wrote {args.out}: {len(result.q)} frames over {result.t[-1] - result.t[0]:.4g} s, {len(result.muscles)} "
          f"muscles, objective {result.objective}; " + ", ".join(f"{k} {int(v)}" for k, v in counts.items())
          + f"; {clipped} frames with an excitation clipped to [0, 1]")
    if args.plot:
        plot_activations(result, args.plot)
        print(f"wrote {args.plot}")
    if args.track:
        print(track_file(body, result, faults, args))


def _solve(body, q, faults, args):
    from tqdm.auto import tqdm

    parts = []
    with tqdm(total=len(q), desc="postures", unit="posture", disable=args.no_progress or len(q) <= CHUNK) as bar:
        for start in range(0, len(q), CHUNK):
            parts.append(body.solve(q[start:start + CHUNK], faults, args.objective, solver=args.solver))
            bar.update(len(parts[-1].q))
    return concatenate(parts)


def _spec_tendons(data: dict) -> list:
    """The names of every tendon of the MJCF ``data["model"]`` names, parsed without compiling it: a superset of the
    body's muscles (the build leaves out those that cross no free joint, which its own check then names)."""
    from ..sim.mjcf import load_spec, quiet_attach_warnings

    with quiet_attach_warnings():
        return [tendon.name for tendon in load_spec(data["model"]).tendons]


def _names_file(data: dict, args) -> str:
    """Where the joint and muscle names of the body ``data`` and ``args`` describe are remembered: a file named by a
    hash of everything that decides them (options, locks, model file bytes, package and MuJoCo versions)."""
    import hashlib
    import json
    from importlib.metadata import PackageNotFoundError, version

    from .. import __version__

    def installed(name):
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    source = str(data.get("model", "paper_arm"))
    model_bytes = open(source, "rb").read() if os.path.isfile(source) else b""
    key = json.dumps([{k: data.get(k) for k in ("model", "muscles", "gravity", "locked_joints", "fixed_base")},
                      args.fixed_base, sorted(args.lock), hashlib.sha256(model_bytes).hexdigest(), __version__,
                      installed("mujoco"), installed("myo-sim")], sort_keys=True, default=str)
    return os.path.join(_cache_root(), "body_names", hashlib.sha256(key.encode()).hexdigest() + ".json")


def _cache_root() -> str:
    """``$BODYSCHEMA_CACHE_DIR``, else ``$XDG_CACHE_HOME/lightning_bodyschema`` (``~/.cache/lightning_bodyschema``)."""
    if os.environ.get("BODYSCHEMA_CACHE_DIR"):
        return os.environ["BODYSCHEMA_CACHE_DIR"]
    return os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
                        "lightning_bodyschema")


def _remembered_names(data: dict, args):
    """``{"joints": [...], "muscles": [...]}`` of this body from an earlier run, or None (never built, unreadable)."""
    import json

    try:
        with open(_names_file(data, args)) as fh:
            names = json.load(fh)
        return names if set(names) == {"joints", "muscles"} else None
    except (OSError, ValueError):
        return None


def _remember_names(data: dict, args, model) -> None:
    """Keep the body's names for the next run's checks (best effort: a cache that cannot be written is skipped)."""
    import json

    from ..npz import atomic_write_bytes

    path = _names_file(data, args)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        text = json.dumps({"joints": list(model.joint_names), "muscles": list(model.muscle_names)})
        atomic_write_bytes(path, text.encode())
    except OSError:
        pass
