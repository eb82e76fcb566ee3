import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.rotations import mat_to_rot6d, rot6d_to_mat
from sim.spaces import ActionSpace, TeleopCommand, TeleopLimits

SPACE = ActionSpace(pos_low=(-0.2, -0.2, 0.8), pos_high=(0.2, 0.2, 1.2))
HOME = np.array([0.0, 0.0, 1.0])
DOWN = np.diag([1.0, -1.0, -1.0])


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", ["delta_pos", "delta_rot"])
def test_teleop_rejects_non_finite_vectors(field, bad):
    with pytest.raises(ValueError, match=f"{field} must be finite"):
        TeleopCommand(**{field: (0.0, bad, 0.0)})


def test_teleop_rejects_non_finite_gripper_and_bad_shapes():
    with pytest.raises(ValueError, match="gripper must be finite"):
        TeleopCommand(gripper=math.nan)
    with pytest.raises(ValueError, match="3 components"):
        TeleopCommand(delta_pos=(0.0, 0.0))
    with pytest.raises(ValueError, match="3 numbers"):
        TeleopCommand(delta_rot=("a", 0, 0))


def test_huge_deltas_are_clamped_to_safe_steps_keeping_direction():
    limits = TeleopLimits()
    target = SPACE.apply_teleop(TeleopCommand((1e6, 0.0, -1e6), (0.0, 0.0, 50.0), 7.0), HOME, DOWN)
    step = target.action[:3] - HOME
    assert np.linalg.norm(step) == pytest.approx(limits.max_delta_pos)
    np.testing.assert_allclose(step / np.linalg.norm(step), [2**-0.5, 0, -(2**-0.5)], atol=1e-9)
    rot = rot6d_to_mat(target.action[3:9])
    angle = np.linalg.norm(Rotation.from_matrix(rot @ DOWN.T).as_rotvec())
    assert angle == pytest.approx(limits.max_delta_rot)
    assert target.action[9] == 1.0
    assert set(target.clamped) == {"delta_pos", "delta_rot", "gripper"}


def test_targets_stay_inside_workspace_bounds():
    corner = np.array([0.19, -0.19, 0.81])
    target = SPACE.apply_teleop(TeleopCommand((0.03, -0.03, -0.03)), corner, DOWN)
    np.testing.assert_allclose(target.action[:3], [0.2, -0.2, 0.8])
    assert "workspace" in target.clamped
    inside = SPACE.apply_teleop(TeleopCommand((0.01, 0.0, 0.0)), HOME, DOWN)
    np.testing.assert_allclose(inside.action[:3], HOME + [0.01, 0, 0])
    assert inside.clamped == ()


def test_small_command_is_applied_exactly():
    rot = Rotation.from_euler("xyz", [3.0, 0.1, 0.4]).as_matrix()
    target = SPACE.apply_teleop(TeleopCommand((0.0, 0.01, 0.0), (0.0, 0.0, 0.1), -1.0), HOME, rot)
    expected = Rotation.from_rotvec([0, 0, 0.1]).as_matrix() @ rot
    np.testing.assert_allclose(rot6d_to_mat(target.action[3:9]), expected, atol=1e-12)
    assert target.action[9] == -1.0


def test_action_space_normalisation_round_trip_and_bounds():
    rng = np.random.default_rng(0)
    rot = Rotation.random(5, random_state=1).as_matrix()
    actions = np.concatenate(
        [rng.uniform(SPACE.pos_low, SPACE.pos_high, (5, 3)), mat_to_rot6d(rot), rng.uniform(-1, 1, (5, 1))], axis=1
    )
    unit = SPACE.normalize(actions)
    assert unit.min() >= 0.0 and unit.max() <= 1.0
    np.testing.assert_allclose(SPACE.denormalize(unit), actions, atol=1e-12)
    np.testing.assert_allclose(SPACE.normalize(SPACE.low), 0.0)
    np.testing.assert_allclose(SPACE.normalize(SPACE.high), 1.0)


def test_action_space_validation():
    with pytest.raises(ValueError, match="pos_low < pos_high"):
        ActionSpace(pos_low=(0, 0, 1), pos_high=(1, 1, 0.5))
    with pytest.raises(ValueError, match="non-finite values in \\['y'\\]"):
        SPACE.validate(np.r_[0.0, np.nan, 1.0, np.zeros(7)])
    with pytest.raises(ValueError, match="shape"):
        SPACE.validate(np.zeros(7))
    with pytest.raises(ValueError, match="max_delta_pos"):
        TeleopLimits(max_delta_pos=-1.0)


def test_rot6d_round_trip():
    rot = Rotation.random(20, random_state=0).as_matrix()
    np.testing.assert_allclose(rot6d_to_mat(mat_to_rot6d(rot)), rot, atol=1e-12)


def test_probe_radius_in_each_dimensions_units():
    """r = 0.05 of the lift workspace (0.45 x 0.5 x 0.35 m) and of the [-1, 1] rotation and gripper."""
    from sim.tasks.lift import LIFT_WORKSPACE

    got = LIFT_WORKSPACE.radius_in_units(0.05)
    assert got["position_cm"] == [2.25, 2.5, 1.75]
    assert got["rot6d"] == 0.1 and got["gripper"] == 0.1
