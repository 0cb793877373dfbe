"""The README's Python and YAML examples run, and return commands.

Every fenced ``python`` and ``yaml`` block of README.md is extracted and either run against a small trained
checkpoint or listed in ``NOT_RUN`` with the reason; a new block that is neither fails
``test_every_block_is_run_or_explained``. Feasibility is physics (the QP on the true arm at q_ref), not the
network, so a briefly trained checkpoint decides ``ok`` / ``infeasible`` as a 10000-epoch one does: the README's
faults were chosen feasible, and its infeasible example infeasible, on a 10000-epoch checkpoint.

The Python blocks run in README order in one namespace, from a folder where the README's checkpoint path
exists, with ``send`` recording what the controller would receive.
"""
from __future__ import annotations

import inspect
import json
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from physics_checks import fit_tiny_checkpoint, torque_residual, train_schema

from lightning_bodyschema.apps.predict import predict_main
from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.sim.spring import tension_from_elongation

ROOT = Path(__file__).resolve().parents[2]
README_CKPT = "runs/quick/diff-1000/lightning_logs/version_0/checkpoints/last.ckpt"  # the path the README loads
# fenced blocks, possibly indented (inside a list item): indent, language, body
_FENCE = re.compile(r"^( *)```(\w+)\n(.*?)^\1```", re.MULTILINE | re.DOTALL)

# blocks identified by a line they contain
FROM_PYTHON, INFEASIBLE, ADAPTER, NEW_SCHEMA = ("schema.adapt(q_ref, faults)", "too_short = Faults",
                                                "schema.adapter(", "class RegressionSchema")
ADAPTING_SCHEMA = "class AdaptingSchema"
DIAGNOSE = "schema.diagnose(log"
REQUESTS, OWN_ROBOT = ("- q_ref:", "model: path/to/my_robot.xml")
RUN = {"python": (FROM_PYTHON, INFEASIBLE, ADAPTER, NEW_SCHEMA, ADAPTING_SCHEMA, DIAGNOSE), "yaml": (REQUESTS, OWN_ROBOT)}
# marker -> why a block cannot run here
NOT_RUN: dict[str, str] = {"static_optimization(arm": "needs myo-sim and two MyoSuite builds: run by "
                                                     "tests/statics/test_static_opt.py::test_readme_example (slow)",
                            "inverse_dynamics(arm": "needs myo-sim and a MyoSuite build: run by "
                                                    "tests/statics/test_inverse_dynamics.py::test_readme_example (slow)"}


def readme_blocks(language: str) -> list[str]:
    text = (ROOT / "README.md").read_text()
    return [textwrap.dedent(textwrap.indent(body, indent)) if indent else body
            for indent, lang, body in _FENCE.findall(text) if lang == language]


def block(language: str, marker: str) -> str:
    found = [b for b in readme_blocks(language) if marker in b]
    assert len(found) == 1, f"expected one README {language} block containing {marker!r}, found {len(found)}"
    return found[0]


def test_every_block_is_run_or_explained():
    for language in ("python", "yaml"):
        for body in readme_blocks(language):
            markers = [m for m in (*RUN[language], *NOT_RUN) if m in body]
            assert len(markers) == 1, f"README {language} block neither run by this file nor in NOT_RUN:\n{body}"


