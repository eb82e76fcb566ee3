"""Paths that files record: relative to a data root, so a committed file names no machine's folders.

A policy's ``config.json`` names the demonstrations it was trained on, its ``calibration.json`` the
folder it was calibrated on, a signal's config the demonstrations it was fitted to, and a benchmark's
JSON the data it used. Written with absolute paths, those files only work on the machine that made
them. ``portable`` writes a path relative to the data root when it lies under it (any other path
absolute, as the only way to name it); ``resolve`` turns a recorded path back into one the process can open.

The data root is ``HITL_DATA_ROOT`` when set, else the current working directory (the repository,
where every ``hitl`` command and ``make`` target runs). A service started elsewhere sets the variable
to the checkout or data volume the policies' folders are relative to.
"""

from __future__ import annotations

import os
from pathlib import Path

DATA_ROOT_ENV = "HITL_DATA_ROOT"


def data_root() -> Path:
    """The folder recorded relative paths are relative to (read at each call: no import-time state)."""
    root = os.environ.get(DATA_ROOT_ENV)
    return Path(os.path.abspath(Path(root).expanduser())) if root else Path.cwd()


def portable(path: str | Path) -> str:
    """``path`` as a file should record it: relative to the data root when under it, else absolute.

    A relative ``path`` is taken as the process would open it (from the working directory)."""
    absolute = Path(os.path.abspath(Path(path).expanduser()))
    try:
        return absolute.relative_to(data_root()).as_posix()
    except ValueError:
        return absolute.as_posix()


def resolve(recorded: str | Path) -> Path:
    """A recorded path as one to open: absolute paths as they are, relative ones under the data root."""
    p = Path(recorded).expanduser()
    return p if p.is_absolute() else data_root() / p


def in_store(data_dir: str | Path, stored: str | Path) -> Path:
    """A file path as the service's metadata store records it (relative to the service's ``data_dir``,
    not to the data root above), as one to open; absolute paths, as older versions stored them, as they are."""
    return Path(data_dir).resolve() / stored


def store_relative(data_dir: str | Path, path: str | Path) -> str:
    """``path``, a file under the service's ``data_dir``, as the metadata store records it (``in_store``)."""
    return str(Path(path).relative_to(Path(data_dir).resolve()))
