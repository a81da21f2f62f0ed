"""Atomic writes: the result appears whole or not at all, with the mode a plain open() gives."""

from __future__ import annotations

import os
import stat
import subprocess
import sys

import pytest

from scene.io import write_atomic, write_text_atomic

PROJECT_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _written_mode(tmp_path, umask: int) -> int:
    script = "import sys; from scene.io import write_text_atomic; write_text_atomic(sys.argv[1], 'x')"
    target = tmp_path / f"umask{umask:03o}.txt"
    subprocess.run(
        [sys.executable, "-c", script, str(target)],
        cwd=PROJECT_ROOT,
        check=True,
        preexec_fn=lambda: os.umask(umask),
    )
    return stat.S_IMODE(target.stat().st_mode)


def test_atomic_files_get_the_umask_mode_not_the_temporary_0600(tmp_path):
    # mkstemp creates 0600; a renamed temporary file used to keep it (results only root could read).
    assert _written_mode(tmp_path, 0o022) == 0o644
    assert _written_mode(tmp_path, 0o027) == 0o640


def test_a_failed_writer_leaves_the_old_file_and_no_temporary(tmp_path):
    path = write_text_atomic(tmp_path / "record.json", "old")

    def failing(tmp):
        tmp.write_text("half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError, match="killed"):
        write_atomic(path, failing)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]
