"""Safe commands, property-based: whatever the faults, ``adapt`` never returns a command outside the limits.

For each schema type (AE, VAE, Diffusion; each trained briefly through the CLI in a module fixture),
hypothesis draws whole batches of fault cases: postures anywhere in the joint range (limits included),
cut / jam sets of every kind (none, the paper's two faults, random subsets, all but one muscle cut, all
jammed), jam lengths from plausible to absurd (metres or kilometres below or above the healthy motor
length, negative lengths), and the adaptation variant (``default`` or the paper's ``literal``, which
diverges to NaN on the diffusion schema). A few cases per batch are drawn element by element by
hypothesis itself (so they shrink well); the rest of the batch is generated from a drawn seed, which keeps
an example to one batched ``adapt`` call and makes 10,000 cases per schema cheap.

The property, per batch of B cases:

* ``len(status) == B`` and every case has a non-empty status;
* an ``ok`` row is all finite with ``0 <= f <= f_max``;
* any other row is all NaN (never numbers that look like a command).

The same cases go through ``evaluation.feasibility.check_feasible``, so the figures also say how many
cases had no physical solution at all, and what ``adapt`` answered for them (``adapt`` has no physics
check: an infeasible case still gets an ``ok``, i.e. a safe but unrealizable command).

Default run: ~1,000 cases per schema. ``-m slow``: >= 10,000 per schema, with a summary printed (``-s``).
"""
from __future__ import annotations

import glob
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lightning_bodyschema.cli import main as cli_main
from lightning_bodyschema.evaluation.cases import FaultCases
from lightning_bodyschema.evaluation.feasibility import check_feasible
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import load_schema

ROOT = Path(__file__).resolve().parents[2]
SCHEMA_CONFIGS = {"AE": "ae-10", "VAE": "vae-10", "Diffusion": "diff"}
EPOCHS = 60
VARIANTS = ("default", "literal")
KINDS = ("none", "paper", "random", "all_but_one_cut", "all_jammed")
MIN_JAM_M = 1e-4  # a jam at or below 0 m is refused as input (test_checkpoint_forged.py); far below stays 0.1 mm
# where a jammed motor stopped, relative to the healthy motor length at q_ref [m]
OFFSETS = ("near", "below", "far_below", "above", "far_above")
QUICK = (8, 128)  # examples x cases per example: ~1,000 cases per schema
FULL = (40, 256)  # 10,240 cases per schema


@pytest.fixture(scope="module")
def schemas(tmp_path_factory):
    """AE-10, VAE-10 and Diff, each trained EPOCHS epochs through ``bodyschema fit`` on one cached dataset."""
    root = tmp_path_factory.mktemp("fuzz")
    trained = {}
    for name, config in SCHEMA_CONFIGS.items():
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
            cli_main(["fit", "--config", str(ROOT / "configs" / f"{config}.yaml"), f"--trainer.max_epochs={EPOCHS}",
                      f"--trainer.check_val_every_n_epoch={EPOCHS}", "--faults.every_n_epochs=0",
                      "--progress.enabled=false", f"--trainer.default_root_dir={root / name}",
                      f"--data.cache_dir={root / 'cache'}"])
        ckpt = sorted(glob.glob(str(root / name / "lightning_logs" / "version_*" / "checkpoints" / "last.ckpt")))[-1]
        trained[name] = load_schema(ckpt)
    return trained


# ---------------------------------------------------------------------------- what hypothesis draws
@dataclass
class BatchSpec:
    variant: str
    seed: int
    kind_weights: list
    offset_weights: list
    p_cut: float
    p_jam: float
    p_at_limit: float
    explicit: list  # [(q tuple, muscle states tuple ('ok'|'cut'|'jam'), l_fixed tuple [m])]


def floats(lo, hi):
    """Finite floats in [lo, hi]; no subnormals: ``torch.set_flush_denormal(True)`` (conftest, the CLI) flushes
    them to zero, and hypothesis refuses to draw them then."""
    return st.floats(float(lo), float(hi), allow_nan=False, allow_infinity=False, allow_subnormal=False)


def _explicit_case(n_joints, n_muscles, q_range):
    """One case drawn element by element: a posture in range, a state per muscle, any finite jam length."""
    q = st.tuples(*(floats(lo, hi) for lo, hi in q_range))
    states = st.lists(st.sampled_from(("ok", "cut", "jam")), min_size=n_muscles, max_size=n_muscles).filter(
        lambda s: set(s) != {"cut"})  # never every muscle cut (refused as input: see test_bad_input)
    l_fixed = st.lists(floats(-1e3, 1e3), min_size=n_muscles,
                       max_size=n_muscles)
    return st.tuples(q, states.map(tuple), l_fixed.map(tuple))


def batch_specs(n_joints, n_muscles, q_range):
    weights = lambda n: st.lists(floats(0.0, 1.0), min_size=n, max_size=n)  # noqa: E731
    return st.builds(BatchSpec, variant=st.sampled_from(VARIANTS), seed=st.integers(0, 2**32 - 1),
                     kind_weights=weights(len(KINDS)), offset_weights=weights(len(OFFSETS)),
                     p_cut=floats(0.0, 1.0), p_jam=floats(0.0, 1.0), p_at_limit=floats(0.0, 0.5),
                     explicit=st.lists(_explicit_case(n_joints, n_muscles, q_range), max_size=4))


