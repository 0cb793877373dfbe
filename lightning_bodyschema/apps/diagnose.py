"""``tools/diagnose.py``: which muscles failed in each log of a sensor log file, as JSON that ``tools/predict.py``
takes as its faults (diagnose, then adapt: two commands)."""
from __future__ import annotations

import json
import os
import time

from ..errors import BodySchemaInputError
from .common import argument_parser, check_out, count_values, exits_cleanly, load_checked_schema, torch_one_thread


def diagnosis_json(diagnosis, meta: dict) -> str:
    """Strict JSON: a list, one entry per log (``Diagnosis.records``), each with ``meta`` beside it."""
    entries = [json.dumps({**record, **meta}, allow_nan=False) for record in diagnosis.records()]
    return "[\n" + ",\n".join(entries) + "\n]\n"


def _parser():
    parser = argument_parser("Diagnose a robot's sensor logs (what it sent, what its sensors read): per log a status "
                             "(no_fault, identified, ambiguous, not_identifiable), per muscle its kind (healthy, cut, "
                             "jam, weak, band), a score and its parameter, and the faults in tools/predict.py's keys "
                             "(.json).", checkpoint=True, device=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--log", required=True, help="sensor log (.csv or .npz; README 'When you don't know what "
                                                     "broke' gives the columns)")
    parser.add_argument("--out", required=True, help="diagnosis file (.json), written only if all succeeds")
    parser.add_argument("--noise-q-rad", type=float, default=1e-3, help="joint reading noise, one sigma [rad]")
    parser.add_argument("--noise-l-m", type=float, default=5e-5, help="motor encoder noise, one sigma [m]")
    parser.add_argument("--noise-f-frac", type=float, default=0.005,
                        help="load cell noise, one sigma, as a fraction of each muscle's f_max")
    return parser


@exits_cleanly
def diagnose_main(argv=None):
    args = _parser().parse_args(argv)
    start = time.perf_counter()
    from ..diagnosis import SensorNoise, read_sensor_log

    noise = SensorNoise(args.noise_q_rad, args.noise_l_m, args.noise_f_frac)
    if not os.path.isfile(args.log):
        raise BodySchemaInputError(f"--log {args.log!r} does not exist")
    if os.path.splitext(args.out)[1].lower() != ".json":
        raise BodySchemaInputError(f"--out {args.out!r}: the diagnosis is written as JSON; give a .json path")
    check_out(args.out, args.ckpt)
    if os.path.abspath(args.out) == os.path.abspath(args.log):
        raise BodySchemaInputError(f"--out {args.out!r} is the log itself; give another file")
    torch_one_thread()
    schema = load_checked_schema(args)
    log = read_sensor_log(args.log, schema.robot_model.joint_names, schema.robot_model.muscle_names)
    diagnosis = schema.diagnose(log, noise)
    text = diagnosis_json(diagnosis, {"checkpoint": os.path.basename(args.ckpt)})
    from ..npz import atomic_write_bytes

    try:
        atomic_write_bytes(args.out, text.encode())
    except OSError as err:
        raise BodySchemaInputError(f"cannot write --out {args.out!r}: {err.strerror or err}") from None
    print(f"wrote {args.out}: {len(diagnosis)} log(s), status {count_values(diagnosis.status.astype(str))}; "
          f"{type(schema).__name__} in {time.perf_counter() - start:.2f} s")
