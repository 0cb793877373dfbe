"""Physics: MuJoCo model of a tendon-driven robot, the muscle spring and static equilibrium.

Never imports Lightning; everything takes and returns numpy arrays (SI units).
"""
from .install import import_mujoco

import_mujoco()  # the package's first MuJoCo import: a broken install stops with one line naming the repair
from .spring import SpringParams, elongation_from_tension, tension_from_elongation
from .model import MusculoskeletalModel, paper_arm_xml
from .equilibrium import EquilibriumSamples, generate_equilibrium_samples, solve_equilibrium_qp

__all__ = [
    "SpringParams", "elongation_from_tension", "tension_from_elongation",
    "MusculoskeletalModel", "paper_arm_xml",
    "EquilibriumSamples", "generate_equilibrium_samples", "solve_equilibrium_qp",
]
