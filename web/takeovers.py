"""The console's "Recent takeovers" folder: the last takeovers of the robot in view with their labels,
and the inputs that label them (good, bad, discard or restore, a note).

``TakeoverBoard`` (one per console) reads the rows from the database, at most once per ``REFRESH_S``
per robot whatever the number of browsers; ``TakeoverFolder`` (one per browser) shows them and sends
a label through ``ConsoleActions.label`` (the operator role, as ``PATCH /segments/{id}`` needs).
"""

from __future__ import annotations

import html
import re
import threading
import time
from dataclasses import dataclass

import viser
from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from server.db import SegmentRecord
from server.errors import ServiceError
from server.labels import LabelChange
from web.actions import ConsoleActions

RECENT = 5  # takeovers shown per robot
REFRESH_S = 1.0


@dataclass(frozen=True)
class TakeoverRow:
    id: int
    operator: str
    steps: int
    status: str
    ended_by: str | None
    label: str | None
    discarded: bool
    note: str | None
    labelled_by: str | None

    @property
    def option(self) -> str:
        return f"#{self.id} · {self.operator} · {self.steps} steps"

    @property
    def verdict(self) -> str:
        parts = [self.label or "unlabelled"] + (["**discarded**"] if self.discarded else [])
        return ", ".join(parts)


_MARKDOWN = re.compile(r"([\\`*_\[\]{}()#+!|~>-])")


def cell(text: str | None) -> str:
    """Free text (an operator's note or name) as one table cell that renders as the text itself: viser
    renders a markdown's raw HTML unsanitized, so the HTML is escaped, and so are markdown's own marks."""
    flat = " ".join((text or "").split())
    return _MARKDOWN.sub(r"\\\1", html.escape(flat, quote=True))


def takeovers_markdown(rows: list[TakeoverRow]) -> str:
    if not rows:
        return "_No takeover of this robot yet._"
    lines = ["| # | operator | steps | ended | label | note |", "|---|---|---|---|---|---|"]
    for r in rows:
        ended = r.ended_by or ("recording" if r.status == "open" else r.status)
        lines.append(f"| {r.id} | {cell(r.operator)} | {r.steps} | {ended} | {r.verdict} | {cell(r.note)} |")
    return "\n".join(lines)


class TakeoverBoard:
    """The last takeovers per robot, shared by the console's browsers (read at most every REFRESH_S)."""

    def __init__(self, sessions: sessionmaker) -> None:
        self.sessions = sessions
        self._cache: dict[int, tuple[float, list[TakeoverRow]]] = {}
        self._lock = threading.Lock()

    def recent(self, robot_id: int) -> list[TakeoverRow]:
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(robot_id)
            if hit is not None and now - hit[0] < REFRESH_S:
                return hit[1]
        q = select(SegmentRecord).where(SegmentRecord.robot_id == robot_id).order_by(SegmentRecord.id.desc())
        with self.sessions() as s:
            rows = [
                TakeoverRow(
                    r.id, r.operator, r.steps, r.status, r.ended_by, r.label, bool(r.discarded), r.note, r.labelled_by
                )
                for r in s.scalars(q.limit(RECENT))
            ]
        with self._lock:
            self._cache[robot_id] = (now, rows)
        return rows

    def changed(self, robot_id: int) -> None:
        """A label was set: the next read goes to the database."""
        with self._lock:
            self._cache.pop(robot_id, None)


class TakeoverFolder:
    """One browser's folder; ``show`` (from the panel's tick) updates it for the robot in view."""

    def __init__(self, gui: viser.GuiApi, board: TakeoverBoard, actions: ConsoleActions, notify) -> None:
        self.board, self.actions, self.notify = board, actions, notify
        self.robot_id: int | None = None
        self.rows: list[TakeoverRow] = []
        self._shown: tuple = ()
        self._note_for: int | None = None  # the takeover whose note the text field holds
        with gui.add_folder("Recent takeovers"):
            self.table = gui.add_markdown(takeovers_markdown([]))
            self.select = gui.add_dropdown("Takeover", options=("–",), initial_value="–")
            self.good = gui.add_button("Good", disabled=True, icon=viser.Icon.THUMB_UP)
            self.bad = gui.add_button("Bad", disabled=True, icon=viser.Icon.THUMB_DOWN)
            self.discard = gui.add_button("Discard", disabled=True, color="red", icon=viser.Icon.TRASH)
            self.restore = gui.add_button("Restore", disabled=True, icon=viser.Icon.RESTORE)
            self.note = gui.add_text("Note", initial_value="", disabled=True)
            self.save_note = gui.add_button("Save note", disabled=True)
        self.good.on_click(lambda _: self._label(label="good"))
        self.bad.on_click(lambda _: self._label(label="bad"))
        self.discard.on_click(lambda _: self._label(discarded=True))
        self.restore.on_click(lambda _: self._label(discarded=False))
        self.save_note.on_click(lambda _: self._label(note=self.note.value))
        self.select.on_update(lambda _: self._show_inputs())

    def _selected(self) -> TakeoverRow | None:
        return next((r for r in self.rows if r.option == self.select.value), None)

    def _label(self, **change) -> None:
        row, rid = self._selected(), self.robot_id
        if row is None or rid is None:
            return
        try:
            self.actions.label(row.id, LabelChange(**change))
        except ServiceError as exc:
            self.notify(f"Label refused ({exc.status})", exc.message, "red")
            return
        self.board.changed(rid)
        self.notify(f"Takeover {row.id}", "label saved", "green")

    def _show_inputs(self) -> None:
        row = self._selected()
        can = self.actions.can_operate and row is not None
        for button in (self.good, self.bad, self.save_note):
            button.disabled = not can
        self.note.disabled = not can
        if row is not None and row.id != self._note_for:  # another takeover: its note, not what was typed
            self.note.value, self._note_for = row.note or "", row.id
        self.discard.disabled = not can or row.discarded
        self.restore.disabled = not can or not row.discarded

    def show(self, robot_id: int) -> None:
        rows = self.board.recent(robot_id)
        key = (robot_id, tuple(rows))
        if key == self._shown:
            return
        robot_changed = robot_id != self.robot_id
        self.robot_id, self.rows, self._shown = robot_id, rows, key
        self.table.content = takeovers_markdown(rows)
        options = tuple(r.option for r in rows) or ("–",)
        keep = self.select.value if not robot_changed and self.select.value in options else options[0]
        self.select.options = options
        self.select.value = keep
        self._show_inputs()
