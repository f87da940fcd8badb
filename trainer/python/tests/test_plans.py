"""The check that every rank of a job is served the same plan."""

from __future__ import annotations

import pytest

from superflow import PlanMismatch, Schedule
from superflow.stream import check_plans


def plan(seed: int = 0, host_count: int = 2) -> dict[str, int]:
    return Schedule(steps=3, min_steps=3, epochs=1, publisher=0, samples=12, global_batch=4,
                    seed=seed, host_count=host_count, keyframes=12, plan_digest=seed + 1).plan()


def rank(r: int, host: int, pipeline: int, **kwargs: int) -> dict:
    return {"rank": r, "host_rank": host, "pipeline": f"node{pipeline}/prefix",
            "plan": plan(**kwargs)}


def test_two_hosts_of_two_ranks_agree() -> None:
    check_plans("run", "svc", [rank(0, 0, 10), rank(1, 0, 10), rank(2, 1, 11), rank(3, 1, 11)])


def test_another_seed_is_named() -> None:
    with pytest.raises(PlanMismatch, match=r"rank 2's pipeline serves another plan.*seed 7 vs 0"):
        check_plans("run", "svc", [rank(0, 0, 10), rank(1, 0, 10), rank(2, 1, 11, seed=7)])


def test_two_hosts_with_the_same_host_rank() -> None:
    with pytest.raises(PlanMismatch, match="both run --host-rank 0"):
        check_plans("run", "svc", [rank(0, 0, 10), rank(1, 0, 11)])


def test_a_host_missing() -> None:
    with pytest.raises(PlanMismatch, match=r"--host-count 2.*read 1"):
        check_plans("run", "svc", [rank(0, 0, 10), rank(1, 0, 10)])


def test_schedule_positions() -> None:
    schedule = Schedule(steps=3, min_steps=2, epochs=2, publisher=0, samples=12, global_batch=4,
                        start_epoch=1, start_sample=6, start_steps=2, start_min_steps=1)
    assert schedule.steps_in(0) == 3 and schedule.steps_in(1) == 2
    assert schedule.consumed(0, 2) == 8 and schedule.consumed(1, 1) == 10
    assert schedule.step_at(0, 8) == 2 and schedule.step_at(0, 12) == 3
    assert schedule.step_at(1, 10) == 1 and schedule.step_at(0, 5) == 0
