"""Service settings: one pydantic-settings ``Settings``, a typed section per concern, from a TOML file
and/or ``HITL_*`` variables.

Sections: ``[controller]`` (the asking signal and the hand-back rule, ``ControllerSettings``), ``[queue]``,
``[cameras]``, ``[recording]``, ``[workers]``, ``[ray]``, ``[inference]``, ``[finetune]``; the service's
own keys (address, database, robots, rate) stay at the top. Each bound is declared once, on its field.
Environment variables win over the file, a section's with ``__`` (``HITL_PORT=9000``,
``HITL_CONTROLLER__BUDGET=8``); ``DATABASE_URL`` (or ``HITL_DATABASE_URL``) selects the database, default
SQLite in WAL mode under ``data_dir``. A name a setting had before (``REMOVED``), from a file, a variable
or a keyword, is refused with its name now.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from policy.hand_back import ControllerConfig

BUNDLED = Path(__file__).resolve().parents[1] / "policies"
ENV_PREFIX = "HITL_"
ENV_NESTED = "__"
# a setting's name before -> its name now ("section.key"); the old one is refused, naming the new one
REMOVED: dict[str, str] = {
    "trigger_mode": "controller.hand_back",
    "budget_steps": "controller.budget",
    "auto_return_steps": "controller.return_after",
    "cooldown_steps": "controller.cooldown",
    **{name: f"controller.{name}" for name in ("signal", "shadow_signals", *ControllerConfig.model_fields)},
    "lease_seconds": "queue.lease_seconds",
    "queue_order": "queue.order",
    "cameras": "cameras.enabled",
    "camera_hz": "cameras.hz",
    "camera_gl": "cameras.gl",
    "camera_width": "cameras.width",
    "camera_height": "cameras.height",
    "record_episodes": "recording.episodes",
    "segment_flush_seconds": "recording.flush_seconds",
    "segment_fsync": "recording.fsync",
    "worker": "workers.kind",
    "robots_per_process": "workers.robots_per_process",
    "worker_niceness": "workers.niceness",
    "freeze_idle": "workers.freeze_idle",
    "ray_address": "ray.address",
    "ray_namespace": "ray.namespace",
    "ray_cpus_per_actor": "ray.cpus_per_actor",
    "inference": "inference.backend",
    "inference_gpus": "inference.gpus",
    "inference_cpus": "inference.cpus",
    "device": "inference.device",
    "torch_threads": "inference.torch_threads",
    "trace_policies": "inference.trace_policies",
}
# old names that are a section's name now: refused only where they hold a value, not a section
_SECTION_NAMES = {"cameras", "inference"}
_SECTION = ConfigDict(extra="forbid")  # a section's keys are its fields, no others


def bundled_policy(task: str) -> Path:
    """The bundled checkpoint for a task: lift tasks share the lift-cube policy."""
    return BUNDLED / ("lift-cube" if task.startswith("lift") else task)


class RobotGroup(BaseModel):
    """``count`` simulated robots on ``task`` driven by the policy folder ``policy`` (default: bundled)."""

    task: str
    count: int = Field(1, ge=1, le=64)
    policy: Path | None = None

    @property
    def policy_dir(self) -> Path:
        return self.policy if self.policy is not None else bundled_policy(self.task)

    @field_validator("task")
    @classmethod
    def _known_task(cls, v: str) -> str:
        from sim.registry import TASKS

        if v not in TASKS:
            raise ValueError(f"unknown task {v!r}; registered tasks: {', '.join(TASKS)}")
        return v


class TakeoverChoice(BaseModel):
    """Which takeovers one lineage's job learns from (``[finetune.selection.<lineage>]``); it wins over
    the service-wide ``successful_only`` and ``takeover_tail``."""

    model_config = {"extra": "forbid"}

    successful_only: bool = Field(False, description="learn only from takeovers in episodes that ended in success")
    takeover_tail: int | None = Field(
        None, ge=1, description="learn from the last N steps of each takeover, those that led to the hand-back"
    )


class FinetuneSettings(BaseModel):
    """The fine-tuning job inside ``hitl serve`` (``[finetune]`` in the TOML file)."""

    model_config = {"extra": "forbid"}

    schedule: str | None = Field(
        "0 3 * * *",
        description="cron expression (server local time) for the nightly job; empty or null: never scheduled",
    )
    niceness: int = Field(19, ge=0, le=19, description="CPU priority of the job's process below the fleet (os.nice)")
    idle_priority: bool = Field(
        True, description="also run the job under Linux SCHED_IDLE: only on CPU time the fleet leaves unused"
    )
    promote: bool = Field(True, description="promote a version that passes the gate (false: leave it a candidate)")
    eval_episodes: int = Field(20, ge=1, le=1000, description="seeded autonomous episodes per evaluation task")
    tolerance: float = Field(0.05, ge=0, lt=1, description="the gate: allowed success drop on the training task")
    min_gain: float = Field(0.0, ge=0, lt=1, description="the gate: required success rise on the target tasks")
    widen_obs_range: bool = Field(
        True, description="widen the new version's observation range to cover its takeover data (false: the parent's)"
    )
    successful_only: bool = Field(False, description="learn only from takeovers in episodes that ended in success")
    takeover_tail: int | None = Field(
        None, ge=1, description="learn from the last N steps of each takeover, those that led to the hand-back"
    )
    selection: dict[str, TakeoverChoice] = Field(
        default_factory=dict,
        description="lineage -> which takeovers its job learns from (default: successful_only and takeover_tail)",
    )
    eval_tasks: dict[str, list[str]] = Field(
        default_factory=dict,
        description="lineage -> the target tasks the gate compares on (default: the tasks its takeovers came from)",
    )
    eval_seed: int = Field(
        50_000,
        ge=0,
        description="first seed of the gate's evaluation episodes: seeds the fleet never runs (robot r runs "
        "seed + 1000 r + k), so the gate is never judged on an episode it trained on",
    )
    fit_episodes: int = Field(
        20,
        ge=1,
        le=1000,
        description="the new version's own autonomous episodes per task on which its asking signal's thresholds are "
        "fitted (policy.finetune.fit_threshold_on_own_episodes)",
    )
    fit_seed: int = Field(
        60_000, ge=0, description="first seed of those episodes: apart from the gate's and from the fleet's"
    )
    steps: int | None = Field(
        None, ge=1, description="fixed training steps (default: grown with the takeover data, FinetuneConfig.steps_for)"
    )
    lease_seconds: float = Field(
        60.0, gt=0, le=3600, description="the job's lease: a job killed outright frees it after this long"
    )
    clock_file: Path | None = Field(
        None,
        description="benchmarks and tests only: the schedule reads the time from this file (ISO 8601) instead "
        "of the system clock, so a benchmark moves the night forward (`hitl bench nights`)",
    )
    threads: int = Field(
        1, ge=1, le=256, description="torch threads of the job, and its processes recording missing pretraining data"
    )

    @field_validator("schedule")
    @classmethod
    def _cron(cls, v: str | None) -> str | None:
        if v is None or not v.strip():
            return None
        from server.finetune.scheduler import parse_cron

        parse_cron(v)
        return v.strip()

    @field_validator("clock_file")
    @classmethod
    def _clock(cls, v: Path | None) -> Path | None:
        if v is not None:
            from server.finetune.scheduler import FileClock

            FileClock(v)  # readable, and holds a time
        return v

    @field_validator("eval_tasks")
    @classmethod
    def _tasks(cls, v: dict[str, list[str]]) -> dict[str, list[str]]:
        for tasks in v.values():
            for task in tasks:
                RobotGroup._known_task(task)
        return v


class ControllerSettings(ControllerConfig):
    """``[controller]``: the asking signal, the signals scored beside it, and the controller's own settings
    (``policy.hand_back.ControllerConfig``, whose fields and bounds these are)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    signal: str = Field(
        "choice-stall",
        description="the assistance signal that asks for help (docs/signals.md; 'denoising': the paper's)",
    )
    shadow_signals: list[str] = Field(default_factory=list, description="signals scored alongside, recorded")

    @field_validator("signal")
    @classmethod
    def _known_signal(cls, v: str) -> str:
        from policy.signals import SIGNALS

        if v not in SIGNALS:
            raise ValueError(f"unknown signal {v!r}; registered signals: {', '.join(SIGNALS)}")
        return v

    @field_validator("shadow_signals")
    @classmethod
    def _known_shadows(cls, v: list[str]) -> list[str]:
        for name in v:
            cls._known_signal(name)
        return v

    def config(self) -> ControllerConfig:
        """The controller's part of these settings."""
        return ControllerConfig(**self.model_dump(include=set(ControllerConfig.model_fields)))


