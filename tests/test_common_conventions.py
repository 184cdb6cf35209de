"""conventions.task_on_map: the one rule for which task a curriculum arm runs on a map."""
import pytest

from bimacppo_common.conventions import TASKS, task_on_map


def test_an_arm_runs_its_own_task_where_the_map_has_it():
    for task in TASKS:
        assert task_on_map(task, TASKS) == task
        assert task_on_map(task, [task, "straight"]) == task


def test_a_one_task_map_runs_its_task_for_every_arm():
    for only in TASKS:
        assert [task_on_map(t, (only,)) for t in TASKS] == [only] * 3


def test_a_missing_task_on_a_map_with_several_is_an_error():
    with pytest.raises(ValueError, match="'right' is not available \\(tasks: left, straight\\)"):
        task_on_map("right", ("left", "straight"))
    with pytest.raises(ValueError, match="task must be one of"):
        task_on_map("u-turn", TASKS)
