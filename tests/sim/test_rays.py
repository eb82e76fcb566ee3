import numpy as np
import pytest

from sim.env import TABLE_TOP_Z
from sim.rays import DOWN_RANGE, LABELS, RAYS, FingerRays
from sim.registry import make_expert, make_task


def _to_pregrasp(task, expert):
    for _ in range(200):
        if expert.placed(task):
            return
        task.step(task.teleop(expert.act(task)).action)
    raise AssertionError("the expert never placed the gripper")


@pytest.mark.parametrize("name", ["lift-cube", "lift-hammer"])
def test_the_rays_see_nothing_in_free_space_and_the_object_between_the_fingers_at_the_grasp(name):
    task = make_task(name)
    obs = task.reset(3)
    rays = obs[task.obs_spec.slices()["finger_rays"]]
    assert len(LABELS) == RAYS == rays.shape[0] == 6

    def pads() -> float:
        left, right = (task.mj_data().xpos[b] for b in FingerRays(task.mj_model()).pads)
        return float(np.linalg.norm(right - left))

    # nothing between the open fingers (each across ray reads the pads' distance) and nothing under them
    # within range (the gripper starts high above the table)
    assert np.allclose(rays[:3], pads()) and pads() > task.gripper_opening()
    assert np.allclose(rays[3:], DOWN_RANGE)
    expert = make_expert(name)
    expert.reset(task, np.random.default_rng(0))
    _to_pregrasp(task, expert)
    rays = task.finger_rays()
    assert rays[:3].max() < 0.6 * pads()  # the object fills the gap between the pads
    site_z = task.ee_pose()[0][2]
    assert rays[3:].max() <= site_z - TABLE_TOP_Z + 1e-3  # the down rays stop at the object or at the table


def test_the_lift_observation_carries_the_rays_last():
    spec = make_task("lift-nut").obs_spec
    assert list(spec.slices())[-1] == "finger_rays" and spec.slices()["finger_rays"].stop == spec.dim