class QueueSettings(BaseModel):
    """``[queue]``: the assistance queue and its leases (``server/fleet/assistance.py``)."""

    model_config = _SECTION

    lease_seconds: float = Field(10.0, gt=0, le=3600, description="an operator's claim lapses after this long idle")
    order: Literal["priority", "cur", "fcfs"] = Field(
        "priority",
        description="how requests are ranked: 'priority' (urgency plus wait, no robot starves), 'cur' "
        "(Fleet-DAgger's: stalled robots, then urgency), 'fcfs' (first come, first served)",
    )


class CameraSettings(BaseModel):
    """``[cameras]``: the console's camera views (``server/cameras.py``)."""

    model_config = _SECTION

    enabled: bool = Field(True, description="render the camera views of robots someone watches")
    hz: float = Field(2.0, gt=0, le=30, description="camera views per second of each watched robot")
    gl: Literal["osmesa", "egl"] = Field(
        "osmesa", description="the renderer's OpenGL: osmesa (software, any machine) or egl (a GPU)"
    )
    width: int = Field(160, ge=16, le=1280)
    height: int = Field(120, ge=16, le=960)


class RecordingSettings(BaseModel):
    """``[recording]``: what reaches the disk, and how often (docs/service.md, 'Durability')."""

    model_config = _SECTION

    episodes: bool = Field(False, description="record every episode, not only takeover segments")
    flush_seconds: float = Field(
        0.0,
        ge=0,
        le=60,
        description="a takeover's steps reach the operating system at least this often; 0: each step before the "
        "next tick, so a killed server loses none",
    )
    fsync: bool = Field(False, description="each flush also reaches the disk: a power loss loses no flushed step")


