"""Named, fully resolved sampler settings: what a variant runs with all T steps and with a strided sampler.

A ``SamplerPreset`` is everything a guided denoising call needs besides the network and the loss: the guidance
(``GuidanceConfig``), the spacing of strided timesteps and DDIM's eta. An ``AdaptPreset`` holds one for the
full-T sampler and one for the strided sampler, both written out; nothing is merged by precedence. A call's
overrides replace the named fields of the chosen preset and nothing else (``SamplerPreset.with_overrides``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from ..errors import BodySchemaInputError
from .guided import GuidanceConfig
from .schedule import SPACINGS

GUIDANCE_FIELDS = tuple(f.name for f in fields(GuidanceConfig))


@dataclass(frozen=True)
class SamplerPreset:
    """guidance: eq:diff-adapt's settings; spacing: the strided timestep list (``NoiseSchedule.timesteps``; unused
    with all T steps); eta: DDIM's eta of every denoising step (1: the DDPM posterior mean, eq:diff-2)."""

    guidance: GuidanceConfig = field(default_factory=GuidanceConfig)
    spacing: str = "quad"
    eta: float = 1.0

    def __post_init__(self):
        if self.spacing not in SPACINGS:
            raise BodySchemaInputError(f"unknown spacing {self.spacing!r}; allowed: {list(SPACINGS)}")
        if isinstance(self.eta, bool) or not 0.0 <= float(self.eta) <= 1.0:
            raise BodySchemaInputError(f"eta={self.eta!r} must be in [0, 1] (0: DDIM, 1: the DDPM posterior mean)")

    OPTIONS = ("spacing", "eta") + GUIDANCE_FIELDS  # the names a call may override

    def with_overrides(self, also: tuple = (), **overrides) -> "SamplerPreset":
        """This preset with the named fields replaced (a value of None keeps the preset's). An unknown name is
        refused, naming it and the allowed ones (``OPTIONS``, plus the caller's own options ``also``)."""
        unknown = sorted(set(overrides) - set(self.OPTIONS))
        if unknown:
            raise BodySchemaInputError(f"unknown sampler option(s) {unknown}; allowed: {list(also) + list(self.OPTIONS)}")
        given = {name: value for name, value in overrides.items() if value is not None}
        if not given:
            return self
        guidance = {name: given.pop(name) for name in GUIDANCE_FIELDS if name in given}
        if "min_abar" in guidance:
            guidance["min_abar"] = float(guidance["min_abar"])
        return replace(self, guidance=replace(self.guidance, **guidance), **given)


@dataclass(frozen=True)
class AdaptPreset:
    """One variant: ``full`` runs with all T steps, ``strided`` with fewer (each a complete ``SamplerPreset``)."""

    full: SamplerPreset
    strided: SamplerPreset

    def resolve(self, strided: bool, also: tuple = (), **overrides) -> SamplerPreset:
        """The preset for a full (``strided=False``) or strided sampler with a call's overrides applied (``also``:
        see ``SamplerPreset.with_overrides``)."""
        return (self.strided if strided else self.full).with_overrides(also, **overrides)


def adapt_preset(guidance: GuidanceConfig, strided_guidance: dict, spacing: str = "quad",
                 eta: float = 1.0) -> AdaptPreset:
    """The ``AdaptPreset`` of ``guidance`` for all T steps and ``guidance`` with the fields ``strided_guidance``
    replaced for the strided sampler (both with ``spacing`` and ``eta``): the one way the tables compose them."""
    return AdaptPreset(SamplerPreset(guidance, spacing, eta),
                       SamplerPreset(replace(guidance, **strided_guidance), spacing, eta))
