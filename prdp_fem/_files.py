"""Input files checked at the edge: what is wrong with a path, said in words.

``Path.exists()`` answers ``False`` for a symbolic link loop and ``Path.resolve()`` raises
``RuntimeError`` on one; :func:`checked_file` tells the cases apart, so that a message says
"is a symbolic link loop" where it would otherwise say "does not exist" or show a traceback.

>>> import tempfile, pathlib
>>> loop = pathlib.Path(tempfile.mkdtemp()) / "loop.msh"
>>> loop.symlink_to(loop.name)
>>> checked_file(loop, "mesh file", ValueError)  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
ValueError: .../loop.msh: is a symbolic link loop (...); expected a mesh file
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from .errors import MeshError

__all__ = ["checked_file"]


def checked_file(path: str | os.PathLike, what: str, error: type[Exception], *,
                 missing: str = "file does not exist") -> int:
    """The size of the regular file ``path``, or ``error`` naming it and what is wrong: it
    does not exist (``missing`` says so; a dangling link is named as one), is a symbolic
    link loop, is not a regular file, or cannot be opened. ``error`` is called as
    ``error(path, problem)`` where it takes a source and a problem
    (:class:`~prdp_fem.errors.MeshError`), else with one message."""
    path = Path(path)

    def fail(problem: str) -> Exception:
        if issubclass(error, MeshError):
            return error(path, f"{problem}; expected a {what}")
        return error(f"{path}: {problem}; expected a {what}")

    try:
        info = path.stat()
    except FileNotFoundError:
        if path.is_symlink():
            raise fail(f"is a symbolic link to {os.readlink(path)!r}, which does not "
                       "exist") from None
        raise fail(missing) from None
    except OSError as exc:  # ELOOP (a symbolic link loop), EACCES on a parent, ENAMETOOLONG
        kind = "is a symbolic link loop" if exc.errno == errno.ELOOP else "cannot be opened"
        raise fail(f"{kind} ({exc.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        raise fail("is not a regular file")
    return info.st_size
