"""Durable files: the one way this project writes a file that readers or a crash may catch half
done (the catalog's geometry and index files, artifact JSON, catalog.json, checkpoints).

A temporary file in the same folder, fsync, a rename over the target, fsync of the folder: a
reader sees the old file or the whole new one, and after a crash the rename is either on disk or
not. The temporary's name carries the writer's process and thread, so that
``remove_stale_temporaries`` can tell a dead writer's leftovers from a live one's.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path

_TMP = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.(?P<tid>\d+)\.tmp$")


def fsync_dir(folder: Path) -> None:
    """Make a rename or a new file in ``folder`` durable (POSIX needs the directory synced)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_file_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` so that readers see the old file or the whole new one, never a part.

    Temporary file in the same folder, fsync, rename over ``path``, fsync of the folder.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def remove_stale_temporaries(folder: Path) -> int:
    """Remove temporary files of ``write_file_atomic`` left by processes that no longer run."""
    removed = 0
    for p in Path(folder).glob(".*.tmp"):
        m = _TMP.match(p.name)
        if m is None:
            continue
        pid = int(m.group("pid"))
        alive = True
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive or pid == os.getpid():
            p.unlink(missing_ok=True)
            removed += 1
    return removed
