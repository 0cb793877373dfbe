"""Commands for a file of requests (``tools/predict.py``): postures or hand targets, each with its own faults.

A request is a target posture ``q_ref`` [rad] or a task-space ``target`` [m] of a site (the hand by
default, reached by inverse kinematics), plus any faults of the robot at that moment. YAML or JSON::

    requests:                                   # or the list itself at the top level
      - q_ref: [0.3, -0.2]
        cut: [shoulder_flexor]                  # names or indices
        jam: {elbow_flexor: 0.151}              # muscle: l_fixed [m]
      - target: [0.35, -0.45, 0.0]
        weak: {elbow_flexor: 60.0}              # muscle: f_max' [N]
        band: {biarticular_flexor: [0.20, 0.21]}   # muscle: [lo, hi] motor length [m]

or an ``.npz`` with ``q_ref (B, N)`` and/or ``target (B, 3)`` (NaN rows where the other is used) and the
optional fault arrays ``cut``, ``fix`` (B, M) bool, ``l_fixed``, ``f_max`` (B, M) and ``l_band (B, M, 2)``
(NaN where a muscle has no such fault). A fault-case file of ``tools/make_cases.py`` is a valid request
file (its ``cond`` is ignored).

The output (``.npz`` or ``.json``, by extension; written atomically, only when every request is valid)
holds per request ``status``, ``q_ref`` (the IK posture of a target request, NaN if unreachable),
``target``, ``target_error_m``, ``l_motor`` [m], ``f`` [N] and the faults as read; with ``--evaluate``
also the evaluator's predictions: ``feasible``, ``E_cut``, ``E_fix``, ``E_tau``, ``E_q``, ``E_weak``,
``E_band`` and the MuJoCo settle check's ``E_q_phys`` and ``settle_status`` (NaN / "" where no command;
``E_q_phys`` NaN as well where the run never came to rest: ``settle_status`` NOT_SETTLED or UNSTABLE).

Only rows with status ``ok`` hold a command; every other row is NaN.
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .common import (argument_parser, check_out, check_robot_names, check_schema_options, count_values, exits_cleanly,
                     load_checked_schema, resolve_sampler, robot_names, torch_one_thread)
from ..errors import BodySchemaInputError
from ..faults import Faults
from ..faults.faults import muscle_index
from ..npz import atomic_write_bytes, load_npz, save_npz
from ..status import status_codes, status_names

REQUEST_KEYS = ("q_ref", "target", "cut", "jam", "weak", "band")
NPZ_ARRAYS = ("q_ref", "target", "cut", "fix", "l_fixed", "f_max", "l_band", "cond", "joints", "muscles")
OUT_FORMATS = (".npz", ".json")
REQUEST_FORMATS = (".yaml", ".yml", ".json", ".npz")
READINGS = ("phys", "paper")  # evaluation.benchmark.READINGS: how the evaluator treats jammed muscles


@dataclass
class Requests:
    """B requests: ``q_ref (B, N)`` [rad] (NaN rows for target requests), ``target (B, 3)`` [m] (NaN rows
    for posture requests) and their ``Faults``."""

    q_ref: np.ndarray
    target: np.ndarray
    faults: Faults

    def __len__(self):
        return len(self.q_ref)

    @property
    def by_target(self) -> np.ndarray:
        """(B,) bool: requests given as a task-space target."""
        return np.isfinite(self.target).all(1)


# ---------------------------------------------------------------------------- reading
def read_requests(path: str, model, diagnosed: Mapping | None = None) -> Requests:
    """Parse and validate a request file against the robot ``model`` (a ``MusculoskeletalModel``); ``diagnosed``: the
    faults of a diagnosis (``tools/diagnose.py``'s ``faults`` entry) added to every request (YAML/JSON files)."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in REQUEST_FORMATS:
        raise BodySchemaInputError(f"request file {path!r}: unknown format {ext or '(none)'!r}; "
                                   f"use one of {list(REQUEST_FORMATS)}")
    try:
        if diagnosed and ext == ".npz":
            raise BodySchemaInputError("--faults takes YAML or JSON requests (add the faults to an .npz yourself)")
        requests = _from_npz(path, model) if ext == ".npz" else _from_mappings(
            with_faults(_load_text(path, ext), diagnosed or {}), model)
        if len(requests) == 0:
            raise BodySchemaInputError("it holds no requests")
        requests.faults.validate(model.n_muscles)
        posture = ~requests.by_target  # target rows get a stand-in so that errors name the request's index
        model.check_q(np.where(posture[:, None], requests.q_ref, model.q_range.mean(1)), within_range=True)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"request file {path}: {err}") from None
    return requests


