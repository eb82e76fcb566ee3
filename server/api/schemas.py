"""Request and response schemas of the API."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, ValidationInfo, field_validator

from policy.hitl_state import Mode
from server.db import NOTE_MAX
from sim.registry import TASKS
from sim.spaces import TeleopCommand

# TeleopCommand owns an operator's command bounds (per component; the robot clamps to 3 cm per step anyway)
MAX_DELTA_POS = TeleopCommand.MAX_DELTA_POS  # m per command and component; larger is rejected
MAX_DELTA_ROT = TeleopCommand.MAX_DELTA_ROT  # rad per command and component
GRIPPER_MIN, GRIPPER_MAX = TeleopCommand.GRIPPER_RANGE
# Id columns are INTEGER: 64-bit in SQLite but 32-bit in PostgreSQL; the API takes what both can store.
ID_MAX = 2**31 - 1

# Every id the API takes, in a path, a query or a body (robots, episodes, segments, policy versions):
# out of the database's range is a 422, never an overflow inside the database driver.
Id = Annotated[int, Field(ge=0, le=ID_MAX)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Quaternion = Annotated[list[float], Field(min_length=4, max_length=4, description="x, y, z, w")]
RobotMode = Literal[tuple(m.value for m in Mode)]  # the same enum in the schema as a plain string


class FieldError(BaseModel):
    """One part of a request that does not validate; its value is not echoed (NaN and infinities are
    not JSON)."""

    loc: list[str | int] = Field(..., description="where: path, query, header or body, then the field")
    msg: str
    type: str


class ErrorOut(BaseModel):
    """Every error answer of the API (4xx): a message, or for a request that does not validate, one
    entry per problem."""

    detail: str | list[FieldError]


class HealthOut(BaseModel):
    status: Literal["ok"]


class ReadyOut(BaseModel):
    ready: bool = Field(..., description="the control loop has ticked (HTTP 503 until then)")


def _not_a_bool(v):
    """JSON's true and false are not numbers (a JSON Schema ``number`` excludes them); pydantic would
    take them as 1 and 0."""
    if isinstance(v, bool):
        raise ValueError("must be a number, not true or false")
    return v


Real = Annotated[float, BeforeValidator(_not_a_bool)]


# Each component is bounded, as the schema says (``minimum``/``maximum`` on every item): a limit on the
# vector's norm cannot be written in JSON Schema, and a client generating from the schema would send
# commands it calls valid and the service refuses. The robot clamps further, per step (3 cm, 0.2 rad).
DeltaPos = Annotated[float, Field(ge=-MAX_DELTA_POS, le=MAX_DELTA_POS), BeforeValidator(_not_a_bool)]
DeltaRot = Annotated[float, Field(ge=-MAX_DELTA_ROT, le=MAX_DELTA_ROT), BeforeValidator(_not_a_bool)]


# The wire form of ``sim.spaces.TeleopCommand`` (its ``to_dict``), with its bounds stated per component in
# the schema; ``to_command`` converts it through ``TeleopCommand.from_dict``. (The class docstring is the
# schema's description.)
class TeleopCommandIn(BaseModel):
    """A delta end-effector pose (world frame) and a gripper command (-1 open .. +1 closed)."""

    model_config = ConfigDict(extra="forbid")
    delta_pos: list[DeltaPos] = Field(
        ..., min_length=3, max_length=3, description=f"metres, each component within ±{MAX_DELTA_POS}"
    )
    delta_rot: list[DeltaRot] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0],
        min_length=3,
        max_length=3,
        description=f"rotation vector, rad, each component within ±{MAX_DELTA_ROT}",
    )
    gripper: Real = Field(..., ge=GRIPPER_MIN, le=GRIPPER_MAX)

    @field_validator("delta_pos", "delta_rot", mode="before")
    @classmethod
    def _three(cls, v, info: ValidationInfo):
        # before pydantic's own checks, to keep the messages clients get
        if isinstance(v, list | tuple):
            if len(v) != 3:
                raise ValueError(f"{info.field_name} must have 3 components, got {len(v)}")
            if any(isinstance(x, float) and not math.isfinite(x) for x in v):
                raise ValueError(f"{info.field_name} has NaN or infinite values")
        return v

    @field_validator("gripper", mode="before")
    @classmethod
    def _gripper(cls, v):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError("gripper is NaN or infinite")
        return v

    def to_command(self) -> TeleopCommand:
        """The domain command (``TeleopCommand.from_dict``: the same checks, from the same bounds)."""
        return TeleopCommand.from_dict(self.model_dump())


class CommandAccepted(BaseModel):
    robot_id: int
    accepted: bool = True
    pending: int = Field(1, description="commands the next control tick applies, this one included")


class UncertaintyOut(BaseModel):
    """The paper's denoising metric at the robot's last scored step (not the asking signal's numbers:
    those are ``AskingOut``)."""

    U: float
    D: float
    var_g: float
    n: int
    threshold: float = Field(description="the paper's denoising threshold (the policy version's)")
    samples: list[Vec3]
    vectors: list[Vec3]
    labels: list[int]
    means: list[Vec3]
    weights: list[float]


class PoseOut(BaseModel):
    position: Vec3
    quaternion: Quaternion


class AskingOut(BaseModel):
    """Why the robot waits, or would ask: the asking signal's numbers. While the robot has an open
    request (waiting, under teleop, or paused from either) they are that request's, equal to its entry in
    ``GET /assistance`` (the score it asked with); otherwise the asking signal's latest."""

    signal: str | None = Field(
        description="the asking signal's name; 'watchdog' when the watchdog asked; null for help requested "
        "through the service (a drill, a benchmark)"
    )
    score: float | None = Field(
        description="the asking signal's score: the request's while one is open, else the latest (null: not scored yet)"
    )
    threshold: float | None = Field(description="the threshold the score is compared with (the request's)")
    wants_help: bool | None = Field(
        description="the asking signal's latest decision (null: not scored yet, or the watchdog or a requested "
        "help asked)"
    )
    reason: str | None = Field(
        description="while the robot has an open request: its reason, as the queue shows it; else null"
    )
    asked_at_step: int | None = Field(
        description="while the robot has an open request: the episode clock step at which it asked; else null"
    )


