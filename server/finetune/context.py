"""What a fine-tuning job's stages are given of the runner that runs them.

``FinetuneRunner`` (``server.finetune.job``) builds a ``JobContext``; ``JobRun.prepare``
(``server.finetune.stages``) takes it, so the stages never need the runner itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.orm import sessionmaker


@dataclass(frozen=True)
class JobContext:
    """The metadata store ``sessions``, the data folder ``data_dir`` (resolved), ``eval_tasks`` (lineage ->
    the gate's target tasks, the settings'), whether to show progress, and where report lines go."""

    sessions: sessionmaker
    data_dir: Path
    eval_tasks: dict[str, list[str]]
    progress: bool
    report: Callable[[str], None]
