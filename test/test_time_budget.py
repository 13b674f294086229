"""The image's soft deadline (``search.time_budget_ms``): which optional steps start, how
their costs are remembered, and what the estimate reports (on whole images: test_estimator.py)."""
import time

import pytest

from brepose_ros.online.time_budget import EASE, FINISH, StepCosts, TimeBudget
from brepose_ros.params import EstimatorParams


def costs(**seconds) -> StepCosts:
    known = StepCosts()
    known.remember(seconds)
    return known


def test_a_step_starts_only_if_its_remembered_cost_and_the_finish_fit_before_the_deadline():
    budget = TimeBudget(time.perf_counter() + 0.5, costs(seeded=0.3, larger=0.1, finish=0.3))
    assert not budget.allows("seeded", "small")  # 0.3 + 0.3 > 0.5
    assert budget.allows("larger")  # 0.1 + 0.3 < 0.5
    assert budget.allows("windows")  # never timed: it runs, and is timed
    assert not budget.allows("seeded", "small")  # each refused step named once
    assert budget.skipped == ["seeded", "small"]
    assert set(budget.spent) == {"larger", "windows"}  # each timed until the next step asks


def test_without_a_budget_every_step_starts_and_is_timed():
    budget = TimeBudget.starting_now(0, costs(seeded=100.0))
    assert budget.allows("seeded")
    time.sleep(0.01)
    budget.generators_done()
    time.sleep(0.02)
    budget.finished()
    assert budget.skipped == []
    assert budget.spent["seeded"] >= 0.01 and budget.spent[FINISH] >= 0.02
    assert budget.costs.expected(FINISH) == budget.spent[FINISH]


def test_a_longer_image_raises_a_cost_at_once_a_shorter_one_lowers_it_slowly():
    known = costs(seeded=0.1)
    known.remember({"seeded": 0.3})
    assert known.expected("seeded") == pytest.approx(0.3)
    known.remember({"seeded": 0.1})
    assert known.expected("seeded") == pytest.approx(0.3 - EASE * 0.2)


def test_the_budget_is_a_ranged_parameter():
    with pytest.raises(ValueError, match="time_budget_ms"):
        EstimatorParams().with_flat({"search.time_budget_ms": -1.0})
