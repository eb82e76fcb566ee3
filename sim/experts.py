"""Scripted experts: the simulated operator.

Every expert acts only through ``TeleopCommand``s, exactly like a human at the
console, and may read the task's privileged state (true object poses, the
intended drawer, the occluded cup). An expert is a list of phases (move to a
target with a gripper command, until within tolerance, then optionally pause);
the per-episode randomisation (approach height, speed, pause lengths, drawer) makes the
demonstrations varied the way human demonstrations are.

Pauses happen only where the state keeps changing while the expert holds still
(the fingers closing or opening, a carried cup settling). The experts never
pause in free space above an object: with an observation history of 1, such a
pause looks the same at every step, and a policy trained on it can learn a
"wait" that never ends.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from scipy.spatial.transform import Rotation

from sim.env import Task
from sim.rotations import wrap_angle
from sim.spaces import TeleopCommand

OPEN, CLOSED = -1.0, 1.0
GRIPPED = 0.07  # finger gap (m) under which the gripper counts as closed (0.08 is fully open)
# resuming mid-task (``Expert.resume``): the end effector counts as at the grasp within AT_GRASP, and
# a carried cup as over its target within ALIGNED horizontally (metres)
AT_GRASP = 0.02
HELD_ABOVE = 0.01  # a lifted object counts as held once this far (m) above where it rested
ALIGNED = 0.01
# a takeover this close to the grasp across the table (m) goes straight for it (``LiftExpert.from_here``): no
# lower than MIN_APPROACH (m) above it before the descent, through the point above it within LOOSE (m, rad)
NEAR = 0.10
MIN_APPROACH = 0.02
LOOSE = (0.025, 0.3)
# the simulated operator tries again (``Expert.retry``) when its plan ended this many steps ago without the
# episode succeeding (the lift came up empty), or when the gripper moved less than STUCK_MOVED (m) over
# STUCK_STEPS steps short of its target (pushing against the object): a person goes back for the object
RETRY_AFTER = 5
STUCK_STEPS = 15
STUCK_MOVED = 0.005
# a carried cup whose bottom clears the red cup's rim by this much (m) goes on at its height (``from_here``)
CARRY_CLEARANCE = 0.02
# m per step of the drawer expert's move across (``OpenDrawerExpert``), drawn per episode; at most 3 cm (SpaceLimits)
ACROSS_SPEED = (0.024, 0.03)
# Gripper pointing down (grip-site z = world -z) at yaw 0. The Panda's fingers
# close along the site's x axis, so a grasped bar lies along the site's y axis;
# "yaw" is the heading of that y axis. At yaw 0 the fingers close along world y.
_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def gripper_yaw(rot: np.ndarray) -> float:
    """Heading of the grip site's y axis (the axis a grasped bar lies along)."""
    return float(np.arctan2(rot[1, 1], rot[0, 1]))


@dataclass
class Phase:
    """Move towards ``target(task)`` (pos (3,), yaw) holding ``gripper``.

    The phase ends when within ``tol`` metres (and 0.08 rad of yaw), or after
    ``max_steps``; then the expert holds still for ``pause`` steps. ``speed`` (metres per step) overrides
    the episode's speed for this phase.
    """

    name: str
    target: Callable[[Task], tuple[np.ndarray, float | None]]
    gripper: float
    tol: float = 0.01
    pause: int = 0
    max_steps: int = 200
    yaw_tol: float = 0.08  # radians
    speed: float | None = None


def command_towards(
    task: Task, pos: np.ndarray, yaw: float | None, gripper: float, speed: float, gain: float = 1.0
) -> TeleopCommand:
    """A teleop command that moves the end effector towards ``pos`` / ``yaw``."""
    cur_pos, cur_rot = task.ee_pose()
    delta = (np.asarray(pos) - cur_pos) * gain
    norm = np.linalg.norm(delta)
    if norm > speed:
        delta *= speed / norm
    target_yaw = gripper_yaw(cur_rot) if yaw is None else yaw
    desired = Rotation.from_euler("z", target_yaw).as_matrix() @ _DOWN
    drot = Rotation.from_matrix(desired @ cur_rot.T).as_rotvec()
    return TeleopCommand(tuple(delta), tuple(drot), gripper)


