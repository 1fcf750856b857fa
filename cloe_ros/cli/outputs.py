"""Where the commands write: checked before any work, and never overwritten without ``--force``.

``cloe infer`` and ``cloe bag recover`` create a new bag and refuse an existing one; the commands
writing a file or a folder of results (``cloe evaluate --json``, ``cloe paper -o``, ``cloe report
-o``) refuse an existing file or a non-empty folder unless given ``--force``.
"""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

from cloe_ros.cli.errors import CliError


def check_new_file(path: Path, force: bool, option: str) -> None:
    """Refuse, before any work, a file ``path`` (given with ``option``) that cannot be written,
    or that exists and ``force`` is not given."""
    if path.is_dir():
        raise CliError(f'{option} {path} is a folder: give the name of a file')
    if path.exists() and not force:
        raise CliError(
            f'{path} exists already, not overwriting: choose another file with {option} or pass '
            '--force to replace it'
        )
    folder = path.parent
    if not folder.is_dir():
        raise CliError(f'cannot write {option} {path}: the folder {folder} does not exist')
    if not os.access(path if path.exists() else folder, os.W_OK):
        raise CliError(f'cannot write {option} {path}: permission denied')


def check_folder(folder: Path, force: bool, replaced: str | None) -> None:
    """Refuse, before any work, a ``folder`` that is a file, or that is not empty and ``force``
    is not given (``replaced``: what ``--force`` replaces in it; None: the command has no
    ``--force``)."""
    if folder.exists() and not folder.is_dir():
        raise CliError(f'{folder} exists and is not a folder: choose another folder with -o')
    if folder.is_dir() and any(folder.iterdir()) and not force:
        hint = '' if replaced is None else f' or pass --force to replace {replaced} in it'
        raise CliError(
            f'{folder} exists and is not empty, not overwriting: choose another folder with -o'
            + hint
        )


def make_folder(folder: Path) -> None:
    """Create ``folder`` (and its parents); a clear error when that is not possible."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CliError(f'cannot create the folder {folder}: {err.strerror or err}') from err
    if not os.access(folder, os.W_OK):
        raise CliError(f'cannot write into the folder {folder}: permission denied')


def json_safe(value):
    """``value`` (dicts, lists, tuples, numbers, numpy scalars and arrays) with every number a
    JSON number: NaN and infinities become null (strict JSON has neither)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if hasattr(value, 'tolist') and not isinstance(value, numbers.Number):  # (numpy arrays)
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, bool):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value) if math.isfinite(value) else None
    return value
