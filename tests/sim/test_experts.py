import numpy as np
import pytest

from sim.experts import CARRY_CLEARANCE, OperatorStyle, operator_rng
from sim.registry import make_expert, make_task
from sim.spaces import TeleopCommand


def test_a_person_keeps_one_way_of_working_per_episode():
    draws = {s: [operator_rng(s, 7, k).uniform(size=3).tolist() for k in (1, 2, 3)] for s in OperatorStyle}
    assert draws["carry-on"][0] == draws["carry-on"][1] == draws["carry-on"][2]  # the same plan at every request
    assert draws["replan"][0] != draws["replan"][1]  # a fresh one at every request
    assert draws["carry-on"][0] == draws["replan"][0]  # the first request plans the same in both
    assert operator_rng("carry-on", 8, 1).uniform() != operator_rng("carry-on", 7, 1).uniform()
    with pytest.raises(ValueError):
        operator_rng("psychic", 7, 1)


def _carry(task, expert, seed: int) -> None:
    """Runs ``expert`` from the reset of ``seed`` until it carries the green cup towards the red one."""
    task.reset(seed)
    expert.reset(task, operator_rng("carry-on", seed, 1))
    for _ in range(300):
        if expert.phase == "carry":
            return
        task.step(task.teleop(expert.act(task)).action)
    raise AssertionError("the expert never carried the cup")


def test_a_carried_cup_taken_over_again_goes_on_at_its_height(task_cache):
    """The policy lowered the carried cup 3 cm (still clear of the red rim): the carry-on operator steers it
    across at that height, where one planning afresh climbs to a new carry height first."""
    task = task_cache("cup-stack")

    def lowered_then_taken_over(style: str) -> tuple[float, list[float]]:
        _carry(task, make_expert("cup-stack"), 11)
        for _ in range(3):  # the policy moves the cup down 3 cm
            task.step(task.teleop(TeleopCommand((0.0, 0.0, -0.01), (0, 0, 0), 1.0)).action)
        s = task.privileged()
        assert s["green_bottom_z"] > s["red_rim_z"] + CARRY_CLEARANCE
        start = float(task.ee_pose()[0][2])
        expert = make_expert("cup-stack", retry=True, style=style)
        expert.take_over(task, 11, 2)
        assert expert.phase == "carry"
        aim = float(expert._target("carry", task)[2]) - start  # the height it carries at, from where it stands
        heights = []
        for _ in range(6):
            task.step(task.teleop(expert.act(task)).action)
            heights.append(float(task.ee_pose()[0][2]) - start)
        return aim, heights

    aim, heights = lowered_then_taken_over("carry-on")
    assert aim == pytest.approx(0.0, abs=1e-9) and max(np.abs(heights)) < 0.006
    aim, _ = lowered_then_taken_over("replan")
    assert abs(aim) > 1e-3  # its plan's own carry height (drawn afresh), not the height it stands at


def test_the_expert_counts_as_placed_only_at_the_grasp_with_the_gripper_open():
    task = make_task("lift-cube")
    task.reset(5)
    expert = make_expert("lift-cube")
    expert.reset(task, np.random.default_rng(1))
    assert not expert.placed(task)
    placed_at = None
    for step in range(200):
        if expert.placed(task):
            placed_at = step
            break
        task.step(task.teleop(expert.act(task)).action)
    assert placed_at is not None and expert.phase == "close"
    grasp = task.privileged()["grasp_point"]
    assert np.linalg.norm(task.ee_pose()[0] - grasp) < 0.02
    for _ in range(12):  # it closes: no longer placed
        task.step(task.teleop(expert.act(task)).action)
    assert not expert.placed(task)


def test_the_drawer_expert_first_crosses_to_the_intended_drawer_at_its_height(task_cache):
    """The choice of drawer is made in the first steps: the expert moves across the cabinet only (along y), fast,
    so eight steps take the gripper several centimetres towards the intended side."""
    task = task_cache("open-drawer")
    for seed in (0, 2):  # the right drawer (-y), the left one (+y)
        task.reset(seed)
        expert = make_expert("open-drawer")
        expert.reset(task, np.random.default_rng(seed))
        start = task.ee_pose()[0].copy()
        handle = task.privileged()["handles"][task.intended]
        for _ in range(8):
            assert expert.phase == "across"
            task.step(task.teleop(expert.act(task)).action)
        moved = task.ee_pose()[0] - start
        assert np.sign(moved[1]) == np.sign(handle[1] - start[1])
        assert abs(moved[1]) > 0.035  # a third of the way to a side drawer's handle (11.4 cm across)
        assert abs(moved[0]) < 0.01 and abs(moved[2]) < 0.01  # neither forward nor down yet
