"""tools/make_cases.py and tools/adapt_cases.py: the happy path through real processes, every user error
as one line ``error: ...`` with exit code 2 and no output file. One 3-epoch checkpoint for the module."""
import os
import subprocess
import sys

import numpy as np
import pytest
from physics_checks import fit_tiny_checkpoint

from lightning_bodyschema.apps.case_tools import adapt_cases_main, make_cases_main
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import FaultCases
from lightning_bodyschema.npz import load_npz, save_npz
from lightning_bodyschema.schemas import load_datamodule
from lightning_bodyschema.status import status_codes

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CASE_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")
N_JOINTS, N_MUSCLES, PER_CONDITION = 2, 6, 40


def start_tool(name, *args):
    return subprocess.Popen([sys.executable, os.path.join(ROOT, "tools", f"{name}.py"), *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process):
    out, err = process.communicate(timeout=120)
    return process.returncode, out, err


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    # 30 epochs: a 3-epoch schema's motor lengths are metres off, and adapt rightly answers out_of_range
    return fit_tiny_checkpoint(tmp_path_factory.mktemp("fit"), "--faults.every_n_epochs=0", epochs=30)


@pytest.fixture(scope="module")
def tool_runs(ckpt, tmp_path_factory):
    """make_cases twice at once with seed 0 (two fresh processes), adapt_cases as soon as seed 0 exists.

    Each process spends ~5 s CPU importing Lightning, so the other-seed run is in-process (the test).
    """
    folder = tmp_path_factory.mktemp("runs")
    paths = {name: folder / f"{name}.npz" for name in ("seed0", "seed0_again", "adapted")}
    makes = {name: start_tool("make_cases", "--ckpt", ckpt, "--seed", 0, "--out", paths[name])
             for name in ("seed0", "seed0_again")}
    runs = {"seed0": finish(makes.pop("seed0"))}
    adapt = start_tool("adapt_cases", "--ckpt", ckpt, "--cases", paths["seed0"], "--out", paths["adapted"])
    runs.update(seed0_again=finish(makes.pop("seed0_again")), adapted=finish(adapt))
    return paths, runs


@pytest.fixture(scope="module")
def made(tool_runs):
    paths, runs = tool_runs
    return paths, {name: runs[name] for name in ("seed0", "seed0_again")}


@pytest.fixture(scope="module")
def adapted(tool_runs):
    paths, runs = tool_runs
    return paths["adapted"], runs["adapted"]


# ---------------------------------------------------------------------------- happy path
def test_make_cases_writes_the_papers_cases_from_the_test_split(ckpt, made):
    paths, runs = made
    for code, out, err in runs.values():
        assert code == 0, err
        assert len(out.strip().splitlines()) == 1 and "120 fault cases (CUT 40, FIX 40, BOTH 40)" in out
    arrays = load_npz(str(paths["seed0"]))
    assert sorted(arrays) == sorted(CASE_ARRAYS + ("joints", "muscles"))  # the robot the masks' columns mean
    model = load_datamodule(ckpt).robot_model
    assert arrays["joints"].tolist() == model.joint_names and arrays["muscles"].tolist() == model.muscle_names
    b = 3 * PER_CONDITION
    assert arrays["q_ref"].shape == (b, N_JOINTS) and arrays["q_ref"].dtype == np.float64
    for name in ("cut", "fix"):
        assert arrays[name].shape == (b, N_MUSCLES) and arrays[name].dtype == bool
    assert arrays["l_fixed"].shape == (b, N_MUSCLES) and arrays["l_fixed"].dtype == np.float64
    assert arrays["cond"].shape == (b,) and arrays["cond"].dtype.kind == "U"
    for cond, n_cut, n_fix in (("CUT", 2, 0), ("FIX", 0, 2), ("BOTH", 1, 1)):
        rows = arrays["cond"] == cond
        assert rows.sum() == PER_CONDITION
        assert np.all(arrays["cut"][rows].sum(1) == n_cut) and np.all(arrays["fix"][rows].sum(1) == n_fix)
    assert np.array_equal(np.isfinite(arrays["l_fixed"]), arrays["fix"])  # NaN exactly where not jammed
    test_q = load_datamodule(ckpt).splits["val"][0].numpy()
    assert all((test_q == q).all(1).any() for q in arrays["q_ref"])  # every q_ref is a test posture
    FaultCases.load(paths["seed0"], N_JOINTS, N_MUSCLES)  # and the file is a valid case file


def test_make_cases_is_byte_reproducible_per_seed(ckpt, made, tmp_path, capsys):  # capsys: quiet
    paths, _ = made
    assert paths["seed0"].read_bytes() == paths["seed0_again"].read_bytes()  # two separate processes
    for seed in (0, 1):
        make_cases_main(["--ckpt", ckpt, "--seed", str(seed), "--out", str(tmp_path / f"seed{seed}.npz")])
    assert (tmp_path / "seed0.npz").read_bytes() == paths["seed0"].read_bytes()
    assert (tmp_path / "seed1.npz").read_bytes() != paths["seed0"].read_bytes()
    assert not np.array_equal(load_npz(str(tmp_path / "seed1.npz"))["q_ref"], load_npz(str(paths["seed0"]))["q_ref"])


def test_make_cases_n_per_condition(ckpt, tmp_path, capsys):
    make_cases_main(["--ckpt", ckpt, "--seed", "3", "--out", str(tmp_path / "c.npz"), "--n-per-condition", "5"])
    assert len(FaultCases.load(tmp_path / "c.npz", N_JOINTS, N_MUSCLES)) == 15
    assert "15 fault cases (CUT 5, FIX 5, BOTH 5)" in capsys.readouterr().out


def test_adapt_cases_writes_safe_commands_beside_the_unchanged_cases(made, adapted):
    out, (code, stdout, err) = adapted
    assert code == 0, err
    assert len(stdout.strip().splitlines()) == 1 and "120 cases" in stdout and " ok" in stdout
    cases, result = load_npz(str(made[0]["seed0"])), load_npz(str(out))
    assert sorted(result) == sorted(CASE_ARRAYS + ("l_motor", "f", "status", "status_code", "joints", "muscles"))
    for name in CASE_ARRAYS:
        assert result[name].dtype == cases[name].dtype
        np.testing.assert_array_equal(result[name], cases[name])  # NaN == NaN here
    assert result["l_motor"].shape == result["f"].shape == (120, N_MUSCLES) and result["status"].shape == (120,)
    assert (status_codes(result["status"]) == result["status_code"]).all()  # names and codes of one vocabulary
    ok = result["status"] == "ok"
    assert ok.sum() > 0 and f"{ok.sum()} ok" in stdout
    assert np.isfinite(result["l_motor"][ok]).all() and np.isfinite(result["f"][ok]).all()
    assert (result["f"][ok] >= 0).all() and (result["f"][ok] <= 150).all()
    assert np.isnan(result["l_motor"][~ok]).all() and np.isnan(result["f"][~ok]).all()
    FaultCases.load(out, N_JOINTS, N_MUSCLES)  # an adapted file is itself a valid case file


def test_check_q_within_range_is_opt_in(arm):
    q = np.array([[0.2, 1.5]])
    assert arm.check_q(q).shape == (1, 2)  # default: unchanged behaviour
    with pytest.raises(BodySchemaInputError, match=r"q\[0\] of joint .* is 1.5, outside its range \[-1, 1\]"):
        arm.check_q(q, within_range=True)
    arm.check_q(arm.q_range.T, within_range=True)  # the limits themselves are inside


# ---------------------------------------------------------------------------- user errors
def _case_file(made, tmp_path, edit):
    arrays = load_npz(str(made[0]["seed0"]))
    edit(arrays)
    save_npz(str(tmp_path / "bad_cases.npz"), **arrays)
    return tmp_path / "bad_cases.npz"


def _nan_q(a):
    a["q_ref"][3, 1] = np.nan


def _wide_cut(a):  # a cut muscle index M: one past the model's last muscle
    extra = np.zeros((len(a["cut"]), 1), bool)
    extra[0] = True
    a["cut"] = np.concatenate([a["cut"], extra], axis=1)


def _q_out_of_range(a):
    a["q_ref"][5, 0] = 1.5  # the paper arm's joints span [-1, 1] rad


def _truncated_ckpt(ckpt, tmp_path):
    data = open(ckpt, "rb").read()
    (tmp_path / "truncated.ckpt").write_bytes(data[: len(data) // 2])
    return tmp_path / "truncated.ckpt"


ERRORS = {  # name: (edit of the case file or None, overriding args (value or f(ckpt, tmp_path)), words in the message)
    "nan_q_ref": (_nan_q, {}, ["q_ref", "NaN"]),
    "cut_too_wide": (_wide_cut, {}, ["cut", "(120, 7)", "(120, 6)"]),
    "q_ref_out_of_range": (_q_out_of_range, {}, ["q_ref", "1.5", "outside its range"]),
    "missing_cases": (None, {"--cases": lambda ckpt, tmp: tmp / "missing.npz"}, ["missing.npz", "does not exist"]),
    "missing_ckpt": (None, {"--ckpt": lambda ckpt, tmp: tmp / "missing.ckpt"}, ["missing.ckpt", "does not exist"]),
    "truncated_ckpt": (None, {"--ckpt": _truncated_ckpt}, ["truncated.ckpt", "truncated"]),
    "unknown_variant": (None, {"--variant": "fancy"}, ["--variant", "'fancy'", "default", "literal"]),
    "unknown_sampler": (None, {"--sampler": "ddim"}, ["--sampler", "'ddim'", "allowed: ['ddpm'"]),
}


def _error_args(name, ckpt, made, tmp_path):
    edit, overrides, words = ERRORS[name]
    args = {"--ckpt": ckpt, "--cases": _case_file(made, tmp_path, edit) if edit else made[0]["seed0"],
            "--out": tmp_path / "out" / "adapted.npz"}
    for key, value in overrides.items():
        args[key] = value(ckpt, tmp_path) if callable(value) else value
    return [str(part) for pair in args.items() for part in pair], words


def _assert_clean_error(code, err, words, tmp_path):
    assert code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]!r}"
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # not even a temp file


@pytest.mark.parametrize("name", sorted(ERRORS))
def test_adapt_cases_user_errors(name, ckpt, made, tmp_path, capsys):
    """In-process (each a fresh process would cost ~5 s of imports); the wrapper is the same code."""
    args, words = _error_args(name, ckpt, made, tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        adapt_cases_main(args)
    _assert_clean_error(exit_info.value.code, capsys.readouterr().err, words, tmp_path)


def test_adapt_cases_user_errors_in_real_processes(ckpt, made, tmp_path):
    """Two errors through real processes at once: the one-line message and exit 2 reach the shell.

    Both are caught before the checkpoint is read (~5 s of imports), which keeps this test fast.
    """
    runs = {}
    for name in ("unknown_sampler", "nan_q_ref"):
        folder = tmp_path / name
        folder.mkdir()
        args, words = _error_args(name, ckpt, made, folder)
        runs[name] = (start_tool("adapt_cases", *args), words, folder)
    for process, words, folder in runs.values():
        code, _, err = finish(process)
        _assert_clean_error(code, err, words, folder)


def test_make_cases_user_errors(ckpt, tmp_path, capsys):
    for args, words in ((["--ckpt", str(tmp_path / "missing.ckpt"), "--seed", "0"], ["missing.ckpt", "does not exist"]),
                        (["--ckpt", ckpt, "--seed", "-1"], ["--seed", "-1"]),
                        (["--ckpt", ckpt, "--seed", "0", "--n-per-condition", "0"], ["--n-per-condition 0"]),
                        (["--ckpt", ckpt], ["--seed", "required"])):
        with pytest.raises(SystemExit) as exit_info:
            make_cases_main([*args, "--out", str(tmp_path / "out" / "cases.npz")])
        _assert_clean_error(exit_info.value.code, capsys.readouterr().err, words, tmp_path)


# ---------------------------------------------------------------------------- the binding protocol
def test_make_cases_binding_protocol_is_feasible_binding_and_byte_reproducible(ckpt, tmp_path, capsys):
    """Twice the same bytes; every case feasible (the QP) and binding (the test split's healthy command breaks it)."""
    from lightning_bodyschema.evaluation import check_feasible
    from lightning_bodyschema.evaluation.cases import BINDING_CONDITIONS, MIN_PAYOUT_M, MIN_PULL_N

    paths = [tmp_path / f"b{k}.npz" for k in range(2)]
    for path in paths:
        make_cases_main(["--ckpt", ckpt, "--protocol", "binding", "--n", "6", "--seed", "0", "--out", str(path)])
    out = capsys.readouterr().out
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert "30 fault cases (CUT 6, FIX 6, BOTH 6, WEAK 6, BAND 6), protocol binding" in out
    assert all(f"  {cond}: rejected" in out for cond in BINDING_CONDITIONS)  # rejection counts by reason
    cases = FaultCases.load(paths[0], N_JOINTS, N_MUSCLES)
    datamodule = load_datamodule(ckpt)
    assert check_feasible(datamodule.robot_model, cases, datamodule.spring)[0].all()
    q, x = (t.numpy() for t in datamodule.splits["val"])
    row = np.array([np.flatnonzero((q == q_ref).all(1))[0] for q_ref in cases.q_ref])  # drawn from the test split
    l_h, f_h = x[row, :N_MUSCLES], x[row, N_MUSCLES:]
    assert np.all(f_h[cases.cut] > MIN_PULL_N)
    assert np.all(l_h[cases.fix] - cases.l_fixed[cases.fix] >= MIN_PAYOUT_M - 1e-12)
    assert np.all(f_h[cases.weak] > cases.f_max[cases.weak])
    lo, hi = np.moveaxis(cases.l_band[cases.band], -1, 0)
    assert np.all(np.maximum(lo - l_h[cases.band], l_h[cases.band] - hi) >= MIN_PAYOUT_M - 1e-12)


def test_make_cases_protocol_option_errors(ckpt, tmp_path, capsys):
    for args, words in ((["--protocol", "random"], ["--protocol", "'random'", "paper", "binding"]),
                        (["--protocol", "binding", "--n", "0"], ["--n 0"]),
                        (["--protocol", "binding", "--n-per-condition", "5"], ["--n-per-condition", "--n"]),
                        (["--n", "4", "--n-per-condition", "5"], ["--n 4", "--n-per-condition 5"])):
        with pytest.raises(SystemExit) as exit_info:
            make_cases_main(["--ckpt", ckpt, "--seed", "0", *args, "--out", str(tmp_path / "out" / "cases.npz")])
        _assert_clean_error(exit_info.value.code, capsys.readouterr().err, words, tmp_path)


def test_make_cases_n_is_the_paper_protocols_n_per_condition(ckpt, made, tmp_path, capsys):
    make_cases_main(["--ckpt", ckpt, "--seed", "0", "--n", "40", "--out", str(tmp_path / "n.npz")])
    assert (tmp_path / "n.npz").read_bytes() == made[0]["seed0"].read_bytes()


# ---------------------------------------------------------------------------- files from other programs
def _zeros_where_no_fault(a):
    """What another program may write: 0 instead of NaN wherever a muscle is not jammed."""
    a["l_fixed"] = np.where(a["fix"], a["l_fixed"], 0.0)


def test_l_fixed_zero_where_not_jammed_adapts_exactly_as_nan(ckpt, made, tmp_path, capsys):
    lenient = _case_file(made, tmp_path, _zeros_where_no_fault)
    assert (load_npz(str(lenient))["l_fixed"] == 0.0).any()
    outs = {}
    for name, path in (("nan", made[0]["seed0"]), ("zero", lenient)):
        outs[name] = tmp_path / f"adapted_{name}.npz"
        adapt_cases_main(["--ckpt", ckpt, "--cases", str(path), "--out", str(outs[name])])
    assert outs["zero"].read_bytes() == outs["nan"].read_bytes()  # commands, statuses and the cases written back
    nan_run = load_npz(str(outs["nan"]))
    np.testing.assert_array_equal(np.isfinite(nan_run["l_fixed"]), nan_run["fix"])  # NaN where not jammed


def test_jammed_muscle_without_l_fixed_is_a_clean_error(ckpt, made, tmp_path, capsys):
    def nan_jam(a):
        a["l_fixed"] = np.where(a["fix"], np.nan, 0.0)  # the zeros are fine; the NaN jams are not

    args = ["--ckpt", ckpt, "--cases", str(_case_file(made, tmp_path, nan_jam)),
            "--out", str(tmp_path / "out" / "adapted.npz")]
    with pytest.raises(SystemExit) as exit_info:
        adapt_cases_main(args)
    _assert_clean_error(exit_info.value.code, capsys.readouterr().err, ["l_fixed", "jammed", "NaN"], tmp_path)