def closest_yaw(current: float, target: float, symmetry: float) -> float:
    """The yaw equivalent to ``target`` (mod ``symmetry``) nearest to ``current``."""
    k = np.round((current - target) / symmetry)
    return float(wrap_angle(target + k * symmetry))


class OperatorStyle(StrEnum):
    """How the simulated operator plans when a robot the policy moved comes back to it.

    ``carry-on`` (default): as a person, with one way of working per episode: the plan's parameters
    (speed, heights, pauses) are drawn once per episode, and each takeover picks the plan up from
    where the robot stands (``Expert.resume``: the phases already done are skipped, ``from_here``
    adapts the rest to the current pose). ``replan``: fresh random parameters at every request, as the
    benchmarks' operator did before; on cup-stack it climbed back to a new carry height at each request
    (docs/benchmarks/hitl.md)."""

    CARRY_ON = "carry-on"
    REPLAN = "replan"


def operator_rng(style: OperatorStyle | str, episode_seed: int, request: int) -> np.random.Generator:
    """The randomness of the simulated operator's plan at its ``request``-th takeover (from 1) of the
    episode seeded ``episode_seed``: the same for every request of an episode in ``carry-on`` style, a
    fresh draw per request in ``replan`` style. The first request draws the same plan in both."""
    style = OperatorStyle(style)
    return np.random.default_rng([int(episode_seed), 1 if style == OperatorStyle.CARRY_ON else int(request)])


