"""Every adaptation path returns the commands it returned before the adaptation code was restructured.

``pinned_adaptation.npz`` holds three small trained schemas (Diff, AE-10, VAE-10 of the paper arm, float64 weights),
fault cases of every kind (CUT / FIX / BOTH, weakened, length-banded, healthy) and the float64 commands the code
returned for them on the day the pin was made, for each sampler path and option set below. A refactor must keep
them to 1e-9 (m and N); a deliberate change of behaviour regenerates the pin and says so in the changelog.
"""
import os

import numpy as np
import pytest
import torch

from lightning_bodyschema.adaptation.command import FAULT_TOL_M, FAULT_TOL_N, motor_length_range
from lightning_bodyschema.faults.bounds import FaultBounds
from lightning_bodyschema.data import EquilibriumDataModule
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema

PIN = np.load(os.path.join(os.path.dirname(__file__), "pinned_adaptation.npz"))
TOL = 1e-9
CLASSES = {"diff": DiffusionSchema, "ae": AutoEncoderSchema, "vae": VAESchema}
LATENT_RUNS = {"fast": {}, "ref": {"fast": False}, "literal": {"variant": "literal"},
               "adam": {"optimizer": "adam", "lr": 0.02, "n_steps": 100}}
RUNS = {
    "diff": {"ddpm_fast": {}, "ddpm_ref": {"fast": False}, "s20_fast": {"n_steps": 20},
             "s20_ref": {"n_steps": 20, "fast": False}, "literal": {"variant": "literal"},
             "strong": {"n_guide": 4, "lr": 1.0}, "s20_strong": {"n_steps": 20, "n_guide": 3, "lr": 0.8},
             "sqrt_abar": {"step_scale": "sqrt_abar", "lr": 0.05},
             "s50_ddim": {"n_steps": 50, "eta": 0.0, "spacing": "linspace"}},
    "ae": LATENT_RUNS, "vae": LATENT_RUNS}
GROUPS = ("paper", "weak", "band", "none")


@pytest.fixture(scope="module")
def schemas():
    robot = EquilibriumDataModule(cache_dir=None).robot  # the robot only: no dataset is generated
    out = {}
    for name, cls in CLASSES.items():
        schema = cls(robot=robot).double()
        state = {k[len(f"w/{name}/"):]: torch.from_numpy(PIN[k]) for k in PIN.files if k.startswith(f"w/{name}/")}
        schema.load_state_dict(state)
        out[name] = schema.eval()
    return out


def _faults(group: str) -> tuple[np.ndarray, Faults]:
    get = lambda k: PIN[f"in/{group}/{k}"] if f"in/{group}/{k}" in PIN.files else None  # noqa: E731
    return get("q"), Faults(get("cut"), get("fix"), get("l_fixed_m"), get("f_max_n"), get("l_band_m"))


def _same(actual, pinned_key):
    np.testing.assert_allclose(actual, PIN[pinned_key], rtol=0, atol=TOL, equal_nan=True, err_msg=pinned_key)


def _same_rows(actual, pinned_key, rows):
    np.testing.assert_allclose(actual[rows], PIN[pinned_key][rows], rtol=0, atol=TOL, equal_nan=True, err_msg=pinned_key)


@pytest.mark.parametrize("name", list(CLASSES))
def test_healthy_commands_are_pinned(schemas, name):
    l_motor, f = schemas[name].infer(PIN[f"out/{name}/infer_q"])
    _same(l_motor, f"out/{name}/infer/l")
    _same(f, f"out/{name}/infer/f")


def test_unguided_samples_are_pinned(schemas):
    schema = schemas["diff"]
    with torch.no_grad():
        q_n = schema.encode_q(torch.as_tensor(PIN["out/diff/infer_q"]))
        _same(schema.generate(q_n, n_steps=20).numpy(), "out/diff/gen20")
        _same(schema.generate(q_n, fast=False).numpy(), "out/diff/gen_ref")


@pytest.mark.parametrize("name,run", [(n, r) for n in CLASSES for r in RUNS[n]])
def test_adapted_commands_are_pinned(schemas, name, run):
    options = dict(RUNS[name][run])
    # the diffusion default became spring inpainting (binding-fault study); its former default is "guided"
    variant = options.pop("variant", "guided" if name == "diff" else "default")
    for group in GROUPS:
        q, faults = _faults(group)
        schema = schemas[name]
        result = schema.adapt(q, faults, variant=variant, check_physics=False, **options)
        # deliberate change: a diverged, finite but absurd command is now out_of_range (was ok), with NaN rows
        absurd = result.status == "out_of_range"
        pinned_l = PIN[f"out/{name}/{run}/{group}/l"]
        l_range = motor_length_range(schema.normalizer.x_mean, schema.normalizer.x_std, schema.n_muscles)
        assert ((pinned_l[absurd] < l_range[0]) | (pinned_l[absurd] > l_range[1])).any(1).all()
        # deliberate change: a command that breaks a fault bound beyond the package's tolerances is fault_not_met
        # (was ok), NaN; the command it would have sent stays in diagnostics and is still the pinned one
        not_met = _not_met(result, faults, schema, f"out/{name}/{run}/{group}", ~absurd)
        keep = ~absurd & ~not_met
        _same_rows(result.l_motor_m, f"out/{name}/{run}/{group}/l", keep)
        _same_rows(result.f_n, f"out/{name}/{run}/{group}/f", keep)
        assert result.status[keep].tolist() == PIN[f"out/{name}/{run}/{group}/status"][keep].tolist()


def _broken(pinned: str, faults: Faults, schema) -> np.ndarray:
    """(B,) bool: the pinned command breaks a jam or band by more than FAULT_TOL_M, or a cut by more than FAULT_TOL_N."""
    length_m, cut_n = FaultBounds.from_faults(faults, schema.spring.f_max_n).broken(PIN[f"{pinned}/l"],
                                                                                     PIN[f"{pinned}/f"])
    return (length_m > FAULT_TOL_M).any(1) | (cut_n > FAULT_TOL_N).any(1)


def _not_met(result, faults: Faults, schema, pinned: str, sane: np.ndarray) -> np.ndarray:
    """(B,) the rows that became fault_not_met: exactly the ``sane`` (not out_of_range) rows pinned ok whose pinned
    command breaks a fault; the command they would have sent (``clipped_*``) is the pinned one."""
    not_met = result.status == "fault_not_met"
    assert (not_met == (_broken(pinned, faults, schema) & (PIN[f"{pinned}/status"] == "ok") & sane)).all()
    _same_rows(result.diagnostics["clipped_l_motor_m"], f"{pinned}/l", not_met)
    _same_rows(result.diagnostics["clipped_f_n"], f"{pinned}/f", not_met)
    return not_met


@pytest.mark.parametrize("name", list(CLASSES))
def test_physics_check_statuses_are_pinned(schemas, name):
    """As pinned, but an ok row whose command (the default variant's, pinned unchecked) breaks a fault bound is now
    fault_not_met."""
    q, faults = _faults("paper")
    status = schemas[name].adapt(q, faults).status
    pinned = PIN[f"out/{name}/checked/status"]
    became = (status == "fault_not_met") & (pinned == "ok")
    assert (status[~became] == pinned[~became]).all()
    run = "s20_fast" if name == "diff" else "fast"
    assert not became.any() or _broken(f"out/{name}/{run}/paper", faults, schemas[name])[became].all()
