"""tools/predict.py: requests (postures or hand targets, with cut / jam / weak / band faults) -> commands.

A 3-epoch checkpoint for the module: the commands are poor, but the plumbing is what is tested here
(test_new_faults.py checks the adaptation itself on a better-trained schema).
"""
import json
import os
import subprocess
import sys
import warnings

import lightning as L
import numpy as np
import pytest

from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.evaluation import FaultCases, check_feasible, make_fault_cases
from lightning_bodyschema.npz import load_npz, save_npz
from lightning_bodyschema.apps.predict import predict_main
from lightning_bodyschema.schemas import DiffusionSchema, load_schema

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
M = 6


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("predict")
    L.seed_everything(0)
    dm = EquilibriumDataModule(n_samples=200, cache_dir=str(root / "cache"))
    schema = DiffusionSchema(robot=dm.robot)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # 40 epochs: a 3-epoch schema's motor lengths are metres off, and adapt rightly answers out_of_range
        trainer = L.Trainer(max_epochs=40, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0)
        trainer.fit(schema, dm)
    path = root / "tiny.ckpt"
    trainer.save_checkpoint(path)
    return str(path), schema.robot_model


def _hand(model, q):
    return model.site_position(np.atleast_2d(q), "hand")[0].tolist()


def _yaml(path, text):
    path.write_text(text)
    return str(path)


def _run(capsys, *argv):
    """predict_main in-process: (exit code, stdout, stderr)."""
    try:
        predict_main([str(a) for a in argv])
        code = 0
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    return code, out, err


def test_yaml_requests_to_json_with_evaluation(ckpt, tmp_path):
    path, model = ckpt
    target = _hand(model, [0.4, -0.3])
    requests = _yaml(tmp_path / "req.yaml", f"""
requests:
  - q_ref: [0.3, -0.2]
    cut: [shoulder_flexor]
    jam: {{elbow_flexor: 0.151}}
  - target: {target}
    weak: {{elbow_flexor: 60.0}}
    band: {{biarticular_flexor: [0.50, 0.53]}}
  - target: [5.0, 5.0, 0.0]
  - q_ref: [0.0, 0.0]
    cut: 3
""")
    out = tmp_path / "commands.json"
    # the real script once, in a fresh process (the rest of the tests run in-process)
    run = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "predict.py"), "--ckpt", path, "--requests",
                          requests, "--out", out, "--evaluate"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert len(run.stdout.strip().splitlines()) == 1 and "4 requests (2 by target)" in run.stdout
    doc = json.loads(out.read_text())
    assert doc["muscles"][0] == "shoulder_flexor" and doc["joints"] == ["shoulder", "elbow"]
    results = doc["results"]
    assert [r["status"] for r in results] == ["ok", "ok", "unreachable", "ok"]
    assert results[0]["q_ref"] == [0.3, -0.2] and results[0]["cut"][0] and results[0]["l_fixed"][2] == 0.151
    assert results[3]["cut"] == [False, False, False, True, False, False]
    reached = np.array(results[1]["q_ref"])
    assert np.linalg.norm(np.array(_hand(model, reached)) - target) <= 1e-3
    assert results[1]["f_max"][2] == 60.0 and results[1]["f"][2] <= 60.0 and results[1]["l_band"][4] == [0.5, 0.53]
    assert results[2]["l_motor"] == [None] * M and results[2]["q_ref"] == [None, None]
    assert results[2]["target_error_m"] > 1.0 and results[2]["E_q"] is None and results[2]["settle_status"] == ""
    for r in (results[0], results[1], results[3]):
        assert all(np.isfinite(r[k]) for k in ("E_tau", "E_q", "E_q_phys")) and r["settle_status"]
        assert isinstance(r["feasible"], bool)
    assert results[0]["E_weak"] is None and results[1]["E_weak"] == 0.0 and results[1]["E_band"] is not None


def test_npz_requests_to_npz_are_deterministic(ckpt, tmp_path, capsys):
    path, model = ckpt
    rng = np.random.default_rng(0)
    q = model.sample_q(rng, 12)
    l_geo = model.kinematics(q)[0]
    cases = make_fault_cases(q, l_geo - 0.003, n_per_condition=2, seed=0)  # a make_cases-style file ...
    arrays = cases.arrays()
    arrays["f_max"] = np.where(np.eye(M, dtype=bool)[rng.integers(0, M, 6)], 50.0, np.nan)  # ... plus new faults
    save_npz(str(tmp_path / "req.npz"), **arrays)
    for name in ("a", "b"):
        code, out, err = _run(capsys, "--ckpt", path, "--requests", tmp_path / "req.npz",
                              "--out", tmp_path / f"{name}.npz")
        assert code == 0, err
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    result = load_npz(str(tmp_path / "a.npz"))
    feasible = check_feasible(load_schema(path).robot_model, FaultCases(**arrays))[0]
    assert result["l_motor"].shape == (6, M) and feasible.any()
    assert result["status"].tolist() == np.where(feasible, "ok", "infeasible").tolist()
    np.testing.assert_array_equal(result["q_ref"], cases.q_ref)
    np.testing.assert_array_equal(result["cut"], cases.cut)
    assert np.isnan(result["target"]).all() and "E_tau" not in result
    weak_f = result["f"][np.isfinite(arrays["f_max"])]
    assert (weak_f[np.isfinite(weak_f)] <= 50.0).all() and np.isfinite(weak_f).sum() == feasible.sum()
    assert result["muscles"].tolist()[2] == "elbow_flexor"


