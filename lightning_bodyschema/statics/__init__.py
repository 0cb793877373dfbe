"""Static optimization and inverse dynamics with faults on the true body (any MJCF or MyoSuite model): tensions, motor
lengths, MuJoCo muscle activations and excitations that hold each posture or drive each frame of a motion. numpy,
MuJoCo, torch and proxsuite; never imports Lightning."""
from .muscles import MuscleCurves, actuated_model, read_muscle_curves
from .dynamics import MotionResult, inverse_dynamics, muscles_for_torque
from .optimize import OBJECTIVES, StaticBody, StaticResult, static_optimization

__all__ = ["MotionResult", "MuscleCurves", "OBJECTIVES", "StaticBody", "StaticResult", "actuated_model",
           "inverse_dynamics", "muscles_for_torque", "read_muscle_curves", "static_optimization"]
