"""Checkpoint fuzz: every reachable field of a real small checkpoint, mutated one at a time.

Each field is deleted, given another type, and (numbers, tensors) made NaN, inf, negative, zero or huge or given
another shape or dtype; the class is swapped; the robot XML gets file references, entities and oversized
allocations. Every mutated file must either be refused by ``load_schema`` with a ``BodySchemaInputError``, or load
into a schema whose every ``adapt`` answer is finite or not ``ok``. Any other exception fails the test. (Sizes are
refused before anything is built, so no mutation can allocate much: the 4 GiB address-space check is in
test_checkpoint_forged.py.) The mutation count is reported in BENCHMARKS.md (reliability).
"""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from physics_checks import fit_tiny_checkpoint

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import DiffusionSchema, load_schema

# fields Lightning keeps for resuming a fit; the loader reads none of them: mutated as a whole, not walked into
OPAQUE = {"optimizer_states", "lr_schedulers", "loops", "callbacks"}
# the optimizer's state is most of the file and of torch.load's time: the walk runs on the checkpoint as
# ``save_weights_only`` writes it, and these entries come back as mutations of their own
RESUME_ONLY = ("optimizer_states", "lr_schedulers")
MIN_MUTATIONS = 400  # what the walk below reaches on the paper arm's diffusion checkpoint (BENCHMARKS.md)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    ckpt = fit_tiny_checkpoint(root / "fit", "--data.n_samples=200", "--faults.every_n_epochs=0",
                               "--progress.enabled=false", "--model.hidden=16", "--model.n_timesteps=50")
    full = torch.load(ckpt, map_location="cpu", weights_only=True)
    return full, load_schema(ckpt)


