"""The muscle's nonlinear spring (paper eq:nonlinear-spring, eq:muscle-elongation-inv).

``f = k (exp(alpha * delta) - 1)`` with ``delta = max(0, l_geo - l_motor)``, written once (``spring_tension_n`` and its
inverse ``spring_elongation_m``). Works on numpy arrays and torch tensors alike; k, alpha and f_max may be scalars or
per-muscle arrays that broadcast.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._arrays import clamp_min, namespace


@dataclass(frozen=True)
class SpringParams:
    """Spring constants; defaults are the paper's (section IV)."""

    k_n: float = 1000.0  # elastic coefficient k [N]
    alpha_per_m: float = 20.0  # nonlinearity alpha [1/m]
    f_max_n: float = 150.0  # maximum muscle tension [N]

    def __post_init__(self):
        from ..errors import BodySchemaInputError

        for name in ("k_n", "alpha_per_m", "f_max_n"):
            value = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(value)) or np.any(value <= 0):
                raise BodySchemaInputError(f"spring parameter {name}={getattr(self, name)!r} must be finite and > 0")

    @property
    def delta_max_m(self):
        """Spring elongation at f_max: the most a taut muscle can stretch [m] (~7 mm for the paper)."""
        return elongation_from_tension(np.asarray(self.f_max_n, float), self)

    def as_dict(self) -> dict:
        return {k: np.asarray(v, float).tolist() for k, v in self.__dict__.items()}


def spring_tension_n(delta_m, k_n, alpha_per_m):
    """The spring law ``f = k (exp(alpha delta) - 1)`` [N] at elongations ``delta_m`` (eq:nonlinear-spring; slack,
    ``delta < 0``, gives 0; inf where exp overflows), with ``k_n`` [N] and ``alpha_per_m`` [1/m] scalars or arrays that
    broadcast. numpy arrays or torch tensors (``_arrays``): the one copy of the law for every caller."""
    return k_n * namespace(delta_m).expm1(alpha_per_m * clamp_min(delta_m, 0.0))


def spring_elongation_m(f_n, k_n, alpha_per_m):
    """The law's inverse ``delta = log(f/k + 1) / alpha`` [m] (eq:muscle-elongation-inv); negative f counts as 0."""
    return namespace(f_n).log1p(clamp_min(f_n, 0.0) / k_n) / alpha_per_m


def tension_from_elongation(delta_m, spring: SpringParams):
    """``spring_tension_n`` with ``spring``'s constants."""
    return spring_tension_n(delta_m, spring.k_n, spring.alpha_per_m)


def elongation_from_tension(f_n, spring: SpringParams):
    """``spring_elongation_m`` with ``spring``'s constants."""
    return spring_elongation_m(f_n, spring.k_n, spring.alpha_per_m)


PAPER_K_PER_F_MAX = 1000.0 / 150.0  # the paper's k [N] per its f_max [N]


def spring_for_model(model, k_n=None, alpha_per_m=20.0, f_max_n=None) -> SpringParams:
    """Spring constants of ``model``'s muscles, with per-muscle strength read from the model where asked.

    f_max_n: a number or per-muscle list [N]; ``"model"``: each muscle's actuator peak force
        (``MusculoskeletalModel.actuator_f_max_n``); None (default): ``"model"`` when the model has muscle
        actuators, else the paper's 150 N.
    k_n: a number or list [N]; ``"model"``: scaled with each muscle's strength, ``k_i = f_max_i * 1000/150``,
        so every muscle stretches at its own f_max by the paper's delta_max (~6.9 mm at alpha = 20/m)
        instead of a weak muscle barely stretching and a 2000 N one stretching by 6 cm; None (default):
        ``"model"`` when f_max came from the model, else the paper's 1000 N. The paper arm keeps
        k = 1000 N, alpha = 20 1/m, f_max = 150 N.
    alpha_per_m: a number or per-muscle list [1/m] (paper: 20).
    """
    from ..errors import BodySchemaInputError

    for name, value in (("f_max_n", f_max_n), ("k_n", k_n)):
        if isinstance(value, str) and value != "model":
            raise BodySchemaInputError(f"{name}={value!r}: give a number, a per-muscle list, or 'model'")
    from_model = f_max_n == "model" or (f_max_n is None and bool(np.isfinite(model.actuator_f_max_n).any()))
    if from_model:
        f_max_n = model.actuator_f_max_n
        missing = [n for n, f in zip(model.muscle_names, f_max_n) if not np.isfinite(f)]
        if missing:
            raise BodySchemaInputError(f"f_max_n='model' but muscles {missing} have no muscle actuator with a peak "
                                       "force in the model; give f_max_n as a number or a per-muscle list")
    elif f_max_n is None:
        f_max_n = 150.0
    if k_n == "model" or (k_n is None and from_model):
        k_n = PAPER_K_PER_F_MAX * np.asarray(f_max_n, float) * np.ones(model.n_muscles)
    elif k_n is None:
        k_n = 1000.0
    for name, value in (("f_max_n", f_max_n), ("k_n", k_n), ("alpha_per_m", alpha_per_m)):
        size = np.size(value)
        if size not in (1, model.n_muscles):
            raise BodySchemaInputError(f"{name} has {size} values; give one, or one per muscle ({model.n_muscles}: "
                                       f"{model.muscle_names})")
    as_value = lambda v: float(v) if np.size(v) == 1 and np.ndim(v) == 0 else [float(x) for x in np.ravel(v)]
    return SpringParams(as_value(k_n), as_value(alpha_per_m), as_value(f_max_n))
