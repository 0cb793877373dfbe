"""lightning_bodyschema: learn and adapt the body schema of musculoskeletal robots."""
__version__ = "0.3.0"  # = pyproject.toml's version (tests/docs/test_version.py)

_STATICS = ("static_optimization", "StaticBody", "StaticResult", "inverse_dynamics", "muscles_for_torque",
            "MotionResult")


def __getattr__(name):
    """``static_optimization``, ``inverse_dynamics``, ``muscles_for_torque``, ``StaticBody``, ``StaticResult`` and
    ``MotionResult`` (``statics/``), imported on first use: importing the package itself stays free of MuJoCo and
    proxsuite."""
    if name in _STATICS:
        from . import statics

        return getattr(statics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_STATICS))
