"""Export a schema's prepared adapter (``AdapterModule`` for the diffusion schema, ``StructuredAdapterModule`` for
the structured one) to one AOTInductor ``.pt2`` package, and load it back.

``export_package(schema, out)`` traces the module with ``torch.export`` and compiles it with AOTInductor (a C++
compiler is needed, tens of seconds per program). A dynamic-batch package holds two programs: ``"model"`` (any
batch 1..MAX_BATCH, the one a plain ``aoti_load_package`` loads) and ``"batch1"`` (the same adapter compiled for
exactly one case); a static ``batch=N`` package holds ``"model"`` alone. Each program carries the package's
metadata (``package_metadata``: the schema kind, names, units, status codes, the checkpoint's hash, and
``"programs"``: the batches it holds, ``"dynamic,1"`` or ``"N"``; absent in a one-program package written before)
as strings, readable from Python (``get_metadata()``) and C++ (``AOTIModelPackageLoader::get_metadata``).
``load_exported(path, expected_sha256=None)`` returns ``ExportedAdapter``: ``(q_ref, faults) -> AdaptationResult``
without the schema, for either kind; a call with one case runs the ``"batch1"`` program where the package has one.

A package holds a compiled shared library: loading one runs its code (unlike a checkpoint read with
``weights_only=True``). Pin the digest the export prints (``expected_sha256``): a file whose SHA-256 differs is
refused before anything in it is loaded.
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
import warnings
import zipfile

import numpy as np
import torch

from .._numpy import to_numpy
from ..adaptation.command import FAULT_TOL_M, FAULT_TOL_N, AdaptationResult, statuses
from ..errors import BodySchemaInputError
from ..npz import default_file_mode
from ..status import STATUS_CODES
from .module import VARIANT, AdapterModule

FORMAT = "lightning_bodyschema.adapter/1"
INPUTS = ("q_ref", "cut", "jam", "l_fixed_m", "f_weak_n", "band_lo_m", "band_hi_m", "seed")
MAX_BATCH = 4096
UNITS = {"q_ref": "rad", "l_fixed_m": "m", "f_weak_n": "N", "band_lo_m": "m", "band_hi_m": "m", "l_motor_m": "m",
         "f_n": "N", "cut": "mask 0/1", "jam": "mask 0/1", "seed": "int64", "status": "int32"}


def file_sha256(path: str) -> str:
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def program_batches(batch) -> list:
    """The batches a package exported for ``batch`` (``parse_batch``'s) holds programs for, the first named
    ``"model"``: a dynamic batch also gets a static batch-1 program (one case per call, a control loop's call,
    without the dynamic program's shape checks and loops)."""
    return ["dynamic", 1] if batch == "dynamic" else [batch]


def program_name(index: int, batch) -> str:
    """The name of a package's ``index``-th program (``program_batches``): ``"model"`` first (the name every
    AOTInductor loader opens by default, so a package keeps loading in code that knows one program), then
    ``"batch<N>"``."""
    return "model" if index == 0 else f"batch{batch}"


def package_metadata(schema, module, ckpt_sha256: str, batch) -> dict[str, str]:
    """The package's metadata: every value a string (JSON for lists and dicts); ``schema_kind`` is
    ``"diffusion"`` or ``"structured"`` (``n_steps``: denoising steps, or the structured package's Newton steps);
    ``batch``: the ``"model"`` program's; ``programs``: every program's batch, comma-separated, in
    ``program_batches`` order."""
    robot = schema.robot_model
    spring = {name: np.asarray(getattr(schema.spring, name), float).tolist()
              for name in ("k_n", "alpha_per_m", "f_max_n")}
    values = {"format": FORMAT, "schema_class": f"{type(schema).__module__}.{type(schema).__qualname__}",
              "schema_kind": module.kind, "variant": VARIANT,
              "n_steps": getattr(module, "n_steps", getattr(module, "max_iter", None)), "joint_names": list(robot.joint_names),
              "muscle_names": list(robot.muscle_names), "q_range_rad": np.asarray(robot.q_range, float).tolist(),
              "inputs": list(INPUTS), "outputs": ["l_motor_m", "f_n", "status"], "units": UNITS,
              "status_codes": STATUS_CODES, "spring": spring, "seeds": module.seeds, "checkpoint_sha256": ckpt_sha256,
              "batch": batch, "programs": ",".join(map(str, program_batches(batch))), "fault_tol_m": FAULT_TOL_M,
              "fault_tol_n": FAULT_TOL_N, "dtype": str(module.dtype)}
    return {key: value if isinstance(value, str) else json.dumps(value) for key, value in values.items()}


def parse_batch(text: str):
    """``"dynamic"`` (1..MAX_BATCH cases per call) or one positive int (a static batch size)."""
    if str(text) == "dynamic":
        return "dynamic"
    try:
        batch = int(text)
    except ValueError:
        batch = 0
    if batch < 1 or batch > MAX_BATCH:
        raise BodySchemaInputError(f"batch size {text!r}: use 'dynamic' or an integer in 1..{MAX_BATCH}")
    return batch


def package_module(schema, n_steps: int = 20, seeds=None):
    """The tensor-only module of ``schema``'s adapter: ``AdapterModule`` (diffusion; ``n_steps`` denoising steps,
    ``seeds``) or ``StructuredAdapterModule`` (structured; ``seeds`` must be None); anything else is refused."""
    from ..schemas import StructuredSchema
    from .structured import StructuredAdapterModule

    if isinstance(schema, StructuredSchema):
        if seeds is not None:
            raise BodySchemaInputError("the structured schema draws nothing: export it without seeds")
        return StructuredAdapterModule(schema)
    return AdapterModule(schema, n_steps, seeds)


@contextlib.contextmanager
def _torch_notes_silenced():
    """torch's FutureWarnings about its own internals (the deprecated pytree ``LeafSpec`` its exported programs hold
    and copy, deprecated helpers its compiler calls): nothing a user of the package can act on."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, module=r"torch\.")
        warnings.filterwarnings("ignore", category=FutureWarning, message=".*LeafSpec.*")
        yield


def exported_program(module, batch):
    """``torch.export`` of a package module (``package_module``) for ``batch`` (``parse_batch``'s), its small
    products written as multiply-sums (``products.fuse_small_products``): the program ``export_package`` compiles."""
    from torch.export import Dim, export

    from .products import fuse_small_products

    example = module.example_inputs(2 if batch == "dynamic" else batch)
    shapes = None
    if batch == "dynamic":
        dim = Dim("batch", min=1, max=MAX_BATCH)
        shapes = tuple({0: dim} for _ in INPUTS[:-1]) + (None,)
    with torch.no_grad(), _torch_notes_silenced():
        try:
            program = export(module, example, dynamic_shapes=shapes, strict=False)
        except torch._dynamo.exc.UserError as error:  # a dynamic batch the traced code fixed to one size
            if shapes is None or "specialized it to be a constant" not in str(error):
                raise
            raise BodySchemaInputError(f"{module.kind} adapter: its code fixes the batch size when traced, so it "
                                       "cannot be exported for a dynamic batch; give a static one (--batch-sizes "
                                       "1)") from None
        return fuse_small_products(program)


def compiled_program(program, metadata: dict[str, str]) -> list:
    """AOTInductor's files for one exported program with ``metadata``: one entry of ``package_aoti``'s dict."""
    gm = program.module(check_guards=False)  # as aoti_compile_and_package compiles it
    args, kwargs = program.example_inputs
    with _torch_notes_silenced():
        return torch._inductor.aot_compile(gm, args, kwargs, options={"aot_inductor.package": True,
                                                                        "aot_inductor.metadata": metadata})


def export_package(schema, out: str, n_steps: int = 20, batch="dynamic", ckpt_sha256: str = "", seeds=None) -> str:
    """Write the AOTInductor package of ``schema``'s adapter (``package_module``) to ``out``: one program per
    ``program_batches(batch)``, named by ``program_name`` (atomically: a temporary file in the same folder, then a
    rename). Returns ``out``."""
    from torch._inductor.package import package_aoti

    module = package_module(schema, n_steps, seeds).eval()
    batch = parse_batch(batch)
    metadata = package_metadata(schema, module, ckpt_sha256, batch)
    files = {program_name(i, b): compiled_program(exported_program(module, b), metadata)
             for i, b in enumerate(program_batches(batch))}
    folder = os.path.dirname(os.path.abspath(out))
    os.makedirs(folder, exist_ok=True)
    handle, tmp = tempfile.mkstemp(prefix=".partial-", suffix=".pt2", dir=folder)
    os.close(handle)
    try:
        package_aoti(tmp, files)
        os.chmod(tmp, default_file_mode())  # as open() would make it: a controller running as another user reads it
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out


class ExportedAdapter:
    """A loaded package of either kind: ``adapter(q_ref (B, N) [rad], faults) -> AdaptationResult`` (``Status``
    members, NaN rows where not ok; ``diagnostics["status_code"]`` the package's integer codes). ``metadata``: the
    parsed metadata (``schema_kind``: ``"diffusion"`` or ``"structured"``); ``run(*tensors)``: the raw package
    call (``INPUTS`` in order), by the program for that many cases (``programs``: batch -> runner, e.g.
    ``{"dynamic": ..., "1": ...}``) or else the ``"model"`` program."""

    def __init__(self, programs: dict, metadata: dict, path: str):
        self.programs, self.path = programs, path
        self.metadata = {key: _parsed(value) for key, value in metadata.items()}
        self.joint_names, self.muscle_names = self.metadata["joint_names"], self.metadata["muscle_names"]
        self.kind = self.metadata.get("schema_kind", "diffusion")
        self.seed = int(self.metadata["seeds"][0])

    def program_for(self, n_cases: int) -> str:
        """The key in ``programs`` of the program a call with ``n_cases`` cases runs: the one compiled for that
        batch where the package holds it (a one-case call in a dynamic package: ``"1"``), else the first."""
        return str(n_cases) if str(n_cases) in self.programs else next(iter(self.programs))

    def run(self, *tensors):
        return self.programs[self.program_for(len(tensors[0]))](*tensors)

    def inputs(self, q_ref, faults, seed=None) -> tuple:
        """The package's input tensors (contiguous float64, one row per case) for ``q_ref`` and ``faults``."""
        n, m = len(self.joint_names), len(self.muscle_names)
        q = np.atleast_2d(np.asarray(q_ref, dtype=np.float64))
        if q.ndim != 2 or q.shape[1] != n:
            raise BodySchemaInputError(f"q_ref has shape {q.shape}; expected (B, {n}) for joints {self.joint_names}")
        if len(faults) != len(q) or np.shape(faults.cut) != (len(q), m):
            raise BodySchemaInputError(f"faults have shape {np.shape(faults.cut)}; expected ({len(q)}, {m}): one row "
                                       f"per posture, muscles {self.muscle_names}")
        batch = self.metadata["batch"]
        if batch != "dynamic" and len(q) != batch:
            raise BodySchemaInputError(f"{len(q)} cases; this package was exported for batch {batch} exactly")
        nan = np.full((len(q), m), np.nan)
        band = faults.l_band_m if faults.l_band_m is not None else np.stack([nan, nan], -1)
        arrays = (q, faults.cut, faults.fix, faults.l_fixed_m, nan if faults.f_max_n is None else faults.f_max_n,
                  band[..., 0], band[..., 1])
        tensors = tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)) for a in arrays)
        return tensors + (torch.tensor(self.seed if seed is None else int(seed), dtype=torch.int64),)

    def __call__(self, q_ref, faults, seed=None) -> AdaptationResult:
        with torch.no_grad():
            l_motor, f, status = self.run(*self.inputs(q_ref, faults, seed))
        codes = to_numpy(status).astype(np.int32)
        return AdaptationResult(to_numpy(l_motor), to_numpy(f), statuses(codes), {"status_code": codes})


def load_exported(path: str, muscle_names=None, joint_names=None, expected_sha256: str | None = None) -> ExportedAdapter:
    """Load a package written by ``export_package`` (either kind); refuse, in one line, a file that is not one
    (missing, corrupt, truncated), one whose SHA-256 is not ``expected_sha256`` (checked before anything in it is
    loaded: a package runs compiled code), or a package for another robot (``muscle_names``/``joint_names`` given
    and different)."""
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"no adapter package at {path!r}")
    if expected_sha256 is not None:
        check_digest(path, expected_sha256)
    try:
        with zipfile.ZipFile(path) as archive:
            broken = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise BodySchemaInputError(f"{path!r} is not a readable .pt2 package (corrupt or truncated: {error})") from None
    if broken is not None:
        raise BodySchemaInputError(f"{path!r} is corrupt: member {broken!r} fails its CRC check")
    try:
        programs, metadata = _load_programs(path)
    except Exception as error:  # noqa: BLE001  (torch raises RuntimeError and others; one line for all)
        raise BodySchemaInputError(f"{path!r} could not be loaded as an AOTInductor package: "
                                   f"{str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
    if metadata.get("format") != FORMAT:
        raise BodySchemaInputError(f"{path!r} is not a lightning_bodyschema adapter package (format "
                                   f"{metadata.get('format')!r}, expected {FORMAT!r})")
    adapter = ExportedAdapter(programs, metadata, path)
    for what, expected, packaged in (("muscles", muscle_names, adapter.muscle_names),
                                     ("joints", joint_names, adapter.joint_names)):
        if expected is not None and list(expected) != list(packaged):
            raise BodySchemaInputError(f"{path!r} was exported for another robot: its {what} are {packaged}, "
                                       f"this robot's are {list(expected)}")
    return adapter


def _load_programs(path: str) -> tuple[dict, dict]:
    """Every program of the package at ``path`` (loaded once each) as batch -> runner, the ``"model"`` program
    first, and its metadata. A package without ``"programs"`` metadata (written with one program) holds
    ``"model"`` alone."""
    from torch.export.pt2_archive import _package as pt2

    with _torch_notes_silenced():
        runners = pt2.load_pt2(path).aoti_runners
    metadata = runners["model"].get_metadata()
    batches = str(metadata.get("programs", metadata.get("batch"))).split(",")
    return {b: runners[program_name(i, b)] for i, b in enumerate(batches)}, metadata


def check_digest(path: str, expected_sha256: str) -> None:
    """Refuse, in one line, a file whose SHA-256 is not ``expected_sha256`` (64 hex digits, any case)."""
    expected = str(expected_sha256).strip().lower()
    if len(expected) != 64 or any(c not in "0123456789abcdef" for c in expected):
        raise BodySchemaInputError(f"expected_sha256={expected_sha256!r}: give the 64 hex digits the export printed")
    actual = file_sha256(path)
    if actual != expected:
        raise BodySchemaInputError(f"{path!r} has SHA-256 {actual}, not the pinned {expected}: refused unloaded "
                                   "(a package runs compiled code)")


def _parsed(value: str):
    try:
        return json.loads(value)
    except (TypeError, ValueError):
        return value
