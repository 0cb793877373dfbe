"""tools/reproduce_paper.py's split of the 7 trainings into per-core queues: the longest queue is as short as any
split allows (by the expected costs), every run is trained exactly once, each queue runs longest first."""
import itertools

from lightning_bodyschema.apps.reproduce import MODELS, RunSpec, _balanced_queues, _expected_cost


def _specs(epochs=10000):
    return [RunSpec(name, config, f"/nowhere/{config}", epochs) for name, config in MODELS.items()]


def test_two_queues_reach_the_smallest_possible_makespan():
    specs = _specs()
    queues = _balanced_queues(specs, 2)
    assert sorted(s.name for q in queues for s in q) == sorted(MODELS)
    makespan = max(sum(_expected_cost(s) for s in q) for q in queues)
    costs = [_expected_cost(s) for s in specs]
    best = min(max(sum(c for c, k in zip(costs, split) if k == q) for q in range(2))
               for split in itertools.product(range(2), repeat=len(costs)))
    assert makespan == best
    # and within one run of a perfect half-and-half split
    assert makespan < sum(costs) / 2 + min(costs)
    for q in queues:
        assert [_expected_cost(s) for s in q] == sorted((_expected_cost(s) for s in q), reverse=True)


def test_more_slots_than_runs_and_no_runs():
    assert [len(q) for q in _balanced_queues(_specs()[:1], 4)] == [1]
    assert _balanced_queues([], 2) == [[]]
    queues = _balanced_queues(_specs(), 8)  # greedy branch: 8^7 splits are too many to enumerate
    assert sorted(s.name for q in queues for s in q) == sorted(MODELS) and len(queues) == 7