class Expert:
    """Runs a list of phases, built per episode by ``plan``.

    ``retry`` (off for demonstrations, on for the simulated operator): when the plan has run to its end
    and ``RETRY_AFTER`` steps later the episode is still going (it ends at success), or when the gripper
    is stuck short of its target (``STUCK_STEPS``, ``STUCK_MOVED``), the expert plans again from the
    scene without ``from_here``'s shortcut (from the approach height, over the object), as a person
    whose grasp came up empty or whose fingers hit the object tries again; ``retries`` counts the
    attempts. Without it, such a takeover went on until the operator's own limit: 1000 steps on
    lift-hammer and lift-hook, where the shortcut's low approach ran the fingers into the object
    (docs/benchmarks/nights.md)."""

    name = "expert"

    def __init__(self) -> None:
        self.phases: list[Phase] = []
        self._i = 0
        self._steps_in_phase = 0
        self._pause_left = 0
        self.speed = 0.02
        self.retry = False
        self.retries = 0
        self._rng: np.random.Generator | None = None
        self._ended = 0  # steps commanded since the plan ran to its end
        self._trail: deque = deque(maxlen=STUCK_STEPS)  # the end effector's last positions (retry only)
        self.style = OperatorStyle.CARRY_ON  # how it plans at a takeover (``take_over``)

    def plan(self, task: Task, rng: np.random.Generator) -> list[Phase]:
        raise NotImplementedError

    def reset(self, task: Task, rng: np.random.Generator) -> None:
        self.speed = float(rng.uniform(0.012, 0.022))
        self.phases = self.plan(task, rng)
        self._i, self._steps_in_phase, self._pause_left, self._ended = 0, 0, 0, 0
        self._rng = rng
        self._trail.clear()

    def take_over(self, task: Task, episode_seed: int, request: int, carry_on: bool = False) -> None:
        """The simulated operator's ``request``-th takeover (from 1) in the episode seeded ``episode_seed``:
        ``resume`` with its plan's randomness drawn as its ``style`` does (``operator_rng``)."""
        self.resume(task, operator_rng(self.style, episode_seed, request), carry_on)

    def resume(self, task: Task, rng: np.random.Generator, carry_on: bool = False) -> None:
        """Takes over mid-episode: plans as ``reset`` does, then skips the phases whose work the scene
        shows is done (an object already held, a gripper already at the grasp), judged only from what
        an operator sees: the end-effector pose, the gripper opening and the scene.

        carry_on: the robot is as this expert left it (nothing moved it since its last command, as
        when control comes straight back after a budgeted takeover): go on with the same plan, as
        an operator would, instead of planning afresh."""
        if carry_on and self.phases and not self.done:
            return
        self.reset(task, rng)
        self.from_here(task)
        self._i = min(self.start_phase(task), len(self.phases) - 1)

    def from_here(self, task: Task) -> None:
        """Adapts the fresh plan to a takeover from where the robot stands, before ``start_phase``
        picks the phase: nothing by default (``LiftExpert``: no climb back to the approach height)."""

    def start_phase(self, task: Task) -> int:
        """Index of the first phase still to do; 0 unless an expert knows better."""
        return 0

    def holding(self, task: Task) -> bool:
        """Whether the scene shows what this expert grasps held (judged, as ``resume`` does, from what an
        operator sees): the point where an operator asked to help with a grasp hands the robot back
        (``lab.assisted.ExpertOperator``). False for an expert that knows no such point."""
        return False

    def placed(self, task: Task) -> bool:
        """Whether the plan has brought the gripper to where it closes on the object and the gripper is still
        open: the pre-grasp pose, where an operator asked to place the gripper hands the robot back
        (``lab.assisted.ExpertOperator``; ``hitl report pregrasp``)."""
        return bool(self.phases) and not self.done and self.phase == "close" and task.gripper_opening() >= GRIPPED

    def _index(self, name: str) -> int:
        return next(i for i, p in enumerate(self.phases) if p.name == name)

    def _target(self, name: str, task: Task) -> np.ndarray:
        """Where phase ``name`` would move the end effector now (m)."""
        return np.asarray(self.phases[self._index(name)].target(task)[0], dtype=np.float64)

    @property
    def phase(self) -> str:
        return self.phases[min(self._i, len(self.phases) - 1)].name

    @property
    def done(self) -> bool:
        return self._i >= len(self.phases)

    def act(self, task: Task) -> TeleopCommand:
        if self.retry and self._rng is not None and self._failed(task):
            self.retries += 1
            self.reset(task, self._rng)  # the whole plan, from the approach height (no shortcut)
            self._i = min(self.start_phase(task), len(self.phases) - 1)
        phase = self.phases[min(self._i, len(self.phases) - 1)]
        pos, yaw = phase.target(task)
        cur_pos, cur_rot = task.ee_pose()
        speed = self.speed if phase.speed is None else phase.speed
        if self._pause_left > 0 and not self.done:
            self._pause_left -= 1
            if self._pause_left == 0:
                self._advance()
            return command_towards(task, cur_pos, yaw, phase.gripper, speed)
        cmd = command_towards(task, pos, yaw, phase.gripper, speed)
        if self.done:
            return cmd
        self._steps_in_phase += 1
        yaw_ok = yaw is None or abs(wrap_angle(gripper_yaw(cur_rot) - yaw)) < phase.yaw_tol
        reached = np.linalg.norm(cur_pos - pos) < phase.tol and yaw_ok
        if reached or self._steps_in_phase >= phase.max_steps:
            if phase.pause > 0:
                self._pause_left = phase.pause
            else:
                self._advance()
        return cmd

    def _advance(self) -> None:
        self._i += 1
        self._steps_in_phase = 0
        self._trail.clear()

    def _failed(self, task: Task) -> bool:
        """The plan ended ``RETRY_AFTER`` steps ago and the episode goes on, or the gripper is stuck
        short of a moving phase's target (see the class)."""
        if self.done:
            self._ended += 1
            return self._ended > RETRY_AFTER
        if self._pause_left > 0:
            return False
        phase = self.phases[self._i]
        pos = task.ee_pose()[0]
        self._trail.append(pos)
        moved = np.linalg.norm(self._trail[-1] - self._trail[0])
        short = np.linalg.norm(pos - np.asarray(phase.target(task)[0])) > max(phase.tol, STUCK_MOVED)
        return len(self._trail) == STUCK_STEPS and moved < STUCK_MOVED and short