def test_npz_target_requests(ckpt, tmp_path, capsys):
    path, model = ckpt
    q = model.sample_q(np.random.default_rng(3), 5)
    target = model.site_position(q, "hand")
    target[4] = [3.0, 0.0, 0.0]
    save_npz(str(tmp_path / "req.npz"), target=target)
    code, out, err = _run(capsys, "--ckpt", path, "--requests", tmp_path / "req.npz", "--out", tmp_path / "out.npz",
                          "--evaluate")
    assert code == 0, err
    result = load_npz(str(tmp_path / "out.npz"))
    assert result["status"].tolist() == ["ok"] * 4 + ["unreachable"]
    err_m = np.linalg.norm(model.site_position(result["q_ref"][:4], "hand") - target[:4], axis=1)
    assert err_m.max() <= 1e-3 and np.isnan(result["f"][4]).all() and np.isnan(result["E_q_phys"][4])


BAD_YAML = {
    "unknown key": ("- q_ref: [0, 0]\n  cutt: [0]\n", "request 0: unknown keys ['cutt']"),
    "both": ("- q_ref: [0, 0]\n  target: [0, 0, 0]\n", "exactly one of q_ref"),
    "neither": ("- cut: [0]\n", "exactly one of q_ref"),
    "short q": ("- q_ref: [0]\n", "expected 2 finite numbers"),
    "q out of range": ("- q_ref: [0, 0]\n- q_ref: [0, 1.5]\n", "q[1] of joint 'elbow' is 1.5"),
    "unknown muscle": ("- q_ref: [0, 0]\n  weak: {biceps: 50}\n", "unknown muscle 'biceps'"),
    "band order": ("- q_ref: [0, 0]\n  band: {elbow_flexor: [0.2, 0.1]}\n", "lo > hi"),
    "band shape": ("- q_ref: [0, 0]\n  band: {elbow_flexor: 0.2}\n", "a band is [lo, hi]"),
    "band and cut": ("- q_ref: [0, 0]\n  cut: [elbow_flexor]\n  band: {elbow_flexor: [0.1, 0.2]}\n",
                     "cut and length-banded"),
    "cut and jam": ("- q_ref: [0, 0]\n  cut: [2]\n  jam: {2: 0.1}\n", "both cut and jammed"),
    "weak value": ("- q_ref: [0, 0]\n  weak: {elbow_flexor: strong}\n", "need a finite number"),
    "jam not a map": ("- q_ref: [0, 0]\n  jam: [elbow_flexor]\n", "expected a mapping"),
    "not a list": ("q_ref: [0, 0]\n", "top-level keys ['q_ref']"),
    "empty": ("[]\n", "holds no requests"),
    "broken yaml": ("- q_ref: [0, 0\n", "cannot parse"),
}


@pytest.mark.parametrize("case", sorted(BAD_YAML))
def test_bad_requests_exit_2_with_one_line_and_no_output(ckpt, tmp_path, capsys, case):
    path, _ = ckpt
    text, message = BAD_YAML[case]
    out = tmp_path / "out.json"
    code, stdout, err = _run(capsys, "--ckpt", path, "--requests", _yaml(tmp_path / "req.yaml", text), "--out", out)
    assert code == 2 and stdout == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ") and message in err, err
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]


@pytest.mark.parametrize("argv, message", [
    (["--out", "{tmp}/out.csv"], "unknown format"),
    (["--requests", "{tmp}/req.json", "--out", "{tmp}/req.json"], "request file itself"),
    (["--out", "{tmp}"], "is a directory"),
    (["--site", "foot"], "unknown --site 'foot'"),
    (["--sampler", "magic"], "unknown --sampler"),
    (["--reading", "magic"], "unknown --reading"),
    (["--reach-tol-mm", "-1"], "--reach-tol-mm"),
    (["--requests", "{tmp}/missing.yaml"], "does not exist"),
    (["--requests", "{tmp}/req.txt"], "unknown format '.txt'"),
    (["--requests", "{tmp}/bad.npz"], "unknown arrays ['q']"),
    (["--ckpt", "{tmp}/missing.ckpt"], "does not exist"),
])
def test_bad_arguments_exit_2(ckpt, tmp_path, capsys, argv, message):
    path, _ = ckpt
    _yaml(tmp_path / "req.yaml", "- target: [0.3, -0.6, 0.0]\n")
    _yaml(tmp_path / "req.json", '[{"q_ref": [0, 0]}]')
    save_npz(str(tmp_path / "bad.npz"), q=np.zeros((1, 2)))
    args = {"--ckpt": path, "--requests": str(tmp_path / "req.yaml"), "--out": str(tmp_path / "out.json")}
    args.update(zip(argv[::2], (a.format(tmp=tmp_path) for a in argv[1::2])))
    code, stdout, err = _run(capsys, *[x for kv in args.items() for x in kv])
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out.json").exists()