class PaperMetricOut(BaseModel):
    """The paper's denoising metric (U = D + α·Var_g), reported whatever signal asks."""

    U: float | None = Field(description="U at the robot's last scored step (null: not computed yet)")
    threshold: float = Field(description="the policy version's denoising threshold")


class RobotSummary(BaseModel):
    id: int
    task: str
    mode: RobotMode
    policy_version: int
    episode_id: int | None
    episode_step: int
    uncertainty: float | None = Field(
        deprecated=True,
        description="deprecated, removed in the next release: ``asking.score`` (the paper's U is ``paper.U``)",
    )
    threshold: float | None = Field(
        deprecated=True,
        description="deprecated, removed in the next release: ``asking.threshold`` (the paper's: ``paper.threshold``)",
    )
    asking: AskingOut
    paper: PaperMetricOut | None = Field(description="the paper's denoising metric; null: the version has none")


class RobotDetail(RobotSummary):
    pose: PoseOut | None
    gripper: float | None
    bodies: dict[str, PoseOut]
    u_history: list[float] = Field(description="the paper's U per scored step, oldest first (at most 300)")
    score_history: list[float] = Field(
        description="the asking signal's score per scored step, oldest first (at most 300), as ``u_history``"
    )
    last_uncertainty: UncertaintyOut | None
    episodes_done: int
    successes: int
    assisted_steps: int
    assistance_events: int
    restarts: int
    fault: str | None


class OperatorView(BaseModel):
    robot_id: int
    task: str
    mode: RobotMode
    pose: PoseOut | None
    gripper: float | None
    bodies: dict[str, PoseOut]
    goal: dict
    last_uncertainty: UncertaintyOut | None
    asking: AskingOut
    episode_seed: int | None = Field(None, description="the seed of the robot's current episode")
    step: int | None = Field(None, description="steps since the episode's reset, holds included (frame t)")
    clock: int | None = Field(None, description="steps that count against the horizon (holds do not)")
    horizon: int | None = Field(None, description="the episode's horizon, in clock steps")
    events: int = Field(0, description="assistance requests in the current episode")


