"""Files replaced atomically: a reader, or a crash, sees the old content or the new one, never a torn file.

The bytes go to a temporary file in the target's directory, which is flushed
and fsynced, then renamed over the target with ``os.replace``, and the
directory is fsynced so the rename itself survives a power loss. On any
failure the temporary file is removed and the old target is left as it was.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Replace the file ``path`` with ``data`` atomically (module docstring); returns the path."""
    target = Path(path)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
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