class WorkerSettings(BaseModel):
    """``[workers]``: where the robots' physics runs."""

    model_config = _SECTION

    kind: Literal["process", "pool", "in-process", "ray"] = Field(
        "process",
        description="a process per robot, robots_per_process robots per process (pool) or per Ray actor "
        "(ray: pip install '.[ray]'), or tasks stepped in the control thread",
    )
    robots_per_process: int = Field(8, ge=1, le=256, description="pool and ray: robots sharing one process (actor)")
    niceness: int = Field(10, ge=0, le=19, description="CPU priority of the workers below the control loop (os.nice)")
    freeze_idle: bool = Field(
        False,
        description="simulated robots only: a robot waiting for its operator, or under teleop without a new "
        "command, is not stepped at all, so results do not depend on operator latency",
    )

    @field_validator("kind")
    @classmethod
    def _ray(cls, v: str) -> str:
        return _ray_installed(v, "workers.kind")


class RaySettings(BaseModel):
    """``[ray]``: the Ray cluster the ``ray`` workers and inference join."""

    model_config = _SECTION

    address: str | None = Field(
        None, description="the cluster to join (host:port or ray://host:port); unset: a local instance"
    )
    namespace: str = Field("hitl", min_length=1, max_length=64, description="Ray namespace of this fleet's actors")
    cpus_per_actor: float = Field(1.0, gt=0, le=64, description="the CPU share each robot actor reserves")


class InferenceSettings(BaseModel):
    """``[inference]``: where and how the policies' networks run."""

    model_config = _SECTION

    backend: Literal["local", "ray"] = Field(
        "local",
        description="each policy version's batched calls run in the control loop's process, or in a Ray actor "
        "per version (pip install '.[ray]'; docs/architecture.md)",
    )
    device: str = Field("cpu", pattern=r"^(cpu|cuda(:\d+)?)$", description="cpu, cuda or cuda:N")
    torch_threads: int = Field(1, ge=1, le=256, description="the control loop's torch threads")
    trace_policies: bool = Field(True, description="serve each noise network as a frozen TorchScript trace")
    gpus: float = Field(0.0, ge=0, le=8, description="backend 'ray': GPUs each actor reserves (> 0: on cuda)")
    cpus: float = Field(1.0, ge=0, le=64, description="backend 'ray': CPUs each actor reserves")

    @field_validator("backend")
    @classmethod
    def _ray(cls, v: str) -> str:
        return _ray_installed(v, "inference.backend")


def _ray_installed(v: str, name: str) -> str:
    from server.ray_cluster import RayUnavailable, ray_available

    if v == "ray" and not ray_available():
        raise ValueError(str(RayUnavailable(f"{name} = 'ray' needs Ray, an optional extra: pip install '.[ray]'")))
    return v


