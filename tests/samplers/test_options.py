"""Sampler options through the schema: sample_steps, step counts, spacings, and the case tool's sampler names."""
import numpy as np
import pytest
import torch
from physics_checks import mixed_faults

from lightning_bodyschema.apps.case_tools import adapt_cases_main
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import make_fault_cases
from lightning_bodyschema.npz import load_npz
from lightning_bodyschema.schemas import DiffusionSchema, load_schema


def test_sample_steps_selects_the_strided_sampler_for_infer_and_adapt(diff60, dm):
    schema, _ = diff60
    fast = DiffusionSchema(robot=dm.robot, sample_steps=20)
    fast.load_state_dict(schema.state_dict())
    fast.eval()
    q, faults = mixed_faults(schema, dm, n=6)
    np.testing.assert_array_equal(fast.infer(q)[1], schema.decode(schema.generate(
        schema.encode_q(torch.as_tensor(q)), n_steps=20))[:, 6:].numpy())
    np.testing.assert_array_equal(fast.adapt(q, faults).f_n, schema.adapt(q, faults, n_steps=20).f_n)
    np.testing.assert_array_equal(fast.adapt(q, faults, n_steps=200).f_n, schema.adapt(q, faults).f_n)
    assert not np.allclose(fast.infer(q)[1], schema.infer(q)[1], atol=1e-6)  # really another sampler


@pytest.mark.parametrize("bad", [0, 201, 2.5, True, "20"])
def test_bad_step_counts_and_spacings_are_refused(diff60, dm, bad):
    schema, _ = diff60
    q, faults = mixed_faults(schema, dm, n=3)
    with pytest.raises(BodySchemaInputError, match="n_steps"):
        schema.adapt(q, faults, n_steps=bad)
    with pytest.raises(BodySchemaInputError, match="sample_steps|n_steps"):
        DiffusionSchema(robot=dm.robot, sample_steps=bad)
    with pytest.raises(BodySchemaInputError, match="spacing"):
        schema.adapt(q, faults, n_steps=20, spacing="cubic")
    with pytest.raises(BodySchemaInputError, match="n_guide"):
        schema.adapt(q, faults, n_steps=20, n_guide=0)


@pytest.mark.parametrize("sampler", ["strided20", "ddim20"])
def test_adapt_cases_runs_the_20_step_sampler_by_name_and_by_its_old_alias(diff60, dm, tmp_path, capsys, sampler):
    schema, trainer = diff60
    ckpt = tmp_path / "diff.ckpt"
    trainer.save_checkpoint(ckpt)
    q, x = dm.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :6].numpy(), 5, 0)
    cases.save(tmp_path / "cases.npz")
    adapt_cases_main(["--ckpt", str(ckpt), "--cases", str(tmp_path / "cases.npz"), "--out", str(tmp_path / "out.npz"),
                      "--sampler", sampler])
    assert "sampler strided20" in capsys.readouterr().out
    out = load_npz(str(tmp_path / "out.npz"))
    expected = load_schema(str(ckpt)).adapt(cases.q_ref, cases.faults, n_steps=20)
    np.testing.assert_array_equal(out["f"], expected.f_n)