class LiftExpert(Expert):
    """Approach above the grasp point, descend, close, lift."""

    name = "lift-scripted"

    def plan(self, task: Task, rng: np.random.Generator) -> list[Phase]:
        approach_h = float(rng.uniform(0.05, 0.14))
        lift_h = float(rng.uniform(0.10, 0.16))
        state = task.privileged()
        cur_yaw = gripper_yaw(task.ee_pose()[1])
        yaw = closest_yaw(cur_yaw, state["grasp_yaw"], state["yaw_symmetry"])
        depth = state["grasp_depth"]

        def grasp_point(t: Task) -> np.ndarray:
            return t.privileged()["grasp_point"]

        def above(t: Task):  # the height is read when called: ``from_here`` may lower it
            return grasp_point(t) + [0, 0, self._approach_h], yaw

        def at(t: Task):
            p = grasp_point(t) - [0, 0, depth]
            p[2] = max(p[2], state["table_z"] + 0.008)
            return p, yaw

        grasped: dict[str, np.ndarray] = {}

        def up(t: Task):
            grasped.setdefault("p", t.ee_pose()[0])
            return grasped["p"] + [0, 0, lift_h], yaw

        self._approach_h = approach_h
        return [
            Phase("approach", above, OPEN, tol=0.012),
            # 1 cm: under execution noise a 6 mm tolerance kept the expert hovering open at the grasp for
            # a random number of steps, and a policy with history 1 learnt to hover there for good
            Phase("descend", at, OPEN, tol=0.01, max_steps=60),
            Phase("close", lambda t: (t.ee_pose()[0], yaw), CLOSED, tol=np.inf, pause=int(rng.integers(6, 10))),
            Phase("lift", up, CLOSED, tol=0.01),
        ]

    def from_here(self, task: Task) -> None:
        """A takeover above the object goes straight for the grasp, as a person does with a robot that
        stopped short of it: with the gripper open, above the grasp point and within ``NEAR`` of it
        across the table, the approach height becomes the height the robot stands at (if lower than
        the plan's), and the point above the grasp is a waypoint passed within ``LOOSE`` (distance,
        yaw) rather than a pose to settle at: the descent finishes the yaw, whose own check is as
        tight as ever. Planning afresh from the 5-14 cm approach height, the simulated operator spent
        its 4-step budgets climbing and its takeovers settling at the waypoint (docs/benchmarks/hitl.md,
        "The object-frame lift policy")."""
        pos, grasp = task.ee_pose()[0], task.privileged()["grasp_point"]
        height = float(pos[2] - grasp[2])
        if task.gripper_opening() >= GRIPPED and np.linalg.norm(pos[:2] - grasp[:2]) < NEAR and height > 0:
            self._approach_h = min(self._approach_h, max(height, MIN_APPROACH))
            i = self._index("approach")
            self.phases[i] = replace(self.phases[i], tol=LOOSE[0], yaw_tol=LOOSE[1])

    def holding(self, task: Task) -> bool:
        """The gripper closed and the object off the table (1 cm above where it rested)."""
        s = task.privileged()
        return bool(task.gripper_opening() < GRIPPED and s["object_pos"][2] > s["rest_z"] + HELD_ABOVE)

    def start_phase(self, task: Task) -> int:
        s = task.privileged()
        pos = task.ee_pose()[0]
        closed = task.gripper_opening() < GRIPPED
        at_grasp = np.linalg.norm(pos - self._target("descend", task)) < AT_GRASP
        if self.holding(task):  # already holding it off the table
            return self._index("lift")
        if at_grasp:  # at the grasp: close (again), and give the fingers their time before lifting
            return self._index("close")
        if not closed and _over(pos, s["grasp_point"], self._approach_h):
            return self._index("descend")
        return 0