class Settings(BaseSettings):
    # a variable set to "none" unsets an optional setting the file sets (`--set controller.return_after=none`)
    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED,
        extra="forbid",
        populate_by_name=True,
        env_parse_none_str="none",
    )

    data_dir: Path = Path("var")
    database_url: str | None = Field(None, validation_alias=AliasChoices("HITL_DATABASE_URL", "DATABASE_URL"))
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    control_hz: float = Field(10.0, ge=0, le=200, description="0: free-running (benchmarks)")
    robots: list[RobotGroup] = Field(default_factory=lambda: [RobotGroup(task="lift-cube", count=1)])
    seed: int = Field(0, description="robot r's episodes run seeds seed + 1000 r + k; also the sampling noise's")
    api_workers: int = Field(
        0,
        ge=0,
        le=64,
        description="0: the API and the console run in the fleet runtime's process; N: in N processes of their own, "
        "which reach the runtime through a local socket and share the database (docs/architecture.md)",
    )
    console: bool = Field(
        True,
        description="serve the operator console at /console/ (its viser server listens on an internal "
        "127.0.0.1 port that any local process can reach: docs/console.md)",
    )
    max_body_bytes: int = Field(64 * 1024, ge=1024)
    policy_poll_seconds: float = Field(
        2.0, gt=0, le=3600, description="how often the fleet checks the registry for a newly active policy version"
    )
    controller: ControllerSettings = Field(default_factory=ControllerSettings)
    queue: QueueSettings = Field(default_factory=QueueSettings)
    cameras: CameraSettings = Field(default_factory=CameraSettings)
    recording: RecordingSettings = Field(default_factory=RecordingSettings)
    workers: WorkerSettings = Field(default_factory=WorkerSettings)
    ray: RaySettings = Field(default_factory=RaySettings)
    inference: InferenceSettings = Field(default_factory=InferenceSettings)
    finetune: FinetuneSettings = Field(default_factory=FinetuneSettings)

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            refuse_removed(data)
        return data

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return init_settings, RemovedEnv(settings_cls), env_settings, dotenv_settings, file_secret_settings

    @model_validator(mode="after")
    def _robots_present(self) -> Settings:
        if not self.robots:
            raise ValueError("robots: the fleet needs at least one robot group")
        folders: dict[str, Path] = {}
        for group in self.robots:
            path = group.policy_dir.resolve()
            other = folders.setdefault(path.name, path)
            if other != path:  # registered as one lineage, whose active version would drive both groups
                raise ValueError(
                    f"robots: two policy folders named {path.name!r} ({other} and {path}): a policy's lineage "
                    "is named after its folder, so they would be one lineage; rename one of the folders"
                )
        return self

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'hitl.db').resolve()}"

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides) -> Settings:
        """Settings from ``path`` (TOML) with environment variables and ``overrides`` on top, section by
        section (``overrides``' sections are dicts: ``controller={"budget": 8}``)."""
        values: dict = {}
        if path is not None:
            path = Path(path)
            if not path.is_file():
                raise FileNotFoundError(f"config file {path} not found")
            try:
                values = tomllib.loads(path.read_text())
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{path}: invalid TOML: {exc}") from exc
            refuse_removed(values, f" in {path}")
        refuse_removed(overrides, " in the overrides")
        env = cls().model_dump(exclude_unset=True)  # environment only: what the environment sets
        return cls(**_merged(_merged(values, env), overrides))


def _merged(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``top`` on top, section by section."""
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


class RemovedEnv(PydanticBaseSettingsSource):
    """Refuses ``HITL_<OLD>`` variables of the removed names (``REMOVED``), naming the new variable:
    pydantic-settings reads variables for declared fields only, so they would be ignored without a word."""

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        env = {k.upper(): v for k, v in os.environ.items()}  # pydantic-settings reads them case-insensitively
        for old, new in REMOVED.items():
            value = env.get(f"{ENV_PREFIX}{old.upper()}")
            if value is not None and not (old in _SECTION_NAMES and value.lstrip().startswith("{")):
                raise ValueError(_removed(env_name(old), env_name(new), " in the environment"))
        return {}


def env_name(key: str) -> str:
    """The variable of a setting (``controller.budget`` -> ``HITL_CONTROLLER__BUDGET``)."""
    return ENV_PREFIX + key.replace(".", ENV_NESTED).upper()


def refuse_removed(values: Mapping[str, Any], where: str = "") -> None:
    """ValueError naming the new name of the first removed name (``REMOVED``) among ``values``' keys."""
    for old, new in REMOVED.items():
        if old in values and not (old in _SECTION_NAMES and isinstance(values[old], Mapping)):
            raise ValueError(_removed(old, new, where))


def _removed(old: str, new: str, where: str = "") -> str:
    return f"setting {old!r}{where} was renamed: use {new!r}"