def _load_text(path: str, ext: str):
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"file {path!r} does not exist")
    try:
        with open(path, encoding="utf-8") as fh:
            if ext == ".json":
                return json.load(fh)
            import yaml

            return yaml.safe_load(fh)
    except (OSError, UnicodeDecodeError, ValueError) as err:  # json.JSONDecodeError is a ValueError
        raise BodySchemaInputError(f"cannot parse ({type(err).__name__}: {str(err).splitlines()[0]})") from None
    except Exception as err:  # yaml.YAMLError and friends
        raise BodySchemaInputError(f"cannot parse ({type(err).__name__}: {' '.join(str(err).split())})") from None


def with_faults(doc, faults: Mapping):
    """The request document with ``faults`` (request keys: cut, jam, weak, band) added to every request; a muscle a
    request names already keeps the request's own fault."""
    if not faults:
        return doc
    items = doc["requests"] if isinstance(doc, Mapping) and "requests" in doc else doc
    if not isinstance(items, list):
        return doc  # refused with its own message by _from_mappings
    merged = []
    for request in items:
        if not isinstance(request, Mapping):
            merged.append(request)
            continue
        request = dict(request)
        own = set(request.get("cut") or []) | {m for key in ("jam", "weak", "band") for m in (request.get(key) or {})}
        request["cut"] = list(request.get("cut") or []) + [m for m in faults.get("cut", []) if m not in own]
        for key in ("jam", "weak", "band"):
            extra = {m: v for m, v in (faults.get(key) or {}).items() if m not in own}
            if extra:
                request[key] = {**extra, **(request.get(key) or {})}
        merged.append(request)
    return merged


def read_diagnosis_faults(path: str, case) -> dict:
    """The ``faults`` of one entry of a ``tools/diagnose.py`` JSON file: the only one, or the one of ``case``."""
    entries = _load_text(path, ".json")
    if not isinstance(entries, list) or not all(isinstance(e, Mapping) and "faults" in e for e in entries):
        raise BodySchemaInputError(f"--faults {path!r} is not a tools/diagnose.py file (a JSON list of entries with "
                                   f"'faults')")
    if case is None and len(entries) != 1:
        raise BodySchemaInputError(f"--faults {path!r} holds {len(entries)} cases; pick one with --case "
                                   f"(cases: {[e.get('case') for e in entries][:10]})")
    pick = entries if case is None else [e for e in entries if e.get("case") == case]
    if not pick:
        raise BodySchemaInputError(f"--case {case} is not in {path!r} (cases: {[e.get('case') for e in entries][:10]})")
    if pick[0].get("status") not in ("identified", "ambiguous"):
        print(f"note: --faults case {pick[0].get('case')} has status {pick[0].get('status')!r}: no fault to add")
    return pick[0]["faults"]


def _from_mappings(doc, model) -> Requests:
    """Requests from a parsed YAML/JSON document: a list of mappings, or ``{"requests": [...]}``."""
    if isinstance(doc, Mapping):
        if set(doc) != {"requests"}:
            raise BodySchemaInputError(f"top-level keys {sorted(map(str, doc))}; expected only 'requests' "
                                       "(or a list of requests at the top level)")
        doc = doc["requests"]
    if not isinstance(doc, list):
        raise BodySchemaInputError(f"expected a list of requests; got {type(doc).__name__}")
    names, n_joints = model.muscle_names, model.n_joints
    q_ref, target = np.full((len(doc), n_joints), np.nan), np.full((len(doc), 3), np.nan)
    faults = {"cut": [], "jam": [], "weak": [], "band": []}
    for i, request in enumerate(doc):
        try:
            _parse_one(request, names, n_joints, q_ref[i], target[i], faults)
        except BodySchemaInputError as err:
            raise BodySchemaInputError(f"request {i}: {err}") from None
    return Requests(q_ref, target, Faults.from_names(names, n_cases=len(doc), **faults))


