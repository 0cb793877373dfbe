"""Recorded data (a robot's own logs, no MJCF): bad files refused with one line, bad rows dropped and counted,
make_dataset's output trains the very weights the simulation module trains, and a model-free schema never calls an
unchecked command ``ok``."""
from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch

from lightning_bodyschema.apps.case_tools import adapt_cases_main, make_cases_main
from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.data import EquilibriumDataModule, ModelFreeRobot, RecordedDataModule, read_recorded
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation.cases import make_fault_cases
from lightning_bodyschema.npz import load_npz, save_npz
from lightning_bodyschema.schemas import DiffusionSchema, load_schema
from lightning_bodyschema.sim import MusculoskeletalModel, SpringParams

N = 120
HEADER = "q_a,q_b,l_m1,l_m2,f_m1,f_m2"


def _rows(n=20, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.uniform(0.1, 0.2, (n, 2)), rng.uniform(1, 100, (n, 2))])


def _csv(path, header=HEADER, rows=None, head_lines=("# units: SI",), extra_rows=()):
    rows = _rows() if rows is None else rows
    lines = list(head_lines) + [header] + [",".join(f"{v:.17g}" for v in row) for row in rows] + list(extra_rows)
    path.write_text("\n".join(lines) + "\n")
    return str(path)


# ---------------------------------------------------------------------------- bad files: one line, exit 2
BAD_FILES = {
    # id: (writer, extra CLI args, words the one error line must contain)
    "missing_column": (lambda p: _csv(p, header="q_a,q_b,l_m1,l_m2,f_m1,f_x", rows=_rows()), (),
                       ("missing column", "f_m2")),
    "unknown_muscle": (lambda p: _csv(p), ("--data.muscles=[m1,m9]",), ("unknown muscle", "m2", "['m1', 'm9']")),
    "text_in_number_column": (lambda p: _csv(p, extra_rows=("0.1,0.2,0.15,0.15,abc,3",)), (),
                              ("column 'f_m1'", "'abc' is not a number")),
    "empty_file": (lambda p: (p.write_text(""), str(p))[1], (), ("is empty", "q_<joint>")),
    "wrong_units_flag": (lambda p: _csv(p, head_lines=("# units: deg, mm",)), (),
                         ("units flag 'deg, mm'", "SI")),
    "header_only": (lambda p: _csv(p, rows=np.empty((0, 6))), (), ("header but no rows",)),
    "column_not_q_l_f": (lambda p: _csv(p, header="q_a,q_b,l_m1,l_m2,f_m1,time", rows=_rows()), (),
                         ("column 'time'", "q_<joint>")),
    "ragged_row": (lambda p: _csv(p, extra_rows=("0.1,0.2,0.15",)), (), ("3 fields", "6 columns")),
    "repeated_column": (lambda p: _csv(p, header="q_a,q_b,l_m1,l_m1,f_m1,f_m2", rows=_rows()), (),
                        ("columns ['l_m1'] appear more than once",)),
    "npz_not_columns": (lambda p: (save_npz(str(p.with_suffix(".npz")), q=np.zeros((5, 2))),
                                   str(p.with_suffix(".npz")))[1], (), ("column 'q'",)),
}


@pytest.mark.parametrize("name", list(BAD_FILES))
def test_bad_recorded_file_is_one_clear_error_exit_2(name, tmp_path, capsys, monkeypatch):
    writer, extra, words = BAD_FILES[name]
    path = writer(tmp_path / "logs.csv")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["fit", "--model=DiffusionSchema", "--data=RecordedDataModule", f"--data.path={path}",
                  "--trainer.max_epochs=1", *extra])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("Seed set")]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]!r}"
    assert not list(tmp_path.glob("lightning_logs")), "nothing may be written for a bad file"


def test_a_csv_saved_with_a_byte_order_mark_reads_like_one_without(tmp_path):
    """Excel's "CSV UTF-8" starts with a BOM, which made the header one unknown column."""
    plain = read_recorded(_csv(tmp_path / "plain.csv"))
    marked = tmp_path / "bom.csv"
    marked.write_bytes(b"\xef\xbb\xbf" + (tmp_path / "plain.csv").read_bytes())
    table = read_recorded(str(marked))
    assert table.joints == plain.joints and table.muscles == plain.muscles
    np.testing.assert_array_equal(table.q, plain.q)


