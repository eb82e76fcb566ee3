"""The controller's settings: the hand-back rule, the watchdog and how the networks run, one typed model.

``ControllerConfig`` is the one place each of these settings is named, described and bounds-checked:
``policy.controller.Controller`` runs it, the service's ``[controller]`` settings
(``server.settings.ControllerSettings``) extend it with the signals, and the assisted rollouts
(``lab.assisted.AssistConfig``) build it. A module of its own, importing no torch, so that reading the
service's settings loads none.
"""

from __future__ import annotations

from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

HandBack = Literal["budgeted", "continuous"]
# what the policy sees first after a hand-back. ``restart``: a fresh observation history, filled with the
# current frame; ``history``: the history as the takeover left it, so a policy that sees several frames sees
# the operator's motion (a policy with an observation history of 1 sees the same)
Resume = Literal["restart", "history"]
HAND_BACK: tuple[str, ...] = get_args(HandBack)
RESUME: tuple[str, ...] = get_args(Resume)


class ControllerConfig(BaseModel):
    """How the controller hands control back and forth (``policy.controller``'s docstring has the rule)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    hand_back: HandBack = Field(
        "budgeted",
        description="'budgeted': control returns after `budget` operator steps per request; 'continuous': the "
        "operator keeps it until they hand back (or `return_after`)",
    )
    budget: int = Field(4, ge=1, le=1000, description="operator steps per assistance request (budgeted)")
    return_after: int | None = Field(
        None, ge=1, description="also hand back after K operator steps on which the signal no longer wants help"
    )
    cooldown: int = Field(
        10,
        ge=0,
        le=100_000,
        description="after a hand-back, policy steps on which the robot does not ask again (urgent requests "
        "excepted: the policy's next step would undo the takeover)",
    )
    resume: Resume = Field(
        "restart",
        description="after a hand-back, the policy's observation history restarts from the current frame ('restart') "
        "or keeps the takeover's frames ('history')",
    )
    watchdog: float | None = Field(
        None,
        gt=0,
        lt=1,  # at the whole horizon the episode is over before the robot could ask
        description="a robot that has used this fraction of its episode's horizon without success asks for help "
        "once, whatever its signal says (unset: only the signal asks)",
    )
    assistance: bool = Field(
        True, description="false: signals are scored and recorded, but no robot asks for help (shadow runs)"
    )
    batch_invariant: bool = Field(
        False, description="run the policy robot by robot: a robot's numbers do not depend on its batch (slower)"
    )
