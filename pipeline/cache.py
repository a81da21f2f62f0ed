"""Content-keyed stage cache shared by concurrent runs (sweeps build each scene's proxy once).

An entry is a directory ``<cache_dir>/<stage>/<key>/``; it is complete only when its
``COMPLETE.json`` marker exists (written last, atomically). Builders run under an exclusive file
lock so that parallel sweep jobs wait for the first builder instead of building twice.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from scene.io import write_json_atomic

log = logging.getLogger(__name__)

MARKER = "COMPLETE.json"


def cache_key(*parts) -> str:
    """A short stable hash of JSON-serialisable parts (configs as plain containers)."""
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:16]


@contextmanager
def exclusive_lock(lock_path: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``lock_path`` (created if missing) for the block."""
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with lock_path.open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def cached_entry(
    cache_dir: str | Path, stage: str, key: str, build: Callable[[Path], dict]
) -> tuple[Path, dict]:
    """Return the entry directory and record of ``stage``/``key``, building it once if needed.

    Args:
        cache_dir: cache root.
        stage: stage name (a sub-folder).
        key: content key of the stage's inputs (``cache_key``).
        build: ``build(entry_dir) -> record``; writes the stage's outputs into ``entry_dir``.

    Returns:
        (entry_dir, record) where record is what ``build`` returned, plus ``cache_hit`` (bool)
        and ``built_s`` (seconds the build took when it ran).
    """
    entry = Path(cache_dir) / stage / key
    marker = entry / MARKER
    with exclusive_lock(Path(cache_dir) / stage / f"{key}.lock"):
        if marker.is_file():
            record = json.loads(marker.read_text())
            log.info("%s: reusing cached %s", stage, entry)
            return entry, {**record, "cache_hit": True}
        if entry.exists():
            log.info("%s: discarding incomplete cache entry %s", stage, entry)
            shutil.rmtree(entry)
        entry.mkdir(parents=True)
        start = time.perf_counter()
        try:
            record = dict(build(entry))
        except BaseException:
            shutil.rmtree(entry, ignore_errors=True)
            raise
        record["built_s"] = time.perf_counter() - start
        write_json_atomic(marker, record)
        return entry, {**record, "cache_hit": False}
