"""Every model name the installed myo-sim registry offers (issue 27): it builds a dataset of static equilibria, or it
is refused with one line that names the option to set; never a traceback.

A refusal naming ``fixed_base`` is followed once (the legs: their pelvis is then held), so a floating body is
walked as a user would after reading the message. The default run walks the bodies that load in a few seconds
(``FAST``); the others (hands, arms, legs, torso with arms, full body, and aliases of walked bodies) are marked slow.
"""
import re

import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import MusculoskeletalModel, generate_equilibrium_samples
from lightning_bodyschema.sim.spring import spring_for_model

myo_sim = pytest.importorskip("myo_sim")

# a refusal must name something the user sets: a data-module option, or the model-loader argument behind it
OPTION = re.compile(r"fixed_base|data\.locked_joints|data\.muscles|allow_unloaded|f_max_n")
FAST = {"elbow", "finger", "myoelbow", "myoelbow_2dof", "myoelbow_exo", "myofinger", "myotorso",
        "myotorso_abdomen", "osl"}  # myolegs (80 muscles) and its variants: slow; osl walks the legs' muscles


def _registry_names() -> list[str]:
    return sorted(set(myo_sim.REGISTRY) | set(myo_sim._composed_models()))


def _walk(name: str, **options):
    """(model, samples) built for ``myo:<name>``, or the one-line refusal (str)."""
    try:
        model = MusculoskeletalModel(f"myo:{name}", **options)
        spring = spring_for_model(model, None, 20.0, None)  # the data module's defaults
        return model, generate_equilibrium_samples(model, 20, seed=0, spring=spring)
    except BodySchemaInputError as err:
        return " ".join(str(err).split())  # what the CLI prints: one line


@pytest.mark.parametrize("name", [n if n in FAST else pytest.param(n, marks=pytest.mark.slow)
                                  for n in _registry_names()])
def test_every_registry_body_builds_equilibria_or_names_the_option_to_set(name):
    outcome = _walk(name)
    if isinstance(outcome, str) and "fixed_base" in outcome:
        outcome = _walk(name, fixed_base=True)  # what the message says to do
    if isinstance(outcome, str):
        assert OPTION.search(outcome), f"myo:{name} refused without naming an option: {outcome}"
        return
    model, samples = outcome
    _, G, tau = model.kinematics(samples.q)  # the model's own kinematics
    residual_nm = np.abs(np.einsum("bmn,bm->bn", -G, samples.f) - tau).max()
    assert samples.q.shape == (20, model.n_joints) and residual_nm <= 1e-6
    assert np.all(samples.f >= 0)


def test_the_default_walk_covers_names_the_registry_has():
    assert FAST <= set(_registry_names())
