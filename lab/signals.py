"""The lab's assistance signals, registered with the product's registry only while a benchmark or an
experiment of the CLI runs (``hitl bench``, ``report``, ``plot``, ``assist``, ``train-signal``: ``registered``).
The service never imports ``lab``, so it can be configured with none of them."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from lab.spread_stall import SpreadStallSignal
from policy.signals.base import AssistanceSignal
from policy.signals.registry import SIGNALS

LAB_SIGNALS: dict[str, type[AssistanceSignal]] = {
    "spread-stall": SpreadStallSignal,  # the previous default, superseded by choice-stall
}


@contextmanager
def registered() -> Iterator[None]:
    """``LAB_SIGNALS`` in ``policy.signals.SIGNALS`` until the block ends (a product signal is never
    replaced; an inner block leaves the outer one's; processes forked inside the block keep them)."""
    added = []
    try:
        for name, cls in LAB_SIGNALS.items():
            if name not in SIGNALS:
                SIGNALS[name] = cls
                added.append(name)
            elif SIGNALS[name] is not cls:
                raise RuntimeError(f"lab signal {name!r} clashes with the product's {SIGNALS[name].__name__}")
        yield
    finally:
        for name in added:
            SIGNALS.pop(name, None)
