"""The console's side panel, as text and plot data built from one tick's ``FleetSnapshot``.

Pure functions (no viser): the fleet overview, the queue rows, a robot's numbers and goal, and its
timeline for uPlot. ``web.console`` puts them on screen and sends only what changed. The asking
signal's numbers are those the API shows (``server.api.robots.asking``): a robot with an open request
shows the request's, the queue's own; the paper's denoising U is shown beside them, labelled as such.
"""

from __future__ import annotations

import html
import math
import time
from dataclasses import dataclass, field

import numpy as np

from policy.hitl_state import Mode
from policy.signals.base import SignalError
from server.fleet.assistance import AssistanceRequest
from server.fleet.robot import RobotView
from server.registry import LineageSummary
from sim.env import Task

MODE_BADGES = {  # plain glyphs only: the console's font has no emoji
    Mode.AUTONOMOUS: "autonomous",
    Mode.WAITING: "**⚠ waiting**",
    Mode.TELEOP: "**teleop**",
    Mode.PAUSED: "paused",
    Mode.DONE: "episode done",
    Mode.FAULTED: "**⚠ faulted**",
}
KEY_MAP = (
    ("I / K", "+x / −x (away from / towards the robot base)"),
    ("J / L", "+y / −y"),
    ("U / O", "+z / −z"),
    ("N / M", "yaw + / −"),
    ("G", "gripper open ↔ close"),
    ("F", "look at the gripper"),
    ("T", "follow the queue: take the robot it puts first"),
    ("C", "claim the robot on view"),
    ("R", "hand back"),
)
KEY_NOTE = "W/A/S/D/Q/E and the arrow keys move the camera."


def plain(text: str) -> str:
    """A name (a token's, set by an admin) as text: viser renders a markdown's raw HTML unsanitized."""
    return html.escape(text, quote=False)


@dataclass(frozen=True)
class FleetSnapshot:
    """One tick's view of the fleet, shared by every browser: robots by id, the queue as the service
    sorts it, and when (monotonic seconds, taken before the reads)."""

    robots: dict[int, RobotView]
    queue: tuple[AssistanceRequest, ...]
    now: float = field(default_factory=time.monotonic)
    lineages: tuple[LineageSummary, ...] = ()

    def request(self, robot_id: int) -> AssistanceRequest | None:
        return next((r for r in self.queue if r.robot_id == robot_id), None)


def asking_threshold(view: RobotView) -> tuple[str, float | None]:
    """The asking signal's name and threshold (None when it is not calibrated)."""
    name = view.slot.asking
    try:
        return name, float(view.slot.controller.signals[name].threshold)
    except (KeyError, SignalError):
        return name, None


def asking_numbers(view: RobotView) -> tuple[str, float | None, float | None]:
    """The signal, score and threshold shown for the robot: its open request's (``RobotView.ask``: the
    queue's numbers, "watchdog" or "requested" for help asked without a signal) while it has one, else
    the asking signal's latest score and its threshold."""
    if (ask := view.ask) is not None:
        return ask.signal or "requested", ask.score, ask.threshold
    name, threshold = asking_threshold(view)
    return name, view.scores.get(name), threshold


def _num(x: float | None, digits: int = 3) -> str:
    """Compact: 3 significant digits, whole numbers from 1000 on (no exponent in a narrow table)."""
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.0f}" if abs(x) >= 10**digits else f"{x:.{digits}g}"


def _cell(text: str, most: int = 60) -> str:
    """Text for a markdown table cell: escaped, pipes kept out of the table's syntax, cut at ``most`` (the fleet
    table sits in the side panel: a longer reason wraps its row tall; the robot's own panel shows it whole)."""
    text = text if len(text) <= most else text[: most - 1] + "…"
    return plain(text).replace("|", "\\|").replace("\n", " ")


def why_waits(view: RobotView, req: AssistanceRequest | None) -> str:
    """Why the robot is not working alone now: its open request's reason (the queue's words), its fault, or
    that it is paused; empty while it works alone."""
    if view.mode == Mode.FAULTED:
        return f"fault: {view.fault or 'its worker stopped'}"
    if req is not None:
        return req.reason
    if view.mode == Mode.PAUSED:
        return "paused by an admin"
    return ""


