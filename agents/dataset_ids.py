"""Minari dataset ids and folders, checked before anything is recorded (Minari itself
checks an id only when it writes, and leaves a folder behind that breaks the others)."""

from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["DATASET_ID", "check_dataset_id", "check_root", "use_root"]

#: A Minari dataset id with its version: ``(namespace/)name-vN`` (letters, digits, ``_``, ``-``)
DATASET_ID = re.compile(r"(?:[A-Za-z0-9_][-\w]*/)*[A-Za-z0-9_][-\w]*-v\d+")


def check_dataset_id(dataset_id, argument: str = "--out") -> str:
    """``dataset_id`` if it is a Minari id ``(namespace/)name-vN``, else a one-line error
    naming ``argument`` (before anything is recorded: Minari itself checks only when it
    writes, and leaves a folder behind)."""
    if not isinstance(dataset_id, str) or not DATASET_ID.fullmatch(dataset_id):
        raise ValueError(f"{argument}: a Minari dataset id is (namespace/)name-vN (letters, digits, _ and -), "
                         f"e.g. heml-gym/tissue-retraction/scripted-v0, got {dataset_id!r}")
    return dataset_id


def check_root(root, argument: str = "--root") -> Path:
    """The Minari datasets folder ``root`` (resolved), or a one-line error if it is a file."""
    path = Path(root).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise ValueError(f"{argument}: {path} is a file, not a folder of Minari datasets")
    return path


def use_root(root, argument: str = "--root") -> Path:
    """Make ``root`` (checked by :func:`check_root`) the Minari datasets folder of this
    process and of those it starts (``MINARI_DATASETS_PATH``); returns it."""
    path = check_root(root, argument)
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    return path
