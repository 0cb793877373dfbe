"""Bad input, table-driven: every class a user can get wrong is refused with ONE clear line.

Each row of ``ROWS`` is one class of bad input: how to trigger it through the real entry point
(``bodyschema`` = ``lightning_bodyschema.cli``, or ``tools/make_dataset.py``, ``make_cases.py``,
``adapt_cases.py``) and the words its message must contain (the bad value and what is allowed). Every
row must exit with code 2, print exactly one ``error: ...`` line and no traceback, and leave no output
behind (no run folder, checkpoint, cache or .npz; not even a temp file).

Most rows run in-process (``main([...])`` with ``SystemExit`` captured): a fresh process costs ~5 s of
imports. Rows marked ``process=True`` run as real subprocesses, all started at once, to prove the exit
code and the one line reach the shell. ``ROWS_LIBRARY`` holds the same checks one level down, for code
that calls the library directly (``Faults.from_names``, ``BodySchema.adapt``, ``load_schema``).

jsonargparse refuses unknown options/keys itself (rows with ``usage=True``): the CLI's parser
(``cli_parser.OneLineErrorParser``) prints its ``error:`` line first, naming the bad key, then one line
pointing at ``--help``, never the usage.
"""
from __future__ import annotations

import subprocess
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from physics_checks import fit_tiny_checkpoint

from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.apps.case_tools import adapt_cases_main, make_cases_main
from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.npz import load_npz, save_npz

ROOT = Path(__file__).resolve().parents[2]
N_PER_CONDITION = 4  # 12 cases: CUT 4, FIX 4, BOTH 4
B = 3 * N_PER_CONDITION

NO_TENDONS_XML = """<mujoco><worldbody><body name="link"><joint name="hinge" type="hinge" range="-1 1"/>
<geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="1"/></body></worldbody></mujoco>"""