def overview_markdown(snapshot: FleetSnapshot, me: str) -> str:
    """Every robot at a glance, in two tables so that each fits the side panel: first its task, mode, how
    its episode goes (step of its horizon) and why it waits; then the asking signal's score against its
    threshold (the request's while it has one), the paper's U against its threshold, outcomes, policy."""
    glance = ["| Robot | Task | Mode | Episode step | Why it waits |", "|---|---|---|---|---|"]
    lines = [
        "| Robot | Asking: score / threshold | Paper's U / threshold | Successes | Assists | Policy |",
        "|---|---|---|---|---|---|",
    ]
    for rid, v in sorted(snapshot.robots.items()):
        name, score, threshold = asking_numbers(v)
        flag = " ⚠" if score is not None and threshold is not None and score > threshold else ""
        u = v.u_history[-1] if v.u_history else None
        req = snapshot.request(rid)
        mode = MODE_BADGES.get(v.mode, v.mode)
        if req is not None and req.holder:
            mode += f" ({'you' if req.holder == me else plain(req.holder)})"
        episode = f"{v.frame.clock} / {v.frame.horizon}" if v.frame is not None else "–"
        glance.append(f"| {rid} | {v.task} | {mode} | {episode} | {_cell(why_waits(v, req))} |")
        lines.append(
            f"| {rid} | {name}: {_num(score)} / {_num(threshold)}{flag} "
            f"| {_num(u)} / {_num(v.slot.threshold)} "
            f"| {v.successes} / {v.episodes_done} | {v.events} ({v.assisted_steps} steps) | v{v.slot.version} |"
        )
    return "\n".join(glance) + "\n\n" + "\n".join(lines)


def queue_head(requests: list[AssistanceRequest] | tuple[AssistanceRequest, ...], me: str) -> tuple[int | None, str]:
    """What "follow the queue" takes: the robot the queue puts first that this operator may claim (free, or
    already theirs), and a line saying so; None and why when there is none (the queue sorts held requests
    last, so a first request held by someone else means every request is held)."""
    if not requests:
        return None, "The queue is empty: no robot waits for help."
    first = requests[0]
    if first.holder is not None and first.holder != me:
        return None, (
            f"Robot {first.robot_id}, first in the queue, is held by {plain(first.holder)}"
            + (f", and so are the other {len(requests) - 1}." if len(requests) > 1 else ".")
        )
    return first.robot_id, f"Robot {first.robot_id} is first in the queue: {first.reason}"


def lineage_markdown(lineages: tuple[LineageSummary, ...]) -> str:
    """Each policy lineage: the active version, its parent and why it is active, and the last
    fine-tuning job (its stage while it runs, the gate's decision once done)."""
    if not lineages:
        return ""
    lines = ["| Policy | Active | From | Last fine-tuning job |", "|---|---|---|---|"]
    for ln in lineages:
        if ln.job_id is None:
            job = "none yet"
        elif ln.job_status in ("queued", "running"):
            job = f"#{ln.job_id} {ln.job_status}" + (f" · {ln.job_stage} {ln.job_progress:.0%}" if ln.job_stage else "")
        elif ln.job_status == "succeeded":
            verdict = "promoted" if ln.job_promoted else "kept as candidate"
            job = f"#{ln.job_id} {verdict} ({ln.job_ended}): {ln.job_gate or ''}"
        else:
            job = f"#{ln.job_id} {ln.job_status}" + (f": {ln.job_error}" if ln.job_error else "")
        extra = f" · {ln.candidates} candidate(s)" if ln.candidates else ""
        lines.append(
            f"| {ln.name} | {ln.active or '–'}{extra} | {ln.parent or '–'} · {ln.reason or ''} | {job[:160]} |"
        )
    for ln in lineages:
        lines += ["", *lineage_history_markdown(ln)]
    return "\n".join(lines)


def _rate(x: float | None, fmt: str = "{:.0%}") -> str:
    return "–" if x is None else fmt.format(x)


def lineage_history_markdown(ln: LineageSummary) -> list[str]:
    """A lineage's versions (status, why: the gate's decision, the help their episodes took) and its
    effort per day: whether the fleet needs less help after each night."""
    lines = [
        f"**{ln.name}: versions**",
        "",
        "| Version | Status | Why | Episodes | Alone | Steps helped / ep. | Requests / ep. |",
        "|---|---|---|---|---|---|---|",
    ]
    for v in ln.history:
        e = v.effort
        lines.append(
            f"| {v.ref} | {v.status} | {(v.reason or '–')[:120]} | {e.episodes} | {_rate(e.autonomous_rate)} | "
            f"{_rate(e.assisted_steps_per_episode, '{:.1f}')} | {_rate(e.requests_per_episode, '{:.1f}')} |"
        )
    if ln.days:
        lines += [
            "",
            f"**{ln.name}: help per day** (UTC)",
            "",
            "| Day | Episodes | Alone | Steps helped / ep. | Requests / ep. |",
            "|---|---|---|---|---|",
        ]
        for day, e in ln.days:
            lines.append(
                f"| {day} | {e.episodes} | {_rate(e.autonomous_rate)} | {_rate(e.assisted_steps_per_episode, '{:.1f}')}"
                f" | {_rate(e.requests_per_episode, '{:.1f}')} |"
            )
    return lines


