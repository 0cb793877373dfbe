"""Static optimization with faults on the true body (any MJCF or MyoSuite model): tensions, motor lengths and MuJoCo
muscle activations that hold each posture. numpy, MuJoCo and proxsuite; never imports Lightning."""
from .muscles import MuscleCurves, actuated_model, read_muscle_curves
from .optimize import OBJECTIVES, StaticBody, StaticResult, static_optimization

__all__ = ["MuscleCurves", "OBJECTIVES", "StaticBody", "StaticResult", "actuated_model", "read_muscle_curves",
           "static_optimization"]
