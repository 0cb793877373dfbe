"""Physics: MuJoCo model of a tendon-driven robot, the muscle spring and static equilibrium.

Never imports Lightning; everything takes and returns numpy arrays (SI units). The equilibrium QP (and with it
torch, through ``solvers``) is imported when first asked for, so the model, the spring and the settle check run on
MuJoCo and numpy alone.
"""
from .install import import_mujoco

import_mujoco()  # the package's first MuJoCo import: a broken install stops with one line naming the repair
from .spring import SpringParams, elongation_from_tension, tension_from_elongation
from .model import MusculoskeletalModel, paper_arm_xml

_EQUILIBRIUM = ("EquilibriumSamples", "generate_equilibrium_samples", "solve_equilibrium_qp")


def __getattr__(name: str):
    if name in _EQUILIBRIUM:
        from . import equilibrium

        return getattr(equilibrium, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "SpringParams", "elongation_from_tension", "tension_from_elongation",
    "MusculoskeletalModel", "paper_arm_xml",
    "EquilibriumSamples", "generate_equilibrium_samples", "solve_equilibrium_qp",
]