def _pick(rng, weights, n):
    p = np.asarray(weights, float)
    p = np.full(len(p), 1.0 / len(p)) if p.sum() <= 0 else p / p.sum()
    return rng.choice(len(p), size=n, p=p)


def make_cases(schema, spec: BatchSpec, batch: int) -> tuple[FaultCases, np.ndarray]:
    """A batch of ``batch`` fault cases (the spec's explicit cases first, the rest generated from its seed),
    and each case's kind (``KINDS`` or ``"explicit"``)."""
    model, m = schema.robot_model, schema.n_muscles
    rng = np.random.default_rng(spec.seed)
    lo, hi = model.q_range.T
    q = model.sample_q(rng, batch)
    at_limit = rng.random(q.shape) < spec.p_at_limit
    q = np.where(at_limit, np.where(rng.random(q.shape) < 0.5, lo, hi), q)  # exactly on a joint limit

    kind = _pick(rng, spec.kind_weights, batch)
    cut, fix = np.zeros((batch, m), bool), np.zeros((batch, m), bool)
    order = np.argsort(rng.random((batch, m)), axis=1)  # a random muscle order per case
    rank = np.argsort(order, axis=1)
    n_cut = rng.integers(0, 3, batch)  # the paper's conditions: 2 + 0, 1 + 1, 0 + 2
    paper = kind == KINDS.index("paper")
    cut[paper], fix[paper] = (rank < n_cut[:, None])[paper], ((rank >= n_cut[:, None]) & (rank < 2))[paper]
    rand = kind == KINDS.index("random")
    draw_cut = rng.random((batch, m)) < spec.p_cut
    cut[rand] = draw_cut[rand]
    fix[rand] = (~draw_cut & (rng.random((batch, m)) < spec.p_jam))[rand]
    all_but_one = kind == KINDS.index("all_but_one_cut")
    cut[all_but_one] = (rank > 0)[all_but_one]
    fix[all_but_one] = ((rank == 0) & (rng.random((batch, 1)) < 0.5))[all_but_one]  # the last one jammed, or not
    fix[kind == KINDS.index("all_jammed")] = True
    every = cut.all(axis=1)  # "every muscle cut" is refused as input: keep one muscle (tested in test_bad_input)
    cut[every, rng.integers(0, m, every.sum())] = False

    l_healthy, _ = schema.infer(q)
    offset = _pick(rng, spec.offset_weights, batch)[:, None]
    size = {"near": rng.normal(0.0, 0.005, (batch, m)), "below": -rng.uniform(0.0, 0.05, (batch, m)),
            "far_below": -(10.0 ** rng.uniform(-1, 3, (batch, m))), "above": rng.uniform(0.0, 0.05, (batch, m)),
            "far_above": 10.0 ** rng.uniform(-1, 3, (batch, m))}
    delta = np.select([offset == OFFSETS.index(k) for k in OFFSETS], [size[k] for k in OFFSETS])
    l_fixed = np.where(fix, np.maximum(l_healthy + delta, MIN_JAM_M), np.nan)

    for b, (q_b, states, l_fixed_b) in enumerate(spec.explicit[:batch]):
        q[b] = q_b
        cut[b], fix[b] = np.array(states) == "cut", np.array(states) == "jam"
        l_fixed[b] = np.where(fix[b], np.maximum(l_fixed_b, MIN_JAM_M), np.nan)
    labels = np.array(KINDS + ("explicit",))[np.where(np.arange(batch) < len(spec.explicit), len(KINDS), kind)]
    cond = np.where(cut.any(1) & fix.any(1), "BOTH", np.where(cut.any(1), "CUT", np.where(fix.any(1), "FIX", "NONE")))
    return FaultCases(q, cut, fix, l_fixed, cond), labels


# ---------------------------------------------------------------------------- the property
def assert_safe(result, batch: int, n_muscles: int, f_max) -> int:
    """The safe-command property for one batch; returns the number of ok rows outside the limits (0)."""
    status = np.asarray(result.status)
    assert status.shape == (batch,), f"status has shape {status.shape} for {batch} cases"
    assert result.l_motor_m.shape == result.f_n.shape == (batch, n_muscles)
    assert all(isinstance(s, str) and s for s in status.tolist()), "a case without a status"
    ok = status == "ok"
    l_motor, f = result.l_motor_m, result.f_n
    f_max = np.broadcast_to(np.asarray(f_max, float), f.shape)
    finite = np.isfinite(l_motor).all(1) & np.isfinite(f).all(1)
    with np.errstate(invalid="ignore"):
        in_limits = finite & (f >= 0.0).all(1) & (f <= f_max).all(1)
    outside = int((ok & ~in_limits).sum())
    assert outside == 0, f"{outside} ok rows not finite or outside [0, f_max], e.g. case {np.flatnonzero(ok & ~in_limits)[0]}"
    not_ok = ~ok
    assert np.isnan(l_motor[not_ok]).all() and np.isnan(f[not_ok]).all(), "a non-ok row carries numbers"
    return outside