def test_nan_and_out_of_range_rows_are_dropped_and_counted(tmp_path, capsys):
    rows = _rows(30)
    rows[3, 4] = np.nan  # a missing tension reading
    rows[5, 0] = 1.5  # outside q_a's range below
    rows[7, 5] = 170.0  # above the 150 N tension limit
    path = _csv(tmp_path / "logs.csv", rows=rows, head_lines=("# units: SI", "# range q_a -1 1"))
    dm = RecordedDataModule(path)
    assert "30 rows, kept 27; dropped 1 with NaN/inf and 2 outside the limits" in capsys.readouterr().out
    kept = np.delete(rows, [3, 5, 7], axis=0)
    np.testing.assert_array_equal(dm.arrays["q"], kept[:, :2])
    np.testing.assert_array_equal(dm.arrays["f"], kept[:, 4:])
    # q_b has no range line: its range is the kept data's span; q_a's is the file's
    np.testing.assert_array_equal(dm.robot_model.q_range, [[-1, 1], [kept[:, 1].min(), kept[:, 1].max()]])


# ---------------------------------------------------------------------------- the round trip
@pytest.fixture(scope="module")
def sim_and_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("roundtrip")
    paths = {ext: str(folder / f"arm.{ext}") for ext in ("csv", "npz")}
    for path in paths.values():
        make_dataset_main(["--n", str(N), "--seed", "3", "--out", path])
    sim = EquilibriumDataModule(n_samples=N, seed=3, cache_dir=None)
    return sim, paths


def _train(dm, epochs=4):
    L.seed_everything(0, verbose=False)
    schema = DiffusionSchema(robot=dm.robot)
    trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, check_val_every_n_epoch=10 ** 6, num_sanity_val_steps=0)
    trainer.fit(schema, dm)
    return schema.eval(), trainer


@pytest.mark.parametrize("ext", ["csv", "npz"])
def test_make_dataset_read_back_trains_the_simulation_modules_weights(sim_and_files, ext):
    sim, paths = sim_and_files
    recorded = RecordedDataModule(paths[ext], seed=3)
    assert isinstance(recorded.robot_model, ModelFreeRobot) and "model_xml" not in recorded.robot
    assert recorded.robot_model.joint_names == sim.robot_model.joint_names
    assert recorded.robot_model.muscle_names == sim.robot_model.muscle_names
    np.testing.assert_array_equal(recorded.robot_model.q_range, sim.robot_model.q_range)  # from the range lines
    a, _ = _train(sim)
    b, _ = _train(recorded)
    np.testing.assert_array_equal(a.normalizer.x_std.numpy(), b.normalizer.x_std.numpy())
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for name in sa:
        assert torch.equal(sa[name], sb[name]), name


# ---------------------------------------------------------------------------- schemas without a model
@pytest.fixture(scope="module")
def model_free(sim_and_files, tmp_path_factory):
    """(model-free schema from its checkpoint, the same weights with the MJCF, checkpoint path)."""
    sim, paths = sim_and_files
    schema, trainer = _train(RecordedDataModule(paths["npz"], seed=3), epochs=150)  # commands within range
    ckpt = str(tmp_path_factory.mktemp("ckpt") / "recorded.ckpt")
    trainer.save_checkpoint(ckpt, weights_only=False)
    with_model = DiffusionSchema(robot=sim.robot)
    with_model.load_state_dict(schema.state_dict())
    return load_schema(ckpt), with_model.eval(), ckpt


def test_model_free_adapt_is_unchecked_never_ok_unless_the_check_is_turned_off(model_free, sim_and_files):
    schema, with_model, _ = model_free
    sim = sim_and_files[0]
    sim.setup("test")
    q, x = sim.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :6].numpy(), 4, seed=0)
    assert not schema.has_physics and with_model.has_physics
    assert schema.robot_model.muscle_names == with_model.robot_model.muscle_names  # names and limits in the ckpt
    torch.manual_seed(0)
    result = schema.adapt(cases.q_ref, cases.faults, n_steps=20)
    torch.manual_seed(0)
    reference = with_model.adapt(cases.q_ref, cases.faults, n_steps=20, check_physics=False)
    assert not result.ok.any() and reference.ok.sum() >= 8
    # where the schema with a model says ok (check off), the model-free one says unchecked; other statuses agree
    np.testing.assert_array_equal(result.status, np.where(reference.ok, "unchecked", reference.status))
    # the same command as the schema with a model: unchecked is a flag, not another answer (the same weights, seed
    # and arithmetic in the same order: bit for bit)
    np.testing.assert_array_equal(result.l_motor_m, reference.l_motor_m)
    np.testing.assert_array_equal(result.f_n, reference.f_n)
    torch.manual_seed(0)
    unchecked_off = schema.adapt(cases.q_ref, cases.faults, n_steps=20, check_physics=False)
    np.testing.assert_array_equal(unchecked_off.status, reference.status)
    with pytest.raises(BodySchemaInputError, match="without a robot model"):
        schema.adapt_to_target([[0.3, -0.6, 0.0]], cases.faults.take(np.array([0])))