class AssistanceRequestOut(BaseModel):
    """An open request, with the numbers it ranks by: the asking signal's, as the robot showed them when it
    asked (the robot's ``asking`` holds the same while it waits)."""

    id: int
    robot_id: int
    signal: str | None = Field(
        description="the signal that asked; 'watchdog' for the watchdog; null for help requested through the service"
    )
    score: float = Field(description="its score when the robot asked (1 for the watchdog and requested help)")
    uncertainty: float = Field(deprecated=True, description="deprecated, removed in the next release: ``score``")
    threshold: float = Field(description="the asking signal's threshold (1 for the watchdog and requested help)")
    reason: str = Field(description="why it asked: the signal's name and its words, or the watchdog's")
    waiting_s: float
    priority: float = Field(
        description="the queue's order, highest first: the urgency (1 - threshold / score for a score over a "
        "positive threshold, else 0; in [0, 1] whatever the signal's scale) plus waiting_s / 10"
    )
    holder: str | None
    lease_expires_in_s: float | None


class EpisodeOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    robot_id: int
    task: str
    seed: int
    policy_id: int | None
    outcome: str | None
    steps: int
    assisted_steps: int
    assistance_events: int
    started_at: datetime
    ended_at: datetime | None


class SegmentOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    robot_id: int
    episode_id: int | None
    task: str
    policy_id: int | None
    operator: str
    reason: str = Field(..., description="the reason of the request the takeover answered, as the queue showed it")
    signal: str | None = Field(
        None,
        description="the request's signal: the asking signal's name, 'watchdog', or null for help requested "
        "through the service and for takeovers recorded before it was stored",
    )
    score: float | None = Field(None, description="the request's score (null: recorded before it was stored)")
    threshold: float | None = Field(None, description="the request's threshold (null: recorded before it was stored)")
    paper_u: float | None = Field(
        None, description="the paper's denoising U when the robot asked (null: not computed, or not stored)"
    )
    status: str = Field(..., description="open, closed, or recovered (left open by a crash, rewritten at start)")
    ended_by: str | None = Field(
        None,
        description="why it ended: hand-back, lease-expired, episode-ended, worker-fault, reset, service-stopped, "
        "crash-recovered",
    )
    steps: int
    started_at: datetime
    ended_at: datetime | None
    label: Literal["good", "bad"] | None = Field(None, description="the operator's verdict on the takeover")
    discarded: bool = Field(False, description="kept on disk, never trained on")
    note: str | None = None
    labelled_by: str | None = Field(None, description="who last changed the label, discard flag or note")
    labelled_at: datetime | None = None