@dataclass
class Tally:
    cases: int = 0
    outside: int = 0
    examples: int = 0

    def __post_init__(self):
        self.status = {v: Counter() for v in VARIANTS}
        self.feasible = Counter()  # (feasible?, status) -> count
        self.kinds = Counter()  # case kind -> count
        self.infeasible_kinds = Counter()


def fuzz(schema, n_examples: int, batch: int, tally: Tally):
    model, m = schema.robot_model, schema.n_muscles

    @settings(max_examples=n_examples, deadline=None, database=None, print_blob=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
    @given(spec=batch_specs(model.n_joints, m, model.q_range))
    def one_batch(spec):
        cases, kinds = make_cases(schema, spec, batch)
        result = schema.adapt(cases.q_ref, cases.faults, variant=spec.variant)
        tally.outside += assert_safe(result, batch, m, schema.spring.f_max_n)
        with np.errstate(over="ignore", invalid="ignore"):  # a jam km below: phi(stretch) overflows to inf, i.e. infeasible
            feasible, _ = check_feasible(model, cases, schema.spring)
        assert feasible.shape == (batch,)
        tally.cases += batch
        tally.examples += 1
        tally.status[spec.variant].update(result.status.tolist())
        tally.feasible.update(zip(feasible.tolist(), result.status.tolist()))
        tally.kinds.update(kinds.tolist())
        tally.infeasible_kinds.update(kinds[~feasible].tolist())

    one_batch()


def summary(name: str, tally: Tally) -> str:
    status = "; ".join(f"{v}: {dict(c)}" for v, c in tally.status.items())
    feasible = sum(n for (f, _), n in tally.feasible.items() if f)
    infeasible_ok = tally.feasible.get((False, "ok"), 0)
    return (f"{name}: {tally.cases} cases in {tally.examples} batches, {tally.outside} commands outside limits; "
            f"status {status}; feasible {feasible}, infeasible {tally.cases - feasible} "
            f"(of which adapt answered ok: {infeasible_ok}); kinds {dict(tally.kinds)}, "
            f"infeasible by kind {dict(tally.infeasible_kinds)}")


def run_and_check(name, schemas, examples, batch, minimum):
    torch.set_num_threads(1)
    tally = Tally()
    fuzz(schemas[name], examples, batch, tally)
    print("\n" + summary(name, tally))
    assert tally.outside == 0
    assert tally.cases >= minimum, f"only {tally.cases} cases tried"
    assert sum(sum(c.values()) for c in tally.status.values()) == tally.cases  # every case has a status
    assert sum(tally.feasible.values()) == tally.cases  # every case has a feasibility verdict
    return tally


@pytest.mark.parametrize("name", list(SCHEMA_CONFIGS))
def test_adapt_commands_are_safe(name, schemas):
    examples, batch = QUICK
    run_and_check(name, schemas, examples, batch, minimum=int(0.75 * examples * batch))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCHEMA_CONFIGS))
def test_adapt_commands_are_safe_10k(name, schemas):
    examples, batch = FULL
    tally = run_and_check(name, schemas, examples, batch, minimum=10_000)
    assert all(sum(c.values()) > 0 for c in tally.status.values()), "both variants must have been drawn"


def test_literal_diffusion_divergence_is_reported_as_nan(schemas):
    """The paper's literal guidance diverges on the diffusion schema (docs/design.md, guidance step): reported, never returned."""
    schema = schemas["Diffusion"]
    q = schema.robot_model.sample_q(np.random.default_rng(0), 32)
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["elbow_flexor", "shoulder_extensor"]] * 32)
    result = schema.adapt(q, faults, variant="literal")
    assert_safe(result, 32, schema.n_muscles, schema.spring.f_max_n)
    assert (result.status == "non_finite").any()


def test_infeasible_cases_are_counted(schemas):
    """check_feasible flags the hopeless draws: all but one muscle cut against gravity, and a jam far below."""
    schema = schemas["AE"]
    model, m = schema.robot_model, schema.n_muscles
    q = model.sample_q(np.random.default_rng(1), 40)
    cut = np.zeros((40, m), bool)
    cut[:20, 1:] = True  # only muscle 0 left: cannot hold two loaded joints
    fix = np.zeros((40, m), bool)
    fix[20:, 0] = True
    l_fixed = np.where(fix, MIN_JAM_M, np.nan)  # jammed at 0.1 mm, ~0.2 m short: the spring would need >> f_max
    cases = FaultCases(q, cut, fix, l_fixed, np.array(["CUT"] * 20 + ["FIX"] * 20))
    feasible, f_star = check_feasible(model, cases, schema.spring)
    assert not feasible.any() and np.isnan(f_star).all()
    result = schema.adapt(cases.q_ref, cases.faults)
    assert_safe(result, 40, m, schema.spring.f_max_n)