class CupStackExpert(Expert):
    """Grasp the green cup near its rim, carry it over the red cup, lower, release."""

    name = "cup-stack-scripted"

    def plan(self, task: Task, rng: np.random.Generator) -> list[Phase]:
        approach_h = float(rng.uniform(0.05, 0.12))
        self._carry_z = task.privileged()["table_z"] + float(rng.uniform(0.17, 0.22))
        release_gap = float(rng.uniform(0.006, 0.012))
        retreat = float(rng.uniform(0.06, 0.10))
        mem: dict[str, np.ndarray] = {}

        def above_green(t: Task):
            return t.privileged()["green_grasp_point"] + [0, 0, approach_h], None

        def at_green(t: Task):
            return t.privileged()["green_grasp_point"], None

        def lift(t: Task):
            p = mem.setdefault("grasp", t.ee_pose()[0])
            return np.array([p[0], p[1], self._carry_z]), None

        def _offset(t: Task) -> np.ndarray:
            s = t.privileged()
            return t.ee_pose()[0] - s["green_pos"]

        def over_red(t: Task):
            s = t.privileged()
            target = s["red_pos"] + _offset(t)
            return np.array([target[0], target[1], self._carry_z]), None

        def lower(t: Task):
            s = t.privileged()
            target = s["red_pos"] + _offset(t)
            drop = s["green_bottom_z"] - (s["red_floor_z"] + release_gap)
            return np.array([target[0], target[1], t.ee_pose()[0][2] - drop]), None

        def retreat_up(t: Task):
            p = mem.setdefault("release", t.ee_pose()[0])
            return p + [0, 0, retreat], None

        hold = lambda t: (t.ee_pose()[0], None)  # noqa: E731
        self._approach_h = approach_h
        return [
            Phase("approach", above_green, OPEN, tol=0.012),
            Phase("descend", at_green, OPEN, tol=0.006, max_steps=60),
            Phase("close", hold, CLOSED, tol=np.inf, pause=int(rng.integers(6, 10))),
            Phase("lift", lift, CLOSED, tol=0.015),
            Phase("carry", over_red, CLOSED, tol=0.006, pause=int(rng.integers(2, 6))),
            Phase("lower", lower, CLOSED, tol=0.005, max_steps=60),
            Phase("release", hold, OPEN, tol=np.inf, pause=int(rng.integers(5, 8))),
            Phase("retreat", retreat_up, OPEN, tol=0.01),
        ]

    def from_here(self, task: Task) -> None:
        """In ``carry-on`` style, a cup taken over while carried goes on at the height it is carried at, when
        its bottom clears the red cup's rim by ``CARRY_CLEARANCE``, as a person steering a carried cup
        would, instead of climbing to the plan's carry height first."""
        s = task.privileged()
        clear = s["green_bottom_z"] > s["red_rim_z"] + CARRY_CLEARANCE
        if self.style == OperatorStyle.CARRY_ON and self.holding(task) and clear:
            self._carry_z = float(task.ee_pose()[0][2])

    def holding(self, task: Task) -> bool:
        """The gripper closed and the green cup 2 cm off the table (carried)."""
        s = task.privileged()
        return bool(task.gripper_opening() < GRIPPED and s["green_bottom_z"] > s["table_z"] + 0.02)

    def start_phase(self, task: Task) -> int:
        s = task.privileged()
        pos = task.ee_pose()[0]
        closed = task.gripper_opening() < GRIPPED
        at_grasp = np.linalg.norm(pos - s["green_grasp_point"]) < AT_GRASP
        if self.holding(task):  # carrying the green cup
            over = self._target("carry", task)
            if np.linalg.norm(pos[:2] - over[:2]) < ALIGNED:  # over the red cup: go on lowering
                return self._index("lower")
            return self._index("carry")
        if at_grasp:  # at the grasp, not lifted yet: close (again) and give the fingers their time
            return self._index("close")
        if not closed and _over(pos, s["green_grasp_point"], self._approach_h):
            return self._index("descend")
        return 0