def fields(value, path=()):
    """Every path (tuple of keys/indices) reachable in the checkpoint, skipping into ``OPAQUE`` entries."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield path + (key,)
            if not (len(path) == 0 and key in OPAQUE):
                yield from fields(item, path + (key,))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield path + (i,)
            yield from fields(item, path + (i,))


def replacements(value, path):
    """(name, new value) pairs for one field; ``DELETE`` removes it."""
    common = [("none", None), ("text", "x"), ("list", [1]), ("dict", {}), ("tensor", torch.ones(2))]
    if isinstance(value, bool):
        return common + [("int", 1), ("text_true", "true")]
    if isinstance(value, int):
        return common + [("neg", -1), ("zero", 0), ("huge", 10 ** 12), ("float", value + 0.5), ("bool", True),
                         ("nan", math.nan)]
    if isinstance(value, float):
        return common + [("nan", math.nan), ("inf", math.inf), ("-inf", -math.inf), ("neg", -1.0), ("zero", 0.0),
                         ("huge", 1e300), ("bool", False)]
    if isinstance(value, str):
        out = common + [("empty", ""), ("long", "y" * 100_000), ("int", 7)]
        if path[-1] in ("class_path", "_class_path", "_instantiator"):
            out += [(f"class_{n}", n) for n in ("os.system", "builtins.object", "subprocess.Popen",
                                                 "lightning_bodyschema.schemas.autoencoder.AutoEncoderSchema",
                                                 "lightning_bodyschema.schemas.autoencoder.VAESchema",
                                                 "lightning_bodyschema.schemas.base.BodySchema",
                                                 "lightning_bodyschema.schemas.loading.read_checkpoint",
                                                 "no_such_module.Schema")]
        if path[-1] == "model_xml":
            out += [(f"xml_{n}", x) for n, x in xml_forgeries(value)]
        return out
    if torch.is_tensor(value):
        return [("none", None), ("text", "x"), ("list", value.tolist() if value.numel() < 50 else [0.0]),
                ("scalar", torch.tensor(1.0)), ("empty", value.new_zeros((0,))), ("int64", value.to(torch.int64)),
                ("bool", value != 0), ("complex", value.to(torch.complex64)),
                ("row_less", value[:-1] if value.ndim else value.reshape(1)),
                ("col_more", torch.cat([value, value[..., :1]], -1) if value.ndim else value.reshape(1, 1)),
                ("transposed", value.T if value.ndim == 2 else value.unsqueeze(0)),
                ("nan", torch.full_like(value, math.nan) if value.is_floating_point() else value),
                ("inf", torch.full_like(value, math.inf) if value.is_floating_point() else value),
                ("neg", -value.abs() - 1), ("zero", torch.zeros_like(value)), ("huge", torch.full_like(value, 1e30)
                                                                              if value.is_floating_point() else value),
                ("sparse", value.to_sparse() if value.ndim else value)]
    if isinstance(value, (list, tuple)):
        return common + [("empty", type(value)()), ("longer", list(value) + list(value[:1])),
                         ("shorter", list(value[:-1]))]
    if isinstance(value, dict):
        return [("none", None), ("text", "x"), ("list", [1]), ("empty", {}), ("extra", {**value, "zz_extra": 1})]
    return common


def xml_forgeries(xml: str):
    body = xml.index("<worldbody>")
    inject = lambda text: xml[:body] + text + xml[body:]  # noqa: E731
    return [("include", inject('<include file="/etc/passwd"/>')),
            ("mesh_file", inject('<asset><mesh name="m" file="/etc/hostname"/></asset>')),
            ("texture_file", inject('<asset><texture name="t" type="2d" file="/etc/hostname"/></asset>')),
            ("hfield_nrow", inject('<asset><hfield name="h" nrow="100000" ncol="100000" size="1 1 1 1"/></asset>')),
            ("texture_huge", inject('<asset><texture name="t" type="2d" builtin="checker" width="65536" '
                                    'height="65536"/></asset>')),
            ("size_memory", inject('<size memory="64G"/>')),
            ("size_nuserdata", inject('<size nuserdata="2000000000"/>')),
            ("replicate", xml.replace("<worldbody>", '<worldbody><replicate count="100000000"><geom size=".1"/>'
                                      "</replicate>", 1)),
            ("doctype", '<!DOCTYPE mujoco [<!ENTITY x SYSTEM "file:///etc/passwd">]>' + xml),
            ("laughs", '<!DOCTYPE m [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>' + xml),
            ("truncated", xml[: len(xml) // 2]), ("not_xml", "paper_arm"), ("path", "/etc/passwd"),
            ("no_tendons", xml[: xml.index("<tendon>")] + xml[xml.index("</tendon>") + 9:]),
            ("mass", xml.replace('mass="', 'mass="1', 1))]


def mutate(checkpoint, path, new):
    out = copy.deepcopy(checkpoint)
    *head, last = path
    node = out
    for key in head:
        node = node[key]
    if isinstance(node, tuple):
        return None  # tuples hold nothing the loader reads (Adam betas)
    if new is DELETE:
        node.pop(last)
    else:
        node[last] = new
    return out


DELETE = object()
CASES_Q = np.array([[0.1, 0.2], [-0.4, 0.6], [0.7, -0.3], [0.0, 0.0]])


def answers_are_safe(schema) -> str | None:
    """None when every adapt answer is finite or non-ok; else what went wrong."""
    names = schema.robot_model.muscle_names
    faults = Faults.from_names(names, cut=[[], [names[0]], [], []], jam=[{}, {}, {names[2]: 0.15}, {}],
                               weak=[{}, {}, {}, {names[3]: 60.0}])
    options = {"n_steps": 5} if isinstance(schema, DiffusionSchema) else {}
    result = schema.adapt(CASES_Q, faults, **options)
    ok = result.status == "ok"
    if not (np.isfinite(result.f_n[ok]).all() and np.isfinite(result.l_motor_m[ok]).all()):
        return f"non-finite ok answer: {result.status}"
    return None


def mutations(full):
    """(label, mutated checkpoint) for every field and every replacement of it."""
    checkpoint = {k: v for k, v in full.items() if k not in RESUME_ONLY}
    for key in RESUME_ONLY:
        for name, new in [("restored", full[key])] + replacements(full[key], (key,)):
            yield f"{key} <- {name}", {**checkpoint, key: new}
    for field in list(fields(checkpoint)):
        node = checkpoint
        for key in field:
            node = node[key]
        for name, new in [("delete", DELETE)] + replacements(node, field):
            mutated = mutate(checkpoint, field, new)
            if mutated is not None:
                yield f"{'.'.join(map(str, field))} <- {name}", mutated


def same_schema(a, b) -> bool:
    """Same class, hyperparameters and weights (NaN never equal): then ``adapt`` answers the same, to the bit."""
    if type(a) is not type(b) or dict(a.hparams) != dict(b.hparams):
        return False
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(sa[k].dtype == sb[k].dtype and torch.equal(sa[k], sb[k]) for k in sa)


def test_every_mutated_checkpoint_is_refused_or_answers_safely(base, tmp_path):
    full, reference = base
    assert answers_are_safe(reference) is None
    path = str(tmp_path / "mutated.ckpt")
    counts, failures = {"refused": 0, "loaded": 0, "adapted": 0}, []
    for label, mutated in mutations(full):
        torch.save(mutated, path)
        try:
            schema = load_schema(path)
        except BodySchemaInputError as err:
            counts["refused"] += 1
            if "\n" in str(err).strip():
                failures.append(f"{label}: multi-line message {err!s:.200}")
            continue
        except Exception as err:  # the point of the test: anything else is a defect
            failures.append(f"{label}: load raised {type(err).__name__}: {err!s:.200}")
            continue
        counts["loaded"] += 1
        if same_schema(schema, reference):
            continue  # a field the loader does not read: the reference's answers, already checked
        counts["adapted"] += 1
        try:
            problem = answers_are_safe(schema)
        except BodySchemaInputError:
            problem = None  # e.g. a forged f_max that makes the test's weakening invalid: a clear refusal
        except Exception as err:
            problem = f"adapt raised {type(err).__name__}: {err!s:.200}"
        if problem:
            failures.append(f"{label}: {problem}")
    total = counts["refused"] + counts["loaded"]
    print(f"\ncheckpoint fuzz: {total} mutations, {counts['refused']} refused, {counts['loaded']} loaded "
          f"({counts['adapted']} with other weights or hyperparameters, adapted: every answer finite or not ok)")
    assert not failures, "\n".join(failures[:40])
    assert total >= MIN_MUTATIONS and counts["refused"] > counts["loaded"] and counts["adapted"] > 0, counts
