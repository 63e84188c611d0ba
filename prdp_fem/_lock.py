"""One writer per output directory: an OS-level lock held for a whole run.

``with directory_lock(out):`` takes an exclusive ``flock`` on ``out/.prdp-fem.lock`` (the
file holds the writer's pid) and keeps it until the block ends. The kernel releases it when
the process dies, so a killed run (``kill -9``) never leaves a stale lock behind. A second
writer -- another study, a resume or ``bench prdp`` on the same directory -- fails at once
with :class:`~prdp_fem.errors.OutputLockedError` naming the directory and the holder's pid.

Where ``fcntl`` does not exist (Windows), the block runs without a lock.

>>> import tempfile
>>> out = tempfile.mkdtemp()
>>> with directory_lock(out) as path:
...     path.name
'.prdp-fem.lock'
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputLockedError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None

__all__ = ["LOCK_NAME", "directory_lock"]

LOCK_NAME = ".prdp-fem.lock"


@contextlib.contextmanager
def directory_lock(directory: str | os.PathLike) -> Iterator[Path]:
    """Hold the write lock of ``directory`` (created if missing) for the block."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / LOCK_NAME
    if fcntl is None:  # pragma: no cover
        yield path
        return
    # opened without truncation: the holder's pid must stay readable to a second writer
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(descriptor, 32, 0).decode(errors="replace").strip() or "unknown"
            raise OutputLockedError(
                f"{directory}: is being written by another prdp-fem process (pid {holder}); "
                "expected one writer per output directory: wait for it, or choose another "
                "--out") from None
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        os.close(descriptor)  # closing releases the lock
