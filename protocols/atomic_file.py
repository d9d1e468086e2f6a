"""Files replaced atomically, and files private to the service's user.

:func:`atomic_write_bytes`: a reader, or a crash, sees the old content or the
new one, never a torn file. The bytes go to a temporary file in the target's
directory, which is flushed and fsynced, then renamed over the target with
``os.replace``, and the directory is fsynced so the rename itself survives a
power loss. On any failure the temporary file is removed and the old target
is left as it was.

:func:`private_file`: a file only its owner may read or write (0600), for the
service's own state (outbox, checkpoints). Passports and session files are
not secrets: they are written readable by all (0644), so that a service user
can read a passport filed by root.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

PUBLIC_MODE = 0o644
"""Mode of the files :func:`atomic_write_bytes` writes: the owner writes, everyone reads."""

PRIVATE_MODE = 0o600
"""Mode of :func:`private_file`: the owner alone reads and writes."""


def atomic_write_bytes(
    path: str | os.PathLike[str], data: bytes, *, mode: int = PUBLIC_MODE
) -> Path:
    """Replace the file ``path`` with ``data`` atomically (module docstring); returns the path.

    The new file has permissions ``mode`` whatever the umask (the temporary
    file starts private, 0600, and is given ``mode`` before it is renamed).
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            os.fchmod(fh.fileno(), mode)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return target


def private_file(path: str | os.PathLike[str]) -> Path:
    """Create ``path`` empty if missing (with its parent folders), and make it private (0600); returns it.

    For an SQLite database opened next: SQLite gives its ``-wal`` and ``-shm``
    files the database file's permissions, so they are private too.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(target, os.O_WRONLY | os.O_CREAT, PRIVATE_MODE)
    try:
        os.fchmod(fd, PRIVATE_MODE)
    finally:
        os.close(fd)
    return target
