"""Atomic file writes: write to a temporary file beside the target, then rename over it.

An interrupted write leaves the previous file (or none), never a truncated one. The file gets the
permissions an ordinary ``open(path, "w")`` would give (``0o666`` less the process umask), not the
owner-only mode of a temporary file, so results on shared storage stay readable by the group.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed.

    A ``path`` that exists as anything but a regular file (a device such as ``/dev/null``, a FIFO, a
    socket, a directory) is refused with ``ValueError`` before anything is written: the rename would
    put a regular file in its place."""
    path = Path(path)
    if path.exists() and not path.is_file():
        raise ValueError(f"{str(path)!r} exists and is not a regular file; refusing to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=path.suffix, dir=path.parent, prefix=f".{path.stem}-")
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_umask())
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """The process umask (read by setting and restoring it: there is no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