# ---------------------------------------------------------------------------- the checkpoint and the namespace
@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A folder holding the README's checkpoint path: a 60-epoch diffusion fit of the paper arm. (After 3 epochs
    the commands are still absurd, beyond 20 healthy spreads, and ``adapt`` rightly calls them ``out_of_range``;
    from ~30 epochs on they are plausible and the physics decides.)"""
    folder = tmp_path_factory.mktemp("readme")
    ckpt = fit_tiny_checkpoint(folder / "runs" / "quick" / "diff-1000", "--data.n_samples=200",
                               "--faults.every_n_epochs=0", "--progress.enabled=false", epochs=60)
    assert Path(ckpt) == folder / README_CKPT
    return folder


@pytest.fixture(scope="module")
def readme_python(workdir):
    """The namespace after the "From Python" block, and what it sent."""
    sent = []
    namespace = {"send": lambda l_motor_m, f_n: sent.append((np.asarray(l_motor_m), np.asarray(f_n)))}
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(workdir)
        exec(compile(block("python", FROM_PYTHON), "README.md:From Python", "exec"), namespace)
    return namespace, sent


def test_from_python_sends_a_command_that_holds_the_posture(readme_python):
    namespace, sent = readme_python
    result, schema = namespace["result"], namespace["schema"]
    assert list(result.status) == ["ok"]
    assert len(sent) == 1  # send() ran: the example returns a command
    l_motor_m, f_n = sent[0]
    assert np.isfinite(l_motor_m).all() and np.isfinite(f_n).all()
    assert f_n[0] == 0.0  # the cut shoulder flexor pulls nothing (tensions are clipped into [0, f_max])
    assert (0.0 <= f_n).all() and (f_n <= schema.spring.f_max_n).all()
    assert result.diagnostics["feasible"][0]  # the physics says a command exists at all


def test_the_infeasible_example_is_infeasible(readme_python):
    namespace, _ = readme_python
    exec(compile(block("python", INFEASIBLE), "README.md:infeasible", "exec"), namespace)  # its assert holds
    result, schema, q_ref = namespace["result"], namespace["schema"], namespace["q_ref"]
    assert not result.diagnostics["feasible"][0]
    assert np.isnan(result.l_motor_m).all() and np.isnan(result.f_n).all()
    # the README's reason: at q_ref the jammed wire would need more than f_max, whatever the other muscles do
    l_geo, _, _ = schema.robot_model.kinematics(np.asarray(q_ref))
    stretch_m = l_geo[0, schema.robot_model.muscle_names.index("elbow_flexor")] - 0.140
    assert stretch_m == pytest.approx(0.0129, abs=5e-5)
    assert tension_from_elongation(np.array(stretch_m), schema.spring) == pytest.approx(295.4, abs=0.5)  # N, > f_max


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_the_prepared_adapter_returns_what_adapt_returns(readme_python, compiled):
    """The block as written compiles the loop (~20 s on first use): the default run uses the eager loop."""
    namespace, _ = readme_python
    source = block("python", ADAPTER)
    if not compiled:
        assert "compiled=True" in source
        source = source.replace("compiled=True", "compiled=False")
    ns = dict(namespace)
    exec(compile(source, "README.md:adapter", "exec"), ns)
    reference = ns["schema"].adapt(ns["q_ref"], ns["faults"], n_steps=20)
    assert list(ns["result"].status) == list(reference.status) == ["ok"]
    np.testing.assert_allclose(ns["result"].l_motor_m, reference.l_motor_m, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ns["result"].f_n, reference.f_n, rtol=0, atol=1e-3)


def test_the_new_architecture_block_learns_the_body_schema(dm):
    """The README's RegressionSchema (with the imports of examples/regression_schema.py) trains through the base
    class: after 40 epochs its healthy commands hold the arm far better than the mean command of the data."""
    namespace = {}
    exec("from typing import Optional\nfrom torch import nn\nfrom lightning_bodyschema.schemas import BodySchema\n"
         + block("python", NEW_SCHEMA), namespace)
    schema, _, _ = train_schema(namespace["RegressionSchema"], 40, dm)
    q, x = dm.splits["val"]
    learned = schema.physical_errors(q, x)["eq_residual_N_m"]
    mean_f = np.broadcast_to(dm.splits["train"][1][:, schema.n_muscles:].numpy().mean(0), (len(q), schema.n_muscles))
    baseline = float(np.median(torque_residual(schema.robot_model, q.numpy(), mean_f)))
    assert learned < 0.5 * baseline, (learned, baseline)


def test_the_new_architecture_block_is_examples_regression_schema():
    """The README shows the network examples/regression_schema.py trains (two hidden layers, as the file has)."""
    def network(text: str) -> str:
        return "".join(text[text.index("nn.Sequential("):].split(")\n")[0].split())

    assert network(block("python", NEW_SCHEMA)) == network((ROOT / "examples" / "regression_schema.py").read_text())


def test_the_adapting_block_meets_a_cut_through_the_adapter(dm):
    """The README's capability example: declared ``adapts_normalized``, the adapter runs its descent, and a cut
    muscle's tension goes from what the healthy command asks to ~0."""
    from lightning_bodyschema.faults import Faults

    namespace = {}
    exec("from typing import Optional\nfrom torch import nn\nfrom lightning_bodyschema.schemas import BodySchema\n"
         + block("python", NEW_SCHEMA) + block("python", ADAPTING_SCHEMA), namespace)
    schema, _, _ = train_schema(namespace["AdaptingSchema"], 5, dm)
    q = dm.splits["val"][0][:4].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["elbow_flexor"]] * 4)
    cut = schema.robot_model.muscle_names.index("elbow_flexor")
    healthy_f = schema.infer(q)[1][:, cut]
    result = schema.adapt(q, faults, check_physics=False)
    assert (result.status == "ok").all() and healthy_f.min() > 1.0
    assert result.diagnostics["cut_violation_n"].max() < 0.01 * healthy_f.min()


