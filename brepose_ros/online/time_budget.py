"""An image's soft deadline (``search.time_budget_ms``): the estimator's optional steps (a
generator after the first, a colour place, the larger check) start only if what they took
on recent images still fits before it, leaving time for the steps that always run (the
finalists' climb, the twin check).

A step never stops midway: the compiled kernels cannot be interrupted, and half a climb is
no pose. So the budget is kept by not starting what would overrun it, which needs each
step's cost before it runs: ``StepCosts`` remembers them per estimator, taking a new
image's time at once when it is longer and letting a shorter one lower it only slowly, so
that one quick image does not let the next start a step that overruns.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

#: the steps that always run after the generators, whose time the budget keeps free
FINISH = "finish"
#: the larger-pose check, an optional step after the generators (not part of the finish)
LARGER_CHECK = "larger"

#: how much of the gap a shorter image closes on a step's remembered cost
EASE = 0.2


class StepCosts:
    """Seconds each optional step (and ``FINISH``) took on an estimator's recent images (one
    estimator's images run one at a time, so no lock)."""

    def __init__(self) -> None:
        self._seconds: dict[str, float] = {}

    def expected(self, step: str) -> float:
        """The step's remembered cost; 0 for a step never timed (it runs, and is timed)."""
        return self._seconds.get(step, 0.0)

    def remember(self, spent: dict[str, float]) -> None:
        for step, seconds in spent.items():
            old = self._seconds.get(step, 0.0)
            self._seconds[step] = seconds if seconds >= old else old + EASE * (seconds - old)


@dataclass
class TimeBudget:
    """One image's deadline: each optional step asks ``allows`` before it starts and is timed
    until the next one asks (or ``close``); the steps refused are kept in ``skipped`` for the
    estimate to report, and the time of those run in ``spent`` for the estimator's
    ``StepCosts``."""

    deadline: float = math.inf
    costs: StepCosts = field(default_factory=StepCosts)
    skipped: list[str] = field(default_factory=list)
    spent: dict[str, float] = field(default_factory=dict)
    _running: tuple[str, float] | None = None
    _generators_done: float | None = None

    @classmethod
    def starting_now(cls, ms: float, costs: StepCosts) -> "TimeBudget":
        """A budget of ``ms`` milliseconds from now (0: none) judged on ``costs``."""
        return cls(time.perf_counter() + ms / 1000.0 if ms > 0 else math.inf, costs)

    def allows(self, *steps: str) -> bool:
        """Whether ``steps[0]`` still fits before the deadline with the finish's time to spare
        (then it is timed until the next ``allows`` or ``close``); if not, ``steps`` (it and
        those that would follow it) are noted as skipped."""
        now = self.close()
        if now + self.costs.expected(steps[0]) + self.costs.expected(FINISH) < self.deadline:
            self._running = steps[0], now
            return True
        self.skipped.extend(s for s in steps if s not in self.skipped)
        return False

    def close(self) -> float:
        """End the step being timed, if any; the time now."""
        now = time.perf_counter()
        if self._running is not None:
            step, start = self._running
            self.spent[step] = self.spent.get(step, 0.0) + now - start
            self._running = None
        return now

    def generators_done(self) -> None:
        """The generators have run: what follows until ``finished`` (the larger check apart)
        is the finish."""
        self._generators_done = self.close()

    def finished(self) -> None:
        """The image is done: its finish timed, every step's time handed to the costs."""
        now = self.close()
        if self._generators_done is not None:
            self.spent[FINISH] = now - self._generators_done - self.spent.get(LARGER_CHECK, 0.0)
        self.costs.remember(self.spent)
