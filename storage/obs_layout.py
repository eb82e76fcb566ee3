"""Observation layouts: the names of an observation vector's channels, in order, and what tells two apart.

A layout is the list of labels ``sim.env.ObsSpec.labels`` gives: one per dimension, ``part`` for a part
of size 1 and ``part[i]`` for the others. Episodes and takeover segments record the one they were
recorded with in their metadata, and a policy's config.json the one it was trained on, all under
``keys.OBS_LABELS``; what differs between two is said here once, by channel name (a part whose every
dimension differs is named as the part), for every check that compares them.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

from storage import keys

_INDEXED = re.compile(r"^(.*)\[(\d+)\]$")


def _part(label: str) -> str:
    m = _INDEXED.match(label)
    return m.group(1) if m else label


def _runs(labels: Sequence[str]) -> list[tuple[str, list[str]]]:
    """Consecutive labels of one part grouped: (part, its labels), in order."""
    out: list[tuple[str, list[str]]] = []
    for label in labels:
        name = _part(label)
        if out and out[-1][0] == name and label != name and out[-1][1][-1] != name:
            out[-1][1].append(label)
        else:
            out.append((name, [label]))
    return out


def parts(labels: Sequence[str]) -> list[tuple[str, int]]:
    """The labels grouped back into (part, size), in order: consecutive labels of one part are one."""
    return [(name, len(run)) for name, run in _runs(labels)]


def describe(labels: Sequence[str]) -> str:
    """``[eef_pos(3), eef_rot6d(6), ..., red_visible]``: the layout by part, with the sizes above 1."""
    return "[" + ", ".join(f"{name}({len(run)})" if len(run) > 1 else run[0] for name, run in _runs(labels)) + "]"


def _names(subset: Sequence[str], within: Sequence[str]) -> str:
    """The labels of ``subset`` (in ``within``'s order), a part named once where all of it is there."""
    chosen, out = set(subset), []
    for name, run in _runs(within):
        picked = [label for label in run if label in chosen]
        if not picked:
            continue
        whole = len(picked) == len(run) and (len(run) > 1 or run[0] == name) and name not in out
        out.extend([name] if whole else [p for p in picked if p not in out])
    return ", ".join(out)


def difference(expected: Sequence[str], given: Sequence[str]) -> list[str]:
    """How ``given`` differs from ``expected`` (empty: the same layout), one phrase each, ``given`` the
    subject: ``missing red_visible`` (expected has it, given not), ``extra object_pos, ...`` (given has
    it, expected not), ``the same channels in another order (channel 9 is ..., not ...)``."""
    expected, given = list(expected), list(given)
    if expected == given:
        return []
    have, want = set(given), set(expected)
    out = []
    if missing := [label for label in expected if label not in have]:
        out.append(f"missing {_names(missing, expected)}")
    if extra := [label for label in given if label not in want]:
        out.append(f"extra {_names(extra, given)}")
    common_e = [label for label in expected if label in have]
    common_g = [label for label in given if label in want]
    if common_e != common_g and len(common_e) == len(common_g):
        e, g = [n for n, _ in parts(common_e)], [n for n, _ in parts(common_g)]
        if e == g:  # the parts in order, the dimensions of one of them not: name the dimensions
            e, g = common_e, common_g
        i = next(i for i, (a, b) in enumerate(zip(e, g, strict=False)) if a != b)
        where = next(j for j, label in enumerate(given) if label == g[i] or _part(label) == g[i])
        what = "the same channels" if not (missing or extra) else "the shared channels"
        out.append(f"{what} in another order (at channel {where}: {g[i]}, not {e[i]})")
    if not out:  # the same labels, one of them repeated another number of times
        out.append(f"{len(given)} channels, not {len(expected)}")
    return out


def recorded(meta: dict | None) -> list[str] | None:
    """The layout ``meta`` (a file's metadata, a policy's config.json) records (None: none, or not as a
    list of names)."""
    labels = (meta or {}).get(keys.OBS_LABELS)
    if isinstance(labels, list) and labels and all(isinstance(label, str) for label in labels):
        return list(labels)
    return None


def mismatched(files: Iterable[tuple[str, dict | None]], expected: Sequence[str]) -> dict[str, str]:
    """{file: how its recorded layout differs from ``expected``} for each (file, metadata) that records
    another one; files that record none are not judged here (their dimension is)."""
    out = {}
    for name, meta in files:
        labels = recorded(meta)
        if labels is not None and (diff := difference(expected, labels)):
            out[name] = f"recorded with another observation layout ({describe(labels)}): " + "; ".join(diff)
    return out
