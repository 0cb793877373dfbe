"""Variants as named presets: the full-T and strided settings are written out, a call's overrides replace named
fields only, unknown options and variants are refused by one check, for the schema, FaultBenchmark and the tools."""
from dataclasses import fields

import pytest

from lightning_bodyschema.callbacks.fault_benchmark import FaultBenchmark
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.samplers import GuidanceConfig
from lightning_bodyschema.samplers.presets import SamplerPreset
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema
from lightning_bodyschema.variants import check_variant

OVERRIDES = [{}, {"lr": 0.7}, {"n_guide": 3, "min_abar": 0}, {"step_scale": "sqrt_abar", "eta": 0.0},
             {"inpaint_n_guide": 3, "spacing": "linspace"}]


def _merged_by_precedence(variant_guidance: GuidanceConfig, strided: bool, overrides: dict) -> GuidanceConfig:
    """The rule the presets replaced, for calls that do not override ``inpaint``: the strided defaults first, the
    inpainting ones over them, the call's overrides last."""
    values = {f.name: getattr(variant_guidance, f.name) for f in fields(GuidanceConfig)}
    if strided:
        values.update(n_guide=2, min_abar=0.5)
        if values["inpaint"] != "none":
            values.update(min_abar=0.3, inpaint_min_abar=0.3)
    values.update({k: v for k, v in overrides.items() if k in values})
    return GuidanceConfig(**{**values, "min_abar": float(values["min_abar"])})


@pytest.fixture(scope="module")
def schema(dm):
    return DiffusionSchema(robot=dm.robot)


@pytest.mark.parametrize("overrides", OVERRIDES)
@pytest.mark.parametrize("n_steps", [None, 200, 20])
def test_every_variant_resolves_to_the_settings_it_had(schema, n_steps, overrides):
    for variant in DiffusionSchema.VARIANTS:
        preset = schema.sampler_preset(variant, n_steps, **overrides)
        old = _merged_by_precedence(DiffusionSchema.ADAPT[variant].full.guidance, n_steps == 20, overrides)
        assert preset.guidance == old, variant
        assert (preset.spacing, preset.eta) == (overrides.get("spacing", "quad"), overrides.get("eta", 1.0))


def test_an_override_replaces_its_field_and_nothing_else(schema):
    strided = DiffusionSchema.ADAPT["default"].strided
    assert strided.guidance.inpaint_min_abar == 0.3  # the strided preset is written out, not derived at call time
    got = schema.sampler_preset("default", 20, inpaint="box")
    assert got.guidance == GuidanceConfig(**{**strided.guidance.__dict__, "inpaint": "box"})


def test_unknown_options_are_refused_by_name_with_the_allowed_ones(schema, dm):
    with pytest.raises(BodySchemaInputError, match=r"\['n_stepz'\].*'n_steps'.*'spacing'.*'inpaint_min_abar'"):
        schema.sampler_preset("default", 20, n_stepz=20)
    with pytest.raises(BodySchemaInputError, match="eta"):
        SamplerPreset(eta=1.5)
    with pytest.raises(BodySchemaInputError, match="spacing"):
        SamplerPreset().with_overrides(spacing="cubic")


def test_one_variant_check_for_the_schema_the_benchmark_and_the_tools(dm):
    diffusion, latent = DiffusionSchema(robot=dm.robot), AutoEncoderSchema(robot=dm.robot)
    assert check_variant(diffusion, "guided") == "guided"
    with pytest.raises(BodySchemaInputError, match=r"unknown --variant 'guided'; allowed: \['default', 'literal'\]"):
        check_variant(latent, "guided", "--variant")
    benchmark = FaultBenchmark(variant="guided")  # a diffusion variant: accepted for a diffusion schema
    benchmark.setup(None, diffusion, "fit")
    with pytest.raises(BodySchemaInputError, match="faults.variant 'guided'"):
        benchmark.setup(None, latent, "fit")
    with pytest.raises(BodySchemaInputError, match="faults.variant 'nope'"):
        FaultBenchmark(variant="nope")