def queue_row(req: AssistanceRequest, view: RobotView | None, now: float, me: str) -> str:
    task = view.task if view is not None else "?"
    held = f" · held by **{'you' if req.holder == me else plain(req.holder)}**" if req.holder else ""
    return f"**Robot {req.robot_id}** · {task} · waiting {now - req.created:.0f} s{held}  \n{req.reason}"


def robot_markdown(view: RobotView, req: AssistanceRequest | None, now: float, me: str, task: Task) -> str:
    """Mode and lease, which signal asked and why (its score against its threshold: the request's while
    the robot has one), the paper's n, D, Var_g and U against its threshold, the goal (``task.goal`` of
    the frame's scene: the task the robot runs, as ``make_task`` builds it)."""
    frame = view.frame
    name, score, threshold = asking_numbers(view)
    asked = f"asked at step {view.ask.asked_at_step}" if view.ask is not None else "asks"
    head = f"### Robot {view.id} · {view.task} · {MODE_BADGES.get(view.mode, view.mode)}"
    lines = [head]
    if req is not None:
        lease = ""
        if req.holder:
            left = max(0.0, (req.lease_until or now) - now)
            lease = f" · held by **{'you' if req.holder == me else plain(req.holder)}** (lease {left:.0f} s)"
        lines.append(f"**Asked:** {req.reason}{lease}")
    if view.mode == Mode.TELEOP and view.teleop_left is not None:
        lines.append(f"**Budget:** {view.teleop_left} operator step{'s' if view.teleop_left != 1 else ''} left")
    if view.fault:
        lines.append(f"**Fault:** {view.fault}")
    r = view.last_result
    rows = ["| | value | threshold |", "|---|---|---|"]
    rows.append(f"| **{name}** ({asked}) | {_num(score)} | {_num(threshold)} |")
    if r is not None:
        over = " ⚠" if view.slot.threshold and view.slot.threshold < r.U else ""
        rows += [
            f"| paper's U = D + α·Var_g | {_num(r.U)}{over} | {_num(view.slot.threshold)} |",
            f"| D (mode divergence) | {_num(r.D)} | |",
            f"| Var_g | {_num(r.var_g)} | |",
            f"| n (modes) | {r.n} | |",
        ]
    lines.append("\n".join(rows))
    if r is None:
        lines.append("_No denoising field: add `denoising` to the service's `shadow_signals` to see it._")
    if frame is not None:
        lines.append(f"**Goal:** {task.goal(frame.goal).text}")
        lines.append(
            f"Episode step {frame.clock} of {frame.horizon} (seed {view.seed}) · "
            f"gripper {frame.gripper * 1000:.0f} mm open"
        )
    return "\n\n".join(lines)


def key_map_markdown() -> str:
    rows = "\n".join(f"| {k} | {v} |" for k, v in KEY_MAP)
    return f"| Key | Action |\n|---|---|\n{rows}\n\n_{KEY_NOTE}_"


def empty_timeline() -> tuple[np.ndarray, ...]:
    """The timeline before a robot has points: two x values and gaps. Never empty arrays: viser 1.1.1's
    uPlot keeps its x range relative to the first data's span, and the span of no data is infinite, so a
    plot given empty data once draws nothing afterwards (the empty timeline of a robot viewed first while
    it waits)."""
    gap = np.full(2, np.nan)
    return np.array([0.0, 1.0]), gap, gap, np.ones(2), gap, gap


def timeline_data(view: RobotView) -> tuple[np.ndarray, ...]:
    """uPlot data: step, the asking signal's score / its threshold, the paper's U / its threshold, the
    threshold (1), help requested (a marker at 1), control changed hands (a marker at 1). NaN is a gap;
    ``empty_timeline`` before the first point."""
    points = view.timeline
    if not points:
        return empty_timeline()
    _, threshold = asking_threshold(view)
    t = np.array([p.t for p in points], dtype=np.float64)
    score = np.array([np.nan if p.score is None or not threshold else p.score / threshold for p in points])
    u_thr = view.slot.threshold
    u = np.array([np.nan if p.U is None or not u_thr else p.U / u_thr for p in points])
    asked = np.array([1.0 if p.asked else np.nan for p in points])
    handed = np.array([1.0 if p.handed else np.nan for p in points])
    return t, score, u, np.ones(len(points)), asked, handed


TIMELINE_SERIES = (
    {"label": "episode step"},
    {"label": "asking score ÷ threshold", "stroke": "#0072B2", "width": 2},
    {"label": "paper's U ÷ threshold", "stroke": "#888888", "width": 1},
    {"label": "threshold", "stroke": "#D55E00", "width": 1, "dash": [6, 4]},
    {"label": "asked", "stroke": "#D55E00", "width": 0, "points": {"show": True, "size": 9, "fill": "#D55E00"}},
    {
        "label": "control changed",
        "stroke": "#009E73",
        "width": 0,
        "points": {"show": True, "size": 9, "fill": "#009E73"},
    },
)