def _parse_one(request, names, n_joints, q_row, target_row, faults):
    if not isinstance(request, Mapping):
        raise BodySchemaInputError(f"expected a mapping with keys {list(REQUEST_KEYS)}; got {type(request).__name__}")
    unknown = sorted(set(map(str, request)) - set(REQUEST_KEYS))
    if unknown:
        raise BodySchemaInputError(f"unknown keys {unknown}; allowed: {list(REQUEST_KEYS)}")
    if ("q_ref" in request) == ("target" in request):
        raise BodySchemaInputError("give exactly one of q_ref (joint angles [rad]) or target (site position [m])")
    if "q_ref" in request:
        q_row[:] = _vector(request["q_ref"], n_joints, "q_ref", "joint angles [rad]")
    else:
        target_row[:] = _vector(request["target"], 3, "target", "x, y, z [m]")
    cut = request.get("cut")
    cut = [] if cut is None else cut
    if isinstance(cut, (str, int)):
        cut = [cut]
    if not isinstance(cut, list):
        raise BodySchemaInputError(f"cut = {cut!r}; expected a list of muscle names or indices")
    for muscle in cut:
        muscle_index(muscle, names)
    faults["cut"].append(cut)
    for key in ("jam", "weak", "band"):
        value = request.get(key)
        value = {} if value is None else value
        if not isinstance(value, Mapping):
            raise BodySchemaInputError(f"{key} = {value!r}; expected a mapping {{muscle: value}}")
        for muscle in value:
            muscle_index(muscle, names)
        faults[key].append(dict(value))