class SegmentLabelIn(BaseModel):
    """What to change about a takeover's label; fields left out stay as they are (``label: null`` removes
    the verdict, an empty ``note`` the note)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"minProperties": 1})
    label: Literal["good", "bad"] | None = Field(None, description="good or bad; null removes it")
    discarded: StrictBool = Field(False, description="true: never train on it (the file is kept)")
    note: str = Field(
        "", max_length=NOTE_MAX, pattern=r"^[^\x00]*$", description="a short note (no NUL); empty removes it"
    )


PolicyName = Annotated[str, Field(min_length=1, max_length=256, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,255}$")]
PolicyRefText = Annotated[
    str,
    Field(
        min_length=1,
        max_length=266,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,255}(@(active|[1-9][0-9]{0,8}))?$",  # registry.PolicyRef's
        description="NAME, NAME@active or NAME@VERSION",
    ),
]


class PolicyOut(BaseModel):
    """One version of a policy lineage (``ref`` = ``name@version``)."""

    model_config = ConfigDict(from_attributes=True)
    id: int
    name: str
    version: int
    ref: str
    path: str
    task: str
    paper_threshold: float | None = Field(None, description="the paper's denoising threshold (its calibration)")
    threshold: float | None = Field(
        deprecated=True, description="deprecated, removed in the next release: ``paper_threshold``"
    )
    asking_signal: str | None = Field(
        None, description="the signal that asks for help for the robots running it (null: no robot runs it now)"
    )
    asking_threshold: float | None = Field(None, description="that signal's threshold (null: no robot runs it now)")
    status: Literal["candidate", "active", "retired"]
    status_reason: str | None = Field(None, description="why: the promotion gate's decision, a promote, a rollback")
    parent_id: int | None
    created_at: datetime
    command: str | None = Field(None, description="the command that produced it")
    manifest: dict = Field(default_factory=dict, description="pretraining episodes and takeover segments it used")
    calibration: dict = Field(default_factory=dict, description="its threshold and calibration set")
    evaluation: dict = Field(default_factory=dict, description="autonomous success per task (episodes, seed)")
    robots: list[int] = Field(default_factory=list, description="robots running this version now")


class PromoteIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ref: str = Field(
        ...,
        max_length=266,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,255}@[1-9][0-9]{0,8}$",
        description="NAME@VERSION: the version to promote",
    )
    reason: str | None = Field(None, max_length=512)


class RollbackIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: PolicyName
    reason: str | None = Field(None, max_length=512)


class FinetuneJobIn(BaseModel):
    """Starts ``hitl finetune`` in a separate, low-priority process."""

    model_config = ConfigDict(extra="forbid")
    policy: PolicyRefText
    since: str | None = Field(
        None,
        max_length=16,
        # a positive duration of at most 999999 units: what ``parse_since`` accepts, nothing it refuses
        pattern=r"^\s*(0*[1-9][0-9]{0,5}(\.[0-9]{1,6})?|0+\.[0-9]{0,5}[1-9][0-9]{0,5})\s*[smhdw]\s*$",
        description="e.g. 24h, 7d: only recent segments",
    )


class FinetuneScheduleOut(BaseModel):
    """The nightly job's schedule in this service, and the job processes it started."""

    schedule: str | None = Field(description="the cron expression; null: never scheduled")
    next_run: datetime | None = Field(description="when the schedule next starts a job (the service's clock)")
    clock: Literal["system", "file"] = Field(description="file: a benchmark's clock (`[finetune] clock_file`)")
    running: bool = Field(description="a job process started by this service is running")
    launches: int = Field(description="job processes started by this service (schedule and API)")
    last_exit_code: int | None = Field(description="exit code of the last one that ended (0: every job succeeded)")


class FinetuneJobOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    lineage: str
    status: Literal["queued", "running", "succeeded", "failed", "interrupted"]
    stage: str | None
    progress: float
    source: str
    trigger: str
    parent_id: int | None
    version_id: int | None = Field(None, description="the version it produced")
    since: datetime | None
    data: dict = Field(
        default_factory=dict,
        description="counts, tasks, skipped segments and the ones the selection left out, with their reason",
    )
    evaluation: dict = Field(default_factory=dict, description="parent and candidate success per task")
    gate: dict = Field(default_factory=dict, description="the promotion gate's decision and its evidence")
    error: str | None
    command: str | None
    created_at: datetime
    started_at: datetime | None
    ended_at: datetime | None


# the registered tasks (``sim.registry``), so that the schema names every task the service accepts
TaskName = Literal[tuple(TASKS)]


class PolicyIn(BaseModel):
    """A policy folder (``model.safetensors`` + ``config.json``) on the server's disk."""

    model_config = ConfigDict(extra="forbid")
    path: str = Field(..., min_length=1, max_length=1024, pattern=r"^[^\x00]+$", description="no NUL characters")
    task: TaskName | None = Field(None, description="default: the task in the folder's config.json")
    parent_id: Id | None = None


class FleetMetrics(BaseModel):
    episodes: int
    success_rate: float | None
    assisted_steps_per_episode: float | None
    assistance_events_per_episode: float | None
    queue_wait_p50_s: float | None
    queue_wait_p95_s: float | None
    queue_wait_max_s: float | None = Field(description="the longest wait from a request to its claim so far")
    queue_oldest_unclaimed_s: float | None = Field(
        description="how long the oldest request not claimed now has waited: a robot left unserved shows here"
    )
    operator_busy_s: dict[str, float]
    operator_idle_s: dict[str, float]  # since the operator's first claim, not in control
    return_on_human_effort: float | None
    robots_by_mode: dict[str, int]
    ticks: int
