"""Know what broke: which muscles failed, and how, from the robot's own sensor log (what it sent and what its
sensors read back), then a ``Faults`` row for ``schema.adapt``. numpy only (and MuJoCo for the simulated
sensors); never imports Lightning. ``schema.diagnose(log)`` and ``schema.monitor()`` wire a schema's learned body
into it."""
from .explain import diagnose
from .log import SensorLog, read_sensor_log, write_sensor_log
from .noise import BodyError, SensorNoise, Thresholds
from .result import KINDS, Diagnosis

__all__ = ["BodyError", "Diagnosis", "KINDS", "SensorLog", "SensorNoise", "Thresholds", "diagnose",
           "read_sensor_log", "write_sensor_log"]
