import json
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


def test_action_space_normalisation_spans_the_bounds():
    rng = np.random.default_rng(0)
    rot = Rotation.random(5, random_state=1).as_matrix()
    actions = np.concatenate(
        [rng.uniform(SPACE.pos_low, SPACE.pos_high, (5, 3)), mat_to_rot6d(rot), rng.uniform(-1, 1, (5, 1))], axis=1
    )
    unit = SPACE.normalize(actions)
    assert unit.min() >= 0.0 and unit.max() <= 1.0
    np.testing.assert_allclose(unit * (SPACE.high - SPACE.low) + SPACE.low, actions, atol=1e-12)
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


# --- TeleopCommand: validation and wire form ---------------------------------------------------------------

BOUNDS = {"delta_pos": TeleopCommand.MAX_DELTA_POS, "delta_rot": TeleopCommand.MAX_DELTA_ROT}


@pytest.mark.parametrize("field", ["delta_pos", "delta_rot"])
@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ((0.0, 0.0), "have 3 components"),
        ((0.0, 0.0, 0.0, 0.0), "have 3 components"),
        ((True, 0.0, 0.0), "be 3 numbers"),
        ((0.0, "0.1", 0.0), "be 3 numbers"),
        ((0.0, None, 0.0), "be 3 numbers"),
        ("abc", "be 3 numbers"),
        (0.1, "be 3 numbers"),
        (None, "be 3 numbers"),
        ((0.0, 10**400, 0.0), "be 3 numbers"),
    ],
)
def test_teleop_command_refuses_a_bad_vector_naming_the_field(field, bad, why):
    with pytest.raises(ValueError, match=f"TeleopCommand.{field} must {why}"):
        TeleopCommand(**{field: bad})


@pytest.mark.parametrize("bad", [True, False, np.bool_(True), None, "1.0", [1.0], math.nan, math.inf, 10**400])
def test_teleop_command_refuses_a_bad_gripper_naming_it(bad):
    with pytest.raises(ValueError, match="TeleopCommand.gripper must be"):
        TeleopCommand(gripper=bad)


def test_teleop_command_stores_plain_floats_from_any_real_numbers():
    cmd = TeleopCommand(np.array([0.01, 0.0, -0.02]), (0, np.int64(1), np.float32(0.5)), np.float64(1.0))
    assert cmd == TeleopCommand((0.01, 0.0, -0.02), (0.0, 1.0, 0.5), 1.0)
    for v in (*cmd.delta_pos, *cmd.delta_rot, cmd.gripper):
        assert type(v) is float


@pytest.mark.parametrize("field", ["delta_pos", "delta_rot"])
def test_an_operators_command_is_bounded_per_component_naming_the_field(field):
    bound = BOUNDS[field]
    edge = TeleopCommand.checked(**{field: (bound, -bound, 0.0)}, gripper=1.0)  # the bounds are inclusive
    assert getattr(edge, field) == (bound, -bound, 0.0)
    over = (0.0, 0.0, -math.nextafter(bound, math.inf))
    with pytest.raises(ValueError, match=f"TeleopCommand.{field}: each component must be within ±{bound}"):
        TeleopCommand.checked(**{field: over})
    with pytest.raises(ValueError, match=f"TeleopCommand.{field}: each component"):
        TeleopCommand.from_dict({"delta_pos": (0, 0, 0), "gripper": 0.0} | {field: over})
    with pytest.raises(ValueError, match=f"TeleopCommand.{field}: each component"):
        TeleopCommand(**{field: over}).check_bounds()
    assert getattr(TeleopCommand(**{field: over}), field) == over  # a composed command: clamped when applied


@pytest.mark.parametrize("gripper", [-1.5, 1.0000001, 7.0])
def test_an_operators_gripper_is_within_its_range(gripper):
    with pytest.raises(ValueError, match=r"TeleopCommand.gripper must be within \[-1.0, 1.0\]"):
        TeleopCommand.checked(gripper=gripper)
    assert TeleopCommand.checked(gripper=-1.0).gripper == -1.0 and TeleopCommand.checked(gripper=1).gripper == 1.0


@pytest.mark.parametrize(
    "cmd",
    [
        TeleopCommand(),
        TeleopCommand((0.1 + 0.2, -0.0, 5e-324), (1 / 3, -0.5, 0.49999999999999994), 0.7000000000000001),
        TeleopCommand(np.float32([0.01, -0.02, 0.03]), (0.0, 0.0, float(np.float32(0.1))), -1.0),
        TeleopCommand((0.25, 0.0, 0.0), (0.0, 0.0, 3.0), 1.0),  # composed: over an operator's bounds
    ],
)
def test_teleop_command_round_trips_exactly_through_its_wire_form(cmd):
    data = cmd.to_dict()
    assert set(data) == {"delta_pos", "delta_rot", "gripper"}
    assert all(type(v) is float for v in (*data["delta_pos"], *data["delta_rot"], data["gripper"]))
    assert json.loads(json.dumps(data)) == data
    back = TeleopCommand.from_dict(data, bounded=False)
    assert back == cmd and back.to_dict() == data
    assert math.copysign(1.0, back.delta_pos[1]) == math.copysign(1.0, cmd.delta_pos[1])  # -0.0 stays -0.0
    assert TeleopCommand.from_json(cmd.to_json(), bounded=False) == cmd


def test_from_dict_reads_the_apis_body_and_nothing_else():
    body = {"delta_pos": [0.0, 0.0, 0.01], "gripper": -1}
    assert TeleopCommand.from_dict(body) == TeleopCommand((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), -1.0)
    with pytest.raises(ValueError, match="TeleopCommand.gripper is missing"):
        TeleopCommand.from_dict({"delta_pos": [0, 0, 0]})
    with pytest.raises(ValueError, match="TeleopCommand.delta_pos is missing"):
        TeleopCommand.from_dict({"gripper": 1.0})
    with pytest.raises(ValueError, match=r"unknown fields \['speed'\]"):
        TeleopCommand.from_dict(body | {"speed": 1})
    with pytest.raises(ValueError, match="JSON object"):
        TeleopCommand.from_dict([0, 0, 0])
    with pytest.raises(ValueError, match="TeleopCommand.delta_pos must be finite"):
        TeleopCommand.from_json('{"delta_pos": [NaN, 0, 0], "gripper": 1}')
    with pytest.raises(ValueError, match="not valid JSON"):
        TeleopCommand.from_json("{")