# ---------------------------------------------------------------------------- shared inputs
@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    """One 3-epoch paper-arm checkpoint, a valid 12-case file, and the broken files the rows point at."""
    root = tmp_path_factory.mktemp("bad_input")
    ckpts = [fit_tiny_checkpoint(root / "fit", "--data.n_samples=200", "--faults.every_n_epochs=0",
                                 "--progress.enabled=false")]
    files = root / "files"
    files.mkdir()
    make_cases_main(["--ckpt", ckpts[-1], "--seed", "0", "--out", str(files / "cases.npz"),
                     "--n-per-condition", str(N_PER_CONDITION)])
    data = Path(ckpts[-1]).read_bytes()
    (files / "truncated.ckpt").write_bytes(data[: len(data) // 2])
    save_npz(str(files / "arrays.npz"), a=np.zeros(3))  # a valid .npz, but not a checkpoint
    import torch

    torch.save({"state_dict": {}}, files / "foreign.ckpt")  # a torch file, but not ours
    (files / "broken.xml").write_text("<mujoco><worldbody><body")
    (files / "no_tendons.xml").write_text(NO_TENDONS_XML)
    (files / "typo.yaml").write_text("trainer:\n  max_epoch: 3\n")
    (files / "typo_init_arg.yaml").write_text(
        "model:\n  class_path: lightning_bodyschema.schemas.DiffusionSchema\n  init_args:\n    n_timestep: 20\n")
    return {"ckpt": ckpts[-1], "files": files, "cases": files / "cases.npz"}


def case_file(ctx, out_dir: Path, edit) -> str:
    """The valid case file with ``edit`` applied, saved beside the row's run (not in its output folder)."""
    arrays = {k: v.copy() for k, v in load_npz(str(ctx["cases"])).items()}
    edit(arrays)
    path = out_dir.parent / f"cases_{edit.__name__}.npz"
    save_npz(str(path), **arrays)
    return str(path)


# ---------------------------------------------------------------------------- case-file edits
def muscles_in_another_order(a):
    """The file names its robot's muscles: the same six in another order mean other muscles for every mask."""
    a["muscles"] = a["muscles"][::-1].copy()


def nan_q_ref(a):
    a["q_ref"][3, 1] = np.nan


def q_ref_out_of_range(a):
    a["q_ref"][5, 0] = 1.5  # the paper arm's joints span [-1, 1] rad


def inf_l_fixed(a):
    case, muscle = np.argwhere(a["fix"])[0]
    a["l_fixed"][case, muscle] = np.inf


def cut_and_jammed(a):
    case, muscle = np.argwhere(a["fix"])[0]
    a["cut"][case, muscle] = True


def every_muscle_cut(a):
    a["cut"][0], a["fix"][0], a["l_fixed"][0] = True, False, np.nan


def seventh_muscle_cut(a):  # muscle index 6 on a 6-muscle robot: one column too many
    extra = np.zeros((len(a["cut"]), 1), bool)
    extra[0] = True
    a["cut"] = np.concatenate([a["cut"], extra], axis=1)


def q_ref_one_dimensional(a):
    a["q_ref"] = a["q_ref"][:, 0]


def cond_one_short(a):
    a["cond"] = a["cond"][:-1]


def integer_cut_mask(a):
    a["cut"] = a["cut"].astype(np.int64)


def other_robot_cases(a):
    """A case file for a 3-joint, 8-muscle arm (arm3_8) given to a paper-arm checkpoint."""
    a["q_ref"] = np.zeros((B, 3))
    a["cut"], a["fix"] = np.zeros((B, 8), bool), np.zeros((B, 8), bool)
    a["cut"][:, 0] = True
    a["l_fixed"] = np.full((B, 8), np.nan)


# ---------------------------------------------------------------------------- the table
@dataclass
class Row:
    id: str
    entry: str  # "cli" (bodyschema), "make_dataset", "make_cases", "adapt_cases"
    args: Callable[[dict, Path], list]  # (ctx, out) -> argv; every output under ``out``
    words: tuple[str, ...]  # must all be in the error line: the bad value and what is allowed
    usage: bool = False  # a parser error: the error line, then one "(... --help lists every option)" line
    process: bool = False  # run as a real subprocess
    note: str = field(default="")


def fit(*extra, model="--model=DiffusionSchema"):
    """``bodyschema fit`` with every output (run folder, dataset cache) inside ``out``."""
    return lambda ctx, out: ["fit", model, "--trainer.max_epochs=1", "--progress.enabled=false",
                             f"--trainer.default_root_dir={out / 'run'}", f"--data.cache_dir={out / 'cache'}",
                             *[e(ctx) if callable(e) else e for e in extra]]


def bodyschema_test(ckpt, *extra):
    """``bodyschema test --ckpt_path ...`` with every output inside ``out``."""
    return lambda ctx, out: ["test", *extra, f"--ckpt_path={ckpt(ctx)}", f"--trainer.default_root_dir={out / 'run'}",
                             f"--data.cache_dir={out / 'cache'}", "--progress.enabled=false"]


def adapt(edit=None, ckpt=None, extra=()):
    """``tools/adapt_cases.py`` on the shared checkpoint and case file, one of them replaced or edited."""
    def args(ctx, out):
        cases = case_file(ctx, out, edit) if edit else str(ctx["cases"])
        return ["--ckpt", ckpt(ctx) if ckpt else ctx["ckpt"], "--cases", cases, "--out", str(out / "adapted.npz"),
                *extra]
    return args


def file(name):
    return lambda ctx: str(ctx["files"] / name)


def missing(name):
    return lambda ctx: str(ctx["files"] / "missing" / name)


PACKAGED = "packaged model ['arm3_8', 'opensim_like_arm', 'paper_arm']"
ROWS = [
    # ---- the robot model
    Row("model_file_missing", "cli", fit(lambda c: f"--data.model={missing('robot.xml')(c)}"),
        ("robot.xml", "does not exist", PACKAGED)),
    Row("model_file_unparsable", "cli", fit(lambda c: f"--data.model={file('broken.xml')(c)}"),
        ("broken.xml", "does not parse", "XML")),
    Row("model_file_unparsable_make_dataset", "make_dataset",
        lambda c, out: ["--model", file("broken.xml")(c), "--n", "20", "--out", str(out / "data.npz")],
        ("broken.xml", "does not parse"), process=True),
    Row("model_without_tendons", "cli", fit(lambda c: f"--data.model={file('no_tendons.xml')(c)}"),
        ("no spatial tendons", "<spatial>")),
    Row("unknown_muscle_name", "cli", fit("--data.muscles=[biceps]"),
        ("['biceps']", "'shoulder_flexor'", "'biarticular_extensor'")),
    Row("spring_constant_negative", "cli", fit("--data.f_max_n=-5"), ("f_max_n=-5", "finite and > 0")),
    # ---- fault cases (tools/adapt_cases.py)
    Row("muscle_index_out_of_range", "adapt_cases", adapt(seventh_muscle_cut),
        ("cut has shape (12, 7)", "expected (12, 6)", "6 muscles")),
    Row("same_muscle_cut_and_jammed", "adapt_cases", adapt(cut_and_jammed),
        ("both cut and jammed", "case 4", "muscle index")),
    Row("every_muscle_cut", "adapt_cases", adapt(every_muscle_cut), ("every muscle is cut", "case 0")),
    Row("nan_in_q_ref", "adapt_cases", adapt(nan_q_ref), ("q_ref", "NaN")),
    Row("inf_in_l_fixed", "adapt_cases", adapt(inf_l_fixed), ("l_fixed", "NaN/inf", "case 4")),
    Row("q_ref_outside_joint_range", "adapt_cases", adapt(q_ref_out_of_range),
        ("q_ref", "q[5]", "'shoulder'", "1.5", "outside its range [-1, 1]"), process=True),
    Row("case_file_q_ref_not_2d", "adapt_cases", adapt(q_ref_one_dimensional), ("q_ref must be 2-D", "(12,)")),
    Row("case_file_cond_wrong_length", "adapt_cases", adapt(cond_one_short), ("cond has shape (11,)", "(12,)")),
    Row("case_file_mask_not_bool", "adapt_cases", adapt(integer_cut_mask), ("cut must be a bool array", "int64")),
    Row("case_file_missing", "adapt_cases", lambda c, out: [
        "--ckpt", c["ckpt"], "--cases", missing("cases.npz")(c), "--out", str(out / "adapted.npz")],
        ("cases.npz", "does not exist")),
    Row("case_file_of_another_muscle_order", "adapt_cases", adapt(muscles_in_another_order),
        ("was written for muscles ['biarticular_extensor'", "the checkpoint's robot has ['shoulder_flexor'",
         "draw the cases for this checkpoint")),
    Row("case_file_of_another_robot", "adapt_cases", adapt(other_robot_cases),
        ("cut has shape (12, 8)", "expected (12, 6)", "2 joints ['shoulder', 'elbow'] and 6 muscles")),
    # ---- configuration
    Row("config_flag_typo", "cli", fit("--trainer.max_epoch=3"),
        ("--trainer.max_epoch=3", "did you mean --trainer.max_epochs?"), usage=True),
    Row("config_yaml_unknown_key", "cli", fit(lambda c: f"--config={file('typo.yaml')(c)}"),
        ("'trainer.max_epoch'", "did you mean --trainer.max_epochs?"), usage=True),
    Row("config_yaml_unknown_init_arg", "cli", fit(lambda c: f"--config={file('typo_init_arg.yaml')(c)}", model=""),
        ("DiffusionSchema does not accept option 'n_timestep'", "did you mean --model.n_timesteps?"), usage=True),
    Row("unknown_schema_class", "cli", fit(model="--model=NoSuchSchema"),
        ("--model NoSuchSchema is not a schema class", "DiffusionSchema"), usage=True),
    Row("epochs_zero", "cli", fit("--trainer.max_epochs=0"), ("--trainer.max_epochs=0", "positive number")),
    Row("epochs_negative", "cli", fit("--trainer.max_epochs=-2"), ("--trainer.max_epochs=-2", "positive number")),
    Row("epochs_endless_with_annealing", "cli", fit("--trainer.max_epochs=-1"),
        ("--trainer.max_epochs=-1", "lr_final=1e-05", "--model.lr_final=null")),
    Row("precision_bf16_true", "cli", fit("--trainer.precision=bf16-true"),
        ("--trainer.precision=bf16-true", "bf16-mixed", "32-true")),
    Row("max_steps_zero", "cli", fit("--trainer.max_steps=0"), ("--trainer.max_steps=0", "positive number")),
    Row("val_check_interval_longer_than_an_epoch", "cli", fit("--trainer.val_check_interval=25"),
        ("--trainer.val_check_interval=25", "10 training batches", "at most 10")),
    Row("val_fraction_leaves_no_train_split", "cli", fit("--data.n_samples=10", "--data.val_fraction=0.96"),
        ("val_fraction=0.96", "0 train", "both splits need samples")),
    Row("val_fraction_leaves_no_validation_split", "cli", fit("--data.n_samples=10", "--data.val_fraction=0.04"),
        ("val_fraction=0.04", "0 validation", "both splits need samples")),
    Row("dataset_size_zero", "cli", fit("--data.n_samples=0"), ("n_samples=0", "integer >= 10")),
    Row("dataset_size_zero_make_dataset", "make_dataset",
        lambda c, out: ["--n", "0", "--out", str(out / "data.npz")], ("n=0", "positive integer")),
    Row("dataset_seed_negative", "cli", fit("--data.seed=-1"), ("seed=-1", "integer >= 0")),
    Row("dataset_workers_negative", "cli", fit("--data.workers=-1"), ("workers=-1", "integer >= 0", "every core")),
    Row("dataset_workers_negative_make_dataset", "make_dataset",
        lambda c, out: ["--n", "20", "--workers", "-1", "--out", str(out / "data.npz")], ("--workers -1", ">= 0")),
    Row("dataset_out_is_a_directory", "make_dataset",
        lambda c, out: ["--n", "20", "--out", str(c["files"])], ("--out", "is a directory")),
    Row("learning_rate_negative", "cli", fit("--model.lr=-1"), ("lr=-1", "lr > 0")),
    Row("latent_not_larger_than_joints", "cli", fit("--model.latent_dim=2", model="--model=AutoEncoderSchema"),
        ("latent_dim=2", "must exceed q_dim=2")),
    # ---- checkpoints
    Row("checkpoint_missing", "cli", bodyschema_test(missing("model.ckpt"), "--model=DiffusionSchema"),
        ("model.ckpt", "does not exist")),
    Row("checkpoint_path_empty", "cli", bodyschema_test(lambda c: "", "--model=DiffusionSchema"),
        ("--ckpt_path ''", "is empty", "last (the newest")),
    Row("checkpoint_best_from_the_command_line", "cli", bodyschema_test(lambda c: "best", "--model=DiffusionSchema"),
        ("--ckpt_path best", "same Python process", "give its file")),
    Row("checkpoint_last_not_found", "cli", bodyschema_test(lambda c: "last", "--model=DiffusionSchema"),
        ("--ckpt_path last", "no .../checkpoints/last.ckpt under", "run")),
    Row("checkpoint_truncated", "cli", bodyschema_test(file("truncated.ckpt"), "--model=DiffusionSchema"),
        ("truncated.ckpt", "cannot be read", "truncated or not a checkpoint"), process=True),
    Row("checkpoint_is_an_npz", "cli", bodyschema_test(file("arrays.npz"), "--model=DiffusionSchema"),
        ("arrays.npz", "cannot be read", "not a checkpoint")),
    Row("checkpoint_foreign_torch_file", "cli", bodyschema_test(file("foreign.ckpt"), "--model=DiffusionSchema"),
        ("foreign.ckpt", "is not a lightning_bodyschema checkpoint")),
    Row("checkpoint_truncated_adapt_cases", "adapt_cases", adapt(ckpt=file("truncated.ckpt")),
        ("truncated.ckpt", "truncated or not a checkpoint")),
    Row("checkpoint_is_an_npz_make_cases", "make_cases",
        lambda c, out: ["--ckpt", file("arrays.npz")(c), "--seed", "0", "--out", str(out / "cases.npz")],
        ("arrays.npz", "not a checkpoint")),
    Row("checkpoint_of_another_robot", "cli",
        bodyschema_test(lambda c: c["ckpt"], f"--config={ROOT / 'configs' / 'arm3_8-diff.yaml'}"),
        ("was trained on another robot", "model XML", "6 muscles", "3 joints", "8 muscles"), process=True),
    Row("checkpoint_of_another_spring", "cli", bodyschema_test(lambda c: c["ckpt"], "--model=DiffusionSchema",
                                                        "--data.f_max_n=100"),
        ("was trained on another robot", "spring differ")),
    # ---- adaptation options
    Row("unknown_variant", "adapt_cases", adapt(extra=("--variant", "fancy")),
        ("--variant 'fancy'", "allowed: [", "'default'", "'literal'")),
    Row("unknown_sampler", "adapt_cases", adapt(extra=("--sampler", "ddim")), ("--sampler 'ddim'", "allowed: ['ddpm'")),
]
assert len({row.id for row in ROWS}) == len(ROWS)

MAINS = {"cli": cli_main, "make_dataset": make_dataset_main, "make_cases": make_cases_main,
         "adapt_cases": adapt_cases_main}


def command(row: Row, ctx, out: Path) -> list[str]:
    argv = [str(a) for a in row.args(ctx, out) if a != ""]
    if row.entry == "cli":
        return [sys.executable, "-m", "lightning_bodyschema.cli", *argv]
    return [sys.executable, str(ROOT / "tools" / f"{row.entry}.py"), *argv]


# ---------------------------------------------------------------------------- checks
def assert_refused(row: Row, code, err: str, out: Path):
    assert code == 2, f"exit code {code}, stderr:\n{err[-3000:]}"
    assert "Traceback" not in err, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [i for i, line in enumerate(lines) if line.startswith("error: ")]
    assert len(errors) == 1, f"expected one 'error: ' line, got:\n{err[-3000:]}"
    if row.usage:  # the parser's error first, then only the pointer to --help (no usage dump)
        assert errors == [0] and len(lines) == 2 and lines[1].endswith("--help lists every option)"), err
        message = lines[0]
    else:
        assert lines == [lines[errors[0]]], f"expected exactly one line, got:\n{err}"
        message = lines[0]
    print(f"\n[{row.id}] {message}")  # shown with -s: the table's messages
    for word in row.words:
        assert word in message, f"{word!r} not in {message!r}"
    leftovers = [p for p in out.rglob("*") if p.is_file()] if out.exists() else []
    assert not leftovers, f"partial output left behind: {leftovers}"


@pytest.fixture(scope="module")
def processes(ctx, tmp_path_factory):
    """The ``process=True`` rows as real subprocesses, all started at once: id -> (code, stderr, out)."""
    started = {}
    for row in ROWS:
        if row.process:
            out = tmp_path_factory.mktemp(row.id) / "out"
            started[row.id] = (subprocess.Popen(command(row, ctx, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                                text=True, cwd=out.parent), out)
    results = {}
    for name, (proc, out) in started.items():
        _, err = proc.communicate(timeout=300)
        results[name] = (proc.returncode, err, out)
    return results


@pytest.mark.parametrize("row", ROWS, ids=[row.id for row in ROWS])
def test_bad_input_is_refused_with_one_line(row, ctx, processes, tmp_path, capsys):
    if row.process:
        code, err, out = processes[row.id]
    else:
        out = tmp_path / "out"
        capsys.readouterr()
        with warnings.catch_warnings(), pytest.raises(SystemExit) as exit_info:
            warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
            MAINS[row.entry]([str(a) for a in row.args(ctx, out) if a != ""])
        code, err = exit_info.value.code, capsys.readouterr().err
    assert_refused(row, code, err, out)


def test_the_table_covers_the_required_classes():
    ids = {row.id for row in ROWS}
    required = {"model_file_missing", "model_file_unparsable", "model_without_tendons", "unknown_muscle_name",
                "muscle_index_out_of_range", "same_muscle_cut_and_jammed", "every_muscle_cut", "nan_in_q_ref",
                "inf_in_l_fixed", "q_ref_outside_joint_range", "case_file_q_ref_not_2d", "config_flag_typo",
                "config_yaml_unknown_key", "epochs_zero", "dataset_size_zero", "latent_not_larger_than_joints",
                "checkpoint_missing", "checkpoint_truncated", "checkpoint_is_an_npz", "checkpoint_of_another_robot",
                "case_file_of_another_robot", "unknown_variant", "unknown_sampler"}
    assert required <= ids, required - ids
    assert sum(row.process for row in ROWS) >= 3 and {row.entry for row in ROWS if row.process} >= {"cli"}


# ---------------------------------------------------------------------------- the same, one level down
@pytest.fixture(scope="module")
def schema(ctx):
    from lightning_bodyschema.schemas import load_schema

    return load_schema(ctx["ckpt"])


def _faults(schema, **kwargs):
    from lightning_bodyschema.faults import Faults

    return Faults.from_names(schema.robot_model.muscle_names, **kwargs)


def _adapt(schema, q, **kwargs):
    from lightning_bodyschema.faults import Faults

    q = np.atleast_2d(q)
    return schema.adapt(q, Faults.none(len(q), schema.n_muscles), **kwargs)


ROWS_LIBRARY = {  # id: (call(schema, ctx), words in the BodySchemaInputError message)
    "faults_muscle_index_6": (lambda s, c: _faults(s, cut=[[6]]), ("muscle index 6", "out of range 0..5")),
    "faults_unknown_muscle_name": (lambda s, c: _faults(s, cut=[["biceps"]]), ("'biceps'", "'shoulder_flexor'")),
    "faults_cut_and_jammed": (lambda s, c: _faults(s, cut=[["elbow_flexor"]], jam=[{"elbow_flexor": 0.15}]),
                              ("both cut and jammed",)),
    "faults_every_muscle_cut": (lambda s, c: _faults(s, cut=[list(range(6))]), ("every muscle is cut",)),
    "faults_nan_l_fixed": (lambda s, c: _faults(s, jam=[{"elbow_flexor": float("nan")}]), ("nan",)),
    "adapt_nan_q_ref": (lambda s, c: _adapt(s, [[0.1, np.nan]]), ("NaN",)),
    "adapt_q_ref_wrong_width": (lambda s, c: _adapt(s, [[0.1, 0.2, 0.3]]), ("(1, 3)", "(B, 2)")),
    "adapt_unknown_variant": (lambda s, c: _adapt(s, [[0.1, 0.2]], variant="fancy"),
                              ("'fancy'", "'default'", "'literal'")),
    "adapt_fault_rows_mismatch": (lambda s, c: s.adapt(np.zeros((3, 2)), _faults(s, cut=[[0], [1]])),
                                  ("3 postures but 2 fault rows",)),
    "check_q_outside_range": (lambda s, c: s.robot_model.check_q([[0.0, -1.2]], within_range=True),
                              ("'elbow'", "-1.2", "outside its range [-1, 1]")),
    "load_schema_other_robot": (lambda s, c: __import__("lightning_bodyschema.schemas", fromlist=["x"]).load_schema(
        c["ckpt"], expected_model_xml_sha256="0" * 64), ("another robot model",)),
    "load_schema_truncated": (lambda s, c: __import__("lightning_bodyschema.schemas", fromlist=["x"]).load_schema(
        str(c["files"] / "truncated.ckpt")), ("truncated",)),
}


@pytest.mark.parametrize("name", sorted(ROWS_LIBRARY))
def test_library_refuses_bad_input(name, schema, ctx):
    call, words = ROWS_LIBRARY[name]
    with pytest.raises(BodySchemaInputError) as info:
        call(schema, ctx)
    message = str(info.value)
    print(f"\n[{name}] {message}")
    assert "\n" not in message.strip(), message
    for word in words:
        assert word.lower() in message.lower(), f"{word!r} not in {message!r}"
