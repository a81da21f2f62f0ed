"""Atomic file writing shared by every stage (a killed run never leaves a half file behind)."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np


def _process_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once at import (os.umask can only be read by setting it, which would race with threads that
# create files): temporary files are created 0600, and the renamed result gets the mode that a plain
# open() would have given it.
FILE_MODE = 0o666 & ~_process_umask()


def write_atomic(path: str | os.PathLike, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` on a temporary file beside ``path``, then rename it into place.

    The temporary file keeps ``path``'s suffix so that writers which pick a format by extension
    (Open3D, trimesh, OpenCV) still work. The result has the usual mode (``FILE_MODE``: 0644 under
    the common umask 022), not the temporary file's 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        writer(tmp_path)
        os.chmod(tmp_path, FILE_MODE)
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    return write_atomic(path, lambda p: p.write_text(text))


def write_json_atomic(path: str | os.PathLike, record) -> Path:
    """Write a JSON record (indented, NaN refused) to ``path`` atomically."""
    return write_text_atomic(path, json.dumps(record, indent=2, allow_nan=False, default=_to_builtin) + "\n")


def _to_builtin(value):

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