def test_tools_make_and_adapt_cases_on_a_model_free_checkpoint(model_free, tmp_path):
    _, _, ckpt = model_free
    cases, out = str(tmp_path / "cases.npz"), str(tmp_path / "commands.npz")
    make_cases_main(["--ckpt", ckpt, "--seed", "0", "--out", cases, "--n-per-condition", "3"])
    adapt_cases_main(["--ckpt", ckpt, "--cases", cases, "--out", out, "--sampler", "strided20"])
    status = load_npz(out)["status"]
    assert len(status) == 9 and "ok" not in status.tolist() and "unchecked" in status.tolist()


# ---------------------------------------------------------------------------- realistic data from simulation
def test_sensor_noise_has_the_asked_spread_and_mismatch_moves_moment_arms_within_the_fraction(tmp_path):
    clean, noisy = str(tmp_path / "clean.npz"), str(tmp_path / "noisy.npz")
    make_dataset_main(["--n", "400", "--seed", "1", "--out", clean])
    make_dataset_main(["--n", "400", "--seed", "1", "--out", noisy, "--noise-q", "0.01", "--noise-l", "0.001",
                       "--noise-f", "2"])
    a, b = read_recorded(clean), read_recorded(noisy)
    for name, sigma in (("q", 0.01), ("l_motor", 0.001), ("f", 2.0)):
        spread = np.std(getattr(b, name) - getattr(a, name))
        assert abs(spread / sigma - 1) < 0.1, (name, spread)

    from lightning_bodyschema.sim.mismatch import mismatched_robot

    arm, q = MusculoskeletalModel("paper_arm"), np.random.default_rng(0).uniform(-1, 1, (50, 2))
    _, G, tau = arm.kinematics(q)
    same, spring = mismatched_robot(arm, SpringParams(), 0.0, 5)
    # fraction 0: the same xml with every size times exactly 1.0, the same MuJoCo arithmetic: bit for bit
    np.testing.assert_array_equal(same.kinematics(q)[1], G)
    other, spring = mismatched_robot(arm, SpringParams(), 0.1, 5)
    _, G2, tau2 = other.kinematics(q)
    arms = np.abs(G) > 1e-3  # moment arms = wrap radii: each scaled by one factor in [0.9, 1.1]
    ratio = G2[arms] / G[arms]
    assert np.all(np.abs(ratio - 1) <= 0.1 + 1e-9) and np.ptp(ratio) > 0.02
    assert 0.8 < np.median(np.abs(tau2) / np.abs(tau).clip(1e-9)) < 1.2 and not np.allclose(tau2, tau)
    assert np.all(np.abs(np.asarray(spring.k_n) / 1000.0 - 1) <= 0.1) and np.ptp(spring.k_n) > 0


def test_a_model_free_checkpoint_whose_limits_were_edited_is_refused(model_free, tmp_path):
    _, _, ckpt = model_free
    checkpoint = torch.load(ckpt, map_location="cpu", weights_only=True)
    assert "model_xml" not in checkpoint["hyper_parameters"]["robot"]  # names and limits, no model
    checkpoint["hyper_parameters"]["robot"]["q_range"][0] = [-2.0, 2.0]  # wider than the data it was trained on
    edited = str(tmp_path / "edited.ckpt")
    torch.save(checkpoint, edited)
    with pytest.raises(BodySchemaInputError, match="does not match its recorded hash"):
        load_schema(edited)
    checkpoint["hyper_parameters"]["robot"]["q_range"][0] = [1.0, -1.0]
    torch.save(checkpoint, edited)
    with pytest.raises(BodySchemaInputError, match=r"robot.q_range .* lo < hi"):
        load_schema(edited)