class OpenDrawerExpert(Expert):
    """Cross to the intended drawer's side at the height it starts from, reach its handle from above, grasp it,
    pull it open.

    The first phase moves only across the cabinet (along y), fast (``ACROSS_SPEED``): the choice of drawer is
    made in the first steps, and a few operator steps there leave the gripper where only demonstrations
    towards the intended drawer pass, so the policy, handed back, goes on to it."""

    name = "open-drawer-scripted"

    def plan(self, task: Task, rng: np.random.Generator) -> list[Phase]:
        approach_h = float(rng.uniform(0.05, 0.13))
        pull = float(rng.uniform(0.14, 0.17))
        via_h = float(rng.uniform(0.0, 0.08))
        across_speed = float(rng.uniform(*ACROSS_SPEED))
        mem: dict[str, np.ndarray] = {}
        drawer = task.privileged()["intended"]
        # The handle is a bar along x: fingers close across it, along world y (yaw 0).
        yaw = closest_yaw(gripper_yaw(task.ee_pose()[1]), 0.0, np.pi)

        def handle(t: Task) -> np.ndarray:
            return t.privileged()["handles"][drawer]

        def across(t: Task):  # along y only, no lower than the approach's height
            pos, h = t.ee_pose()[0], handle(t)
            return np.array([pos[0], h[1], max(pos[2], h[2] + approach_h + via_h)]), yaw

        def above(t: Task):
            return handle(t) + [0, 0, approach_h + via_h], yaw

        def near(t: Task):
            return handle(t) + [0, 0, approach_h], yaw

        def at(t: Task):
            return handle(t), yaw

        def pull_out(t: Task):
            p = mem.setdefault("grasp", t.ee_pose()[0])
            return p + t.privileged()["pull_axis"] * pull, yaw

        hold = lambda t: (t.ee_pose()[0], yaw)  # noqa: E731
        self._drawer, self._approach_h = drawer, approach_h
        return [
            # tolerances above the 1 cm execution noise of the demonstrations: tighter ones kept the expert
            # hovering at each waypoint for a random number of steps, and the policy learnt to hover there
            Phase("across", across, OPEN, tol=0.02, speed=across_speed),
            Phase("approach", above, OPEN, tol=0.02),
            Phase("align", near, OPEN, tol=0.015),
            Phase("descend", at, OPEN, tol=0.01, max_steps=60),
            Phase("close", hold, CLOSED, tol=np.inf, pause=int(rng.integers(6, 10))),
            Phase("pull", pull_out, CLOSED, tol=0.01, max_steps=120),
        ]

    def holding(self, task: Task) -> bool:
        """The gripper closed within 2 cm of the intended drawer's handle."""
        handle = np.asarray(task.privileged()["handles"])[self._drawer]
        return bool(task.gripper_opening() < GRIPPED and np.linalg.norm(task.ee_pose()[0] - handle) < AT_GRASP)

    def start_phase(self, task: Task) -> int:
        s = task.privileged()
        pos = task.ee_pose()[0]
        handle = np.asarray(s["handles"])[self._drawer]
        closed = task.gripper_opening() < GRIPPED
        if self.holding(task):  # holding the intended handle
            return self._index("pull")
        if not closed and np.linalg.norm(pos - handle) < AT_GRASP:  # at the handle, fingers still open
            return self._index("close")
        if not closed and _over(pos, handle, self._approach_h):
            return self._index("descend")
        return 0


def _over(pos: np.ndarray, target: np.ndarray, height: float) -> bool:
    """Within 1.5 cm of ``target`` horizontally and at most ``height`` + 1 cm above it."""
    pos, target = np.asarray(pos), np.asarray(target)
    return bool(np.linalg.norm(pos[:2] - target[:2]) < 0.015 and pos[2] - target[2] < height + 0.01)