def _vector(value, n: int, name: str, what: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (n,) or not np.all(np.isfinite(v)):
        raise BodySchemaInputError(f"{name} = {value!r}; expected {n} finite numbers ({what})")
    return v


def _from_npz(path: str, model) -> Requests:
    arrays = load_npz(path)
    unknown = sorted(set(arrays) - set(NPZ_ARRAYS))
    if unknown:
        raise BodySchemaInputError(f"unknown arrays {unknown}; allowed: {list(NPZ_ARRAYS)}")
    if "q_ref" not in arrays and "target" not in arrays:
        raise BodySchemaInputError("needs a q_ref (B, N) or a target (B, 3) array")
    check_robot_names(arrays, model, "the request file")  # a make_cases.py file names its robot's joints and muscles
    batch = len(arrays.get("q_ref", arrays.get("target")))
    shapes = {"q_ref": (batch, model.n_joints), "target": (batch, 3), "cut": (batch, model.n_muscles),
              "fix": (batch, model.n_muscles), "l_fixed": (batch, model.n_muscles),
              "f_max": (batch, model.n_muscles), "l_band": (batch, model.n_muscles, 2)}
    for name, shape in shapes.items():
        if name in arrays and arrays[name].shape != shape:
            raise BodySchemaInputError(f"{name} has shape {arrays[name].shape}; expected {shape} "
                                       f"(B = {batch}, N = {model.n_joints} joints, M = {model.n_muscles} muscles)")
        kinds = "b" if name in ("cut", "fix") else "fiu"
        if name in arrays and arrays[name].dtype.kind not in kinds:
            raise BodySchemaInputError(f"{name} must be a {'bool' if kinds == 'b' else 'float'} array; "
                                       f"got dtype {arrays[name].dtype}")
    q_ref = arrays.get("q_ref", np.full(shapes["q_ref"], np.nan)).astype(float)
    target = arrays.get("target", np.full(shapes["target"], np.nan)).astype(float)
    given_q, given_t = np.isfinite(q_ref).all(1), np.isfinite(target).all(1)
    partial = (np.isfinite(q_ref).any(1) & ~given_q) | (np.isfinite(target).any(1) & ~given_t)
    bad = np.flatnonzero(partial | (given_q == given_t))
    if bad.size:
        raise BodySchemaInputError(f"request {int(bad[0])}: give exactly one finite row of q_ref or target (the "
                                   f"other NaN); {bad.size} request(s) affected")
    none = Faults.none(batch, model.n_muscles)
    faults = Faults(arrays.get("cut", none.cut), arrays.get("fix", none.fix), arrays.get("l_fixed", none.l_fixed_m),
                    arrays.get("f_max"), arrays.get("l_band"))
    return Requests(q_ref, target, faults)


# ---------------------------------------------------------------------------- predicting
def predict(schema, requests: Requests, variant: str = "default", site: str = "hand", tol_m: float = 1e-4,
            evaluate: bool = False, reading: str = "phys", **options) -> dict:
    """{name: (B, ...) array}: commands for every request in one batch (one for postures, one for targets).

    ``reading``: how the evaluator treats jammed muscles, ``"phys"`` (they pull with their stretch) or
    ``"paper"`` (the paper's E_tau, which leaves them out); used for ``feasible`` and the metrics.
    """
    if reading not in READINGS:
        raise BodySchemaInputError(f"unknown reading {reading!r}; allowed: {list(READINGS)}")
    n, m = len(requests), schema.n_muscles
    out = {"status": np.full(n, None, dtype=object), "q_ref": requests.q_ref.copy(), "target": requests.target,
           "target_error_m": np.full(n, np.nan), "l_motor": np.full((n, m), np.nan), "f": np.full((n, m), np.nan)}
    for rows, by_target in ((np.flatnonzero(~requests.by_target), False), (np.flatnonzero(requests.by_target), True)):
        if rows.size == 0:
            continue
        faults = requests.faults.take(rows)
        if by_target:
            result = schema.adapt_to_target(requests.target[rows], faults, site=site, variant=variant, tol_m=tol_m,
                                            **options)
            out["q_ref"][rows], out["target_error_m"][rows] = (result.diagnostics["q_ref"],
                                                               result.diagnostics["target_error_m"])
        else:
            result = schema.adapt(requests.q_ref[rows], faults, variant=variant, **options)
        out["l_motor"][rows], out["f"][rows], out["status"][rows] = result.l_motor_m, result.f_n, result.status
    out["status"], out["status_code"] = status_names(out["status"]), status_codes(out["status"])  # files: no objects
    out.update(_fault_arrays(requests.faults))
    if evaluate:
        out.update(evaluate_predictions(schema, out, requests.faults, jammed_pull=reading == "phys"))
    return out


def _fault_arrays(faults: Faults) -> dict:
    shape = faults.cut.shape
    return {"cut": faults.cut, "fix": faults.fix, "l_fixed": faults.l_fixed_m,
            "f_max": np.full(shape, np.nan) if faults.f_max_n is None else faults.f_max_n,
            "l_band": np.full(shape + (2,), np.nan) if faults.l_band_m is None else faults.l_band_m}


def evaluate_predictions(schema, out: dict, faults: Faults, jammed_pull: bool) -> dict:
    """The evaluator's verdict on every ``ok`` command: feasibility QP, metrics, MuJoCo settle check."""
    from dataclasses import replace

    from ..evaluation import EXTRA_METRICS, METRICS, FaultCases, ForwardSolverParams, check_feasible
    from ..evaluation import condition_of, evaluate_commands
    from ..sim.settle import SettleStatus, settle

    n = len(out["status"])
    ok = np.flatnonzero(out["status"] == "ok")
    metrics = {name: np.full(n, np.nan) for name in METRICS + EXTRA_METRICS + ("E_q_phys",)}
    longest = max(len(member.name) for member in SettleStatus)  # sized by the names: none is cut
    metrics.update(feasible=np.zeros(n, bool), settle_status=np.full(n, "", dtype=f"<U{longest}"))
    if ok.size == 0:
        return metrics
    sub = faults.take(ok)
    cases = FaultCases(out["q_ref"][ok], sub.cut, sub.fix, np.where(sub.fix, sub.l_fixed_m, np.nan),
                       condition_of(sub.cut, sub.fix, sub.weak, sub.band), sub.f_max_n, sub.l_band_m)
    model, spring = schema.robot_model, schema.spring
    l_motor, f = out["l_motor"][ok], out["f"][ok]
    metrics["feasible"][ok] = check_feasible(model, cases, spring, jammed_tension_in_torque=jammed_pull)[0]
    scores = evaluate_commands(model, cases, l_motor, f, spring,
                               replace(ForwardSolverParams(), jammed_tension_in_torque=jammed_pull))
    for name in METRICS + EXTRA_METRICS:
        metrics[name][ok] = scores[name]
    physical = settle(model, l_motor, f, cases, spring=spring)
    metrics["E_q_phys"][ok] = physical.E_q_rest  # NaN where the run never came to rest: settle_status says why
    metrics["settle_status"][ok] = [SettleStatus(int(s)).name for s in physical.status]
    return metrics


# ---------------------------------------------------------------------------- writing
def write_predictions(path: str, out: dict, schema, meta: dict) -> None:
    """Atomic ``.npz`` (arrays, plus ``muscles`` / ``joints`` names) or ``.json`` (one entry per request)."""
    names = robot_names(schema.robot_model)
    try:
        if path.lower().endswith(".npz"):
            save_npz(path, **out, **names)
        else:
            atomic_write_bytes(path, _as_json(out, names, meta).encode())
    except OSError as err:
        raise BodySchemaInputError(f"cannot write --out {path!r}: {err.strerror or err}") from None


def _as_json(out: dict, names: dict, meta: dict) -> str:
    """Strict JSON (NaN -> null), one line per request: ``{meta..., "muscles", "joints", "results": [...]}``."""
    def plain(value):
        value = np.asarray(value)
        if value.dtype.kind == "f":
            return np.where(np.isfinite(value), value, None).tolist()
        return value.tolist()

    head = {**meta, "muscles": names["muscles"].tolist(), "joints": names["joints"].tolist()}
    rows = [json.dumps({key: plain(value[i]) for key, value in out.items()}, allow_nan=False)
            for i in range(len(out["status"]))]
    return json.dumps(head, allow_nan=False)[:-1] + ', "results": [\n' + ",\n".join(rows) + "\n]}\n"


def _check_out_format(path: str, requests_path: str):
    if os.path.splitext(path)[1].lower() not in OUT_FORMATS:
        raise BodySchemaInputError(f"--out {path!r}: unknown format; use one of {list(OUT_FORMATS)}")
    if os.path.abspath(path) == os.path.abspath(requests_path):
        raise BodySchemaInputError(f"--out {path!r} is the request file itself; give another file")


@exits_cleanly
def predict_main(argv=None):
    parser = argument_parser("Commands for a file of requests (postures or hand targets, each with its own faults: cut, "
                     "jam, weak, band); writes l_motor [m], f [N] and a status per request (.npz or .json).",
                             checkpoint=True, device=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--requests", required=True, help="request file (.yaml, .yml, .json or .npz)")
    parser.add_argument("--out", required=True, help="output file (.npz or .json), written only if all succeeds")
    parser.add_argument("--variant", default="default", help="adaptation variant: default or literal (the paper's)")
    parser.add_argument("--sampler", default="ddpm", help="denoising sampler (see tools/adapt_cases.py)")
    parser.add_argument("--site", default="hand", help="site that target requests place (default: hand)")
    parser.add_argument("--reach-tol-mm", type=float, default=0.1,
                        help="a target farther than this from every reachable site position is 'unreachable'")
    parser.add_argument("--evaluate", action="store_true",
                        help="add the evaluator's predictions: feasible, E_cut, E_fix, E_tau, E_q, E_weak, E_band, "
                             "E_q_phys (MuJoCo settle check)")
    parser.add_argument("--reading", default="phys", help="evaluator's jam reading: phys (default) or paper")
    parser.add_argument("--faults", default=None, metavar="DIAGNOSIS.json",
                        help="add the faults of a tools/diagnose.py file to every request (diagnose, then adapt)")
    parser.add_argument("--case", type=int, default=None, help="with --faults: the diagnosis case to take")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    args.sampler, options = resolve_sampler(args.sampler)
    if args.reading not in READINGS:
        raise BodySchemaInputError(f"unknown --reading {args.reading!r}; allowed: {list(READINGS)}")
    if not (np.isfinite(args.reach_tol_mm) and args.reach_tol_mm > 0):
        raise BodySchemaInputError(f"--reach-tol-mm {args.reach_tol_mm} must be a positive number")
    check_out(args.out, args.ckpt)
    _check_out_format(args.out, args.requests)
    diagnosed = read_diagnosis_faults(args.faults, args.case) if args.faults else None
    torch_one_thread()
    schema = load_checked_schema(args)
    check_schema_options(schema, args.variant, args.sampler, options)
    requests = read_requests(args.requests, schema.robot_model, diagnosed)
    if requests.by_target.any() and args.site not in schema.kinematic_twin().site_names:
        raise BodySchemaInputError(f"unknown --site {args.site!r}; the model's sites are "
                                   f"{schema.kinematic_twin().site_names}")
    try:
        out = predict(schema, requests, args.variant, args.site, args.reach_tol_mm * 1e-3, args.evaluate,
                      args.reading, **options)
    except NotImplementedError as err:  # a custom schema without adaptation
        raise BodySchemaInputError(f"checkpoint {args.ckpt!r}: {err}") from None
    meta = {"checkpoint": os.path.basename(args.ckpt), "schema": type(schema).__name__, "variant": args.variant,
            "sampler": args.sampler, "site": args.site, "reading": args.reading if args.evaluate else None}
    write_predictions(args.out, out, schema, meta)
    print(f"wrote {args.out}: {len(requests)} requests ({int(requests.by_target.sum())} by target), status "
          f"{count_values(out['status'])}; {type(schema).__name__}, variant {args.variant}"
          f"{', evaluated' if args.evaluate else ''} in {time.perf_counter() - start:.2f} s")
