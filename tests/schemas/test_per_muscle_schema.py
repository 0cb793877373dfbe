"""StructuredSchema(length_model="per_muscle"): which joints each muscle crosses (MJCF, user, data), a body that
matches MuJoCo's to micrometres on the paper arm, exactly zero moment arms off the crossed joints, recorded data,
bad input, and checkpoints of the dense schema still answering as before."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from physics_checks import fit_structured as _fit

from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.data import EquilibriumDataModule, RecordedDataModule
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks import cell_fit as cells
from lightning_bodyschema.schemas import StructuredSchema, load_schema
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.robot import check_muscle_joints

PAPER_JOINTS = {"shoulder_flexor": ["shoulder"], "shoulder_extensor": ["shoulder"], "elbow_flexor": ["elbow"],
                "elbow_extensor": ["elbow"], "biarticular_flexor": ["shoulder", "elbow"],
                "biarticular_extensor": ["shoulder", "elbow"]}
PER_MUSCLE = dict(length_model="per_muscle", path_degree=10, torque_model="polynomial", torque_degree=8)


@pytest.fixture(scope="module")
def paper_arm():
    return _fit(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), **PER_MUSCLE)


def test_crossing_comes_from_the_mjcf():
    assert MusculoskeletalModel("paper_arm").crossing().tolist() == [
        [True, False], [True, False], [False, True], [False, True], [True, True], [True, True]]


def test_myoelbow_crossing_from_its_tendon_jacobian():
    pytest.importorskip("myo_sim")
    elbow = MusculoskeletalModel("myo:myoelbow_2dof")  # the triceps long head and biceps cross the shoulder too
    crossing = dict(zip(elbow.muscle_names, elbow.crossing()[:, 0]))
    assert crossing == {"TRIlong_tendon": True, "TRIlat_tendon": False, "TRImed_tendon": False,
                        "BIClong_tendon": True, "BICshort_tendon": True, "BRA_tendon": False}
    assert elbow.crossing()[:, 1].all()


@pytest.mark.slow
def test_myoarm_crossing_has_199_uncrossed_pairs():
    pytest.importorskip("myo_sim")
    import yaml

    locks = yaml.safe_load(open("configs/myoarm.yaml"))["data"]["locked_joints"]
    crossing = MusculoskeletalModel("myo:myoarm", locked_joints=locks).crossing()
    assert crossing.shape == (50, 7) and int((~crossing).sum()) == 199
    assert sorted(crossing.sum(1).tolist()) == sorted([1] * 6 + [2] * 5 + [3] * 23 + [4] * 14 + [5] * 2)


def test_configs_myoarm_is_the_geometric_body_its_polynomial_one_under_both_names_and_one_robot():
    import yaml

    arm, polynomial, per_muscle, dense = (yaml.safe_load(open(f"configs/{name}.yaml")) for name in
                                          ("myoarm", "myoarm-polynomial", "myoarm-per-muscle", "myoarm-dense"))
    assert arm["model"]["init_args"]["length_model"] == "geometric"  # the recommended myoArm body (issue 51)
    assert polynomial["model"]["init_args"]["length_model"] == "per_muscle"  # what configs/myoarm.yaml was
    assert {k: v for k, v in polynomial.items() if k != "trainer"} == {
        k: v for k, v in per_muscle.items() if k != "trainer"}
    for other in (polynomial, per_muscle, dense):  # one robot and one dataset
        assert other["data"] == arm["data"]
    assert "length_model" not in dense["model"]["init_args"]  # the dense MLP body


def test_the_learned_body_matches_mujoco_and_moment_arms_vanish_off_the_crossed_joints(paper_arm):
    schema, _ = paper_arm
    assert schema.hparams.muscle_joints == PAPER_JOINTS  # stored with the checkpoint's hyperparameters
    q = schema.robot_model.sample_q(np.random.default_rng(5), 300)
    l_true, G_true, tau_true = schema.robot_model.kinematics(q)
    l_geo, G, tau = schema.body_si(torch.as_tensor(q))
    assert np.median(np.abs(l_geo - l_true)) < 1e-6  # least squares on exact lengths: below a micrometre
    assert np.median(np.abs(G - G_true)) < 1e-5
    assert np.median(np.linalg.norm(tau - tau_true, axis=1)) < 0.01 * np.median(np.linalg.norm(tau_true, axis=1))
    uncrossed = np.abs(G_true).max(0) < 1e-9  # MuJoCo: rounding only (sim.model.UNCROSSED_ARM_M)
    assert uncrossed.sum() == 4 and (G[:, uncrossed] == 0).all()


def test_moment_arms_are_finite_differences_of_the_learned_lengths(paper_arm):
    schema = paper_arm[0].double()
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(6), 20))
    G = schema.body_si(q)[1]
    h = 1e-6
    for j in range(schema.n_joints):
        step = torch.zeros(schema.n_joints, dtype=torch.float64)
        step[j] = h
        fd = (schema.body_si(q + step)[0] - schema.body_si(q - step)[0]) / (2 * h)
        np.testing.assert_allclose(G[:, :, j], fd, atol=1e-9, rtol=1e-6)
    schema.float()


def test_a_refit_in_eval_mode_is_not_answered_from_the_inference_cache(paper_arm):
    """``body`` keeps the fitted coefficients' layouts in the inference cache: a least-squares refit clears it (else
    the refitted schema would answer with the old body)."""
    schema = copy.deepcopy(paper_arm[0]).eval()
    data = EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None)
    data.setup("fit")
    q, x = data.splits["train"]
    probe = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(7), 5))
    before = schema.body_si(probe)[0]  # builds the cache's entry
    longer = x.clone()
    longer[:, :schema.n_muscles] += 1e-3  # every motor 1 mm longer at the same tension
    schema._fit_paths(q, longer)
    np.testing.assert_allclose(schema.body_si(probe)[0], before + 1e-3, atol=1e-7)


def test_a_copy_starts_with_an_empty_inference_cache_and_answers_the_same(paper_arm):
    """A deep copy of a schema whose cache holds numpy snapshots (the path switches'; they hold the numpy module,
    which does not copy) copies, builds its own entries, and answers as the original."""
    schema = copy.deepcopy(paper_arm[0]).eval()
    q = schema.robot_model.sample_q(np.random.default_rng(8), 5)
    switches = schema.path_switches(q)
    copied = copy.deepcopy(schema)
    assert len(schema.inference_cache) > 0 and len(copied.inference_cache) == 0
    for a, b in zip(schema.body_si(torch.as_tensor(q)), copied.body_si(torch.as_tensor(q))):
        np.testing.assert_array_equal(a, b)
    assert all(np.array_equal(v, copied.path_switches(q)[k]) for k, v in switches.items())


def test_checkpoint_round_trip_answers_the_same(paper_arm, tmp_path):
    schema, trainer = paper_arm
    path = str(tmp_path / "per_muscle.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    loaded = load_schema(path)
    q = torch.tensor([[0.3, 0.8], [-0.2, 1.2]], dtype=torch.float64)
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


def _assert_answers_the_same_without(schema, trainer, path, keys):
    """Saved without the hyperparameters ``keys`` (a checkpoint from before they existed), it loads and gives the
    same body."""
    trainer.save_checkpoint(path, weights_only=False)
    checkpoint = torch.load(path, weights_only=True)
    for key in keys:
        del checkpoint["hyper_parameters"][key]
    torch.save(checkpoint, path)
    loaded = load_schema(path)
    q = torch.tensor([[0.3, 0.8], [-0.2, 1.2]], dtype=torch.float64)
    for a, b in zip(schema.body_si(q), loaded.body_si(q)):
        np.testing.assert_array_equal(a, b)


def test_a_checkpoint_with_cells_answers_the_same_and_still_matches_mujoco(tmp_path, monkeypatch):
    monkeypatch.setattr(cells, "CELL_MEDIANS", 1.0)  # the paper arm's paths are smooth: cells for the worse half
    monkeypatch.setattr(cells, "CELL_FLOOR", 0.0)
    schema, trainer = _fit(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), path_cells=2, **PER_MUSCLE)
    assert len(schema.length_net.cell_muscles) > 0
    path = str(tmp_path / "cells.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    q = schema.robot_model.sample_q(np.random.default_rng(8), 300)
    for a, b in zip(schema.body_si(torch.as_tensor(q)), load_schema(path).body_si(torch.as_tensor(q))):
        np.testing.assert_array_equal(a, b)
    l_true, G_true, _ = schema.robot_model.kinematics(q)
    l_geo, G, _ = schema.body_si(torch.as_tensor(q))
    assert np.median(np.abs(l_geo - l_true)) < 1e-6 and np.median(np.abs(G - G_true)) < 1e-5


def test_separable_paths_take_their_groups_from_the_mjcf_and_a_checkpoint_keeps_them(tmp_path):
    schema, trainer = _fit(EquilibriumDataModule(n_samples=1000, seed=0, cache_dir=None), path_separable=True,
                           **PER_MUSCLE)
    assert schema.hparams.path_blocks == [[0, -1], [0, -1], [-1, 0], [-1, 0], [0, 1], [0, 1]]
    path = str(tmp_path / "separable.ckpt")
    trainer.save_checkpoint(path, weights_only=False)
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(9), 300))
    for a, b in zip(schema.body_si(q), load_schema(path).body_si(q)):
        np.testing.assert_array_equal(a, b)
    l_true, G_true, _ = schema.robot_model.kinematics(q.numpy())
    l_geo, G, _ = schema.body_si(q)
    assert np.median(np.abs(l_geo - l_true)) < 1e-6 and np.median(np.abs(G - G_true)) < 1e-5
    assert (G[:, 4:, :] != 0).all()  # the biarticular muscles keep both moment arms


def test_a_per_muscle_checkpoint_from_before_the_branches_answers_as_before(paper_arm, tmp_path):
    _assert_answers_the_same_without(*paper_arm, str(tmp_path / "one_branch.ckpt"),
                                     ("path_branches", "path_gate_degree"))


def test_a_per_muscle_checkpoint_from_before_the_cells_answers_as_before(paper_arm, tmp_path):
    _assert_answers_the_same_without(*paper_arm, str(tmp_path / "no_cells.ckpt"), ("path_cells", "path_cell_degrees"))


def test_a_dense_schema_checkpoint_without_the_new_options_answers_as_before(tmp_path):
    """A checkpoint written before length_model existed (its hyperparameters lack the new keys) loads as the dense
    schema and gives the same body."""
    schema, trainer = _fit(EquilibriumDataModule(n_samples=200, seed=1, cache_dir=None), hidden=16, n_hidden=2)
    _assert_answers_the_same_without(schema, trainer, str(tmp_path / "old.ckpt"), (
        "length_model", "path_degree", "path_terms", "path_hidden", "path_layers", "muscle_joints", "torque_degree",
        "path_branches", "path_gate_degree"))


# ---------------------------------------------------------------------------- recorded data
@pytest.fixture(scope="module")
def recorded_csv(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("recorded") / "arm.csv")
    make_dataset_main(["--n", "600", "--seed", "3", "--out", path])
    return path


def test_recorded_data_detects_the_crossings_and_says_so(recorded_csv, capsys):
    schema, _ = _fit(RecordedDataModule(recorded_csv, seed=3), **PER_MUSCLE)
    assert schema.hparams.muscle_joints == PAPER_JOINTS
    assert "muscle_joints detected from the data" in capsys.readouterr().err
    q = MusculoskeletalModel("paper_arm").sample_q(np.random.default_rng(7), 50)
    G = schema.body_si(torch.as_tensor(q))[1]
    assert (G[:, 0, 1] == 0).all() and (G[:, 2, 0] == 0).all()


def test_separable_paths_on_recorded_data_are_refused_in_one_line(recorded_csv):
    with pytest.raises(BodySchemaInputError, match="path_separable=True needs the robot's MJCF.*path_separable=False"):
        _fit(RecordedDataModule(recorded_csv, seed=3), path_separable=True, **PER_MUSCLE)


def test_a_recorded_mapping_that_misses_a_crossed_joint_warns_with_the_figure(recorded_csv):
    wrong = {**PAPER_JOINTS, "biarticular_flexor": ["elbow"]}
    said = r"'biarticular_flexor' is said not to cross joint 'shoulder'.* [0-9.]+ mm/rad"
    with pytest.warns(UserWarning, match=said):
        schema, _ = _fit(RecordedDataModule(recorded_csv, seed=3, muscle_joints=wrong), **PER_MUSCLE)
    assert schema.hparams.muscle_joints["biarticular_flexor"] == ["elbow"]


@pytest.mark.parametrize("mapping, match", [
    ({**PAPER_JOINTS, "no_such_muscle": ["elbow"]}, "unknown muscle 'no_such_muscle'; the muscles are"),
    ({**PAPER_JOINTS, "elbow_flexor": ["wrist"]}, r"muscle_joints\['elbow_flexor'\] names unknown joint 'wrist'; "
                                                  "the joints are"),
    ({k: v for k, v in PAPER_JOINTS.items() if k != "elbow_flexor"}, "no entry for muscle"),
    ({**PAPER_JOINTS, "elbow_flexor": []}, "is empty"),
])
def test_bad_muscle_joints_are_refused_in_one_line(recorded_csv, mapping, match):
    with pytest.raises(BodySchemaInputError, match=match) as err:
        RecordedDataModule(recorded_csv, seed=3, muscle_joints=mapping)
    assert "\n" not in str(err.value)


def test_bad_length_and_torque_models_are_refused():
    robot = EquilibriumDataModule(n_samples=20, cache_dir=None).robot
    with pytest.raises(BodySchemaInputError,
                       match=r"length_model='spline'; allowed: \['mlp', 'per_muscle', 'geometric'\]"):
        StructuredSchema(robot=robot, length_model="spline")
    with pytest.raises(BodySchemaInputError, match="needs length_model='per_muscle'"):
        StructuredSchema(robot=robot, torque_model="polynomial")
    with pytest.raises(BodySchemaInputError, match="unknown joint 'wrist'"):
        StructuredSchema(robot=robot, length_model="per_muscle",
                         muscle_joints={**PAPER_JOINTS, "elbow_flexor": "wrist"})
    assert check_muscle_joints(PAPER_JOINTS, list(PAPER_JOINTS), ["shoulder", "elbow"]) == PAPER_JOINTS
    with pytest.raises(BodySchemaInputError, match=r"branches=3; allowed: 1 \(one polynomial per muscle\) or 2"):
        StructuredSchema(robot=robot, length_model="per_muscle", muscle_joints=PAPER_JOINTS, path_branches=3)
    with pytest.raises(BodySchemaInputError, match=r"path_cells=0 must be an integer >= 1 \(pieces per joint"):
        StructuredSchema(robot=robot, length_model="per_muscle", muscle_joints=PAPER_JOINTS, path_cells=0)
    allowed = r"path_cell_joints='shoulder'; allowed: \['crossed', 'largest_group'\]"
    with pytest.raises(BodySchemaInputError, match=allowed):
        StructuredSchema(robot=robot, length_model="per_muscle", muscle_joints=PAPER_JOINTS, path_cells=2,
                         path_cell_joints="shoulder")
    with pytest.raises(BodySchemaInputError, match=r"path_cell_keep='p99'; allowed: \['median_and_p99', 'median'\]"):
        StructuredSchema(robot=robot, length_model="per_muscle", muscle_joints=PAPER_JOINTS, path_cell_keep="p99")
    with pytest.raises(BodySchemaInputError, match="path_separable=True needs length_model='per_muscle'"):
        StructuredSchema(robot=robot, path_separable=True)


def test_a_gravity_torque_fitted_before_the_slide_fix_is_refused_in_one_line():
    """Format 1 checkpoints fitted the masses to kinematics that rotated each slide joint's body (myoLegs' knees): a
    schema on such a tree refuses them, one on a tree of hinges only (the paper arm) takes them."""
    pytest.importorskip("myo_sim")
    legs = EquilibriumDataModule(model="myo:myolegs", fixed_base=True, n_samples=20, cache_dir=None).robot
    schema = StructuredSchema(robot=legs, length_model="per_muscle", torque_model="gravity")
    assert schema.torque_net.slides == 8
    assert "refit it with `bodyschema fit`" in schema.checkpoint_refusal({"model_xml_sha256": "0" * 64})
    assert schema.checkpoint_refusal({"format": 2}) is None
    arm = EquilibriumDataModule(n_samples=20, cache_dir=None).robot
    hinges = StructuredSchema(robot=arm, length_model="per_muscle", torque_model="gravity", muscle_joints=PAPER_JOINTS)
    assert hinges.torque_net.slides == 0 and hinges.checkpoint_refusal({}) is None