def test_the_diagnosis_block_names_a_cut_and_adapts_to_it(tmp_path):
    """The "When you don't know what broke" block on a log of the paper arm with its elbow flexor cut (simulated in
    MuJoCo from the checkpoint's own healthy commands, with the documented noise). The checkpoint at the README's
    path is a structured schema here (fitted in seconds): a 60-epoch diffusion body is centimetres off (its measured
    body error), and on such a body no cut is observable (the block then rightly says ``no_fault``)."""
    from physics_checks import fit_structured

    from lightning_bodyschema.diagnosis import SensorLog, SensorNoise, write_sensor_log
    from lightning_bodyschema.diagnosis.sensors import noisy, true_readings
    from lightning_bodyschema.faults import Faults

    dm = EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None)
    schema, trainer = fit_structured(dm, length_model="per_muscle", path_degree=10, torque_model="gravity")
    (tmp_path / README_CKPT).parent.mkdir(parents=True)
    trainer.save_checkpoint(str(tmp_path / README_CKPT), weights_only=False)
    arm = schema.robot_model
    q = np.array([[0.3, -0.2], [0.5, 0.1], [-0.2, 0.4]])
    l_cmd, f_cmd = schema.infer(q)
    faults = Faults.from_names(arm.muscle_names, cut=[["elbow_flexor"]] * 3)
    read = noisy(true_readings(arm, schema.spring, q, l_cmd, f_cmd, faults), schema.spring, SensorNoise(),
                 np.random.default_rng(0))
    write_sensor_log(str(tmp_path / "log.csv"), SensorLog.from_rows(arm.joint_names, arm.muscle_names, read[0],
                                                                    read[1], l_cmd, f_cmd, read[2]))
    namespace = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(tmp_path)
        exec(compile(block("python", DIAGNOSE), "README.md:diagnose", "exec"), namespace)
    record, result = namespace["diagnosis"].records()[0], namespace["result"]
    assert record["status"] == "identified" and record["faults"] == {"cut": ["elbow_flexor"]}
    assert list(result.status) == ["ok"] and result.f_n[0, arm.muscle_names.index("elbow_flexor")] == 0.0


# ---------------------------------------------------------------------------- YAML
def test_the_request_block_is_examples_requests_yaml():
    shown = yaml.safe_load(block("yaml", REQUESTS))
    assert shown == yaml.safe_load((ROOT / "examples" / "requests.yaml").read_text())


def test_every_request_of_examples_requests_yaml_returns_a_command(workdir, tmp_path):
    out = tmp_path / "commands.json"
    predict_main(["--ckpt", str(workdir / README_CKPT), "--requests", str(ROOT / "examples" / "requests.yaml"),
                  "--out", str(out)])
    results = json.loads(out.read_text())["results"]
    assert [r["status"] for r in results] == ["ok"] * len(results) and len(results) == 2
    for r in results:
        assert all(np.isfinite(r["l_motor"])) and all(np.isfinite(r["f"]))
    weak = results[1]
    assert weak["f"][2] <= 60.0  # the weakened elbow flexor's tension stays within its f_max'


def test_the_own_robot_block_names_real_data_options():
    """The "Bring your own robot" block has a placeholder path, so it cannot run; its keys must be real options."""
    shown = yaml.safe_load(block("yaml", OWN_ROBOT))
    options = set(inspect.signature(EquilibriumDataModule.__init__).parameters) - {"self"}
    assert set(shown["data"]) <= options, set(shown["data"]) - options
